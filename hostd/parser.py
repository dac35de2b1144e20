"""The argument parser of `hostd`, below everything that needs it: hostd/cli.py parses and
dispatches with it, hostd/docgen.py generates the man page and the shell completions from it
(and install-service installs those), so none of them imports cli.py.

A subcommand is registered in ONE place, `build_parser`: the toolkit's own commands are declared
here (their code is hostd/commands.py); a room (bench, service, sim, ...) has its own
`add_parser(sub)` in hostd/<room>/cli.py, called from the list at the end of `build_parser`.
"""

from __future__ import annotations

import argparse

from hostd import __version__, commands
from hostd.cliopts import (
    Parser,
    _finite,
    _positive,
    geometry_parent,
    index_parent,
    loader_parent,
    needs_subcommand,
    renamed,
)
from hostd.codec import formats


def build_parser() -> argparse.ArgumentParser:
    ap = Parser(
        prog="hostd",
        description="Vibrotactile texture codec, quality index, renderer and device daemon.",
    )
    ap.add_argument("--version", action="version", version=f"hostd {__version__}")
    sub = ap.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    loader, geom, idx = loader_parent(), geometry_parent(), index_parent()

    p = sub.add_parser("encode", parents=[loader, geom, idx],
                       help="compress a height profile into a .vtx stream")
    p.add_argument("profile", help="profile file (csv/txt/npy) or synthetic:wood[:SEED]")
    p.add_argument("-o", "--output", required=True, help="output .vtx file")
    p.add_argument("--format", choices=list(formats.FORMATS), default=formats.DEFAULT,
                   help="stream format (default " + formats.DEFAULT + "; "
                   + "; ".join(f"{f.name}: {f.summary}" for f in formats.FORMATS.values()) + ")")
    p.add_argument("--method", choices=sorted({m for f in formats.FORMATS.values() for m in f.methods}),
                   default=None, help="shaped: step g·b(f_k) (v2 only); quant, cut: the paper's methods")
    p.add_argument("--g-db", dest="g", type=_finite, default=None,
                   help="shaped: step relative to the detection threshold, dB (multiple of 0.25)")
    renamed(p, "--g-db", "--g")
    p.add_argument("--levels", type=int, default=None, help="quantization steps L (quant)")
    p.add_argument("--b0-db", dest="b0", type=_finite, default=None, help="threshold shift b0 in dB (cut)")
    renamed(p, "--b0-db", "--b0")
    p.add_argument("--value-bits", type=int, default=None, choices=[0, 8, 16, 32],
                   help="cut survivors: 0 = exact float64 (v1 only; the v1 default), else "
                   "integers of this width (v2 default 16)")
    p.add_argument("--coder", default="auto", choices=["auto", "none", "deflate"],
                   help="v1 lossless entropy stage (default auto: the smaller)")
    p.add_argument("--target-iobj", type=_finite, default=None,
                   help="rate control: the smallest stream whose Iobj <= X and SPQI >= --spqi-min, "
                   "both measured on the stream returned (only --method's knob when given, else "
                   "every method); the output leads with the one that set the size, often SPQI "
                   "(then Iobj is well under X; JSON: binding, size_set_by)")
    p.add_argument("--spqi-min", type=_finite, default=0.9,
                   help="rate control's waveform criterion: SPQI of the played signal >= this "
                   "(default 0.9; as hostd iobj REF STREAM reports it)")
    p.add_argument("--guard-db", type=_finite, default=None,
                   help="rate control: also require wSNR (SNR weighted by the detection threshold "
                   "b(f)) >= this, dB (default: off; the proxy is reported, SPQI is measured)")
    p.add_argument("--guard-ssnr-db", type=_finite, default=None,
                   help="rate control: also require sSNR (SNR weighted by the SPQI model's "
                   "threshold curve) >= this, dB (default: off)")
    p.add_argument("--no-guard", action="store_true",
                   help="rate control on Iobj alone (no waveform criterion; can return a wrong "
                   "waveform, see docs)")
    p.add_argument("--json", action="store_true",
                   help="print the result (setting, bytes, Ip, Ia, Iobj, SPQI, waveform_verified, "
                   "size_set_by) as JSON on stdout")
    p.set_defaults(func=commands.cmd_encode)

    p = sub.add_parser("decode", help="reconstruct heights (µm, one per line) from a stream")
    p.add_argument("stream")
    p.add_argument("-o", "--output", default=None,
                   help="output: .csv or .txt (one height per line; default stdout) or .npy")
    p.set_defaults(func=commands.cmd_decode)

    p = sub.add_parser("inspect", help="print a stream's header and coefficients")
    p.add_argument("stream")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=commands.cmd_inspect)

    p = sub.add_parser("iobj", parents=[loader_parent(None), geometry_parent(from_stream=True), idx],
                       help="Ip, Ia, Iobj of a stream (against a profile or its header), or of a decoded "
                       "profile against its reference",
                       description="Ip, Ia, Iobj of a .vtx stream, against REFERENCE_PROFILE or its own "
                       "header; or of DECODED_PROFILE (another codec's output in any profile format, e.g. "
                       "an .hjif) against REFERENCE_PROFILE, both read with the same options, N' from "
                       "--ref-speed-mm-s and --fmax-hz (default 50 mm/s and 400 Hz for a decoded profile).")
    p.add_argument("first", metavar="[REFERENCE_PROFILE] STREAM|DECODED_PROFILE")
    p.add_argument("stream", nargs="?", default=None, help=argparse.SUPPRESS)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=commands.cmd_iobj)

    p = sub.add_parser("render", help="the displacement a hand at constant speed feels, as a WAV file")
    p.add_argument("stream", help=".vtx stream")
    p.add_argument("-o", "--output", required=True, help="output .wav file")
    p.add_argument("--speed-mm-s", dest="speed", type=_finite, default=50.0,
                   help="hand speed, mm/s (default 50)")
    renamed(p, "--speed-mm-s", "--speed")
    p.add_argument("--seconds", type=_positive, default=5.0, help="duration, s (default 5)")
    p.add_argument("--rate-hz", dest="rate", type=_positive, default=48000.0,
                   help="WAV sample rate, Hz (default 48000; 3000 = the device's rate)")
    renamed(p, "--rate-hz", "--rate")
    p.add_argument("--start-mm", type=_finite, default=0.0, help="start position, mm (default 0)")
    p.add_argument("--full-scale-um", type=_positive, default=40.0,
                   help="displacement at WAV full scale (±1.0), µm (default 40 = half the piezo's "
                   "80 µm travel, the output stage's limit)")
    p.add_argument("--format", choices=["int16", "float32"], default="int16",
                   help="WAV samples: int16 PCM (default, round(32767 h / full scale)) or float32")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=commands.cmd_render)

    p = sub.add_parser("demo", help="the main job: the daemon on the embedded default device, end to end")
    p.add_argument("-o", "--output", dest="out", default=None, help="directory for the demo's files")
    renamed(p, "--output", "--out")
    p.add_argument("--sim", action="store_true", help="use the simulated display, not the firmware host port")
    p.add_argument("--render", choices=["auto", "host", "device"], default="auto",
                   help="who renders: auto (the display when it can, protocol v2; the default, as "
                   "[render] where), host (stream 3 kHz samples) or device")
    p.add_argument("--seconds", type=_positive, default=3.5, help="play time per texture (default 3.5)")
    p.add_argument("--codec-only", action="store_true", help="only the codec table (no daemon)")
    p.set_defaults(func=commands.cmd_demo)

    p = sub.add_parser("fit", parents=[loader_parent(None)],
                       help="fit (a, b) of Iobj to subjective scores (CSV)")
    p.add_argument("scores", help="CSV: texture,method,level,score and Ip,Ia or stream[,profile]")
    p.add_argument("--nonnegative", action="store_true", help="constrain a, b >= 0")
    p.add_argument("--scale-max", type=float, default=3.0,
                   help="top of the rating scale (default 3, the paper's 0..3 grades)")
    p.add_argument("--scale-min", type=float, default=0.0,
                   help="bottom of the rating scale (default 0); scores outside are refused")
    p.add_argument("--bootstrap", type=int, default=2000, metavar="N",
                   help="bootstrap resamples for the intervals of (a, b) (default 2000; 0 = none)")
    p.add_argument("--exclude-saturated", action="store_true",
                   help="exclude stimuli whose mean score is at --scale-max (flagged)")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=commands.cmd_fit)

    p = sub.add_parser("report", help="reports: rate-quality")
    rsub = p.add_subparsers(dest="report", metavar="REPORT")
    p.set_defaults(func=needs_subcommand(p, "a report"))
    r = rsub.add_parser("rate-quality", parents=[loader, geom, idx],
                        help="sweep both methods: bytes vs Ip, Ia, Iobj (CSV, Markdown, PNG)")
    r.add_argument("profile", help="profile file or synthetic:wood[:SEED]")
    r.add_argument("-o", "--output", dest="out", default="rate-quality", help="output directory")
    renamed(r, "--output", "--out")
    r.add_argument("--no-progress", action="store_true")
    r.add_argument("--json", action="store_true", help="print notes and every row as JSON")
    r.set_defaults(func=commands.cmd_report_rate_quality)

    p = sub.add_parser("completion", help="print the shell completion script (bash, zsh, fish)",
                       description="Print the completion script; install-service installs all three. By "
                       "hand: hostd completion bash > ~/.local/share/bash-completion/completions/hostd; "
                       "hostd completion fish > ~/.config/fish/completions/hostd.fish; "
                       "hostd completion zsh > ~/.zfunc/_hostd (a directory on $fpath)")
    p.add_argument("shell", choices=["bash", "zsh", "fish"])
    p.set_defaults(func=commands.cmd_completion, root_parser=ap)
    p = sub.add_parser("manpage", help="print the man page hostd(8) (roff), generated from this parser",
                       description="install-service installs it as /usr/local/share/man/man8/hostd.8")
    p.add_argument("--markdown", action="store_true",
                   help="the same reference as Markdown (the docs site's command-line page)")
    p.set_defaults(func=commands.cmd_manpage, root_parser=ap)

    # ---- rooms: each registers its subcommands with its own add_parser(sub); a new room adds
    # its import and its call here (and nowhere else: docgen, completion and --help follow)
    from hostd.bench.cli import add_parser as add_bench
    from hostd.corpus.cli import add_parser as add_corpus
    from hostd.experiment.cli import add_parser as add_experiment
    from hostd.export_cli import add_parser as add_export
    from hostd.fleet.cli import add_parser as add_fleet
    from hostd.service.cli import add_parsers as add_service
    from hostd.sim.cli import add_parser as add_sim

    add_export(sub)
    add_bench(sub, [loader_parent(None)])
    add_corpus(sub, [loader_parent(10.0)])
    add_service(sub)
    # generated from the whole parser (docgen does not import this module: it is handed the parser)
    sub.choices["install-service"].set_defaults(root_parser=ap)
    add_sim(sub)
    add_experiment(sub)
    add_fleet(sub)

    from hostd.helptext import add_epilogs

    add_epilogs(ap)  # the README's examples in each command's --help
    return ap
