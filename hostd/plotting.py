"""Small plotting helpers shared by the reports and benchmarks (matplotlib, imported lazily)."""

from __future__ import annotations

import numpy as np

# what Agg and matplotlib's vector backends write, by the file's extension (savefig honours it)
IMAGE_SUFFIXES = (".png", ".pdf", ".svg", ".svgz", ".jpg", ".jpeg", ".webp", ".tif", ".tiff", ".eps", ".ps")


def check_image_path(path: str, option: str) -> None:
    """Refuse, before any work, a figure name whose extension no backend writes (a plot of
    minutes' work must not fail at its last step); one line that says what to use."""
    from pathlib import Path

    from hostd.errors import ConfigError

    suffix = Path(path).suffix.lower()
    if suffix not in IMAGE_SUFFIXES:
        raise ConfigError(f"{option} {path}: the figure is written in the format its extension names; "
                          f"{suffix or 'no extension'} is none of {', '.join(IMAGE_SUFFIXES)} "
                          f"(e.g. {Path(path).with_suffix('.png').name})")


def place_labels(ax, items: list[tuple[float, float, str]], fontsize: float = 6.5,
                 draw: bool = True, avoid: list | None = None) -> list:
    """Annotate points without overlaps: each label takes the first of a few offsets where its
    box (measured by the renderer, not estimated) stays inside the axes and overlaps no earlier
    label, no box in `avoid` and no point; a label that finds no free place is left out (its
    point stays, the CSV holds every value). The figure's layout must be final (draw=True draws
    it first; draw=False when the caller has laid it out). Returns the boxes placed."""
    fig = ax.figure
    if draw:
        fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    to_px = ax.transData.transform
    placed = list(avoid or [])
    points = [tuple(to_px((x, y))) for x, y, _ in items]
    offsets = ((4, 3), (4, -4), (-4, 3), (-4, -4), (6, 10), (6, -10))
    area = ax.bbox
    for (x, y, text), _p in zip(items, points, strict=True):
        for dx, dy in offsets:
            ann = ax.annotate(text, (x, y), xytext=(dx, dy), textcoords="offset points", fontsize=fontsize,
                              ha="left" if dx >= 0 else "right", va="bottom" if dy >= 0 else "top")
            box = ann.get_window_extent(renderer)
            inside = (area.x0 <= box.x0 and box.x1 <= area.x1 and area.y0 <= box.y0 and box.y1 <= area.y1)
            free = inside and not any(box.overlaps(b) for b in placed) and not any(
                box.x0 - 2 <= qx <= box.x1 + 2 and box.y0 - 2 <= qy <= box.y1 + 2 for qx, qy in points)
            if free:
                placed.append(box)
                break
            ann.remove()
    return placed


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
