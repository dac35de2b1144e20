"""Height profiles from files: CSV/TXT (one or two columns, instrument headers tolerated) and .npy.

Everything is converted to micrometres on a uniform grid; a patch of the chosen length is
taken from the start (or an offset) of the profile.
"""

from __future__ import annotations

import io
import math
import re
import warnings
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from hostd.errors import ProfileError, ProfileNotFound
from hostd.texture.formats import UNITS_TO_UM, LoadOptions, parse_columns  # noqa: F401 (re-exported)

_SPLIT = re.compile(r"[,;\s]+")
MAX_ROWS = 50_000_000


@dataclass(frozen=True)
class Profile:
    """Uniformly sampled heights in µm with their spacing in µm."""

    heights_um: np.ndarray
    spacing_um: float
    source: str = ""
    note: str = ""  # what the file's reader said worth telling (formats.Columns.note)

    @property
    def n(self) -> int:
        return int(self.heights_um.size)

    @property
    def length_mm(self) -> float:
        return self.n * self.spacing_um / 1000.0


def unit_factor(unit: str, axis: str) -> float:
    try:
        return UNITS_TO_UM[unit]
    except KeyError:
        raise ProfileError(
            f"unknown {axis} unit {unit!r}: use one of m, mm, um, nm"
        ) from None


PROGRESS_BYTES = 1 << 26  # progress bar on files above 64 MiB
_NUM_TOKEN = re.compile(rb"^[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?$|^[+-]?(nan|inf|infinity)$", re.I)


def _split(line: bytes, delim: bytes | None) -> list[bytes]:
    return line.split(delim) if delim is not None else line.split()


def _is_num(tok: bytes) -> bool:
    return bool(_NUM_TOKEN.match(tok.strip()))


def _data_layout(head: bytes, decimal_comma: bool):
    """(byte offset of the first data line, its line number, delimiter, numeric columns) or None.

    A data line is one whose non-empty fields are all numbers, followed by lines of the same
    shape (instrument preambles such as a Dektak export's are skipped)."""
    lines = head.split(b"\n")
    offset = 0
    for i, raw in enumerate(lines[:-1]):
        line = raw.split(b"#", 1)[0].strip()
        if decimal_comma:
            line = line.replace(b",", b".")
        delim = b"," if b"," in line else b";" if b";" in line else b"\t" if b"\t" in line else None
        toks = _split(line, delim)
        cols = [j for j, t in enumerate(toks) if t.strip()]
        if line and cols and all(_is_num(toks[j]) for j in cols):
            following = [r.split(b"#", 1)[0].strip() for r in lines[i + 1 : i + 4]]
            following = [(r.replace(b",", b".") if decimal_comma else r) for r in following if r]
            if all([j for j, t in enumerate(_split(r, delim)) if t.strip()] == cols
                   and all(_is_num(t) for t in _split(r, delim) if t.strip()) for r in following):
                return offset, i + 1, delim, cols
        offset += len(raw) + 1
    return None


class _Source:
    """A text file read by numpy's C parser, block by block: drives the progress bar and ends
    the input early once an ascending x column has passed the patch's end."""

    def __init__(self, fh, bar, delim: str | None, xcol: int | None, stop_x: float | None) -> None:
        self.fh, self.bar, self.delim, self.xcol, self.stop_x = fh, bar, delim, xcol, stop_x
        self.x0: float | None = None
        self.stopped = False

    def _x(self, line: str) -> float | None:
        toks = line.split(self.delim) if self.delim else line.split()
        try:
            return float(toks[self.xcol])
        except (IndexError, ValueError):
            return None

    def read(self, size: int = -1) -> str:
        if self.stopped:
            return ""
        block = self.fh.read(size)
        self.bar.update(len(block))
        if self.stop_x is None or self.xcol is None or not block:
            return block
        if self.x0 is None:
            self.x0 = self._x(block.split("\n", 1)[0])
        end = block.rfind("\n")  # the last complete line of this block ends here
        if end <= 0:
            return block
        x = self._x(block[block.rfind("\n", 0, end) + 1 : end])
        if x is not None and self.x0 is not None and x - self.x0 > self.stop_x:
            self.stopped = True
            return block[: end + 1]
        return block


def read_columns(path: Path, columns: tuple[int, ...] | None = None, decimal_comma: bool = False,
                 stop_x: float | None = None, progress: bool = False) -> np.ndarray:
    """Numeric rows of a text file as an (n, 1) or (n, 2) array of float64.

    Fast path: find the first data line (skipping any instrument preamble), then one pass of
    numpy's C parser (the reader behind `np.loadtxt`) over the rest, fed block by block so
    that a progress bar can follow it and reading can stop once an ascending x column has run
    `stop_x` past its first value (a patch of a huge file). Files whose rows change shape or
    hold text further down fall back to a line-by-line reader that skips non-numeric lines
    and keeps the most common width.
    """
    try:
        size = path.stat().st_size
        fh = path.open("r", encoding="latin-1", newline="")
    except FileNotFoundError:
        raise ProfileNotFound(f"no such profile file: {path}") from None
    except OSError as exc:
        raise ProfileError(f"cannot read {path}: {exc.strerror or exc}") from None
    with fh:
        head = fh.read(1 << 16).encode("latin-1")
        layout = _data_layout(head, decimal_comma)
        if layout is None or decimal_comma:
            fh.seek(0)
            if layout is None:
                return _read_columns_slow(fh.read().encode("latin-1"), path, columns, decimal_comma)
        if decimal_comma:  # the C parser has no decimal-comma option: translate the text first
            _off, first_line, delim, found = layout
            text = fh.read()[_off:].replace(",", ".")
            usecols = _usecols(path, found, columns, first_line)
            arr = _parse(io.StringIO(text), delim, usecols, None)
            return arr if arr is not None else _read_columns_slow(
                text.encode("latin-1"), path, columns, False)
        offset, first_line, delim, found = layout
        usecols = _usecols(path, found, columns, first_line)
        est_rows = _estimate_rows(head[offset:], size - offset)
        if est_rows > MAX_ROWS and stop_x is None:
            raise ProfileError(
                f"{path} holds about {est_rows:,} rows ({size / 2**20:.0f} MiB), more than the "
                f"{MAX_ROWS:,} a profile may have: take a patch with --length-mm (and --offset-mm)")
        from hostd.tty import progress_bar

        for attempt_stop in ((stop_x, None) if stop_x is not None else (None,)):
            fh.seek(offset)
            with progress_bar(progress and size >= PROGRESS_BYTES, total=size - offset, unit="B",
                              unit_scale=True, desc=f"reading {path.name}", leave=False) as bar:
                src = _Source(fh, bar, None if delim is None else delim.decode(),
                              usecols[0] if len(usecols) == 2 else None, attempt_stop)
                arr = _parse(src, delim, usecols, first_line)
            if arr is None:
                fh.seek(0)
                return _read_columns_slow(fh.read().encode("latin-1"), path, columns, False)
            if not src.stopped or np.all(np.diff(arr[:, 0]) > 0):
                break  # an early stop is only trusted on an ascending x column
    if arr.shape[0] == 0:
        raise ProfileError(f"{path}: no numeric rows found")
    if arr.shape[0] > MAX_ROWS:
        raise ProfileError(f"{path}: more than {MAX_ROWS:,} rows: take a patch with --length-mm "
                           "(and --offset-mm)")
    return arr


def _parse(src, delim: bytes | None, usecols: tuple[int, ...], first_line: int | None):
    """numpy's C reader on a file-like (fast, with our block hook), else np.loadtxt; None when
    the text does not have one shape all along (the caller falls back)."""
    d = None if delim is None else delim.decode()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "input contained no data"
        try:
            try:
                from numpy.lib._npyio_impl import _load_from_filelike

                arr = _load_from_filelike(
                    src, delimiter=d, comment="#", quote='"', imaginary_unit="j", usecols=list(usecols),
                    skiplines=0, max_rows=-1, converters=None, dtype=np.dtype(np.float64),
                    encoding="latin-1", filelike=True, byte_converters=False)
            except (ImportError, TypeError):  # numpy changed its internals: the public reader
                lines = iter(lambda: src.read(1 << 20), "")
                arr = np.loadtxt(io.StringIO("".join(lines)), dtype=np.float64, comments="#",
                                 delimiter=d, usecols=usecols, ndmin=2)
        except ValueError:
            return None
    return arr.reshape(arr.shape[0], -1) if arr.ndim != 2 else arr


def _usecols(path: Path, found: list[int], columns: tuple[int, ...] | None, line: int) -> tuple[int, ...]:
    if columns is not None:
        if max(columns) >= max(found) + 1:
            raise ProfileError(f"{path}:{line}: --columns asks for column {max(columns) + 1} but the "
                               f"data rows have {len(found)} fields")
        return columns
    if len(found) > 2:
        raise ProfileError(f"{path}:{line}: the data rows have {len(found)} numeric columns: choose "
                           "x and height with --columns X,Y (1-based), or the heights with --columns Y")
    return tuple(found)


def _estimate_rows(sample: bytes, data_bytes: int) -> int:
    lines = max(sample.count(b"\n"), 1)
    return int(data_bytes / max(len(sample), 1) * lines)


def _read_columns_slow(data: bytes, path: Path, columns: tuple[int, ...] | None,
                       decimal_comma: bool) -> np.ndarray:
    """Line by line: non-numeric lines skipped, the most common row width kept (the numbers
    gathered in flat float64 buffers, 8 bytes each, not Python lists)."""
    from array import array

    text = data.decode("utf-8", errors="replace")
    del data
    if decimal_comma:
        text = text.replace(",", ".")
    found = {1: array("d"), 2: array("d")}
    rows = 0
    for raw in io.StringIO(text):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        toks = [t for t in _SPLIT.split(line) if t]
        if columns is not None:
            if len(toks) <= max(columns):
                continue
            toks = [toks[c] for c in columns]
        if len(toks) not in (1, 2):
            continue
        try:
            vals = [float(t) for t in toks]
        except ValueError:
            continue  # header, metadata or comment line (e.g. a Dektak export's preamble)
        found[len(vals)].extend(vals)
        rows += 1
        if rows > MAX_ROWS:
            raise ProfileError(f"{path}: more than {MAX_ROWS:,} rows: take a patch with --length-mm")
    if not rows:
        raise ProfileError(f"{path}: no numeric rows of one or two columns found "
                           "(choose columns with --columns X,Y; decimal commas need --decimal-comma)")
    width = max((1, 2), key=lambda w: (len(found[w]) // w, -w))
    return np.frombuffer(found[width], dtype=np.float64).reshape(-1, width).copy()


def nonfinite_lines(path: Path, decimal_comma: bool = False, limit: int = 3) -> list[int]:
    """Line numbers (1-based) of the first data lines holding NaN or Inf (for the error message)."""
    out = []
    with path.open("rb") as fh:
        for i, raw in enumerate(fh, start=1):
            toks = _SPLIT.split(raw.split(b"#", 1)[0].decode("latin-1").strip())
            if any(t.lower().lstrip("+-") in ("nan", "inf", "infinity") for t in toks):
                out.append(i)
                if len(out) >= limit:
                    break
    return out


MAX_VALUES = 2 * MAX_ROWS  # numbers a binary profile file (.npy, .mat, .wav) may declare


def _npy_header(p: Path):
    """(shape, dtype, data offset) of a .npy file, checked against the file's size and MAX_VALUES
    before anything is allocated; every failure a ProfileError naming what was expected."""
    from numpy.lib import format as npyfmt

    from hostd.texture.formats import open_profile

    expect = "a .npy file written by numpy.save (a numeric array of heights)"
    with open_profile(p) as fh:
        size = fh.seek(0, 2)
        fh.seek(0)
        try:
            version = npyfmt.read_magic(fh)
            read_header = {(1, 0): npyfmt.read_array_header_1_0,
                           (2, 0): npyfmt.read_array_header_2_0,  # 3.0: 2.0's layout, UTF-8
                           (3, 0): npyfmt.read_array_header_2_0}.get(version)
            if read_header is None:
                raise ValueError(f"format version {version}")
            shape, _fortran, dtype = read_header(fh, max_header_size=10_000)
        except Exception as exc:  # ValueError, EOFError, SyntaxError of a damaged header
            raise ProfileError(f"{p} is not {expect}: its header cannot be read ({exc}); save the "
                               "array with numpy.save(path, a)") from None
        offset = fh.tell()
    if dtype.hasobject or dtype.kind not in "biufc" or dtype.fields is not None:
        raise ProfileError(f"{p} holds an array of {dtype} (Python objects or records), which hostd "
                           "never loads: save a numeric array (numpy.save(path, a.astype(float)))")
    count = math.prod(shape)
    if count > MAX_VALUES:
        raise ProfileError(f"{p} declares {count:,} numbers, more than the {MAX_VALUES:,} a profile "
                           "may have: save a shorter patch")
    if count * dtype.itemsize > size - offset:
        raise ProfileError(f"{p} declares shape {shape} of {dtype} ({count * dtype.itemsize:,} bytes) "
                           f"but holds {size - offset:,} bytes of data: the file is truncated")
    return shape, dtype, offset


def read_npy(p: Path, opts: LoadOptions) -> np.ndarray:
    """The .npy reader of the format registry (hostd.texture.formats)."""
    _npy_header(p)
    try:
        arr = np.load(p, allow_pickle=False, mmap_mode="r")
    except FileNotFoundError:
        raise ProfileNotFound(f"no such profile file: {p}") from None
    except (OSError, ValueError) as exc:
        raise ProfileError(f"cannot read {p} as .npy: {exc}") from None
    if np.iscomplexobj(arr):
        raise ProfileError(f"{p} holds complex numbers ({arr.dtype}): heights must be real; save "
                           "np.real(a) (or np.abs(a)) if that is what you mean")
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)
            or arr.dtype == np.bool_):
        raise ProfileError(f"{p}: dtype {arr.dtype} is not numeric")
    if opts.columns is not None:
        if arr.ndim != 2 or max(opts.columns) >= arr.shape[1]:
            raise ProfileError(f"{p}: --columns does not fit an array of shape {arr.shape}")
        arr = arr[:, list(opts.columns)]
    arr = np.asarray(arr, dtype=np.float64)
    if arr.ndim == 1:
        return arr.reshape(-1, 1)
    if arr.ndim == 2 and arr.shape[1] in (1, 2):
        return arr
    if arr.ndim == 2 and arr.shape[0] == 2:
        return arr.T.copy()
    raise ProfileError(f"{p}: expected heights (N,) or (N, 2) x/height columns, got {arr.shape} "
                       "(choose columns with --columns X,Y)")


def read_text(p: Path, opts: LoadOptions) -> np.ndarray:
    """The text reader of the format registry: any suffix no other format claims."""
    if not p.exists():
        raise ProfileNotFound(f"no such profile file: {p}")
    from hostd.texture import manifest

    if manifest.looks_like_manifest(p):
        fields = ", ".join(f for f in manifest.header_fields(p) if f)
        raise ProfileError(f"{p} is a texture manifest (columns {fields}), not a profile: give it to "
                           "`hostd corpus run`, or give the profile files it lists")
    stop_x = None
    if opts.length_mm is not None and math.isfinite(opts.length_mm):
        # a patch of a two-column file: read no further than it needs (plus a margin)
        end_um = (max(opts.offset_mm, 0.0) + opts.length_mm) * 1000.0
        stop_x = 1.01 * end_um / unit_factor(opts.x_unit, "x")
    return read_columns(p, opts.columns, opts.decimal_comma, stop_x=stop_x, progress=opts.progress)


def load_columns(path: str | Path, opts: LoadOptions | None = None):
    """The file's numbers and what it says of its units (hostd.texture.formats.Columns)."""
    from hostd.texture import formats

    return formats.read(Path(path), opts or LoadOptions())


def load_array(path: str | Path, opts: LoadOptions | None = None) -> np.ndarray:
    """(n, 1) heights or (n, 2) x, height in the file's units, through the format registry."""
    return load_columns(path, opts).data


def load_profile(path: str | Path, opts: LoadOptions | None = None) -> Profile:
    """Load, convert units, resample to a uniform grid and cut the patch."""
    opts = opts or LoadOptions()
    cols = load_columns(path, opts)
    arr = cols.data
    fx = unit_factor(cols.x_unit or opts.x_unit, "x")
    fy = unit_factor(cols.y_unit or opts.y_unit, "y")
    spacing = cols.spacing if cols.spacing is not None else opts.spacing
    finite = np.isfinite(arr).all(axis=1)
    if not finite.all():
        bad = int(np.count_nonzero(~finite))
        where = ""
        from hostd.texture import formats

        if formats.format_for(path) is formats.TEXT:
            lines = nonfinite_lines(Path(path), opts.decimal_comma)
            where = f" (line{'s' if len(lines) > 1 else ''} {', '.join(map(str, lines))}" \
                f"{', ...' if bad > len(lines) else ''})" if lines else ""
        else:
            where = f" (rows {', '.join(str(i) for i in np.flatnonzero(~finite)[:3])})"
        raise ProfileError(f"{path}: {bad} row{'s' if bad > 1 else ''} hold NaN or Inf{where}; "
                           "clean the file first")
    if arr.shape[0] < 2:
        raise ProfileError(f"{path}: holds {arr.shape[0]} sample; a profile needs at least 2 "
                           "(is this the right file, or are the columns right?)")
    if arr.shape[1] == 1:
        if spacing is None:
            raise ProfileError(f"{path} has one column of heights: give the spacing with --spacing")
        dx_um = spacing * fx
        _check_spacing(dx_um)
        y_um = arr[:, 0] * fy
    else:
        x_um = arr[:, 0] * fx
        y_um = arr[:, 1] * fy
        x_um, y_um = _sorted_unique(x_um, y_um, str(path))
        dx_um = spacing * fx if spacing else (x_um[-1] - x_um[0]) / (x_um.size - 1)
        _check_spacing(dx_um)
        y_um, opts = _resample(x_um, y_um, dx_um, opts, str(path))
    prof = cut_patch(y_um, dx_um, opts, str(path))
    return replace(prof, note=cols.note) if cols.note else prof


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


def _resample(x_um: np.ndarray, y_um: np.ndarray, dx_um: float, opts: LoadOptions,
              name: str) -> tuple[np.ndarray, LoadOptions]:
    """Linear interpolation onto x0 + i dx (a no-op for data already uniform at dx), of the patch's
    samples only: an x range wide for its spacing never allocates a grid of its own size. Returns
    the samples from the patch's start and the options that cut the patch from them."""
    ratio = (x_um[-1] - x_um[0]) / dx_um
    if not math.isfinite(ratio) or ratio > 1e15:
        raise ProfileError(f"{name}: x spans {x_um[-1] - x_um[0]:.6g} µm at a spacing of {dx_um:.6g} µm: "
                           "check --x-unit and --spacing")
    count = math.floor(ratio * (1 + 1e-9)) + 1
    start = round(opts.offset_mm * 1000.0 / dx_um)
    if start < 0 or start >= count - 1:
        raise ProfileError(f"{name}: offset {opts.offset_mm} mm is outside the profile")
    n = count - start
    if opts.length_mm is not None and math.isfinite(opts.length_mm) and opts.length_mm > 0:
        n = min(n, round(opts.length_mm * 1000.0 / dx_um))
    from hostd.codec.transform import MAX_SAMPLES

    if n > MAX_SAMPLES:
        raise ProfileError(f"{name}: the patch would hold {n:,} samples, more than {MAX_SAMPLES:,}: "
                           "take a shorter patch with --length-mm, or resample with a coarser --spacing")
    grid = x_um[0] + dx_um * np.arange(start, start + max(n, 2), dtype=np.float64)
    return np.interp(grid, x_um, y_um), replace(opts, offset_mm=0.0)


def cut_patch(y_um: np.ndarray, dx_um: float, opts: LoadOptions, name: str = "") -> Profile:
    """Take length_mm from offset_mm; the whole rest if length_mm is None or longer than the data.

    The patch length is N * spacing (the DCT's period convention), so N = round(L / dx).
    """
    if y_um.size < 2:
        raise ProfileError(f"{name}: holds {y_um.size} sample; a profile needs at least 2")
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
        raise ProfileError(f"{name}: the patch holds fewer than 2 samples (sample spacing {dx_um:.4g} µm "
                           f"with x read in {opts.x_unit}): check --x-unit (is x really in that unit?)")
    from hostd.codec.transform import MAX_SAMPLES

    if n > MAX_SAMPLES:
        raise ProfileError(f"{name}: the patch would hold {n:,} samples, more than {MAX_SAMPLES:,}: "
                           "take a shorter patch with --length-mm, or resample with a coarser --spacing")
    y = np.array(y_um[start : start + n], dtype=np.float64)
    if opts.detrend == "mean":
        y -= y.mean()
    elif opts.detrend == "linear":
        t = np.arange(n, dtype=np.float64)
        y -= np.polyval(np.polyfit(t, y, 1), t)
    elif opts.detrend != "none":
        raise ProfileError(f"unknown --detrend {opts.detrend!r}: use none, mean or linear")
    return Profile(heights_um=y, spacing_um=float(dx_um), source=name)


def bundled_profile():
    """The bundled real instrument profile (data/profiles/dektak-1.csv, whole, linear detrend),
    or None when the installation lacks it."""
    from hostd.paths import find

    p = find("profiles", "dektak-1.csv")
    if not p.exists():
        return None
    return load_profile(p, LoadOptions(x_unit="um", y_unit="um", length_mm=None, detrend="linear"))
