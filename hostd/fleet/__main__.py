"""`python -m hostd.fleet ship --config FILE [--once]`: the shipper without the whole command line.

`hostd fleet ship` execs this (the same process id, as systemd started it): the full parser of
`hostd` loads every room's command definitions, some 4 MB the shipper would keep for its life, and
its budget is 25 MB (docs/fleet.md). Errors: one line on stderr, exit 2, as `hostd`."""

from __future__ import annotations

import argparse
import sys


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="hostd fleet")
    sub = ap.add_subparsers(dest="what", required=True)
    s = sub.add_parser("ship")
    s.add_argument("--config", required=True)
    s.add_argument("--once", action="store_true")
    args = ap.parse_args(argv)
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
