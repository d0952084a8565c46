"""An image's line table (``images/<id>.lines.csv``): columns, values, times against
the POS."""
from __future__ import annotations

import numpy as np
import pandas as pd

from swathflow.ingest.csvtable import finite_columns, read_table
from swathflow.ingest.problems import Collector, first_rows


def plain_table(path) -> dict[str, np.ndarray] | None:
    """The columns of a line table that is a header row of distinct plain names and rows
    of finite numbers only, read by numpy (a few times cheaper than pandas); None for
    anything else (quotes, empty or non-numeric cells, ragged rows...), which pandas then
    reads, and the check reports cell by cell."""
    try:
        with open(path, encoding="utf-8") as f:
            names = [n.strip() for n in f.readline().split(",")]
            if len(set(names)) != len(names) or not all(names) or any(
                    q in n for n in names for q in "\"'"):
                return None
            v = np.loadtxt(f, delimiter=",", comments=None, dtype=float, ndmin=2)
    except (ValueError, OSError, UnicodeDecodeError):
        return None
    if v.shape[0] == 0 or v.shape[1] != len(names) or not np.isfinite(v).all():
        return None
    return {n: np.ascontiguousarray(v[:, k]) for k, n in enumerate(names)}


def line_table(entry, need, shape, traj, c: Collector) -> dict | None:
    lp = entry.lines_file
    if not lp.exists():
        c.add(lp, f"[[images]] id={entry.id!r}", "line table not found",
              "check the lines key of this image")
        return None
    cols = plain_table(lp)
    if cols is not None and all(col in cols for col in need):
        return _check_rows(lp, entry, cols, shape, traj, c)
    df = read_table(lp, need, c, "image line")
    if df is None:
        return None
    n0 = len(c.problems)
    check = list(need) + [col for col in df.columns if col not in need
                          and pd.api.types.is_numeric_dtype(df[col])]
    cols = finite_columns(df, lp, check, c, "every line needs finite numbers")
    return _check_rows(lp, entry, cols, shape, traj, c, n0)


def _check_rows(lp, entry, cols: dict, shape, traj, c: Collector, n0=None) -> dict | None:
    """Row count, line numbers and times of a line table's numeric ``cols``; the columns,
    or None when they have errors."""
    n0 = len(c.problems) if n0 is None else n0
    n = len(cols["line"])
    if shape is not None and n != shape[0]:
        c.add(lp, "", f"{n} rows but the image {entry.file.name} has {shape[0]} lines",
              "the line table needs exactly one row per image line")
    if np.isfinite(cols["line"]).all() and not np.array_equal(cols["line"], np.arange(n)):
        c.add(lp, f"column line, file row(s) {first_rows(cols['line'] != np.arange(n))}",
              "line numbers must be 0, 1, 2, ... in order", "one row per line, in order")
    t = cols["time"]
    if np.isfinite(t).all():
        line_times(lp, t, traj, c)
    return cols if len(c.problems) == n0 or all(
        p.level == "warning" for p in c.problems[n0:]) else None


def line_times(lp, t, traj, c: Collector) -> None:
    dec = np.diff(t) <= 0
    if dec.any():
        c.add(lp, f"column time, file row(s) {first_rows(np.r_[False, dec])}",
              "times must increase strictly from line to line",
              "sort the lines by time; remove duplicate lines")
        return
    if traj is None:
        return
    t0, t1 = traj.time[0], traj.time[-1]
    out = (t < t0) | (t > t1)
    if out.any():
        c.add(lp, f"column time, file row(s) {first_rows(out)}",
              f"{int(out.sum())} line time(s) outside the POS time span "
              f"[{t0:.3f}, {t1:.3f}] s (e.g. {t[out][0]:.3f} s)",
              "use a POS that covers the whole image (no extrapolation), or check "
              "the time scale (GPS seconds of week)")
        return
    i = np.clip(np.searchsorted(traj.time, t, side="right") - 1, 0, traj.time.size - 2)
    gap = traj.time[i + 1] - traj.time[i]
    if (gap > traj.max_gap).any():
        c.add(lp, f"column time, file row(s) {first_rows(gap > traj.max_gap)}",
              f"line times fall in a POS gap of {gap.max():.2f} s "
              f"(> max_gap {traj.max_gap} s)",
              "use a POS without gaps here, or raise [pos].max_gap")
        return
    # a gap shorter than max_gap is interpolated across: say so when it is unusual
    typical = traj.typical_step()
    odd = gap > max(5 * typical, 0.05)
    if odd.any():
        c.warn(lp, f"column time, file row(s) {first_rows(odd)}",
               f"{int(odd.sum())} line(s) fall in a POS gap of {gap[odd].max():.3f} s "
               f"(the POS rate is {1 / typical:.0f} Hz): interpolated across",
               "use a POS without gaps over this image if the motion is not smooth")
