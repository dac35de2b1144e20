"""Height profiles from files: CSV/TXT (one or two columns, instrument headers tolerated) and .npy.

Everything is converted to micrometres on a uniform grid; a patch of the chosen length is
taken from the start (or an offset) of the profile.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hostd.errors import ProfileError

UNITS_TO_UM = {"m": 1e6, "mm": 1e3, "um": 1.0, "µm": 1.0, "nm": 1e-3}
_SPLIT = re.compile(r"[,;\s]+")
MAX_ROWS = 50_000_000


@dataclass(frozen=True)
class Profile:
    """Uniformly sampled heights in µm with their spacing in µm."""

    heights_um: np.ndarray
    spacing_um: float
    source: str = ""

    @property
    def n(self) -> int:
        return int(self.heights_um.size)

    @property
    def length_mm(self) -> float:
        return self.n * self.spacing_um / 1000.0


@dataclass(frozen=True)
class LoadOptions:
    """The loader options every profile-reading command shares (see `hostd encode --help`)."""

    x_unit: str = "um"
    y_unit: str = "um"
    spacing: float | None = None  # in x_unit: for one-column data, or the resampling target
    length_mm: float | None = 10.0  # patch length; None = whole profile
    offset_mm: float = 0.0
    detrend: str = "none"  # none | mean | linear


def unit_factor(unit: str, axis: str) -> float:
    try:
        return UNITS_TO_UM[unit]
    except KeyError:
        raise ProfileError(
            f"unknown {axis} unit {unit!r}: use one of m, mm, um, nm"
        ) from None


def read_columns(path: Path) -> np.ndarray:
    """Numeric rows of a text file as an (n, 1) or (n, 2) array; non-numeric lines are skipped."""
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise ProfileError(f"cannot read {path}: {exc.strerror or exc}") from None
    rows: list[list[float]] = []
    widths: dict[int, int] = {}
    for raw in text.splitlines():
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        toks = [t for t in _SPLIT.split(line) if t]
        try:
            vals = [float(t) for t in toks]
        except ValueError:
            continue  # header, metadata or comment line (e.g. a Dektak export's preamble)
        if len(vals) in (1, 2):
            rows.append(vals)
            widths[len(vals)] = widths.get(len(vals), 0) + 1
        if len(rows) > MAX_ROWS:
            raise ProfileError(f"{path}: more than {MAX_ROWS} rows")
    if not rows:
        raise ProfileError(f"{path}: no numeric rows of one or two columns found")
    width = max(widths, key=lambda w: widths[w])
    arr = np.array([r for r in rows if len(r) == width], dtype=np.float64)
    return arr.reshape(-1, width)


def load_array(path: str | Path) -> np.ndarray:
    p = Path(path)
    if p.suffix.lower() == ".npy":
        try:
            arr = np.load(p, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise ProfileError(f"cannot read {p} as .npy: {exc}") from None
        arr = np.asarray(arr, dtype=np.float64)
        if arr.ndim == 1:
            return arr.reshape(-1, 1)
        if arr.ndim == 2 and arr.shape[1] in (1, 2):
            return arr
        if arr.ndim == 2 and arr.shape[0] == 2:
            return arr.T.copy()
        raise ProfileError(f"{p}: expected heights (N,) or (N, 2) x/height columns, got {arr.shape}")
    if not p.exists():
        raise ProfileError(f"no such profile file: {p}")
    return read_columns(p)


def load_profile(path: str | Path, opts: LoadOptions | None = None) -> Profile:
    """Load, convert units, resample to a uniform grid and cut the patch."""
    opts = opts or LoadOptions()
    fx = unit_factor(opts.x_unit, "x")
    fy = unit_factor(opts.y_unit, "y")
    arr = load_array(path)
    if not np.all(np.isfinite(arr)):
        bad = int(np.count_nonzero(~np.isfinite(arr).all(axis=1)))
        raise ProfileError(f"{path}: {bad} rows hold NaN or Inf; clean the file first")
    if arr.shape[1] == 1:
        if opts.spacing is None:
            raise ProfileError(f"{path} has one column of heights: give the spacing with --spacing")
        dx_um = opts.spacing * fx
        _check_spacing(dx_um)
        y_um = arr[:, 0] * fy
    else:
        x_um = arr[:, 0] * fx
        y_um = arr[:, 1] * fy
        x_um, y_um = _sorted_unique(x_um, y_um, str(path))
        dx_um = opts.spacing * fx if opts.spacing else (x_um[-1] - x_um[0]) / (x_um.size - 1)
        _check_spacing(dx_um)
        y_um = _resample(x_um, y_um, dx_um)
    prof = cut_patch(y_um, dx_um, opts, str(path))
    return prof


def _check_spacing(dx_um: float) -> None:
    if not (math.isfinite(dx_um) and dx_um > 0):
        raise ProfileError(f"spacing must be a finite number > 0, got {dx_um} µm")


def _sorted_unique(x: np.ndarray, y: np.ndarray, name: str) -> tuple[np.ndarray, np.ndarray]:
    order = np.argsort(x, kind="stable")
    x, y = x[order], y[order]
    keep = np.concatenate([[True], np.diff(x) > 0])
    x, y = x[keep], y[keep]
    if x.size < 2:
        raise ProfileError(f"{name}: needs at least two distinct x positions")
    return x, y


def _resample(x_um: np.ndarray, y_um: np.ndarray, dx_um: float) -> np.ndarray:
    """Linear interpolation onto x0 + i dx; a no-op for data already uniform at dx."""
    span = x_um[-1] - x_um[0]
    count = math.floor(span / dx_um * (1 + 1e-9)) + 1
    grid = x_um[0] + dx_um * np.arange(count)
    return np.interp(grid, x_um, y_um)


def cut_patch(y_um: np.ndarray, dx_um: float, opts: LoadOptions, name: str = "") -> Profile:
    """Take length_mm from offset_mm; the whole rest if length_mm is None or longer than the data.

    The patch length is N * spacing (the DCT's period convention), so N = round(L / dx).
    """
    start = round(opts.offset_mm * 1000.0 / dx_um)
    if start < 0 or start >= y_um.size - 1:
        raise ProfileError(f"{name}: offset {opts.offset_mm} mm is outside the profile")
    avail = y_um.size - start
    if opts.length_mm is None:
        n = avail
    else:
        if not (math.isfinite(opts.length_mm) and opts.length_mm > 0):
            raise ProfileError(f"--length-mm must be > 0, got {opts.length_mm}")
        n = min(avail, round(opts.length_mm * 1000.0 / dx_um))
    if n < 2:
        raise ProfileError(f"{name}: the patch holds fewer than 2 samples")
    y = np.array(y_um[start : start + n], dtype=np.float64)
    if opts.detrend == "mean":
        y -= y.mean()
    elif opts.detrend == "linear":
        t = np.arange(n, dtype=np.float64)
        y -= np.polyval(np.polyfit(t, y, 1), t)
    elif opts.detrend != "none":
        raise ProfileError(f"unknown --detrend {opts.detrend!r}: use none, mean or linear")
    return Profile(heights_um=y, spacing_um=float(dx_um), source=name)
