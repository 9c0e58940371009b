"""afmid.report.figures.save_figure: one layout and one drawing for both files, the PNG as savefig writes it."""

from __future__ import annotations

import re

import numpy as np
import pytest

from afmid.report.figures import FIGURE_DPI, pyplot, save_figure


def _figure():
    """A figure whose constrained layout depends on text extents (long labels, a title, a figure legend)."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(7.0, 2.6))
    x = np.linspace(0.0, 1.0, 50)
    for k, ax in enumerate(axes):
        ax.plot(x, np.sin(2 * np.pi * (k + 1) * x), label=f"curve {k}")
        ax.set(xlabel="separation z (nm)", ylabel="force on tip (nN, repulsive +)", title=f"({k}) a title")
    fig.legend(loc="outside lower center", ncol=2)
    return fig


def _svg_axes_boxes(svg: str) -> list[tuple[float, ...]]:
    """(x0, y0, x1, y1) in SVG points of each axes' background patch, y downward from the top."""
    boxes = []
    for match in re.finditer(r'<g id="axes_\d+">\s*<g id="patch_\d+">\s*<path d="([^"]+)"', svg):
        numbers = [float(v) for v in re.findall(r"-?\d+(?:\.\d+)?", match.group(1))]
        xs, ys = numbers[0::2], numbers[1::2]
        boxes.append((min(xs), min(ys), max(xs), max(ys)))
    return boxes


def test_the_png_has_the_bytes_savefig_writes(tmp_path):
    """Drawn once on the Agg canvas and written from its pixels: the same file as ``savefig`` at the same dpi."""
    ours, theirs = tmp_path / "ours", tmp_path / "theirs"
    ours.mkdir()
    theirs.mkdir()
    assert save_figure(_figure(), ours, "figure") == "figure.png"
    reference = _figure()
    reference.savefig(theirs / "figure.png", dpi=FIGURE_DPI)
    pyplot().close(reference)
    assert (ours / "figure.png").read_bytes() == (theirs / "figure.png").read_bytes()


def test_the_svg_keeps_the_layout_of_the_png(tmp_path):
    """The layout is solved once, at the PNG's resolution, and frozen: each axes of the SVG stands where that
    solution puts it (a reference figure laid out at :data:`FIGURE_DPI`), not where a second solution at the SVG's
    72 dpi would (text extents differ with the resolution: on the demo's figures the edges move by 0.2-6 pt). The
    SVG writes points to at most 6 decimals, hence the bound 0.01 pt."""
    fig = _figure()
    save_figure(fig, tmp_path, "figure")
    reference = _figure()
    reference.set_dpi(FIGURE_DPI)
    reference.draw_without_rendering()
    width, height = reference.get_size_inches() * 72.0
    boxes = _svg_axes_boxes((tmp_path / "figure.svg").read_text(encoding="utf-8"))
    assert len(boxes) == len(reference.axes) == 2
    for ax, box in zip(reference.axes, boxes):
        pos = ax.get_position()
        assert box == pytest.approx((pos.x0 * width, (1 - pos.y1) * height, pos.x1 * width, (1 - pos.y0) * height),
                                    abs=0.01)
    pyplot().close(reference)
    assert fig.get_dpi() == pytest.approx(100.0)  # the figure's own dpi given back after the PNG's drawing
