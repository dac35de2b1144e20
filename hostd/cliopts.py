"""Options and profile reading shared by every command that reads a profile: `hostd` (cli.py),
`hostd bench` (bench/cli.py) and `hostd sim` import them from here, so neither CLI module imports
the other for them (cli.py <-> bench/cli.py was a cycle).

The argparse parser with options anywhere and one-line errors, warnings once per message, the
profile-loading, geometry and index option groups, and read_profile with its plausibility checks.
"""

from __future__ import annotations

import argparse
import math
import re
import sys


class Parser(argparse.ArgumentParser):
    """argparse with options anywhere between the positionals (every command) and one-line errors.

    Options may come before, between or after positionals (`hostd iobj REF --length-mm 10 S`):
    each leaf command parses with `parse_known_intermixed_args`. Errors are one line on stderr
    with the hint to `--help`, exit code 2.
    """

    _intermixing = False

    def parse_known_args(self, args=None, namespace=None):
        if self._intermixing or any(isinstance(a, argparse._SubParsersAction) for a in self._actions):
            return super().parse_known_args(args, namespace)
        self._intermixing = True
        try:
            ns, extras = super().parse_known_intermixed_args(args, namespace)
        finally:
            self._intermixing = False
        # a required option with an old spelling (renamed): argparse cannot see that the alias
        # gave it, so it is checked here, after both spellings had their chance
        missing = [a for a in self._actions if getattr(a, "required_by_name", False)
                   and getattr(ns, a.dest, None) is None]
        if missing:
            self.error("the following arguments are required: "
                       + ", ".join("/".join(a.option_strings) for a in missing))
        return ns, extras

    def error(self, message: str):
        message = " ".join(message.split())
        m = _INVALID_CHOICE.match(message)
        if m:  # a mistyped command or choice: the closest one, not the whole list
            import difflib

            choices = re.findall(r"'([^']*)'", m.group(3))
            close = difflib.get_close_matches(m.group(2), choices, n=1, cutoff=0.6)
            if close:
                message = f"{m.group(1)}invalid choice: '{m.group(2)}', did you mean '{close[0]}'?"
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


class _OldSpelling(argparse.Action):
    """A renamed option's old spelling: hidden from help, completion and the man page; it does
    what the new spelling does, after a note on stderr (once per spelling and process)."""

    def __init__(self, option_strings, dest, target: argparse.Action, new: str):
        super().__init__(option_strings, dest, nargs=target.nargs, const=target.const,
                         default=argparse.SUPPRESS, type=target.type, choices=target.choices,
                         help=argparse.SUPPRESS, metavar=target.metavar)
        self.target, self.new = target, new

    def __call__(self, parser, namespace, values, option_string=None):
        warn_once(f"hostd: {option_string} is deprecated: use {self.new} (the old spelling goes in the "
                  "next release)")
        self.target(parser, namespace, values, self.new)


def renamed(container, new: str, *old: str) -> None:
    """Keep the old spellings `old` of the option `new` (already added to `container`, a parser or
    an argument group) working for one release, as hidden deprecated aliases. One name per
    concept, with its unit (tests/test_toolkit_cli.py walks the parser for the spellings that
    must not come back)."""
    target = container._option_string_actions[new]
    if target.required:  # checked by Parser.parse_known_args, so that an old spelling satisfies it
        target.required, target.required_by_name = False, True
    for o in old:
        container._add_action(_OldSpelling([o], target.dest, target, new))


_NOTED: set[str] = set()


def warn_once(line: str) -> None:
    if line not in _NOTED:
        _NOTED.add(line)
        print(line, file=sys.stderr)


_INVALID_CHOICE = re.compile(r"^(argument [^:]+: )invalid choice: '(.*?)' \(choose from (.*)\)$")


def needs_subcommand(parser: argparse.ArgumentParser, what: str):
    """The `func` of a command group called without its subcommand (`hostd bench`, `hostd report`):
    its help on stderr and exit code 2, one behaviour for every group."""

    def func(_args) -> int:
        sys.stderr.write(parser.format_help())
        print(f"{parser.prog}: error: choose {what} (see above)", file=sys.stderr)
        return 2

    return func


_WARNED: set[str] = set()


def warn(command: str, message: str) -> None:
    """A warning on stderr, once per message and process."""
    if message not in _WARNED:
        _WARNED.add(message)
        print(f"hostd {command}: warning: {message}", file=sys.stderr)


def _positive(v: str) -> float:
    try:
        x = float(v)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {v!r}") from None
    if not (math.isfinite(x) and x > 0):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0: {v!r}")
    return x


def _finite(v: str) -> float:
    try:
        x = float(v)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {v!r}") from None
    if not math.isfinite(x):
        raise argparse.ArgumentTypeError(f"must be finite: {v!r}")
    return x


def loader_parent(length_default: float | None = 10.0) -> argparse.ArgumentParser:
    """The profile-loading options shared by every command that reads a profile."""
    p = Parser(add_help=False)
    g = p.add_argument_group("profile loading")
    units = ["m", "mm", "um", "nm"]
    g.add_argument("--x-unit", default=None, choices=units, help="unit of x / spacing (default um)")
    g.add_argument("--y-unit", default="um", choices=units, help="unit of heights (default um)")
    g.add_argument("--spacing", type=_positive, default=None,
                   help="sample spacing in x-unit (one-column files; or resampling target)")
    g.add_argument("--length-mm", type=_positive, default=length_default,
                   help="patch length taken from the profile, mm "
                   + ("(default 10; the whole profile if shorter)" if length_default
                      else "(default: the stream's)"))
    g.add_argument("--offset-mm", type=float, default=0.0, help="patch start, mm (default 0)")
    g.add_argument("--detrend", default="none", choices=["none", "mean", "linear"])
    g.add_argument("--columns", default=None, metavar="X,Y",
                   help="text files: which columns (1-based) hold x and height, e.g. 2,3; or one "
                   "column Y for heights only (with --spacing). Default: one or two columns")
    g.add_argument("--decimal-comma", action="store_true",
                   help="text files: numbers use a decimal comma (1,5); columns split on ; tab or space")
    g.add_argument("--member", "--var", dest="member", default=None, metavar="NAME",
                   help="container files: which array. .mat: the variable that holds the profile when "
                   "there are several (or X,Y: an x and a height vector); .hjif/.hmpg: "
                   "PERCEPTION[/CHANNEL], each an index or id=N (default: the only one, or the texture "
                   "over space)")
    g.add_argument("--full-scale-um", type=_positive, default=None, metavar="UM",
                   help=".hjif/.hmpg: the displacement of amplitude 1.0, µm, for files that state none "
                   "(default 1 --y-unit); hostd export: the full scale it writes (default: the source's)")
    return p


def geometry_parent(from_stream: bool = False) -> argparse.ArgumentParser:
    """--ref-speed-mm-s, --fmax-hz, --thresholds. from_stream: a command that reads a stream, whose header
    carries v_ref and f_max (default None: the stream's; given, they are checked against it)."""
    p = Parser(add_help=False)
    g = p.add_argument_group("geometry and perception")
    g.add_argument("--ref-speed-mm-s", dest="speed", type=_positive, default=None if from_stream else 50.0,
                   help="reference hand speed v_ref, mm/s: the speed the texture's frequencies "
                   "f_k = k v / 2L refer to (default " + ("the stream's)" if from_stream else "50)"))
    renamed(g, "--ref-speed-mm-s", "--speed")
    g.add_argument("--fmax-hz", dest="fmax", type=_positive, default=None if from_stream else 400.0,
                   help="band limit at v_ref, Hz (default " + ("the stream's)" if from_stream else "400)"))
    renamed(g, "--fmax-hz", "--fmax")
    g.add_argument("--thresholds", default=None, metavar="CSV",
                   help="detection-threshold curve (default: the stream's if embedded, else "
                   "shipped default curve)" if from_stream else
                   "detection-threshold curve (default: the shipped default curve, the paper's)")
    return p


def index_parent() -> argparse.ArgumentParser:
    p = Parser(add_help=False)
    g = p.add_argument_group("quality index")
    g.add_argument("--preset", default="both", choices=["both", "wood", "sandpaper"],
                   help="(a, b) fitted in the paper (default both: 0.581, 0.464)")
    g.add_argument("--a", type=_finite, default=None, help="weight of Ip (overrides --preset)")
    g.add_argument("--b", type=_finite, default=None, help="weight of Ia (overrides --preset)")
    g.add_argument("--calibration", action=CalibrationAction, default=None, metavar="FILE",
                   help="a display's calibration (hostd experiment calibration): its (a, b) and, "
                   "unless --thresholds is given, its threshold curve")
    return p


class CalibrationAction(argparse.Action):
    """--calibration FILE: loaded (one-line error if bad) and, unless --thresholds was given,
    its curve becomes the command's --thresholds (every reader of that option reads a
    calibration file as-is); _ab takes its (a, b) unless --a/--b say otherwise."""

    def __call__(self, parser, namespace, value, option_string=None):
        from hostd.errors import HostdError
        from hostd.perception import calibration

        try:
            cal = calibration.load(value)
        except HostdError as e:
            parser.error(f"--calibration: {e}")
        setattr(namespace, self.dest, cal)
        if hasattr(namespace, "thresholds") and getattr(namespace, "thresholds", None) is None:
            namespace.thresholds = value


def _ab(args: argparse.Namespace) -> tuple[float, float]:
    from hostd.perception.indices import PRESETS

    a, b = PRESETS[args.preset]
    cal = getattr(args, "calibration", None)
    if cal is not None:
        a, b = cal.a, cal.b
    return (args.a if args.a is not None else a, args.b if args.b is not None else b)


def load_opts(args: argparse.Namespace, length_mm: float | None = None):
    from hostd.texture.load import LoadOptions, parse_columns

    return LoadOptions(
        x_unit=getattr(args, "x_unit", None) or "um",
        y_unit=args.y_unit,
        spacing=args.spacing,
        length_mm=args.length_mm if args.length_mm is not None else length_mm,
        offset_mm=args.offset_mm,
        detrend=args.detrend,
        columns=parse_columns(getattr(args, "columns", None)),
        decimal_comma=bool(getattr(args, "decimal_comma", False)),
        progress=sys.stderr.isatty(),
        member=getattr(args, "member", None),
        full_scale_um=getattr(args, "full_scale_um", None),
    )


def read_profile(spec: str, args: argparse.Namespace, length_mm: float | None = None):
    """A profile file, or 'synthetic:wood[:SEED]' / 'synthetic:sandpaper[:SEED]'."""
    from hostd.texture import synth
    from hostd.texture.load import cut_patch, load_profile

    command = getattr(args, "command", "") or ""
    if synth.is_spec(spec):
        ignored = [name for name, given in (
            ("--spacing", getattr(args, "spacing", None) is not None),
            ("--x-unit", getattr(args, "x_unit", None) is not None),
            ("--columns", getattr(args, "columns", None) is not None),
            ("--member/--var", getattr(args, "member", None) is not None),
            ("--decimal-comma", getattr(args, "decimal_comma", False)),
            ("--y-unit", getattr(args, "y_unit", "um") != "um")) if given]
        if ignored:
            warn(command, f"{', '.join(ignored)} ignored for {spec} (synthetic profiles are "
                 "generated in µm at 0.5 µm spacing)")
        prof = synth.from_spec(spec)
        return cut_patch(prof.heights_um, prof.spacing_um, load_opts(args, length_mm), spec)
    prof = load_profile(spec, load_opts(args, length_mm))
    if prof.note:
        warn(command, f"{spec}: {prof.note}")
    import numpy as np

    rms_um = float(np.std(prof.heights_um))
    if not RMS_PLAUSIBLE_UM[0] <= rms_um <= RMS_PLAUSIBLE_UM[1]:
        warn(command, f"{spec}: height RMS {rms_um:.3g} µm is implausible for a texture (1 nm to 1 mm): "
             f"check --y-unit (heights were read as {getattr(args, 'y_unit', 'um')})")
    return prof


RMS_PLAUSIBLE_UM = (1e-3, 1e3)  # a texture's height RMS: 1 nm .. 1 mm; outside, the unit is likely wrong
