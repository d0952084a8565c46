"""The HTML reports' pages: Jinja2 templates shipped as package data
(``swathflow/templates/*.html.j2``), autoescaped; figures go in as inline SVG (marked safe
where they are made). Filters for the tables: ``num`` (a number with ``nd`` decimals, ``-``
for missing), ``yesno``."""
from __future__ import annotations

import functools
import math

__all__ = ["render", "num", "safe", "table"]


def num(x, nd: int = 3) -> str:
    """A table cell's text: ``-`` for None/NaN, integers as they are, else ``nd`` decimals
    (scientific for very small or large values)."""
    import numpy as np
    if x is None or (isinstance(x, (float, np.floating)) and not math.isfinite(x)):
        return "-"
    if isinstance(x, (bool, np.bool_)):
        return "yes" if x else ""
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    if isinstance(x, (list, tuple)):
        return ", ".join(num(v, nd) for v in x)
    try:
        v = float(x)
    except (TypeError, ValueError):
        return str(x)
    v += 0.0                               # no "-0.000"
    if v != 0 and (abs(v) < 10 ** -nd or abs(v) >= 1e6):
        return f"{v:.{nd}e}"
    return f"{v:.{nd}f}"


@functools.lru_cache(maxsize=1)
def _environment():
    import jinja2
    env = jinja2.Environment(loader=jinja2.PackageLoader("swathflow", "templates"),
                             autoescape=True, undefined=jinja2.StrictUndefined,
                             trim_blocks=True, lstrip_blocks=True, keep_trailing_newline=True)
    env.filters["num"] = num
    return env


def safe(html: str):
    """``html`` (made by our own code: an SVG figure, a rendered section) marked safe for
    the templates."""
    import markupsafe
    return markupsafe.Markup(html)


def render(template: str, **context) -> str:
    """The template ``template`` (in swathflow/templates) rendered with ``context``."""
    return _environment().get_template(template).render(**context)


def table(df, nd: int = 3, left=(), units: dict | None = None) -> dict:
    """A DataFrame as the templates' table (macro ``table`` of macros.html.j2): header
    cells (name, unit, left-aligned) and rows of (text, left-aligned) cells."""
    units = units or {}
    cols = list(df.columns)
    head = [(str(c), units.get(c, ""), c in left) for c in cols]
    rows = [[(str(v) if c in left else num(v, nd), c in left) for c, v in zip(cols, r)]
            for r in df.itertuples(index=False)]
    return {"head": head, "rows": rows}
