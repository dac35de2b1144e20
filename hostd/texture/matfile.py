"""MATLAB .mat profiles (v4 to v7, scipy.io.loadmat; imported only when a .mat file is read).

A .mat file is a container: the array taken is the one numeric variable it holds, or the one
`--var NAME` (LoadOptions.member) names; `--var X,Y` pairs two vectors as x and height. A
vector (N,), (N, 1) or (1, N) is heights; (N, 2) or (2, N) is x, height. v7.3 files are HDF5,
which scipy does not read: the message says how to save the file so that it can.
"""

from __future__ import annotations

import math
import mmap
import struct
import zlib
from pathlib import Path

import numpy as np

from hostd.errors import ProfileError
from hostd.texture.formats import Columns

V73_HINT = ("is a MATLAB v7.3 (HDF5) file, which hostd cannot read: save it as v7 in MATLAB "
            "(save('profile.mat', 'NAME', '-v7')) or write the array as CSV (writematrix)")


def _numeric(v) -> bool:
    return (isinstance(v, np.ndarray) and v.size > 0 and v.dtype.kind in "biuf"
            and v.ndim <= 2)


# Before scipy reads a .mat file (scipy.io.loadmat inflates every compressed variable whole and
# sizes arrays from the file's declared dimensions), its structure is walked here: every declared
# size is checked against the bytes that hold it, a compressed variable is inflated in a
# streaming pass that stops at INFLATE_RATIO x its compressed size (or INFLATE_MARGIN, whichever
# is larger), and a cell or struct array must hold the elements it declares. A file that fails
# is refused in one line before scipy allocates anything.
INFLATE_RATIO = 64  # a measured profile compresses 1-4x; a zlib bomb some 1000x
INFLATE_MARGIN = 8 << 20  # bytes any compressed variable may inflate to, whatever its ratio
MAX_DIMS = 64
MAX_CELLS = 1 << 16  # cell and struct elements in one file (each becomes a Python object)
MAX_DEPTH = 16  # nesting of cells and structs
_MI_MATRIX, _MI_COMPRESSED = 14, 15
_CELL, _STRUCT, _OBJECT = 1, 2, 3
_V4_ITEMSIZE = {0: 8, 1: 4, 2: 4, 3: 2, 4: 2, 5: 1}


class _Bad(Exception):
    """A declared size the file does not back (the message is the reason)."""


class _Walker:
    """The checks of a MATLAB v5 element tree over a buffer (bytes, mmap or a memoryview)."""

    def __init__(self, endian: str, max_values: int) -> None:
        self.buf, self.e, self.max_values = b"", endian, max_values
        self.cells = 0  # over the whole file

    def variable(self, buf, pos: int, end: int) -> None:
        self.buf = buf
        try:
            self.matrix(pos, end, 0)
        finally:
            self.buf = b""  # an mmap is closed after its variable

    def elem(self, pos: int, end: int) -> tuple[int, int, int, int]:
        """(type, size, data offset, next offset) of the element at pos, within end."""
        if pos + 8 > end:
            raise _Bad(f"an element at byte {pos} is cut short")
        first, second = struct.unpack_from(self.e + "II", self.buf, pos)
        if first >> 16:  # the small data element format: type and size in one word, 4 data bytes
            n = first >> 16
            if n > 4:
                raise _Bad(f"a small element at byte {pos} declares {n} bytes")
            return first & 0xFFFF, n, pos + 4, pos + 8
        if pos + 8 + second > end:
            raise _Bad(f"an element at byte {pos} declares {second:,} bytes but {end - pos - 8:,} are left")
        return first, second, pos + 8, pos + 8 + ((second + 7) & ~7)

    def matrix(self, pos: int, end: int, depth: int) -> int:
        """Check the miMATRIX element at pos; the offset after it."""
        if depth > MAX_DEPTH:
            raise _Bad(f"cells or structs nested deeper than {MAX_DEPTH}")
        typ, n, p, nxt = self.elem(pos, end)
        if typ != _MI_MATRIX:
            raise _Bad(f"an element of type {typ} at byte {pos} where an array was expected")
        mend = p + n
        if n == 0:
            return nxt
        _t, fn, fp, p = self.elem(p, mend)  # array flags
        if fn < 4:
            raise _Bad("an array without its flags")
        cls = struct.unpack_from(self.e + "I", self.buf, fp)[0] & 0xFF
        _t, dn, dp, p = self.elem(p, mend)  # dimensions
        if dn // 4 > MAX_DIMS:
            raise _Bad(f"an array of {dn // 4:,} dimensions")
        dims = struct.unpack_from(f"{self.e}{dn // 4}i", self.buf, dp)
        if any(d < 0 for d in dims):
            raise _Bad(f"negative dimensions {dims}")
        count = math.prod(dims)
        if count > self.max_values:
            raise _Bad(f"an array of {count:,} elements, more than the {self.max_values:,} a profile "
                       "file may declare")
        _t, _n, _p, p = self.elem(p, mend)  # name
        if cls == _OBJECT:
            _t, _n, _p, p = self.elem(p, mend)  # class name
        if cls in (_STRUCT, _OBJECT):
            _t, ln, lp, p = self.elem(p, mend)  # field name length
            flen = struct.unpack_from(self.e + "i", self.buf, lp)[0] if ln >= 4 else 0
            _t, nn, _np, p = self.elem(p, mend)  # field names
            if nn and flen <= 0:
                raise _Bad("struct field names without their length")
            count *= nn // flen if flen > 0 else 0
        if cls in (_CELL, _STRUCT, _OBJECT):
            if count * 8 > mend - p:
                raise _Bad(f"a cell or struct array declares {count:,} elements in {mend - p:,} bytes")
            self.cells += count
            if self.cells > MAX_CELLS:
                raise _Bad(f"more than {MAX_CELLS:,} cell or struct elements: not a profile file (save "
                           "the profile's arrays alone)")
            for _ in range(count):
                p = self.matrix(p, mend, depth + 1)
            return nxt
        while p < mend:  # numeric, char, sparse and opaque parts: each within the array
            _t, _n, _p, p = self.elem(p, mend)
        return nxt


def _inflate_bounded(fh, n: int, name: str) -> bytearray:
    """A compressed element's n bytes inflated, refused as soon as the output passes the limit."""
    limit = max(INFLATE_MARGIN, INFLATE_RATIO * n)
    z = zlib.decompressobj()
    out = bytearray()
    left = n
    while left > 0:
        chunk = fh.read(min(left, 1 << 16))
        if not chunk:
            raise _Bad("a compressed variable is cut short")
        left -= len(chunk)
        while chunk:
            out += z.decompress(chunk, limit + 1 - len(out))
            chunk = z.unconsumed_tail
            if len(out) > limit:
                raise _Bad(f"a compressed variable of {n:,} bytes inflates to more than {limit:,} "
                           f"(over {INFLATE_RATIO}x: not a measured profile; save it uncompressed "
                           "with save(..., '-v6') if it is one)")
        if z.eof:
            break
    return out


def check_structure(fh, size: int, name: str, max_values: int) -> None:
    """Refuse (ProfileError) a .mat file whose declared sizes its bytes do not back."""
    from scipy.io.matlab import matfile_version

    fh.seek(0)
    try:
        major, _minor = matfile_version(fh)
    except Exception as exc:
        raise ProfileError(f"{name} is not a MATLAB .mat file ({exc})") from None
    if major == 2:
        raise ProfileError(f"{name} {V73_HINT}")
    try:
        if major == 0:
            _check_v4(fh, size, max_values)
            return
        fh.seek(126)
        endian = "<" if fh.read(2) == b"IM" else ">"
        pos = 128
        walker = _Walker(endian, max_values)
        while pos + 8 <= size:
            fh.seek(pos)
            typ, n = struct.unpack(endian + "II", fh.read(8))
            if typ >> 16:
                pos += 8
                continue
            if n > size - pos - 8:
                raise _Bad(f"a variable at byte {pos} declares {n:,} bytes but {size - pos - 8:,} are "
                           "left: the file is truncated")
            if typ == _MI_COMPRESSED:
                data = _inflate_bounded(fh, n, name)
                walker.variable(data, 0, len(data))
                del data  # freed before the next variable and before scipy reads the file
            elif typ == _MI_MATRIX:
                with mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as mm:
                    walker.variable(mm, pos, pos + 8 + n)
            pos += 8 + n
    except _Bad as exc:
        raise ProfileError(f"{name}: refused before reading it: {exc}") from None
    except (struct.error, zlib.error) as exc:
        raise ProfileError(f"{name}: a damaged MATLAB file ({exc})") from None


def _check_v4(fh, size: int, max_values: int) -> None:
    pos = 0
    while pos + 20 <= size:
        fh.seek(pos)
        raw = fh.read(20)
        mopt = struct.unpack("<i", raw[:4])[0]
        e = "<" if 0 <= mopt < 5000 else ">"
        mopt, rows, cols, imagf, namlen = struct.unpack(e + "5i", raw)
        prec = (mopt // 10) % 10
        if not 0 <= mopt < 5000 or prec not in _V4_ITEMSIZE or min(rows, cols, namlen) < 0:
            raise _Bad(f"a v4 variable header at byte {pos} is not one ({mopt}, {rows}x{cols})")
        if rows * cols > max_values:
            raise _Bad(f"a v4 variable of {rows:,}x{cols:,}, more than the {max_values:,} values a "
                       "profile file may declare")
        n = 20 + namlen + rows * cols * _V4_ITEMSIZE[prec] * (2 if imagf else 1)
        if pos + n > size:
            raise _Bad(f"a v4 variable at byte {pos} declares {n:,} bytes but {size - pos:,} are left")
        pos += n


def _load(p: Path) -> dict[str, np.ndarray]:
    import scipy.io

    from hostd.texture.formats import open_profile
    from hostd.texture.load import MAX_VALUES

    with open_profile(p) as fh:
        size = fh.seek(0, 2)
        check_structure(fh, size, str(p), MAX_VALUES)
        fh.seek(0)
        try:
            return scipy.io.loadmat(fh, squeeze_me=False, struct_as_record=True)
        except NotImplementedError:  # scipy's own word for v7.3
            raise ProfileError(f"{p} {V73_HINT}") from None
        except MemoryError:
            raise ProfileError(f"{p}: too large to read into memory") from None
        except Exception as exc:  # scipy raises ValueError, TypeError, OSError ... on a broken file
            raise ProfileError(f"cannot read {p} as a MATLAB .mat file: {exc}") from None


def _as_columns(p: Path, name: str, v: np.ndarray) -> np.ndarray:
    if v.dtype.kind == "c":
        raise ProfileError(f"{p}: variable {name!r} is complex: heights must be real")
    a = np.asarray(v, dtype=np.float64)
    if a.ndim <= 1 or 1 in a.shape:
        return a.reshape(-1, 1)
    if a.shape[1] == 2:
        return a
    if a.shape[0] == 2:
        return a.T.copy()
    raise ProfileError(f"{p}: variable {name!r} has shape {a.shape}; a profile is a vector of heights "
                       "or two columns x, height (--var X,Y pairs two vectors)")


def read_mat(p: Path, opts) -> Columns:
    """The .mat reader of the format registry (hostd.texture.formats)."""
    variables = {k: v for k, v in _load(p).items() if not k.startswith("__")}
    numeric = {k: v for k, v in variables.items() if _numeric(v)}
    listing = ", ".join(f"{k} {'x'.join(map(str, v.shape))}" for k, v in numeric.items()) or "none"
    member = opts.member
    if member is None:
        if len(numeric) != 1:
            what = "no numeric array" if not numeric else f"several arrays ({listing})"
            raise ProfileError(f"{p} holds {what}: choose one with --var NAME (or --var X,Y for "
                               "an x and a height vector)")
        ((name, v),) = numeric.items()
        return Columns(_as_columns(p, name, v), note=f"read its one numeric variable, {name!r}")
    names = [s.strip() for s in member.split(",")]
    for n in names:
        if n not in variables:
            raise ProfileError(f"{p} has no variable {n!r} (its numeric arrays: {listing})")
        if not _numeric(variables[n]):
            raise ProfileError(f"{p}: variable {n!r} is not a numeric array (its numeric arrays: {listing})")
    if len(names) == 1:
        return Columns(_as_columns(p, names[0], variables[names[0]]))  # what --var asked: nothing to note
    if len(names) != 2:
        raise ProfileError(f"--var {member!r}: give NAME, or X,Y (two vectors)")
    x, y = (_as_columns(p, n, variables[n]) for n in names)
    if x.shape[1] != 1 or y.shape[1] != 1 or x.shape[0] != y.shape[0]:
        raise ProfileError(f"--var {member}: {names[0]} and {names[1]} must be vectors of one length "
                           f"({listing})")
    return Columns(np.column_stack([x[:, 0], y[:, 0]]))
