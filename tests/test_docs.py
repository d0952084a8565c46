"""The documentation: the benchmark table is what its script writes from its data, the
project names nothing outside the clone, the docs carry no diary labels, and the README's
links and test command hold."""
import json
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TABLE = ROOT / "benchmarks" / "benchmarks_table.py"
DOCS = [ROOT / "README.md", ROOT / "CHANGELOG.md", ROOT / "deploy" / "README.md",
        ROOT / "plugins" / "rotating-mirror" / "README.md",
        *sorted((ROOT / "docs").glob("*.md")), *sorted((ROOT / "tests" / "data").rglob("*.md"))]
#: places outside a clone (written in parts, so that this file does not name them itself)
FORBIDDEN = re.compile(rb"\.\./" rb"shared|SWATHFLOW_" rb"SHARED|/wo" rb"rk/|/tmp/[\w.-]+\.py")


def _table(*argv: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(TABLE), *argv], capture_output=True, text=True)


def _tracked() -> list[Path]:
    out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True)
    return [ROOT / p for p in out.stdout.decode().split("\0") if p]


def test_benchmark_page_is_what_the_script_writes():
    r = _table("--check")
    assert r.returncode == 0, r.stderr


def test_check_fails_on_a_stale_page(tmp_path):
    results = json.loads((ROOT / "benchmarks" / "results.json").read_text())
    results["rows"][0]["ours"] = [99.0]
    (tmp_path / "results.json").write_text(json.dumps(results))
    page = tmp_path / "benchmarks.md"
    page.write_text((ROOT / "docs" / "benchmarks.md").read_text())
    r = _table("--check", "--results", str(tmp_path / "results.json"), "--page", str(page))
    assert r.returncode == 1 and "benchmarks_table.py" in r.stderr


def test_a_row_shows_median_range_and_ratio_of_its_runs(tmp_path):
    """Two runs of 2 s and 4 s against a peer's 10 s and 12 s: ratios 5 and 3."""
    row = {"key": "k", "what": "a job", "peer": "a peer", "unit": "s", "better": "lower",
           "ours": [2.0, 4.0], "peer_figures": [10.0, 12.0], "command": "python x.py",
           "date": "2026-12-04"}
    throughput = dict(row, key="t", better="higher", ours=[30.0], peer_figures=[10.0])
    (tmp_path / "r.json").write_text(json.dumps({"rows": [row, throughput]}))
    page = tmp_path / "p.md"
    assert _table("--results", str(tmp_path / "r.json"), "--page", str(page)).returncode == 0
    lines = [x for x in page.read_text().splitlines() if x.startswith("| a job")]
    assert lines[0] == ("| a job | - | a peer: 11.0 s (10.0-12.0, 2 runs) | 3.00 s (2.00-4.00, "
                        "2 runs) | **4.00x** (3.00-5.00) | `python x.py` | 2026-12-04 |")
    assert "| **3.00x** |" in lines[1]


def test_every_row_names_a_command_that_exists_and_a_past_date():
    import datetime as dt
    rows = json.loads((ROOT / "benchmarks" / "results.json").read_text())["rows"]
    assert rows
    for row in rows:
        script = next((w for w in row["command"].split() if w.endswith(".py")), None)
        if script is not None:
            assert (ROOT / script).is_file(), (row["key"], script)
        assert dt.date.fromisoformat(row["date"]) <= dt.date.today(), row["key"]


def test_no_tracked_file_names_a_place_outside_the_clone():
    hits = []
    for path in _tracked():
        if path == Path(__file__).resolve() or not path.is_file():
            continue
        for n, line in enumerate(path.read_bytes().splitlines(), 1):
            if FORBIDDEN.search(line):
                hits.append(f"{path.relative_to(ROOT)}:{n}: {line.decode(errors='replace')[:100]}")
    assert not hits, "\n".join(hits)


def test_docs_carry_no_stop_labels():
    assert all(p.is_file() for p in DOCS[:4])
    hits = [f"{p.relative_to(ROOT)}:{n}: {line[:100]}" for p in DOCS
            for n, line in enumerate(p.read_text().splitlines(), 1)
            if re.search(r"\bstops? [0-9]+\b", line, re.IGNORECASE)]
    assert not hits, "\n".join(hits)


def test_readme_is_short_and_its_test_command_is_what_ci_runs():
    readme = (ROOT / "README.md").read_text()
    assert len(readme.splitlines()) <= 300
    ci = [x for x in (ROOT / ".ci" / "run").read_text().splitlines()
          if x.strip() and not x.startswith(("#", "set ", "cd "))]
    assert len(ci) == 1 and ci[0] in readme


def test_relative_links_in_the_docs_point_at_files():
    broken = []
    for p in DOCS:
        for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", p.read_text()):
            if "://" in target or target.startswith("mailto:"):
                continue
            if not (p.parent / target).exists():
                broken.append(f"{p.relative_to(ROOT)}: {target}")
    assert not broken, "\n".join(broken)
