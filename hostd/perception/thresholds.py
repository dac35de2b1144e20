"""Vibrotactile detection-threshold curves b(f): a table, linear interpolation, constant outside."""

from __future__ import annotations

import functools
import hashlib
import os
import struct
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hostd import paths
from hostd.errors import ThresholdError, ThresholdNotFound

MAX_POINTS = 4096


@dataclass(frozen=True, eq=False)
class ThresholdCurve:
    """Detection threshold in µm (peak) against frequency in Hz.

    Between table points the threshold is interpolated linearly, as in the paper; outside the
    table it is held at the first or last value.
    """

    freq_hz: np.ndarray
    threshold_um: np.ndarray
    name: str = "custom"
    _id: bytes = field(init=False, repr=False)
    _slopes: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        f = np.array(self.freq_hz, dtype=np.float64).reshape(-1)
        b = np.array(self.threshold_um, dtype=np.float64).reshape(-1)
        _validate(f, b, self.name)
        f.setflags(write=False)
        b.setflags(write=False)
        object.__setattr__(self, "freq_hz", f)
        object.__setattr__(self, "threshold_um", b)
        object.__setattr__(self, "_id", curve_id_bytes(f, b))
        # per-segment slopes (b_{j+1} - b_j) / (f_{j+1} - f_j), as np.interp computes them
        slopes = np.divide(np.subtract(b[1:], b[:-1]), np.subtract(f[1:], f[:-1])) if f.size > 1 \
            else np.zeros(0)
        object.__setattr__(self, "_slopes", slopes)

    def __call__(self, f_hz: np.ndarray | float) -> np.ndarray:
        """b(f) in µm; f may be any shape.

        np.interp's formula, b_j + s_j (f - f_j) with s_j = (b_{j+1} - b_j) / (f_{j+1} - f_j),
        written as separate elementwise operations so that no compiler can fuse them into a
        multiply-add: b(f_k) reaches stream bytes (the reference sums, the shaped steps) and
        must be the same bits on every CPU.
        """
        f = np.asarray(f_hz, dtype=np.float64)
        xp, fp = self.freq_hz, self.threshold_um
        if xp.size == 1:
            return np.full(f.shape, fp[0])[()]
        j = np.minimum(np.maximum(np.searchsorted(xp, f, side="right") - 1, 0), xp.size - 2)
        x0 = xp[j]
        y0 = fp[j]
        out = np.add(np.multiply(self._slopes[j], np.subtract(f, x0)), y0)
        out = np.where(f == x0, y0, out)
        out = np.where(f <= xp[0], fp[0], np.where(f >= xp[-1], fp[-1], out))
        if np.isnan(out).any():
            raise ThresholdError("threshold asked at a NaN frequency")
        return out[()]

    @property
    def id_bytes(self) -> bytes:
        """8-byte identifier: the first 8 bytes of SHA-256 over the canonical table."""
        return self._id

    @property
    def curve_id(self) -> str:
        return self._id.hex()

    def to_bytes(self) -> bytes:
        """Serialized table for embedding in a stream: u16 count, then (f64 Hz, f64 µm) pairs."""
        return canonical_table(self.freq_hz, self.threshold_um)


def canonical_table(freq_hz: np.ndarray, threshold_um: np.ndarray) -> bytes:
    pairs = np.empty((freq_hz.size, 2), dtype="<f8")
    pairs[:, 0] = freq_hz
    pairs[:, 1] = threshold_um
    return struct.pack("<H", freq_hz.size) + pairs.tobytes()


def curve_id_bytes(freq_hz: np.ndarray, threshold_um: np.ndarray) -> bytes:
    return hashlib.sha256(canonical_table(freq_hz, threshold_um)).digest()[:8]


def _validate(f: np.ndarray, b: np.ndarray, name: str) -> None:
    if f.size != b.size:
        raise ThresholdError(f"{name}: frequency and threshold columns differ in length")
    if f.size < 1:
        raise ThresholdError(f"{name}: a threshold curve needs at least one point")
    if f.size > MAX_POINTS:
        raise ThresholdError(f"{name}: more than {MAX_POINTS} points")
    if not (np.all(np.isfinite(f)) and np.all(np.isfinite(b))):
        raise ThresholdError(f"{name}: every frequency and threshold must be a finite number")
    if np.any(np.diff(f) <= 0):
        raise ThresholdError(f"{name}: frequencies must be strictly increasing")
    if np.any(f < 0):
        raise ThresholdError(f"{name}: frequencies must be >= 0 Hz")
    if np.any(b <= 0):
        raise ThresholdError(f"{name}: thresholds must be > 0 µm")


def from_bytes(data: bytes, name: str = "embedded") -> ThresholdCurve:
    """Inverse of ThresholdCurve.to_bytes; validates like a CSV load."""
    if len(data) < 2:
        raise ThresholdError(f"{name}: threshold table truncated")
    (count,) = struct.unpack_from("<H", data)
    if count < 1 or len(data) != 2 + 16 * count:
        raise ThresholdError(f"{name}: threshold table has a wrong size")
    pairs = np.frombuffer(data, dtype="<f8", offset=2).reshape(count, 2)
    return ThresholdCurve(pairs[:, 0].copy(), pairs[:, 1].copy(), name=name)


def load_csv(path: str | Path) -> ThresholdCurve:
    """Load a curve from CSV: lines 'frequency_hz,threshold_um'; '#' comments and a header line.

    A header that names its columns (frequency_hz, threshold_um, and others such as the
    interval ci_low_um, ci_high_um that `hostd experiment threshold` writes) selects those two
    by name and ignores the rest. (A command's --thresholds also takes a calibration file:
    hostd.perception.calibration.load_curve reads either.)"""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ThresholdNotFound(f"no such threshold curve: {p}") from None
    except OSError as exc:
        raise ThresholdError(f"cannot read threshold curve {p}: {exc.strerror or exc}") from None
    except UnicodeDecodeError:
        raise ThresholdError(f"{p}: not a text file (a CSV 'frequency_hz,threshold_um' expected)") from None
    f: list[float] = []
    b: list[float] = []
    named: tuple[int, int] | None = None
    width = 2
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        parts = [s.strip() for s in line.replace(";", ",").replace("\t", ",").split(",")]
        if named is None:
            parts = [s for s in parts if s]
        if named is None and not f and "frequency_hz" in parts and "threshold_um" in parts:
            named = (parts.index("frequency_hz"), parts.index("threshold_um"))
            width = len(parts)
            continue
        if named is not None:
            if len(parts) != width:
                raise ThresholdError(f"{p}:{lineno}: expected {width} columns as the header names")
            parts = [parts[named[0]], parts[named[1]]]
            if not parts[1]:
                raise ThresholdError(f"{p}:{lineno}: missing threshold_um at {parts[0] or '?'} Hz: "
                                     "give a number > 0, or remove the row")
        elif len(parts) != 2:
            raise ThresholdError(f"{p}:{lineno}: expected 'frequency_hz,threshold_um'")
        try:
            fv, bv = float(parts[0]), float(parts[1])
        except ValueError:
            if not f and named is None:  # a header line before the first point
                continue
            raise ThresholdError(f"{p}:{lineno}: not a number: {line!r}") from None
        if not (bv > 0):
            raise ThresholdError(f"{p}:{lineno}: threshold {parts[1]} µm at {parts[0]} Hz: thresholds "
                                 "must be > 0 µm")
        f.append(fv)
        b.append(bv)
    return ThresholdCurve(np.array(f), np.array(b), name=p.stem)


def default_curve() -> ThresholdCurve:
    return load_csv(paths.find("thresholds", "default.csv"))


def shipped_curves(max_age_s: float = 0.0) -> dict[bytes, ThresholdCurve]:
    """Every curve under thresholds/ (the override's and the shipped ones), keyed by its 8-byte
    id. Cached: the cache holds while the two directories and the .csv files found in them
    keep their modification times, so a curve file added, removed, renamed or rewritten (also
    in place) is seen on the next call. Checking that takes a few os.stat calls (~5 µs each
    on a VM); a caller may skip the check for max_age_s seconds after the last one (a decoder
    does, and checks again when the curve it needs is missing: entries are keyed by their
    content's hash, so a cached one is never a wrong curve, at most one removed moments ago)."""
    dirs = (_override_thresholds_dir(os.environ.get("HOSTD_CONFIG_DIR")), _package_thresholds_dir())
    hit = _SCAN_CACHE.get(dirs)
    if hit is not None:
        now = time.monotonic()
        if now - hit[3] < max_age_s:
            return hit[2]
        if _mtimes(hit[0]) == hit[1]:
            hit[3] = now
            return hit[2]
    checked = time.monotonic()
    stamp = _mtimes(dirs)  # before the scan: a change during the scan makes the next call rescan
    entries = []
    for d in reversed(dirs):
        try:
            with os.scandir(d) as it:
                entries += [(e.path, e.stat().st_mtime_ns) for e in it
                            if e.name.endswith(".csv") and e.is_file()]
        except OSError:
            pass
    files = tuple(sorted(entries))
    curves = _load_dir(files)
    paths_all = dirs + tuple(p for p, _ in files)
    _SCAN_CACHE.clear()  # one entry: the current $HOSTD_CONFIG_DIR
    _SCAN_CACHE[dirs] = [paths_all, stamp + tuple(m for _, m in files), curves, checked]
    return curves


# (paths watched, their modification times, the curves, time.monotonic() of the last check)
_SCAN_CACHE: dict[tuple[str, str], list] = {}


@functools.lru_cache(maxsize=4)
def _override_thresholds_dir(_env: str | None) -> str:
    """paths.override_dir()'s thresholds/, memoized on the variable it reads."""
    return str(paths.override_dir() / "thresholds")


@functools.cache
def _package_thresholds_dir() -> str:
    """The package's own thresholds/ (fixed for the life of the process)."""
    return str(paths.shipped_dir() / "thresholds")


def _mtimes(files: tuple[str, ...]) -> tuple[int | None, ...]:
    out = []
    for f in files:
        try:
            out.append(os.stat(f).st_mtime_ns)
        except OSError:
            out.append(None)
    return tuple(out)


@functools.lru_cache(maxsize=8)
def _load_dir(files: tuple[tuple[str, int], ...]) -> dict[bytes, ThresholdCurve]:
    out: dict[bytes, ThresholdCurve] = {}
    if files:
        for p, _mtime in files:
            try:
                c = load_csv(p)
            except ThresholdError:
                continue
            out[c.id_bytes] = c
    return out


def resolve(path: str | Path | None) -> ThresholdCurve:
    """A user-given curve file, or the shipped default."""
    return load_csv(path) if path else default_curve()
