"""One registry of the profile file formats hostd reads, keyed by file suffix.

Every command that reads a profile goes through `hostd.texture.load.load_profile`, which asks
this registry for the reader of the file's suffix (text is the fallback for any other suffix).
A reader is named "module:function" and imported only when a file of its kind is read, so a
format's dependencies (scipy.io for .mat, the JSON model of .hjif) cost nothing elsewhere.

A reader takes (path, LoadOptions) (defined here: what every reader is given; the loader
re-exports it) and returns `Columns`: the numbers as an (n, 1) array of
heights or an (n, 2) array of x, height, in the units the file uses. A format that states
its own units or spacing says so in `Columns` (those override --x-unit/--y-unit/--spacing);
the loader then converts to µm, resamples to a uniform grid and cuts the patch as for text.
A container format (several arrays in one file) picks one with `LoadOptions.member`.

To add a format: write its reader in its own module and add one `Format` to `_BUILTIN`
(or call `register` at run time, e.g. from a plug-in).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hostd.errors import ProfileError

UNITS_TO_UM = {"m": 1e6, "mm": 1e3, "um": 1.0, "µm": 1.0, "nm": 1e-3}


def parse_columns(spec: str | None) -> tuple[int, ...] | None:
    """'--columns 2,3' (1-based x,height) or '3' (heights only) -> 0-based indices."""
    if spec is None or str(spec).strip() == "":
        return None
    try:
        cols = tuple(int(t) - 1 for t in str(spec).split(","))
    except ValueError:
        raise ProfileError(f"--columns {spec!r}: give X,Y (1-based, e.g. 1,2) or Y alone") from None
    if not 1 <= len(cols) <= 2 or min(cols) < 0 or len(set(cols)) != len(cols):
        raise ProfileError(f"--columns {spec!r}: give X,Y (1-based, e.g. 1,2) or Y alone")
    return cols


@dataclass(frozen=True)
class LoadOptions:
    """The loader options every profile-reading command shares (see `hostd encode --help`)."""

    x_unit: str = "um"
    y_unit: str = "um"
    spacing: float | None = None  # in x_unit: for one-column data, or the resampling target
    length_mm: float | None = 10.0  # patch length; None = whole profile
    offset_mm: float = 0.0
    detrend: str = "none"  # none | mean | linear
    columns: tuple[int, ...] | None = None  # 0-based (x, height) or (height,) of a text file
    decimal_comma: bool = False
    progress: bool = False  # a progress bar on stderr while reading large files
    member: str | None = None  # container formats: which array (a .mat variable, an .hjif channel)
    full_scale_um: float | None = None  # .hjif/.hmpg that state no scale: amplitude 1.0 in µm


@dataclass(frozen=True)
class Columns:
    """What a reader found: heights (n, 1) or x, height (n, 2), float64, in the file's units.

    x_unit / y_unit / spacing: set when the file itself states them (they then override the
    command's options); None leaves the command's --x-unit / --y-unit / --spacing in force.
    `spacing` is in x_unit and is used for one-column data. `note` is a line worth telling
    the user (e.g. which member of a container was taken)."""

    data: np.ndarray
    x_unit: str | None = None
    y_unit: str | None = None
    spacing: float | None = None
    note: str = ""


@dataclass(frozen=True)
class Format:
    name: str  # shown in messages and `hostd formats`-style listings
    suffixes: tuple[str, ...]  # lower case, with the dot: (".mat",)
    reader: str  # "module:function", imported on first use
    summary: str = ""


_BUILTIN: tuple[Format, ...] = (
    Format("numpy", (".npy",), "hostd.texture.load:read_npy",
           "a NumPy array: heights (N,) or x, height (N, 2) / (2, N)"),
    Format("text", (".csv", ".txt", ".dat", ".asc", ".xyz", ".prf", ".tsv"),
           "hostd.texture.load:read_text",
           "one or two numeric columns; instrument preambles skipped (--columns, --decimal-comma)"),
    Format("MPEG-I Haptics", (".hjif", ".hmpg"), "hostd.texture.hjif:read",
           "ISO/IEC 23090-31 (.hmpg through the reference Decoder): one channel (--member P[/C])"),
    Format("matlab", (".mat",), "hostd.texture.matfile:read_mat",
           "MATLAB v4-v7 (v7.3 is HDF5: save with -v7); --var NAME picks an array, --var X,Y two vectors"),
    Format("WAV", (".wav",), "hostd.texture.wav:read_wav",
           "a recording: one channel's samples (--columns CHANNEL) as heights, --spacing between them"),
)
TEXT = _BUILTIN[1]  # any suffix not registered is read as text

_registry: dict[str, Format] = {}


def register(fmt: Format, *, replace: bool = False) -> None:
    """Add a format (each suffix once unless replace=True)."""
    for s in fmt.suffixes:
        s = s.lower()
        if not s.startswith("."):
            raise ValueError(f"suffix {s!r} must start with '.'")
        if s in _registry and not replace and _registry[s] != fmt:
            raise ValueError(f"suffix {s} is already read by format {_registry[s].name!r}")
        _registry[s] = fmt


for _f in _BUILTIN:
    register(_f)


def formats() -> list[Format]:
    """The registered formats, each once, in registration order."""
    seen: dict[str, Format] = {}
    for f in _registry.values():
        seen.setdefault(f.name, f)
    return list(seen.values())


def format_for(path: str | Path) -> Format:
    return _registry.get(Path(path).suffix.lower(), TEXT)


def _resolve(fmt: Format) -> Callable[..., Columns]:
    mod, _, func = fmt.reader.partition(":")
    try:
        return getattr(importlib.import_module(mod), func)
    except (ImportError, AttributeError) as exc:
        raise ProfileError(f"the {fmt.name} reader ({fmt.reader}) cannot be loaded: {exc}; "
                           "reinstall hostd (or the extra this format needs)") from None


# What a file's first bytes say it is (checked before any reader parses it): signature, the
# kind it names (a registered format's name, or None: a kind hostd does not read), in words.
MAGIC: tuple[tuple[bytes, str | None, str], ...] = (
    (b"\x93NUMPY", "numpy", "a NumPy .npy array"),
    (b"MATLAB 7.3 MAT-file", "matlab", "a MATLAB v7.3 (HDF5) file"),
    (b"MATLAB ", "matlab", "a MATLAB .mat file"),
    (b"\x89HDF\r\n\x1a\n", None, "an HDF5 file"),
    (b"PK\x03\x04", None, "a ZIP archive (.npz, .xlsx, .docx, ...)"),
    (b"\x1f\x8b", None, "gzip-compressed data (gunzip it first)"),
    (b"BZh", None, "bzip2-compressed data (bunzip2 it first)"),
    (b"\xfd7zXZ\x00", None, "xz-compressed data (unxz it first)"),
    (b"(\xb5/\xfd", None, "zstd-compressed data (unzstd it first)"),
    (b"\xd0\xcf\x11\xe0", None, "an OLE document (an old .xls/.doc: export it as CSV)"),
    (b"%PDF", None, "a PDF document"),
    (b"\x89PNG", None, "a PNG image"),
    (b"\xff\xd8\xff", None, "a JPEG image"),
    (b"II*\x00", None, "a TIFF image"),
    (b"MM\x00*", None, "a TIFF image"),
    (b"fLaC", None, "FLAC audio (convert it: ffmpeg -i IN -c:a pcm_f32le OUT.wav)"),
    (b"OggS", None, "Ogg audio (convert it: ffmpeg -i IN -c:a pcm_f32le OUT.wav)"),
    (b"ID3", None, "MP3 audio (convert it: ffmpeg -i IN -c:a pcm_f32le OUT.wav)"),
    (b"\x7fELF", None, "a program (ELF)"),
    (b"\xff\xfe", None, "UTF-16 text (save it as UTF-8: iconv -f UTF-16 -t UTF-8 IN > OUT)"),
    (b"\xfe\xff", None, "UTF-16 text (save it as UTF-8: iconv -f UTF-16 -t UTF-8 IN > OUT)"),
)
SNIFF_BYTES = 1 << 12
_WAV_RIFF = (b"RIFF", b"RIFX", b"RF64")


def sniff(head: bytes) -> tuple[str | None, str]:
    """(kind, in words) of a file from its first bytes: kind is a registered format's name, "text"
    for bytes that can be text, or None for a kind hostd does not read ("binary data" when no
    signature is known but the bytes hold NULs or other control characters)."""
    if head[:4] in _WAV_RIFF and head[8:12] == b"WAVE":
        return "WAV", "a WAV recording"
    for sig, kind, words in MAGIC:
        if head.startswith(sig):
            return kind, words
    ctrl = sum(head.count(bytes([c])) for c in range(32) if c not in (9, 10, 12, 13, 26))
    if b"\x00" in head or ctrl > len(head) // 100:
        return None, "binary data"
    return "text", "text"


# The kinds a format's reader accepts (formats not listed here check their own bytes). A
# MATLAB v4 file has no signature: its reader checks its header.
ACCEPTS: dict[str, tuple[str | None, ...]] = {
    "numpy": ("numpy",), "text": ("text",), "WAV": ("WAV",), "matlab": ("matlab", None),
}

EXPECTED = {
    "numpy": "a NumPy .npy file (numpy.save's format, which begins with \\x93NUMPY)",
    "text": "text (one or two numeric columns)",
    "WAV": "a WAV recording (RIFF/WAVE)",
    "matlab": "a MATLAB .mat file",
}
FIX = {
    "numpy": "save the array with numpy.save(path, a), or give it as CSV",
    "WAV": "convert it: ffmpeg -i IN -c:a pcm_f32le OUT.wav",
    "matlab": "save the array in MATLAB with save('profile.mat', 'NAME', '-v7'), or as CSV (writematrix)",
}


def open_profile(p: Path, error: type[ProfileError] = ProfileError):
    """A profile file opened for reading in binary; every failure one line: a missing file is
    ProfileNotFound, a FIFO, device, socket or directory is refused without waiting on it, any
    other OSError says what the system said (`error`: the reader's own ProfileError kind)."""
    from hostd.errors import ProfileNotFound
    from hostd.fileio import NotRegular, open_regular

    try:
        return open_regular(p)
    except FileNotFoundError:
        raise ProfileNotFound(f"no such profile file: {p}") from None
    except NotRegular as exc:
        raise error(str(exc)) from None
    except OSError as exc:
        raise error(f"cannot read {p}: {exc.strerror or exc}") from None


def _head(p: Path) -> bytes:
    with open_profile(p) as fh:
        return fh.read(SNIFF_BYTES)


def check_kind(p: Path, fmt: Format, head: bytes) -> None:
    """Refuse a file whose bytes are not of the kind its name promises (one line saying what
    it is and what to do)."""
    accepts = ACCEPTS.get(fmt.name)
    if accepts is None:
        return
    kind, words = sniff(head)
    unsigned = kind is None and words == "binary data"  # a MATLAB v4 file has no signature
    if (kind is not None and kind in accepts) or (unsigned and None in accepts):
        return
    if not head:
        raise ProfileError(f"{p} is empty: give a profile file")
    expected = EXPECTED.get(fmt.name) or f"a {fmt.name} file ({fmt.summary.split(':')[0]})"
    other = next((f for f in formats() if f.name == kind), None)
    if other is not None and other is not fmt:
        raise ProfileError(f"{p} holds {words}, not {expected}: name it *{other.suffixes[0]} to read "
                           f"it as {other.name}")
    known = ", ".join(sorted({s for f in formats() for s in f.suffixes}))
    raise ProfileError(f"{p} holds {words}, not {expected}: "
                       f"{FIX.get(fmt.name) or f'give a profile file (hostd reads {known})'}")


def read(path: str | Path, opts: LoadOptions) -> Columns:
    """The file's numbers through its format's reader, checked for shape.

    The file must be a regular file (a FIFO or device is refused, never waited on) whose first
    bytes agree with its suffix (`sniff`: a WAV named .csv, random bytes named .npy are refused
    saying what they are). Any exception of a reader becomes a one-line ProfileError naming the
    file."""
    from hostd.errors import HostdError

    p = Path(path)
    fmt = format_for(p)
    check_kind(p, fmt, _head(p))
    reader = _resolve(fmt)
    try:
        cols = reader(p, opts)
    except HostdError:
        raise
    except MemoryError:
        raise ProfileError(f"{p}: too large to read into memory: take a smaller file or patch") from None
    except RecursionError:
        raise ProfileError(f"cannot read {p} as {fmt.name}: it nests too deeply") from None
    except Exception as exc:  # a reader's own failure on bytes it did not expect: one line
        raise ProfileError(f"cannot read {p} as {fmt.name}: {type(exc).__name__}: "
                           f"{str(exc).splitlines()[0] if str(exc) else 'damaged file'}") from None
    if not isinstance(cols, Columns):
        cols = Columns(np.asarray(cols, dtype=np.float64))
    arr = cols.data
    if arr.ndim != 2 or arr.shape[1] not in (1, 2):
        raise ProfileError(f"{path}: the {fmt.name} reader gave shape {arr.shape}, not (N, 1) or (N, 2)")
    return cols
