"""Small plotting helpers shared by the reports and benchmarks (matplotlib, imported lazily)."""

from __future__ import annotations

import numpy as np


def place_labels(ax, items: list[tuple[float, float, str]], fontsize: float = 6.5,
                 draw: bool = True) -> None:
    """Annotate points without overlaps: each label takes the first of a few offsets whose box
    (estimated in pixels) does not overlap an earlier label or point; a label that finds no
    free place is left out (its point stays, the CSV holds every value). The figure is drawn
    first for its final pixel scale; draw=False when the caller has just drawn it (several
    axes of one figure need one draw)."""
    fig = ax.figure
    if draw:
        fig.canvas.draw()
    to_px = ax.transData.transform
    char_w, line_h = 0.62 * fontsize * fig.dpi / 72, 1.25 * fontsize * fig.dpi / 72
    placed: list[tuple[float, float, float, float]] = []
    points = [tuple(to_px((x, y))) for x, y, _ in items]
    offsets = ((4, 3), (4, -10), (-8, 5), (-8, -12), (6, 10), (6, -16))
    for (x, y, text), (px, py) in zip(items, points, strict=True):
        w = char_w * len(text)
        for dx, dy in offsets:
            x0 = px + dx if dx >= 0 else px + dx - w
            box = (x0, py + dy, x0 + w, py + dy + line_h)
            hits_label = any(not (box[2] < b[0] or box[0] > b[2] or box[3] < b[1] or box[1] > b[3])
                             for b in placed)
            hits_point = any(box[0] - 2 <= qx <= box[2] + 2 and box[1] - 2 <= qy <= box[3] + 2
                             for qx, qy in points)
            inside = (ax.bbox.x0 <= box[0] and box[2] <= ax.bbox.x1
                      and ax.bbox.y0 <= box[1] and box[3] <= ax.bbox.y1)
            if inside and not (hits_label or hits_point):
                placed.append(box)
                ax.annotate(text, (x, y), xytext=(dx if dx >= 0 else dx - w * 72 / fig.dpi, dy),
                            textcoords="offset points", fontsize=fontsize)
                break


def log_byte_axis(ax, lo: float, hi: float) -> None:
    """A logarithmic x axis over lo..hi (bytes) with plain-number ticks that do not collide:
    the finest of 1 / 1-3 / 1-2-5 / finer steps per decade that gives at most 7 ticks (at
    least 3 where possible); no minor tick labels (matplotlib labels those on a short log
    axis, and they overlap)."""
    from matplotlib.ticker import FixedLocator, FuncFormatter, NullFormatter

    ax.set_xscale("log")
    lo, hi = max(lo, 1.0), max(hi, lo * 1.2)
    x0, x1 = lo / 1.15, hi * 1.15
    ax.set_xlim(x0, x1)
    decades = range(int(np.floor(np.log10(x0))), int(np.ceil(np.log10(x1))) + 1)
    ticks: list[float] = []
    for steps in ((1,), (1, 3), (1, 2, 5), (1, 1.5, 2, 3, 5, 7), (1, 1.2, 1.5, 2, 2.5, 3, 4, 5, 6, 7, 8, 9)):
        t = [m * 10.0 ** d for d in decades for m in steps if x0 <= m * 10.0 ** d <= x1]
        if len(t) > 7:
            break
        ticks = t
        if len(t) >= 3 and steps == (1, 2, 5):
            break
    ax.xaxis.set_major_locator(FixedLocator(ticks))
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _pos: f"{v:g}"))
    ax.xaxis.set_minor_formatter(NullFormatter())
