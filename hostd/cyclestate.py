"""The real-time cycle's state records, declared once in hostd/device/cycle_state.toml.

Each record is a ctypes.Structure whose layout is the C struct of hostd/device/cycle_state.h,
which setup.py generates from the same file at build (c_header; stdlib only, so the build needs
nothing else: python hostd/cyclestate.py writes it by hand). A stage class derives from its
record, so its fields live in the struct and the compiled cycle reads and writes them through
the buffer protocol (no attribute crosses by name); everything else the stage holds (configs,
caches, arrays) stays in its __dict__. A field declared "f64?" or "i64?" may be None: the
struct keeps a `<name>_set` flag beside the value, and the Python attribute maps it; "f64[N]" is
a fixed array (a ctypes array in Python), N a number or a constant of protocol.toml's [protocol]
("i64[buffer_capacity]": the device's, read from its one declaration).
"""

from __future__ import annotations

import ctypes
import sys
import tomllib
from pathlib import Path

SCHEMA_PATH = Path(__file__).resolve().parent / "device" / "cycle_state.toml"
SCHEMA: dict[str, dict[str, str]] = tomllib.loads(SCHEMA_PATH.read_text())
CTYPES = {"f64": ctypes.c_double, "i64": ctypes.c_int64, "bool": ctypes.c_bool}
C_TYPES = {"f64": "double", "i64": "int64_t", "bool": "bool"}
HEADER_PATH = SCHEMA_PATH.with_suffix(".h")
# the device protocol's constants, for array lengths that are one (read here by path, as setup.py
# runs this file alone: hostd.device.protocol reads the same file)
PROTOCOL: dict[str, int] = tomllib.loads((SCHEMA_PATH.parent / "protocol.toml").read_text())["protocol"]


def _length(n: str) -> int | None:
    """An array's length: a number, or the name of a protocol constant (None: neither)."""
    v = int(n) if n.isdigit() else PROTOCOL.get(n)
    return v if isinstance(v, int) and not isinstance(v, bool) and v > 0 else None


def fields(kind: str) -> list[tuple[str, str, int]]:
    """(C member name, type, array length or 0) of a record, in layout order: an optional field
    is its value then its `_set` flag."""
    out = []
    for name, t in SCHEMA[kind].items():
        base, _, n = t.rstrip("?").partition("[")
        k = _length(n[:-1]) if n.endswith("]") else None
        if base not in CTYPES or (n and k is None):
            raise ValueError(f"cycle_state.toml [{kind}] {name}: type {t!r} is not f64, i64 or bool "
                             "(optionally [N], N a number or a protocol.toml constant, or ?)")
        out.append((name, base, k or 0))
        if t.endswith("?"):
            out.append((f"{name}_set", "bool", 0))
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
               {"_fields_": [(n, CTYPES[t] * k if k else CTYPES[t]) for n, t, k in fields(kind)]})
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
            return {n: list(v) if isinstance(v, ctypes.Array) else v
                    for n in SCHEMA[kind] for v in (getattr(obj, n),)}
    return {}


def c_header() -> str:
    """hostd/device/cycle_state.h: a struct per record, hs_<kind>_t, and HS_RECORDS(X)."""
    lines = ["/* GENERATED at build (setup.py) from hostd/device/cycle_state.toml by hostd/cyclestate.py:",
             " * not in git. The layout is the ctypes.Structure of hostd.cyclestate.record(kind): a stage",
             " * object is read as its struct through the buffer protocol. */",
             "#ifndef HOSTD_CYCLE_STATE_H", "#define HOSTD_CYCLE_STATE_H", "",
             "#include <stdbool.h>", "#include <stdint.h>", ""]
    for kind in SCHEMA:
        members = [f"    {C_TYPES[t]} {n}{f'[{k}]' if k else ''};" for n, t, k in fields(kind)]
        lines += ["typedef struct {", *members, f"}} hs_{kind}_t;", ""]
    lines += ["#define HS_RECORDS(X) " + " ".join(f"X({k})" for k in SCHEMA), "", "#endif"]
    return "\n".join(lines) + "\n"


def write_header(out: Path = HEADER_PATH) -> None:
    """Write the C header (setup.py does at build)."""
    out.write_text(c_header())


if __name__ == "__main__":
    write_header(Path(sys.argv[1]) if len(sys.argv) > 1 else HEADER_PATH)
