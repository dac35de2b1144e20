"""`python -m hostd.fleet ship --config FILE [--once]`: the shipper without the whole command line.

`hostd fleet ship` execs this (the same process id, as systemd started it): the full parser of
`hostd` loads every room's command definitions, some 4 MB the shipper would keep for its life, and
its budget is 25 MB (docs/fleet.md). Errors: one line on stderr, exit 2, as `hostd`."""

from __future__ import annotations

import argparse
import os
import sys
import types


def _lighter_psycopg() -> None:
    """Two of psycopg's imports the shipper never uses, left out of its process (1.2 MB of its PSS
    on Python 3.11, measured with /proc/PID/smaps_rollup): typing_extensions, which psycopg only
    needs for TypeVar(default=...), a hint for type checkers; and importlib.metadata (with email
    and zipfile), which psycopg.version loads only to read its own version number. Each stand-in
    gives the real thing on any other use: typing_extensions' other names import the real module
    then; psycopg.version stays real when its dist-info cannot be found by name."""
    import importlib
    import importlib.util
    import typing

    if "psycopg" in sys.modules:
        return
    if "typing_extensions" not in sys.modules and sys.version_info < (3, 13):
        stub = types.ModuleType("typing_extensions")

        def type_var(name, *constraints, default=None, infer_variance=False, **kw):
            return typing.TypeVar(name, *constraints, **kw)

        def real_attr(name):  # any other name: the real module, from then on
            if name.startswith("__"):  # the import system's looks (__path__ on `from ... import`)
                raise AttributeError(name)
            real = sys.modules.get("typing_extensions")
            if real is stub:
                del sys.modules["typing_extensions"]
                try:
                    real = importlib.import_module("typing_extensions")
                except BaseException:
                    sys.modules["typing_extensions"] = stub
                    raise
            return getattr(real, name)

        stub.TypeVar = type_var
        stub.__getattr__ = real_attr
        sys.modules["typing_extensions"] = stub
    spec = importlib.util.find_spec("psycopg")
    where = spec.submodule_search_locations if spec else None
    if where:
        site = os.path.dirname(next(iter(where)))
        try:
            version = next((n[len("psycopg-"):-len(".dist-info")] for n in os.listdir(site)
                            if n.startswith("psycopg-") and n.endswith(".dist-info")), None)
        except OSError:
            version = None
        if version:
            v = types.ModuleType("psycopg.version")
            v.__version__ = version
            sys.modules["psycopg.version"] = v


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="hostd fleet")
    sub = ap.add_subparsers(dest="what", required=True)
    s = sub.add_parser("ship")
    s.add_argument("--config", required=True)
    s.add_argument("--once", action="store_true")
    args = ap.parse_args(argv)
    _lighter_psycopg()
    from hostd.errors import HostdError
    from hostd.fleet.cli import run_ship

    try:
        return run_ship(args.config, args.once)
    except HostdError as e:
        print(f"hostd fleet: error: {e}", file=sys.stderr)
        return e.exit_code
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
