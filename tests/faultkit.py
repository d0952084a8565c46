"""The fault suites' shared steps (tests/test_faults*.py): run the real command line and
read what it printed, check that ``validate`` refuses a mission on one line naming the
cause, and break a copy of a mission the way a user would (an edited mission.toml, the
POS rewritten as CSV). The missions themselves are conftest's ``fault_base`` and ``m``."""
from __future__ import annotations

from pathlib import Path

from swathflow.flows.cli import main


def run(capsys, *argv) -> tuple[int, str]:
    """The command line's exit code and all it printed (stdout and stderr): never a
    traceback."""
    code = main([str(a) for a in argv])
    cap = capsys.readouterr()
    text = cap.out + cap.err
    assert "Traceback" not in text
    return code, text


def run_fresh(*argv) -> tuple[str, str]:
    """The command line run in a fresh interpreter: ``"RC <exit code> <flow> <dask>"``
    (``flow`` when the flow's module, which imports Prefect, was imported by the time the
    command returned, ``dask`` when Dask's distributed was, ``-`` for either not), and all
    it printed."""
    import subprocess
    import sys
    code = ("import sys\nfrom swathflow.flows.cli import main\n"
            "rc = main(sys.argv[1:])\n"
            "print('RC', rc, 'flow' if 'swathflow.flows.mission' in sys.modules else '-', "
            "'dask' if 'distributed' in sys.modules else '-')\n")
    r = subprocess.run([sys.executable, "-c", code, *map(str, argv)], capture_output=True,
                       text=True, timeout=300)
    status = next((ln for ln in r.stdout.splitlines() if ln.startswith("RC ")), "")
    return status, r.stdout + r.stderr


def bad(capsys, m, *words) -> str:
    """``validate m`` exits 2 and one problem line holds every word (and a fix), never the
    "unexpected content" of an error nobody foresaw: that line."""
    code, text = run(capsys, "validate", m)
    assert code == 2, text
    lines = [ln for ln in text.splitlines() if all(w.lower() in ln.lower() for w in words)]
    assert lines, f"no line with {words}:\n{text}"
    assert "fix:" in lines[0]
    assert "unexpected content" not in text
    return lines[0]


def toml(m: Path, old: str, new: str, count: int = 1) -> None:
    """mission.toml of ``m`` with ``old`` (which must be there) replaced by ``new``."""
    p = m / "mission.toml"
    s = p.read_text()
    assert old in s, old
    p.write_text(s.replace(old, new, count))


def pos_csv(m: Path, change) -> None:
    """The mission's SBET rewritten as a CSV POS (``change`` applied to its table), and
    mission.toml pointed at it."""
    import pandas as pd

    from swathflow.formats.pos import read_pos
    ds = read_pos(m / "pos.sbet")
    df = pd.DataFrame({"time": ds.time.values, **{k: ds[k].values for k in ds.data_vars}})
    change(df).to_csv(m / "pos.csv", index=False, float_format="%.10f")
    (m / "pos.sbet").unlink()
    toml(m, 'file = "pos.sbet"\nformat = "sbet"', 'file = "pos.csv"\nformat = "csv"')
