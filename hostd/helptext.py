"""The README's command-line examples, in every command's --help (its epilog) and so in the man
page: an installed user has no README. EXAMPLES is the README's "Command line" block verbatim
(tests/test_users.py keeps the two the same)."""

from __future__ import annotations

import argparse
import functools
import re

EXAMPLES = """\
hostd encode PROFILE -o OUT.vtx --target-iobj 0.05              # rate control: the smallest stream with
                                                                #   Iobj <= 0.05 and SPQI >= 0.9 (measured)
hostd encode PROFILE -o OUT.vtx --method shaped --g-db -10   # threshold-shaped steps 10^(g/20) b(f_k) (v2)
hostd encode PROFILE -o OUT.vtx --method quant --levels 14      # linear quantization (eq. 5, 6)
hostd encode PROFILE -o OUT.vtx --method cut --b0-db -4         # threshold-cut (eq. 7)
hostd encode PROFILE -o OUT.vtx --format v1 --method quant --levels 14   # the original v1 stream
hostd encode ... --json                                         # the setting, bytes, Ip, Ia, Iobj as JSON
hostd decode IN.vtx -o PROFILE.csv                              # reconstructed heights, µm, one per line
hostd inspect IN.vtx --json                                     # header, sizes, ratios, ref P/A, coefficients
hostd iobj IN.vtx --json                                        # receiver side: index from the stream alone
hostd iobj REFERENCE_PROFILE IN.vtx --json                      # sender side: against the original
hostd iobj REFERENCE_PROFILE DECODED_PROFILE --json             # another codec's output (e.g. an .hjif)
hostd fit SCORES.csv [--json] [--nonnegative] [--exclude-saturated] [--bootstrap N]   # (a, b), SE, intervals
hostd experiment threshold -o thr --participant p01             # detection thresholds b(f) on your display
hostd experiment similarity DESIGN.toml -o sim --participant p01   # the paper's test: scores for hostd fit
hostd experiment calibration -o lab.toml --thresholds thr/thresholds.csv --fit fit.json   # your (a, b), b(f)
hostd experiment bench [--runs 400] [--check] [--json]          # the procedures on simulated observers
hostd report rate-quality PROFILE -o DIR [--json]               # CSV, Markdown, PNG: Iobj, Ip, Ia, SPQI, CPU
hostd render IN.vtx --speed-mm-s 50 --seconds 5 -o OUT.wav      # what a hand at 50 mm/s feels, as a WAV file
hostd export IN.vtx|PROFILE -o OUT.hjif [--speed-mm-s 80]       # MPEG-I Haptics .hjif (the standard)
HOSTD_RUN_MPEG_RM=1 hostd encode IN.hmpg --spacing 6.25 ...      # .hmpg: the sandboxed MPEG-I reference
hostd bench accuracy [--json] [--plot F.png]                    # every render knob: error vs CPU
hostd bench pipeline | latency | codec | scoring | sim | load | offline | all   # real-time cost, latency...
hostd bench soak [--seconds 600] [--load]                       # the daemon for minutes: played fraction
hostd demo [--sim] [--render host|device]                       # the daemon on the embedded display
hostd corpus run DIR|MANIFEST... --codec hostd-v2 --codec my.py:Codec -o R.sqlite   # codecs x settings
hostd corpus report R.sqlite -o DIR                             # BD-rate tables, rate-quality PNGs
hostd corpus run synthetic:wood:1-5 --codec v2 --codec mpeg-rm --report DIR  # BD-rate vs the standard
hostd corpus export R.sqlite -o R.parquet                       # the store as Parquet (or .csv)
hostd corpus compare R.sqlite@1 R.sqlite@2 -o DIR               # BD-rate of run 2's curves against run 1's
hostd corpus runs R.sqlite                                      # a store's runs: number, start, hostd, rows
hostd bench corpus [--json]                                     # the corpus runner: efficiency, overhead
hostd bench soak --render device --runs 3 --seconds 40 --check  # device mode's footprint: PSS, threads, CPU
hostd bench cli | scoring | cycle --compiled-only [--check [ci]]  # guarded figures: exit 1 past a bound

hostd run [--config F]                                          # the daemon (systemd runs it; default config
                                                                #   $HOSTD_CONFIG, else /etc/hostd/hostd.toml)
hostd send FILE.vtx [--name N]; hostd list; hostd select NAME   # client of the control socket
hostd status [--json]; hostd stop [--daemon]                    # health from the device's own counters
hostd quality [--since 1h] [--csv|--json]                       # the quality log: Iobj and what was delivered
hostd fleet ship --config /etc/hostd/fleet.toml [--once]        # this PC's quality log to the central store
hostd fleet migrate --url URL; hostd fleet add-pc ROLE --url URL  # the central schema; a display PC's role
hostd fleet report --db URL --role viewer -o DIR                # the fleet's report (HTML, PNG, CSV)
hostd fleet simulate --check                                    # the central store's scale, measured
hostd sim SCENE [--json] [--plot DIR]                           # delivered quality per effect (scenes)
hostd doctor [--config F] [--json]                              # device, permissions, real time, config, db
hostd install-service [--prefix P] [--dry-run] [--enable]       # unit, udev rule, sysusers, tmpfiles, config,
                                                                #   man page, bash/zsh/fish completion
hostd completion bash|zsh|fish; hostd manpage                   # generated from the parser
"""


def _commands(piece: str) -> list[tuple[str, ...]]:
    """The command paths one example runs: 'hostd bench pipeline | latency' -> two."""
    words = piece.split()
    if len(words) < 2 or words[0] != "hostd":
        return []
    head = [w for w in words[1:] if not w.startswith(("-", "[", "."))]
    m = re.match(r"hostd (\S+) (\S+(?: \| \S+)+)", piece)
    if m:
        return [(m.group(1), alt) for alt in m.group(2).split(" | ")]
    if len(head) >= 2 and "|" in head[1]:  # hostd completion bash|zsh|fish
        return [(head[0], alt) for alt in head[1].split("|")]
    return [tuple(head[:2])]


@functools.cache
def examples() -> tuple[tuple[tuple[str, ...], str], ...]:
    """(command path, the example as the README writes it, with its comment when the line
    holds one command). Parsed once: every command's epilog asks (45 parses were 27 ms of each
    command line's start, `hostd bench cli`)."""
    out = []
    for line in EXAMPLES.splitlines():
        if not line.startswith("hostd "):
            continue
        text, _, comment = line.partition("#")
        pieces = [p.strip() for p in text.rstrip().split("; ")]
        for piece in pieces:
            shown = f"{piece}   # {comment.strip()}" if len(pieces) == 1 and comment else piece
            for path in _commands(piece):
                out.append((path, shown))
    return tuple(out)


def epilog_for(path: tuple[str, ...]) -> str | None:
    """The examples of the command at path (its own and its subcommands'), or None."""
    lines = list(dict.fromkeys(t for p, t in examples() if p[:len(path)] == path))
    return "examples:\n" + "\n".join("  " + t for t in lines) if lines else None


class HelpFormatter(argparse.HelpFormatter):
    """argparse's formatter, with an epilog of examples kept line by line."""

    def _fill_text(self, text, width, indent):
        if text.startswith("examples:\n"):
            return "\n".join(indent + line for line in text.splitlines())
        return super()._fill_text(text, width, indent)


TOP_EPILOG = """\
examples:
  hostd encode PROFILE -o OUT.vtx --target-iobj 0.05   # compress: the smallest stream with Iobj <= 0.05
  hostd render OUT.vtx -o OUT.wav                      # what a hand at 50 mm/s feels
  hostd send OUT.vtx; hostd select OUT                 # play it on the display (the daemon's socket)
  hostd demo                                           # the daemon on the embedded display, end to end
every command's --help ends with its examples; man 8 hostd (hostd manpage) has them all"""


def add_epilogs(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()) -> None:
    """Give every subcommand of parser the README's examples of it as its epilog (and hostd
    itself a few, with where to find the rest)."""
    if not path and not parser.epilog:
        parser.epilog = TOP_EPILOG
        parser.formatter_class = HelpFormatter
    for a in parser._actions:
        if isinstance(a, argparse._SubParsersAction):
            for name, sub in a.choices.items():
                ep = epilog_for((*path, name))
                if ep and not sub.epilog:
                    sub.epilog = ep
                    sub.formatter_class = HelpFormatter
                add_epilogs(sub, (*path, name))
