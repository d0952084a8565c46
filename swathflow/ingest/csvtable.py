"""The mission's CSV tables (``gcp.csv``, the images' line tables) read one way: by pandas,
column names stripped, the required columns and every numeric cell checked, each problem
added to the mission check's :class:`~swathflow.ingest.problems.Collector` with the file
and its rows named."""
from __future__ import annotations

import numpy as np
import pandas as pd

from swathflow.ingest.problems import Collector, first_rows


def read_table(path, need, c: Collector, rows: str, dtype=None) -> pd.DataFrame | None:
    """The table at ``path`` with the columns ``need`` among its own, or None when it
    cannot be read as CSV or lacks one (the problem added; ``rows`` says what a row of it
    is, for the fix)."""
    try:
        df = pd.read_csv(path, dtype=dtype)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError,
            ValueError, OSError) as exc:
        c.add(path, "", f"cannot be read as CSV: {str(exc).splitlines()[0][:200]}",
              f"write a header row {','.join(need)} and one row per {rows}")
        return None
    df.columns = [str(col).strip() for col in df.columns]
    miss = [col for col in need if col not in df.columns]
    if miss:
        c.add(path, "header", f"missing column(s) {', '.join(miss)}",
              f"the header must contain {','.join(need)}")
        return None
    return df


def finite_columns(df: pd.DataFrame, path, names, c: Collector,
                   fix: str) -> dict[str, np.ndarray]:
    """The columns ``names`` of ``df`` as float arrays; their missing, NaN or non-numeric
    cells each column's problem (file rows named, ``fix`` told)."""
    cols = {}
    for col in dict.fromkeys(names):
        v = pd.to_numeric(df[col], errors="coerce").to_numpy(float)
        bad = ~np.isfinite(v)
        if bad.any():
            c.add(path, f"column {col}, file row(s) {first_rows(bad)}",
                  f"{int(bad.sum())} missing, NaN or non-numeric value(s)", fix)
        cols[col] = v
    return cols
