"""Command-line interface: parses with hostd.parser.build_parser and runs the chosen command
(its `func`), printing a HostdError as one line with its exit code."""

from __future__ import annotations

import sys

from hostd.cliopts import load_opts, read_profile, warn  # noqa: F401  (kept importable from here)
from hostd.commands import format_fields  # noqa: F401
from hostd.errors import HostdError
from hostd.parser import build_parser


def _unrecognized(ap, argv: list[str], extra: list[str]):
    """The command's own error for options it does not take, with the closest option it does
    ('--metod' -> did you mean '--method'?), instead of hostd's for the whole line."""
    import argparse
    import difflib

    p = ap
    for word in argv:
        subs = [a for a in p._actions if isinstance(a, argparse._SubParsersAction)]
        if subs and word in subs[0].choices:
            p = subs[0].choices[word]
    message = f"unrecognized arguments: {' '.join(extra)}"
    options = [o for a in p._actions for o in a.option_strings]
    for e in extra:
        if e.startswith("-"):
            close = difflib.get_close_matches(e.split("=", 1)[0], options, n=1, cutoff=0.6)
            if close:
                message += f", did you mean '{close[0]}'?"
                break
    p.error(message)


def main(argv: list[str] | None = None) -> int:
    ap = build_parser()
    argv = sys.argv[1:] if argv is None else list(argv)
    args, extra = ap.parse_known_args(argv)
    if extra:
        _unrecognized(ap, argv, extra)
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
