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


def read(path: str | Path, opts: LoadOptions) -> Columns:
    """The file's numbers through its format's reader, checked for shape."""
    fmt = format_for(path)
    cols = _resolve(fmt)(Path(path), opts)
    if not isinstance(cols, Columns):
        cols = Columns(np.asarray(cols, dtype=np.float64))
    arr = cols.data
    if arr.ndim != 2 or arr.shape[1] not in (1, 2):
        raise ProfileError(f"{path}: the {fmt.name} reader gave shape {arr.shape}, not (N, 1) or (N, 2)")
    return cols
