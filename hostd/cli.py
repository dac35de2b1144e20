"""Command-line interface: parses with hostd.parser.build_parser and runs the chosen command
(its `func`), printing a HostdError as one line with its exit code."""

from __future__ import annotations

import sys

from hostd.cliopts import load_opts, read_profile, warn  # noqa: F401  (kept importable from here)
from hostd.commands import format_fields  # noqa: F401
from hostd.errors import HostdError
from hostd.parser import build_parser


def main(argv: list[str] | None = None) -> int:
    ap = build_parser()
    args = ap.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except HostdError as exc:
        print(f"hostd {args.command}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print(f"hostd {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 0


if __name__ == "__main__":
    raise SystemExit(main())
