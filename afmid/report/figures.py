"""A report figure on disk and on the page: PNG for the page, SVG beside it for publication.

Every figure a report writes is saved twice with the same stem (pinned, issue 15): ``STEM.png`` (embedded in
``report.html``, so the page opens offline on its own) and ``STEM.svg`` (vector, for a paper or a poster),
linked under the figure as "SVG". The SVG carries no creation date, so the same figure gives the same file.
Point clouds that would make an SVG heavy are drawn with ``rasterized=True`` by their figure (the rest of the
figure stays vector).
"""

from __future__ import annotations

import base64
import html
from pathlib import Path

#: The formats every report figure is written in, the first embedded in the page.
FIGURE_FORMATS = ("png", "svg")


def save_figure(fig, folder: Path, stem: str, dpi: float | None = None) -> str:
    """Write ``fig`` as ``folder/STEM.png`` (at ``dpi``, default the figure's) and ``folder/STEM.svg``, close
    it and return the PNG's file name."""
    import matplotlib.pyplot as plt

    folder = Path(folder)
    try:
        fig.savefig(folder / f"{stem}.png", **({} if dpi is None else {"dpi": dpi}))
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
