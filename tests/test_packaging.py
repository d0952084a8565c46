"""The wheel carries every subpackage (a missing one would drop out silently)."""
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory):
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps",
                    "--no-build-isolation", "-w", str(out), str(ROOT)], check=True,
                   capture_output=True)
    return next(out.glob("swathflow-*.whl"))


def test_wheel_contains_all_source_modules(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    mapping = {"core": "swathflow", "sensors": "swathflow/sensors", "tasks": "swathflow/tasks",
               "flows": "swathflow/flows"}
    missing = []
    for folder, pkg in mapping.items():
        for src in (ROOT / folder).rglob("*.py"):
            rel = src.relative_to(ROOT / folder)
            if f"{pkg}/{rel.as_posix()}" not in names:
                missing.append(f"{folder}/{rel}")
    assert not missing, f"not in the wheel: {missing} (add the subpackage to pyproject.toml)"
    assert any(n.endswith("entry_points.txt") for n in names)


def test_no_top_level_swathflow_folder():
    assert not (ROOT / "swathflow").exists(), "core/ is the swathflow package (DESIGN.md)"
