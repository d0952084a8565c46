"""docs/benchmarks.md, written from benchmarks/results.json: one table, a row per measure.

    python benchmarks/benchmarks_table.py            # rewrite docs/benchmarks.md
    python benchmarks/benchmarks_table.py --check    # exit 1 if docs/benchmarks.md differs

A new figure goes into results.json, by hand or from a benchmark with
``record(key, ours, peer_figures=..., date=...)`` (which also rewrites the page); the page
is never edited by hand. ``tests/test_docs.py`` runs ``--check``.
"""
from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import statistics
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results.json"
PAGE = ROOT / "docs" / "benchmarks.md"

HEAD = """\
# Benchmarks

<!-- Written by benchmarks/benchmarks_table.py from benchmarks/results.json: do not edit. -->

The latest figure of every measure, each taken side by side with its peer in one run on a
2-core machine shared with other jobs (rows dated before 2026-12-04 ran on a slower one).
Read the **ratio** within its row, not the seconds across rows: the machine's speed moves
from run to run. The ratio is how many times better ours is than the peer (the peer's time
over ours, or our throughput over the peer's): above 1 we are faster. With several runs a
cell gives the median and, in brackets, the range over the runs.

`DEMO` in the commands is the demo mission with seed 3:
`swathflow simulate DEMO --preset demo --seed 3`. Every script in `benchmarks/` prints its
figures and the command that reproduces them; the GDAL peers need Debian's `gdal-bin`.
`OLD` is the `swathflow` command of another build installed beside this one (the rows
"before" used 0.1.0: `git worktree add OLD-SRC v0.1.0`, then a venv there with
`pip install -e .`).
To record a new figure, update `benchmarks/results.json` (by hand, or with
`benchmarks_table.record(...)` from a benchmark) and run
`python benchmarks/benchmarks_table.py`.

| what | target | peer | ours | ratio | reproduce | date |
|---|---|---|---|---|---|---|
"""


def number(v: float) -> str:
    """Three significant digits, without an exponent (1102, 47.3, 2.26, 0.0199)."""
    if v == 0:
        return "0"
    a = abs(v)
    decimals = 0 if a >= 100 else 1 if a >= 10 else 2 if a >= 1 else 3 if a >= 0.1 else 4
    return f"{v:.{decimals}f}"


def figures(values: list[float], unit: str) -> str:
    """One run: the value; several: their median and range."""
    if len(values) == 1:
        return f"{number(values[0])} {unit}"
    lo, hi = min(values), max(values)
    return (f"{number(statistics.median(values))} {unit} "
            f"({number(lo)}-{number(hi)}, {len(values)} runs)")


def ratios(row: dict) -> list[float]:
    """Our advantage over the peer in each run (a pair of figures per run), else of the
    medians; empty without peer figures."""
    ours, peer = row["ours"], row.get("peer_figures") or []
    if not peer:
        return []
    if len(peer) != len(ours):
        ours, peer = [statistics.median(ours)], [statistics.median(peer)]
    if row["better"] == "lower":
        return [p / o for o, p in zip(ours, peer)]
    return [o / p for o, p in zip(ours, peer)]


def ratio_cell(row: dict) -> str:
    r = ratios(row)
    span = row.get("ratio_range")
    if not r and not span:
        return "-"
    if not r:
        return f"{number(span[0])}-{number(span[1])}x"
    text = f"**{number(statistics.median(r))}x**"
    if span:
        return text + f" ({number(span[0])}-{number(span[1])})"
    if len(r) > 1:
        return text + f" ({number(min(r))}-{number(max(r))})"
    return text


def peer_cell(row: dict) -> str:
    if not row.get("peer"):
        return "-"
    if row.get("peer_figures"):
        return f"{row['peer']}: {figures(row['peer_figures'], row['unit'])}"
    return row["peer"]


def table_row(row: dict) -> str:
    cells = [row["what"], row.get("target", "-"), peer_cell(row),
             figures(row["ours"], row["unit"]), ratio_cell(row), f"`{row['command']}`",
             row["date"]]
    return "| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |"


def check_row(row: dict) -> None:
    """A row the page can show: the fields, the kinds and a real date."""
    need = ("key", "what", "unit", "better", "ours", "command", "date")
    missing = [k for k in need if k not in row]
    if missing:
        raise ValueError(f"row {row.get('key', '?')!r} lacks {', '.join(missing)}")
    if row["better"] not in ("lower", "higher"):
        raise ValueError(f"row {row['key']!r}: better must be 'lower' or 'higher'")
    if not row["ours"] or not all(isinstance(v, (int, float)) and v > 0
                                  for v in row["ours"] + (row.get("peer_figures") or [])):
        raise ValueError(f"row {row['key']!r}: figures must be positive numbers")
    if (row.get("peer_figures") or row.get("ratio_range")) and not row.get("peer"):
        raise ValueError(f"row {row['key']!r}: peer figures without a peer")
    dt.date.fromisoformat(row["date"])


def render(results: dict) -> str:
    rows = results["rows"]
    for row in rows:
        check_row(row)
    keys = [row["key"] for row in rows]
    if len(set(keys)) != len(keys):
        raise ValueError("results.json: every row needs its own key")
    return HEAD + "\n".join(table_row(row) for row in rows) + "\n"


def load(path: Path = RESULTS) -> dict:
    return json.loads(Path(path).read_text(encoding="utf-8"))


def write(path: Path, text: str) -> None:
    """Replace ``path`` atomically."""
    tmp = Path(f"{path}.tmp.{os.getpid()}")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def record(key: str, ours, peer_figures=None, date: str | None = None,
           results: Path = RESULTS, page: Path = PAGE) -> None:
    """Store a benchmark's new figures under row ``key`` (today's date unless given) and
    rewrite the page."""
    data = load(results)
    row = next((r for r in data["rows"] if r["key"] == key), None)
    if row is None:
        raise KeyError(f"{results}: no row {key!r}")
    row["ours"] = [float(v) for v in ours]
    if peer_figures is not None:
        row["peer_figures"] = [float(v) for v in peer_figures]
        row.pop("ratio_range", None)
    row["date"] = date or dt.datetime.now(dt.UTC).date().isoformat()
    text = render(data)
    write(results, json.dumps(data, indent=2) + "\n")
    write(page, text)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true",
                    help="write nothing; exit 1 if the page is not what this would write")
    ap.add_argument("--results", type=Path, default=RESULTS, help=argparse.SUPPRESS)
    ap.add_argument("--page", type=Path, default=PAGE, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    text = render(load(args.results))
    if args.check:
        have = args.page.read_text(encoding="utf-8") if args.page.exists() else ""
        if have != text:
            print(f"{args.page} is not what {RESULTS.relative_to(ROOT)} gives: run "
                  f"python benchmarks/benchmarks_table.py", file=sys.stderr)
            return 1
        print(f"{args.page}: up to date")
        return 0
    write(args.page, text)
    print(f"wrote {args.page}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
