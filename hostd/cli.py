"""Command-line interface: argument parsing only; each subcommand calls into the packages."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from hostd import __version__
from hostd.cliopts import (  # noqa: F401  (read_profile, warn, load_opts: kept importable from here)
    Parser,
    _ab,
    _finite,
    _positive,
    geometry_parent,
    index_parent,
    load_opts,
    loader_parent,
    needs_subcommand,
    read_profile,
    warn,
)
from hostd.errors import HostdError


def _dump(obj) -> None:
    print(json.dumps(obj, indent=None, allow_nan=False))


def _read_stream(path: str):
    from hostd.codec.stream import decode
    from hostd.errors import StreamError

    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise StreamError(f"cannot read {path}: {exc.strerror or exc}") from None
    return decode(data)


def _write_bytes_atomic(path: str, data: bytes) -> None:
    """Output files: hostd.fileio.write_output (atomic for regular files, write-through for
    devices and FIFOs, '-' is stdout, the umask honoured)."""
    from hostd.fileio import write_output

    write_output(path, data)


# ---------------------------------------------------------------- commands


def cmd_encode(args: argparse.Namespace) -> int:
    from hostd.api import encode_heights

    prof = read_profile(args.profile, args)
    res = encode_heights(prof.heights_um, prof.length_mm, method=args.method, fmt=args.format,
                         target_iobj=args.target_iobj,
                         spqi_min=None if args.no_guard else args.spqi_min,
                         guard_db=None if args.no_guard else args.guard_db,
                         ssnr_db=None if args.no_guard else args.guard_ssnr_db, g_db=args.g,
                         levels=args.levels, b0_db=args.b0, value_bits=args.value_bits,
                         coder=args.coder, speed_mm_s=args.speed, fmax_hz=args.fmax,
                         thresholds=args.thresholds, ab=_ab(args))
    data = res.pop("stream")
    _write_bytes_atomic(args.output, data)
    for note in res["notes"]:
        warn("encode", note)
    if res.get("size_set_by") == "waveform":
        print(f"hostd encode: note: the waveform criterion (SPQI >= {res['spqi_min']:g}), not Iobj, set "
              f"the size: Iobj {res['Iobj']:.4f} is under --target-iobj {args.target_iobj:g}; a lower "
              "--spqi-min (or --no-guard, Iobj alone) gives a smaller stream", file=sys.stderr)
    if res["chosen"] is not None:
        print(f"chose {res['chosen']} after {res['encodes']} encodes in "
              f"{res['search_cpu_s'] * 1e3:.0f} ms CPU", file=sys.stderr)
    if args.json:
        _dump({"output": args.output, **res})
        return 0
    sp = "" if res["spqi"] is None else f", SPQI {res['spqi']:.3f}"
    print(
        f"{args.output}: {args.format} {res['method']}, N={res['n']}, N'={res['n_keep']}, "
        f"{res['bytes']} bytes ({100 * res['ratio_coeffs']:.1f}% of 16-bit coefficients, "
        f"{100 * res['ratio_profile']:.2f}% of the 16-bit profile), Iobj {res['Iobj']:.4f}{sp}",
        file=sys.stderr,
    )
    return 0


def cmd_decode(args: argparse.Namespace) -> int:
    s = _read_stream(args.stream)
    y = s.reconstruct()
    text = "\n".join(repr(float(v)) for v in y) + "\n"
    if args.output in (None, "-"):
        sys.stdout.write(text)
    else:
        _write_bytes_atomic(args.output, text.encode())
    return 0


def cmd_inspect(args: argparse.Namespace) -> int:
    s = _read_stream(args.stream)
    info = s.summary()
    if "guard_wsnr_db" not in info:
        info["guard_wsnr_db"] = None
        info["guard_note"] = ("a v1 stream does not record its wSNR: "
                              "hostd iobj REFERENCE_PROFILE STREAM measures it")
    if args.json:
        _dump(info)
        return 0
    for k, v in info.items():
        if k != "coefficients":
            print(f"{k:>15}: {v}")
    print(f"{'coefficients':>15}: {len(info['coefficients'])} values (use --json to list them)")
    return 0


def cmd_iobj(args: argparse.Namespace) -> int:
    from hostd.perception import thresholds
    from hostd.quality import score_stream

    if args.stream is None:
        stream_path, ref_spec = args.first, None
    else:
        stream_path, ref_spec = args.stream, args.first
    s = _read_iobj_stream(stream_path, ref_spec)
    for opt, given, header, unit in (("--speed", args.speed, s.speed_mm_s, "mm/s"),
                                     ("--fmax", args.fmax, s.fmax_hz, "Hz")):
        if given is not None and not math.isclose(given, header, rel_tol=1e-9):
            warn("iobj", f"{opt} {given:g} ignored: the stream was made for {header:g} {unit} (its "
                 "header's geometry defines the components scored)")
    curve = thresholds.load_csv(args.thresholds) if args.thresholds else None
    ref = None
    if ref_spec is not None:
        ref = read_profile(ref_spec, args, length_mm=s.length_mm).heights_um
    a, b = _ab(args)
    sc = score_stream(s, reference_um=ref, curve=curve, a=a, b=b)
    out = sc.as_dict()
    out["reference"] = "profile" if ref is not None else "stream_header"
    from hostd.quality import guard_report

    out.update(guard_report(s, reference_um=ref, curve=curve))
    out["reference_mismatch"] = False
    if ref is not None:
        from hostd.quality import reference_mismatch

        mismatch = reference_mismatch(s, float(sc.P), float(sc.A))
        out["reference_mismatch"] = mismatch is not None
        if mismatch:
            warn("iobj", mismatch)
    from hostd.codec import transform
    from hostd.perception import peer

    if ref is None:
        out["peer_note"] = "peer metrics (SPQI, ST-SIM) need the original: pass REFERENCE_PROFILE"
    else:
        out.update(peer.peer_scores(transform.analyze(ref, s.n_keep), s.coefficients, s.n,
                                    s.length_mm, s.speed_mm_s))
        if not peer.available():
            out["peer_note"] = peer.NOTE_MISSING
    out.update(bytes=s.nbytes, ratio_coeffs=s.ratio_coeffs, ratio_profile=s.ratio_profile,
               method=s.method)
    for k in ("st_sim", "spqi"):  # a peer metric that overflows at this scale: said, never NaN
        if out.get(k) is not None and not math.isfinite(out[k]):
            out[k] = None
            out["peer_note"] = f"{k} is not finite for heights of this magnitude (the metric overflows)"
    if args.json:
        _dump(out)
    else:
        print(format_fields(out))
    return 0


def format_fields(out: dict) -> str:
    """key: value lines, keys aligned, floats to 6 significant digits (JSON keeps full precision)."""
    width = max(map(len, out))

    def fmt(v) -> str:
        if isinstance(v, float) or type(v).__name__.startswith("float"):  # (numpy floats too)
            return f"{float(v):.6g}"
        return str(v)

    return "\n".join(f"{k:>{width}}: {fmt(v)}" for k, v in out.items())


def _read_iobj_stream(stream_path: str, ref_spec: str | None):
    """The STREAM of `hostd iobj [REFERENCE] STREAM`; a file that is not a stream names itself and
    the order, and says so when the two arguments look swapped."""
    from hostd.errors import StreamError

    try:
        return _read_stream(stream_path)
    except StreamError as e:
        hint = "the order is REFERENCE_PROFILE then STREAM (the .vtx last)"
        if ref_spec is not None:
            try:
                _read_stream(ref_spec)
                hint = f"{ref_spec} is the stream: arguments swapped? {hint}"
            except StreamError:
                pass
        raise StreamError(f"STREAM {stream_path}: {e} ({hint})") from None


def cmd_fit(args: argparse.Namespace) -> int:
    from hostd.perception import fit
    from hostd.quality import score_stream

    def score_one(stream_path, profile_spec):
        st = _read_stream(str(stream_path))
        ref = None
        if profile_spec is not None:
            ref = read_profile(str(profile_spec), args, length_mm=st.length_mm).heights_um
        sc = score_stream(st, reference_um=ref)
        return float(sc.Ip), float(sc.Ia)

    stimuli = fit.read_scores(args.scores, score_one)
    res = fit.fit(stimuli, nonnegative=args.nonnegative, scale_max=args.scale_max,
                  scale_min=args.scale_min, exclude_saturated=args.exclude_saturated,
                  n_boot=args.bootstrap)
    for w in res.warnings:
        warn("fit", w)
    if args.json:
        _dump(res.as_dict())
        return 0
    def num(v: float) -> str:  # 4 decimals, or 4 significant digits for weights far from 1
        return f"{v:.4f}" if v == 0 or 1e-3 <= abs(v) < 1e6 else f"{v:.4e}"

    sign = "-" if res.b < 0 else "+"
    print(f"Iobj = {num(res.a)} Ip {sign} {num(abs(res.b))} Ia   ({res.n_used} stimuli"
          f"{', a, b >= 0' if res.nonnegative else ''})")
    pct = f"{100 * res.ci_level:g}%"
    for name, v, se, ci in (("a", res.a, res.se_a, res.ci_a), ("b", res.b, res.se_b, res.ci_b)):
        se_s = "n/a" if se is None else num(se)
        ci_s = "n/a" if ci is None else f"[{num(ci[0])}, {num(ci[1])}]"
        print(f"  {name} = {num(v)}   standard error {se_s}   bootstrap {pct} interval {ci_s}")
    print(f"{'index':<6} {'r2_pearson':>11} {'r2_fit':>8}")
    for name, m in res.metrics.items():
        rp = "n/a" if m["r2_pearson"] is None else f"{m['r2_pearson']:.3f}"
        rf = "n/a" if m["r2_fit"] is None else f"{m['r2_fit']:.3f}"
        print(f"{name:<6} {rp:>11} {rf:>8}")
    print("r2_pearson: squared Pearson correlation with the scores (the paper's R^2); "
          "r2_fit: coefficient of determination of the no-intercept fit")
    for e in res.excluded:
        print(f"excluded: {e['texture']} {e['method']} {e['level']}: {e['why']}")
    return 0


def cmd_report_rate_quality(args: argparse.Namespace) -> int:
    from hostd.codec import transform
    from hostd.extras import need
    from hostd.perception import thresholds
    from hostd.report import rate_quality

    need("matplotlib", "plot", "hostd report rate-quality (its PNG)")  # before the sweep
    prof = read_profile(args.profile, args)
    curve = thresholds.resolve(args.thresholds)
    geom = transform.Geometry(prof.n, prof.length_mm, args.speed, args.fmax)
    res = rate_quality(prof.heights_um, geom, curve, args.out, title=Path(args.profile).name,
                       ab=_ab(args), progress=not (args.no_progress or args.json))
    if args.json:
        _dump({"dir": res["dir"], "notes": res["notes"], "rows": res["rows"],
               "files": [f"{res['dir']}/rate_quality.{e}" for e in ("csv", "md", "png")]})
        return 0
    for n in res["notes"]:
        print(n)
    print(f"wrote {res['dir']}/rate_quality.csv, .md, .png ({len(res['rows'])} streams)")
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    import io

    import numpy as np
    import scipy.io.wavfile

    from hostd.api import render_stroke
    from hostd.errors import ConfigError

    s = _read_stream(args.stream)
    if not (0 < args.seconds <= 3600):
        raise ConfigError(f"--seconds must be within 0..3600, got {args.seconds:g}")
    if not (1000 <= args.rate <= 384000):
        raise ConfigError(f"--rate must be 1000..384000 Hz, got {args.rate:g}")
    out = render_stroke(s, speed_mm_s=args.speed, seconds=args.seconds, rate_hz=args.rate,
                        x0_mm=args.start_mm)
    h = out["height_um"]
    peak = float(np.max(np.abs(h))) if h.size else 0.0
    full = args.full_scale_um
    x = h / full
    clipped = int(np.count_nonzero(np.abs(x) > 1.0))
    if clipped:
        warn("render", f"{clipped} samples exceed the WAV full scale (peak {peak:.3g} µm > "
             f"--full-scale-um {full:g}) and were clipped: raise --full-scale-um")
    x = np.clip(x, -1.0, 1.0)
    data = (np.round(x * 32767).astype(np.int16) if args.format == "int16" else x.astype(np.float32))
    buf = io.BytesIO()
    scipy.io.wavfile.write(buf, round(args.rate), data)
    _write_bytes_atomic(args.output, buf.getvalue())
    info = {"output": args.output, "samples": int(h.size), "rate_hz": float(args.rate),
            "speed_mm_s": args.speed, "seconds": args.seconds, "format": args.format,
            "full_scale_um": full, "peak_um": peak, "clipped": clipped}
    if args.json:
        _dump(info)
    else:
        print(f"{args.output}: {h.size} samples at {args.rate:g} Hz ({args.format}), peak {peak:.4g} µm, "
              f"full scale ±{full:g} µm = ±1.0", file=sys.stderr)
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from hostd.demo import codec_demo, daemon_demo

    if args.codec_only:
        return codec_demo(out_dir=args.out)
    return daemon_demo(out_dir=args.out, seconds_per_texture=args.seconds, force_sim=args.sim,
                       render_at=args.render)


def cmd_completion(args: argparse.Namespace) -> int:
    from hostd.docgen import completion

    sys.stdout.write(completion(args.shell))
    return 0


def cmd_manpage(args: argparse.Namespace) -> int:
    from hostd.docgen import man_page

    sys.stdout.write(man_page())
    return 0


# ---------------------------------------------------------------- parser


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
    p.add_argument("--format", choices=["v2", "v1"], default="v2",
                   help="stream format (default v2; v1 is the original 84-byte-header format)")
    p.add_argument("--method", choices=["shaped", "quant", "cut"], default=None,
                   help="shaped: step g·b(f_k) (v2 only); quant, cut: the paper's methods")
    p.add_argument("--g", type=_finite, default=None,
                   help="shaped: step relative to the detection threshold, dB (multiple of 0.25)")
    p.add_argument("--levels", type=int, default=None, help="quantization steps L (quant)")
    p.add_argument("--b0", type=_finite, default=None, help="threshold shift b0 in dB (cut)")
    p.add_argument("--value-bits", type=int, default=None, choices=[0, 8, 16, 32],
                   help="cut survivors: 0 = exact float64 (v1 only; the v1 default), else "
                   "integers of this width (v2 default 16)")
    p.add_argument("--coder", default="auto", choices=["auto", "none", "deflate"],
                   help="v1 lossless entropy stage (default auto: the smaller)")
    p.add_argument("--target-iobj", type=_finite, default=None,
                   help="rate control: the smallest stream whose Iobj <= X and SPQI >= --spqi-min, "
                   "both measured on the stream returned (only --method's knob when given, else "
                   "every method)")
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
    p.set_defaults(func=cmd_encode)

    p = sub.add_parser("decode", help="reconstruct heights (µm, one per line) from a stream")
    p.add_argument("stream")
    p.add_argument("-o", "--output", default=None, help="output file (default stdout)")
    p.set_defaults(func=cmd_decode)

    p = sub.add_parser("inspect", help="print a stream's header and coefficients")
    p.add_argument("stream")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_inspect)

    p = sub.add_parser("iobj", parents=[loader_parent(None), geometry_parent(from_stream=True), idx],
                       help="Ip, Ia, Iobj of a stream (against a profile or its header)")
    p.add_argument("first", metavar="[REFERENCE_PROFILE] STREAM")
    p.add_argument("stream", nargs="?", default=None, help=argparse.SUPPRESS)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_iobj)

    p = sub.add_parser("render", help="the displacement a hand at constant speed feels, as a WAV file")
    p.add_argument("stream", help=".vtx stream")
    p.add_argument("-o", "--output", required=True, help="output .wav file")
    p.add_argument("--speed", type=_finite, default=50.0, help="hand speed, mm/s (default 50)")
    p.add_argument("--seconds", type=_positive, default=5.0, help="duration, s (default 5)")
    p.add_argument("--rate", type=_positive, default=48000.0,
                   help="WAV sample rate, Hz (default 48000; 3000 = the device's rate)")
    p.add_argument("--start-mm", type=_finite, default=0.0, help="start position, mm (default 0)")
    p.add_argument("--full-scale-um", type=_positive, default=40.0,
                   help="displacement at WAV full scale (±1.0), µm (default 40 = half the piezo's "
                   "80 µm travel, the output stage's limit)")
    p.add_argument("--format", choices=["int16", "float32"], default="int16",
                   help="WAV samples: int16 PCM (default, round(32767 h / full scale)) or float32")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_render)

    p = sub.add_parser("demo", help="the main job: the daemon on the embedded default device, end to end")
    p.add_argument("--out", default=None, help="directory for the demo's files")
    p.add_argument("--sim", action="store_true", help="use the simulated display, not the firmware host port")
    p.add_argument("--render", choices=["auto", "host", "device"], default="auto",
                   help="who renders: auto (the display when it can, protocol v2; the default, as "
                   "[render] where), host (stream 3 kHz samples) or device")
    p.add_argument("--seconds", type=_positive, default=3.5, help="play time per texture (default 3.5)")
    p.add_argument("--codec-only", action="store_true", help="only the codec table (no daemon)")
    p.set_defaults(func=cmd_demo)

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
    p.set_defaults(func=cmd_fit)

    p = sub.add_parser("report", help="reports: rate-quality")
    rsub = p.add_subparsers(dest="report", metavar="REPORT")
    p.set_defaults(func=needs_subcommand(p, "a report"))
    r = rsub.add_parser("rate-quality", parents=[loader, geom, idx],
                        help="sweep both methods: bytes vs Ip, Ia, Iobj (CSV, Markdown, PNG)")
    r.add_argument("profile", help="profile file or synthetic:wood[:SEED]")
    r.add_argument("-o", "--out", default="rate-quality", help="output directory")
    r.add_argument("--no-progress", action="store_true")
    r.add_argument("--json", action="store_true", help="print notes and every row as JSON")
    r.set_defaults(func=cmd_report_rate_quality)

    p = sub.add_parser("completion", help="print the shell completion script (bash, zsh)",
                       description="Print the completion script; install-service installs both. By "
                       "hand: hostd completion bash > ~/.local/share/bash-completion/completions/hostd")
    p.add_argument("shell", choices=["bash", "zsh"])
    p.set_defaults(func=cmd_completion)
    p = sub.add_parser("manpage", help="print the man page hostd(8) (roff), generated from this parser",
                       description="install-service installs it as /usr/local/share/man/man8/hostd.8")
    p.set_defaults(func=cmd_manpage)

    from hostd.bench.cli import add_parser as add_bench
    from hostd.service.cli import add_parsers as add_service
    from hostd.sim.cli import add_parser as add_sim

    add_bench(sub, [loader_parent(None)])
    add_service(sub)
    add_sim(sub)
    return ap


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
