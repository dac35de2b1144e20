"""The real-time cycle's state records, declared once in hostd/device/cycle_state.toml.

Each record is a ctypes.Structure whose layout is the C struct of hostd/device/cycle_state.h
(generated from the same file by hostd.device.gen_header). A stage class derives from its
record, so its fields live in the struct and the compiled cycle reads and writes them through
the buffer protocol (no attribute crosses by name); everything else the stage holds (configs,
caches, arrays) stays in its __dict__. A field declared "f64?" or "i64?" may be None: the
struct keeps a `<name>_set` flag beside the value, and the Python attribute maps it.
"""

from __future__ import annotations

import ctypes
import tomllib
from pathlib import Path

SCHEMA_PATH = Path(__file__).resolve().parent / "device" / "cycle_state.toml"
SCHEMA: dict[str, dict[str, str]] = tomllib.loads(SCHEMA_PATH.read_text())
CTYPES = {"f64": ctypes.c_double, "i64": ctypes.c_int64, "bool": ctypes.c_bool}


def fields(kind: str) -> list[tuple[str, str]]:
    """(C member name, type) of a record, in layout order: an optional field is its value
    then its `_set` flag."""
    out = []
    for name, t in SCHEMA[kind].items():
        base = t.rstrip("?")
        if base not in CTYPES:
            raise ValueError(f"cycle_state.toml [{kind}] {name}: type {t!r} is not f64, i64 or bool")
        out.append((name, base))
        if t.endswith("?"):
            out.append((f"{name}_set", "bool"))
    return out


def _optional(value, flag) -> property:
    """The Python face of an optional field: None when its flag is clear."""

    def get(self):
        return value.__get__(self) if flag.__get__(self) else None

    def set_(self, v):
        if v is None:
            flag.__set__(self, False)
        else:
            value.__set__(self, v)
            flag.__set__(self, True)

    return property(get, set_)


def _record(kind: str) -> type[ctypes.Structure]:
    raw = type(f"_{kind}_raw", (ctypes.Structure,),
               {"_fields_": [(n, CTYPES[t]) for n, t in fields(kind)]})
    opt = {n: _optional(getattr(raw, n), getattr(raw, f"{n}_set"))
           for n, t in SCHEMA[kind].items() if t.endswith("?")}
    return type(f"{kind.title()}Record", (raw,), opt)


RECORDS: dict[str, type[ctypes.Structure]] = {k: _record(k) for k in SCHEMA}


def record(kind: str) -> type[ctypes.Structure]:
    """The record class of a stage (its base class)."""
    return RECORDS[kind]


def state_fields(obj) -> dict:
    """obj's record fields as its Python attributes show them (an optional one: None or a
    value), name -> value; {} for an object that holds no record."""
    for kind, cls in RECORDS.items():
        if isinstance(obj, cls):
            return {n: getattr(obj, n) for n in SCHEMA[kind]}
    return {}
