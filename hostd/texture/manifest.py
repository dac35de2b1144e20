"""A texture database as one file: a manifest (CSV or TOML) naming each profile with its own
loader options, so that recordings of mixed instruments and units are one corpus.

CSV: a header row, then one row per texture; '#' starts a comment line; empty cells take the
default. TOML: optional `[defaults]`, then `[[texture]]` tables with the same keys.

    key            meaning (as the CLI's loader options)                    default
    file           path (relative to the manifest) or synthetic:KIND[:SEED]  required
    name           the texture's name in results                             the file's stem
    units          x and y unit at once (m, mm, um, nm)                       um
    x_unit, y_unit each on its own (override `units`)
    spacing        sample spacing in x_unit (one-column files)               from the file
    columns        1-based columns "X,Y" or "Y" (text files)                 auto
    offset_mm      patch start, mm                                           0
    length_mm      patch length, mm ("all" or empty: the whole profile)      10
    detrend        none, mean, linear                                        none
    decimal_comma  true/false                                                false
    member         the array of a container file (.mat variable, .hjif channel)
    group          a label for summaries (material class, instrument, ...)       none

A key the manifest does not know is an error naming the line (a typo must not silently fall
back to a default unit).
"""

from __future__ import annotations

import csv
import io
import math
import os
import stat
from dataclasses import dataclass, replace
from pathlib import Path

from hostd.errors import HostdError, ProfileError
from hostd.texture.formats import UNITS_TO_UM, LoadOptions, parse_columns

MAX_BYTES = 16 << 20  # a manifest is a list of files: 16 MiB is some 100,000 rows
KEYS = ("file", "name", "units", "x_unit", "y_unit", "spacing", "columns", "offset_mm", "length_mm",
        "detrend", "decimal_comma", "member", "group")


@dataclass(frozen=True)
class Entry:
    """One texture of a corpus: where it is, what to call it, and how to load it."""

    name: str
    source: str  # a path (absolute) or synthetic:KIND[:SEED]
    options: LoadOptions
    group: str = ""  # a label for per-group summaries (hostd corpus report)


def header_fields(path: str | Path) -> list[str]:
    """The first non-comment line of a CSV split at commas, stripped and lower-cased ([] for a
    file that cannot be read as text)."""
    return [f.strip().lower() for f in _first_line(Path(path)).split(",")]


def looks_like_manifest(path: str | Path) -> bool:
    """A .toml file, or a CSV whose header row names manifest keys only (with or without the
    `file` column: read() refuses one without it, saying so, rather than reading it as a profile)."""
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix == ".toml":
        return True
    if suffix != ".csv":
        return False
    fields = [f for f in header_fields(p) if f]
    return bool(fields) and ("file" in fields or set(fields) <= set(KEYS))


def is_manifest(path: str | Path) -> bool:
    p = Path(path)
    if not p.is_file():
        return False
    return looks_like_manifest(p)


def _text(p: Path) -> str:
    """The manifest's text: a regular file (a FIFO is refused, not waited on) of at most MAX_BYTES."""
    from hostd.fileio import NotRegular, open_regular

    try:
        with open_regular(p) as fh:
            data = fh.read(MAX_BYTES + 1)
    except NotRegular as exc:
        raise ProfileError(str(exc)) from None
    if len(data) > MAX_BYTES:
        raise ProfileError(f"{p}: a manifest of more than {MAX_BYTES >> 20} MiB: split it")
    return data.decode("utf-8")


def _first_line(p: Path) -> str:
    from hostd.fileio import open_regular

    try:
        with open_regular(p) as fh:
            for raw in fh:
                line = raw.decode("utf-8", errors="replace")
                if line.strip() and not line.lstrip().startswith("#"):
                    return line.strip()
                if len(raw) > 1 << 16:
                    break
    except (OSError, HostdError):
        return ""
    return ""


def read(path: str | Path, defaults: LoadOptions | None = None) -> list[Entry]:
    """The manifest's entries, in file order; `defaults` fills what an entry leaves out."""
    p = Path(path)
    try:
        if p.suffix.lower() == ".toml":
            import tomllib

            doc = tomllib.loads(_text(p))
            base = dict(doc.get("defaults", {}))
            items = [({**base, **t}, f"[[texture]] #{i + 1}") for i, t in enumerate(doc.get("texture", []))]
            unknown = set(doc) - {"defaults", "texture"}
            if unknown:
                raise ProfileError(f"{p}: unknown table(s) {', '.join(sorted(unknown))}: use "
                                   "[defaults] and [[texture]]")
        else:
            lines = [ln for ln in io.StringIO(_text(p), newline="")
                     if ln.strip() and not ln.lstrip().startswith("#")]
            header = [f.strip().lower() for f in next(csv.reader(lines[:1]), [])]
            if "file" not in header:
                raise ProfileError(f"{p}: a manifest needs a `file` column naming each profile (its "
                                   f"header is {', '.join(h for h in header if h) or 'empty'}; known "
                                   f"columns: {', '.join(KEYS)})")
            rows = list(csv.DictReader(lines))
            items = [({k.strip(): (v or "").strip() for k, v in r.items()
                       if k is not None and (v or "").strip()}, f"row {i + 2}") for i, r in enumerate(rows)]
    except HostdError:
        raise
    except FileNotFoundError:
        raise ProfileError(f"no such manifest: {p}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ProfileError(f"cannot read the manifest {p}: {exc}") from None
    except Exception as exc:  # tomllib.TOMLDecodeError, csv.Error
        raise ProfileError(f"{p}: not a valid manifest: {exc}") from None
    if not items:
        raise ProfileError(f"{p}: the manifest lists no texture (a header 'file,...' then one row each)")
    out = [_entry(item, where, p, defaults or LoadOptions()) for item, where in items]
    names = [e.name for e in out]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ProfileError(f"{p}: texture name(s) used twice: {', '.join(dup)}; give each a `name`")
    return out


def _entry(item: dict, where: str, manifest: Path, base: LoadOptions) -> Entry:
    bad = set(item) - set(KEYS)
    if bad:
        raise ProfileError(f"{manifest} {where}: unknown key(s) {', '.join(sorted(bad))}; known: "
                           f"{', '.join(KEYS)}")
    if not item.get("file"):
        raise ProfileError(f"{manifest} {where}: no file")
    src = str(item["file"])
    if not src.startswith("synthetic:"):
        fp = Path(src)
        src = str(fp if fp.is_absolute() else (manifest.parent / fp).resolve())
        try:
            mode = os.stat(src).st_mode
        except OSError:
            mode = None  # a missing file is the loader's to report, with the texture's row
        if mode is not None and not stat.S_ISREG(mode):
            from hostd.fileio import file_kind

            raise ProfileError(f"{manifest} {where}: {item['file']} is {file_kind(mode)}: only regular "
                               "files are read")
    opts = base
    try:
        if "units" in item:
            opts = replace(opts, x_unit=_unit(item["units"]), y_unit=_unit(item["units"]))
        for k in ("x_unit", "y_unit"):
            if k in item:
                opts = replace(opts, **{k: _unit(item[k])})
        if "spacing" in item:
            opts = replace(opts, spacing=_pos(item["spacing"], "spacing"))
        if "columns" in item:
            opts = replace(opts, columns=parse_columns(str(item["columns"])))
        if "offset_mm" in item:
            opts = replace(opts, offset_mm=_num(item["offset_mm"], "offset_mm"))
        if "length_mm" in item:
            v = item["length_mm"]
            whole = str(v).lower() in ("all", "none")
            opts = replace(opts, length_mm=None if whole else _pos(v, "length_mm"))
        if "detrend" in item:
            if item["detrend"] not in ("none", "mean", "linear"):
                raise ProfileError(f"detrend {item['detrend']!r}: use none, mean or linear")
            opts = replace(opts, detrend=str(item["detrend"]))
        if "decimal_comma" in item:
            opts = replace(opts, decimal_comma=_bool(item["decimal_comma"]))
        if "member" in item:
            opts = replace(opts, member=str(item["member"]))
    except ProfileError as exc:
        raise ProfileError(f"{manifest} {where}: {exc}") from None
    name = str(item.get("name") or (src if src.startswith("synthetic:") else Path(src).stem))
    return Entry(name=name, source=src, options=opts, group=str(item.get("group") or ""))


def _unit(v) -> str:
    if str(v) not in UNITS_TO_UM:
        raise ProfileError(f"unit {v!r}: use m, mm, um or nm")
    return "um" if str(v) == "µm" else str(v)


def _num(v, what: str) -> float:
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise ProfileError(f"{what} {v!r} is not a number") from None
    if not math.isfinite(x):
        raise ProfileError(f"{what} must be finite, got {v!r}")
    return x


def _pos(v, what: str) -> float:
    x = _num(v, what)
    if x <= 0:
        raise ProfileError(f"{what} must be > 0, got {v!r}")
    return x


def _bool(v) -> bool:
    if isinstance(v, bool):
        return v
    s = str(v).strip().lower()
    if s in ("1", "true", "yes", "y"):
        return True
    if s in ("0", "false", "no", "n", ""):
        return False
    raise ProfileError(f"decimal_comma {v!r}: use true or false")
