"""What every report figure shares, on matplotlib's object-oriented API: a
:class:`~matplotlib.figure.Figure` on its own Agg canvas (no pyplot, no global state),
written as inline SVG (the HTML reports, text kept as text) or PNG; map frames in a
projected CRS with full coordinates in metres, a scale bar and a north arrow.

Imported only where a report is made (matplotlib's import costs about half a second), never
at package import. Output is reproducible: SVG ids are salted with a fixed string and no
date is written, so the same figure gives the same bytes.
"""
from __future__ import annotations

import contextlib
import io
import math
import threading

import matplotlib
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter
from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

from swathflow.io import atomic_path

__all__ = ["figure", "svg", "write_png", "map_frame", "scale_bar", "north_arrow",
           "nice_length", "RC", "DIRECTION_COLOURS"]

#: matplotlib settings of every report figure (applied with ``matplotlib.rc_context``,
#: never to the process): reproducible SVG, text as text, compact fonts
RC = {"svg.hashsalt": "swathflow", "svg.fonttype": "none", "font.size": 9,
      "axes.titlesize": 10, "axes.labelsize": 9, "legend.fontsize": 8,
      "figure.dpi": 100, "savefig.dpi": 100, "axes.titlelocation": "left"}
#: the swing directions' colours in every figure
DIRECTION_COLOURS = {"L": "#1f77b4", "R": "#d62728"}


#: matplotlib's rcParams are one dictionary a process: two threads drawing reports at once
#: (the flow draws them beside its other work) would each restore the other's settings on
#: leaving ``rc_context``, leaking RC into the user's matplotlib; one at a time
_RC_LOCK = threading.RLock()


@contextlib.contextmanager
def report_style():
    """:data:`RC` in force on this thread's figure work, the user's settings restored after
    (one report figure at a time in the process)."""
    with _RC_LOCK, matplotlib.rc_context(RC):
        yield


def figure(width: float, height: float, margins=None, wspace: float = 0.2,
           hspace: float = 0.2, **kw) -> Figure:
    """A figure of ``width`` x ``height`` inches on its own Agg canvas: constrained layout,
    or with ``margins`` (left, right, bottom, top in inches) fixed margins (half the
    drawing time: constrained layout measures every tick label again and again)."""
    layout = None if margins is not None else kw.pop("layout", "constrained")
    with report_style():
        fig = Figure(figsize=(width, height), layout=layout, **kw)
    if margins is not None:
        left, right, bottom, top = margins
        fig.subplots_adjust(left=left / width, right=1 - right / width,
                            bottom=bottom / height, top=1 - top / height,
                            wspace=wspace, hspace=hspace)
    FigureCanvasAgg(fig)
    return fig


def svg(fig: Figure) -> str:
    """The figure as SVG text for inlining in HTML (no XML prolog, no date)."""
    buf = io.StringIO()
    with report_style():
        fig.savefig(buf, format="svg", metadata={"Date": None, "Creator": None})
    text = buf.getvalue()
    text = text[text.index("<svg"):]
    # inline in HTML: the parser knows the SVG and xlink names; the RDF block says nothing
    text = text.replace(' xmlns:xlink="http://www.w3.org/1999/xlink"', "", 1)
    a, b = text.find("<metadata>"), text.find("</metadata>")
    return text[:a] + text[b + len("</metadata>"):] if 0 <= a < b else text


#: Pillow's PNG options of a written figure: zlib level 3 encoded the mosaic's report
#: picture's map 2.5x faster than Pillow's default 6 (65 against 161 ms), 1 % larger
PNG_OPTIONS = {"compress_level": 3}


def write_png(fig: Figure, path) -> str:
    """Write the figure as PNG to ``path`` atomically (:data:`PNG_OPTIONS`); returns the
    path."""
    import os
    path = os.fspath(path)
    with report_style(), atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png", metadata={"Software": None}, pil_kwargs=PNG_OPTIONS)
    return path


def nice_length(span: float) -> float:
    """A round length (1, 2 or 5 times a power of ten) near a fifth of ``span``."""
    target = max(span, 1e-9) / 5.0
    k = 10 ** math.floor(math.log10(target))
    return next(m * k for m in (5, 2, 1) if m * k <= target)


def _metres(v: float) -> str:
    return f"{v:g} m" if v < 1000 else f"{v / 1000:g} km"


def scale_bar(ax, length: float | None = None, loc: str = "lower left") -> float:
    """A scale bar of ``length`` ground units (m; default: a round fifth of the axes'
    width) in the axes' corner ``loc``; returns the length."""
    x0, x1 = ax.get_xlim()
    length = nice_length(abs(x1 - x0)) if length is None else length
    bar = AnchoredSizeBar(ax.transData, length, _metres(length), loc, pad=0.4,
                          borderpad=0.6, sep=3, frameon=True, size_vertical=0,
                          fontproperties={"size": 8})
    bar.patch.set_alpha(0.8)
    ax.add_artist(bar)
    return length


def north_arrow(ax, label: str = "N") -> None:
    """A north arrow in the axes' upper right corner (the axes' y axis points north:
    grid north of a projected CRS)."""
    ax.annotate(label, xy=(0.95, 0.95), xytext=(0.95, 0.80), xycoords="axes fraction",
                textcoords="axes fraction", ha="center", va="center", fontsize=10,
                fontweight="bold",
                arrowprops=dict(arrowstyle="-|>", facecolor="black", lw=1.2),
                bbox=dict(boxstyle="round,pad=0.15", fc="white", ec="none", alpha=0.8))


def map_frame(ax, crs_name: str, units: str = "m", bar: bool = True) -> None:
    """Make ``ax`` a map frame: equal scale, axes labelled easting/northing in ``units`` of
    ``crs_name`` with full coordinates on the ticks (no offset), a scale bar and a north
    arrow."""
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel(f"easting ({units}), {crs_name}")
    ax.set_ylabel(f"northing ({units})")
    from matplotlib.ticker import MaxNLocator
    ax.xaxis.set_major_locator(MaxNLocator(nbins=6, steps=[1, 2, 2.5, 5, 10]))
    ax.yaxis.set_major_locator(MaxNLocator(nbins=4, steps=[1, 2, 2.5, 5, 10]))
    fmt = FuncFormatter(lambda v, _: f"{v:,.0f}".replace(",", "\u2009"))
    ax.xaxis.set_major_formatter(fmt)
    ax.yaxis.set_major_formatter(fmt)
    ax.tick_params(axis="both", labelsize=7.5)
    ax.tick_params(axis="y", labelrotation=90)
    for t in ax.get_yticklabels():
        t.set_verticalalignment("center")
    if bar:
        scale_bar(ax)
    north_arrow(ax)
