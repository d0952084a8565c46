"""Packaging: the wheel carries every module at the path that names it, and both an editable
and a wheel install import from the repository root and from elsewhere."""
import subprocess
import sys
import sysconfig
import tomllib
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
#: source folder -> package path in the wheel: swathflow/ as it is, and the required
#: top-level folders mapped by pyproject's package-dir (flows/ -> swathflow/flows, ...)
MAPPING = {"swathflow": "swathflow", **{
    folder: pkg.replace(".", "/")
    for pkg, folder in PROJECT["tool"]["setuptools"]["package-dir"].items()}}
PROBE = ("import swathflow, swathflow.flows.mission, swathflow.tasks, "
         "swathflow.sensors.pendulum, swathflow.sensormodel; "
         "from swathflow.sensormodel import list_sensors; "
         "print(swathflow.__file__); print(sorted(list_sensors()))")


@pytest.fixture(scope="module")
def wheel(tmp_path_factory):
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps",
                    "--no-build-isolation", "-w", str(out), str(ROOT)], check=True,
                   capture_output=True)
    return next(out.glob("swathflow-*.whl"))


def test_the_mapping_covers_the_required_folders():
    assert {"swathflow", "flows", "tasks", "sensors"} == set(MAPPING)
    assert MAPPING["flows"] == "swathflow/flows"


def test_wheel_contains_all_source_modules(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    missing = []
    for folder, pkg in MAPPING.items():
        for src in (ROOT / folder).rglob("*.py"):
            rel = src.relative_to(ROOT / folder)
            if f"{pkg}/{rel.as_posix()}" not in names:
                missing.append(f"{folder}/{rel}")
    assert not missing, f"not in the wheel: {missing} (add the subpackage to pyproject.toml)"
    assert any(n.endswith("entry_points.txt") for n in names)
    assert "swathflow/py.typed" in names
    templates = sorted((ROOT / "swathflow" / "templates").glob("*.html.j2"))
    assert templates, "no report templates in swathflow/templates"
    missing = [t.name for t in templates if f"swathflow/templates/{t.name}" not in names]
    assert not missing, f"templates not in the wheel: {missing} (pyproject package-data)"


def _probe(python: str, cwd: Path, env: dict | None = None) -> list[str]:
    r = subprocess.run([python, "-c", PROBE], cwd=cwd, capture_output=True, text=True,
                       env=env, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    return r.stdout.splitlines()


@pytest.mark.parametrize("where", ["root", "elsewhere"])
def test_the_editable_install_imports(where, tmp_path):
    """The test run's own install (``pip install -e``): the core package is the source
    folder swathflow/, and the built-in sensors register through their entry points."""
    cwd = ROOT if where == "root" else tmp_path
    path, sensors = _probe(sys.executable, cwd)
    assert Path(path) == ROOT / "swathflow" / "__init__.py"
    assert {"pendulum", "pushbroom"} <= set(eval(sensors))


def test_a_wheel_install_imports_from_elsewhere(wheel, tmp_path):
    """The wheel unpacked into a fresh target folder (its dependencies from this venv):
    imported from another folder, every module comes from the wheel."""
    target = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps",
                    "--target", str(target), str(wheel)], check=True, capture_output=True)
    venv_site = sysconfig.get_paths()["purelib"]
    env = {"PYTHONPATH": str(target), "PATH": "/usr/bin:/bin", "HOME": str(tmp_path),
           "PYTHONNOUSERSITE": "1"}
    # -I would drop PYTHONPATH; -S keeps the venv's editable finder of swathflow out, and
    # the venv's packages come in as a plain path after the target
    r = subprocess.run([sys.executable, "-S", "-c",
                        f"import sys; sys.path.append({venv_site!r}); " + PROBE],
                       cwd=tmp_path, capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    path, sensors = r.stdout.splitlines()
    assert Path(path) == target / "swathflow" / "__init__.py"
    assert {"pendulum", "pushbroom"} <= set(eval(sensors))
