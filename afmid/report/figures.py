"""A report figure on disk and on the page: PNG for the page, SVG beside it for publication.

Every figure a report writes is saved twice with the same stem (pinned): ``STEM.png`` (embedded in
``report.html``, so the page opens offline on its own) and ``STEM.svg`` (vector, for a paper or a poster),
linked under the figure as "SVG". The SVG carries no creation date, so the same figure gives the same file.
Point clouds that would make an SVG heavy are drawn with ``rasterized=True`` by their figure (the rest of the
figure stays vector).

One publication style for every report figure (:data:`PAPER_STYLE`, set by :func:`pyplot`): 8-pt text, axis
labels with units (nm, nN, µs), no top/right spines, a constrained layout, PNGs at :data:`FIGURE_DPI`; log axes
through :func:`log_axis`, whose tick labels do not overlap.
"""

from __future__ import annotations

import base64
import html
from pathlib import Path

#: The formats every report figure is written in, the first embedded in the page.
FIGURE_FORMATS = ("png", "svg")

#: Resolution of the PNGs (the SVG beside each is vector).
FIGURE_DPI = 200

#: Width (inches) of a figure that spans the page / a two-column paper's full width.
FULL_WIDTH = 7.0

#: The one style of the report's figures (matplotlib rcParams).
PAPER_STYLE = {
    "figure.dpi": 100, "savefig.dpi": FIGURE_DPI, "figure.constrained_layout.use": True,
    "font.size": 8, "axes.titlesize": 8.5, "axes.labelsize": 8, "xtick.labelsize": 7, "ytick.labelsize": 7,
    "legend.fontsize": 7, "legend.frameon": False, "axes.titleweight": "normal",
    "axes.spines.top": False, "axes.spines.right": False, "axes.grid": True, "grid.alpha": 0.25,
    "grid.linewidth": 0.5, "axes.linewidth": 0.7, "lines.linewidth": 1.2, "lines.markersize": 3,
    "xtick.major.width": 0.7, "ytick.major.width": 0.7, "xtick.direction": "out", "ytick.direction": "out",
    "svg.hashsalt": "afmid",  # the SVG's element ids do not change from run to run
    "svg.fonttype": "none",  # text stays text in the SVG (editable in a paper)
}


def pyplot():
    """``matplotlib.pyplot`` on the Agg backend with :data:`PAPER_STYLE` applied."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.rcParams.update(PAPER_STYLE)
    return plt


def plain_number(value: float, _pos=None) -> str:
    """A tick label without exponent or trailing zeros: 0.05, 0.1, 2, 300, 1e+04 only beyond 1e4."""
    if value == 0:
        return "0"
    if 1e-3 <= abs(value) < 1e5:
        return f"{value:.4g}"
    return f"{value:.0e}".replace("e+0", "e").replace("e-0", "e-")


def log_axis(ax, which: str = "y") -> None:
    """Put ``ax``'s ``which`` axis ("x" or "y") on a log scale with plain-number labels at the decades and, on a
    range under two decades, at 2x and 5x the decade only (all the minor ticks labelled would overlap)."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    axis = ax.yaxis if which == "y" else ax.xaxis
    (ax.set_yscale if which == "y" else ax.set_xscale)("log")
    axis.set_major_locator(LogLocator(base=10))
    axis.set_major_formatter(FuncFormatter(plain_number))
    low, high = (ax.get_ylim() if which == "y" else ax.get_xlim())
    if low > 0 and high / low < 100:
        axis.set_minor_locator(LogLocator(base=10, subs=(2.0, 5.0)))
        axis.set_minor_formatter(FuncFormatter(plain_number))
    else:
        axis.set_minor_formatter(NullFormatter())


def save_figure(fig, folder: Path, stem: str, dpi: float | None = None) -> str:
    """Write ``fig`` as ``folder/STEM.png`` (at ``dpi``, default :data:`FIGURE_DPI`) and ``folder/STEM.svg``,
    close it and return the PNG's file name.

    The figure is laid out and drawn once: one Agg drawing at the PNG's resolution solves the constrained
    layout (the costliest part, every text's extent) and renders the pixels the PNG is written from (the same
    bytes ``savefig`` writes, which would lay the figure out in a drawing of its own first); the layout is then
    frozen, so the SVG is the same figure with its elements in the same places, not a second solution at 72 dpi.
    """
    import matplotlib.image
    import matplotlib.pyplot as plt
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    folder = Path(folder)
    try:
        canvas = fig.canvas if isinstance(fig.canvas, FigureCanvasAgg) else FigureCanvasAgg(fig)
        shown_dpi = fig.get_dpi()
        fig.set_dpi(FIGURE_DPI if dpi is None else dpi)
        canvas.draw()
        fig.set_layout_engine("none")
        matplotlib.image.imsave(folder / f"{stem}.png", canvas.buffer_rgba(), format="png", origin="upper",
                                dpi=fig.get_dpi())
        fig.set_dpi(shown_dpi)
        fig.savefig(folder / f"{stem}.svg", format="svg", metadata={"Date": None})
    finally:
        plt.close(fig)
    return f"{stem}.png"


def svg_name(png_name: str) -> str:
    """The SVG written beside a figure's PNG (same stem)."""
    return str(Path(png_name).with_suffix(".svg"))


def figure_html(folder: Path, png_name: str, caption: str) -> str:
    """A ``<figure>``: the PNG embedded (base64), the caption, and a link to the SVG beside it in the folder."""
    data = base64.b64encode((Path(folder) / png_name).read_bytes()).decode()
    svg = html.escape(svg_name(png_name), quote=True)
    return (f'<figure><img src="data:image/png;base64,{data}" alt="{html.escape(caption)}">'
            f'<figcaption>{html.escape(caption)} <a class="svg" href="{svg}">SVG</a></figcaption></figure>')
