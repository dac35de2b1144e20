"""Command-line interface: argument parsing only; each subcommand calls into the packages."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from hostd import __version__
from hostd.errors import HostdError


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
            return super().parse_known_intermixed_args(args, namespace)
        finally:
            self._intermixing = False

    def error(self, message: str):
        message = " ".join(message.split())
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


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
    if not (np.isfinite(x) and x > 0):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0: {v!r}")
    return x


def _finite(v: str) -> float:
    try:
        x = float(v)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {v!r}") from None
    if not np.isfinite(x):
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
    return p


def geometry_parent() -> argparse.ArgumentParser:
    p = Parser(add_help=False)
    g = p.add_argument_group("geometry and perception")
    g.add_argument("--speed", type=_positive, default=50.0,
                   help="reference hand speed v_ref, mm/s (default 50)")
    g.add_argument("--fmax", type=_positive, default=400.0,
                   help="band limit at v_ref, Hz (default 400)")
    g.add_argument("--thresholds", default=None, metavar="CSV",
                   help="detection-threshold curve (default config/thresholds/default.csv)")
    return p


def index_parent() -> argparse.ArgumentParser:
    p = Parser(add_help=False)
    g = p.add_argument_group("quality index")
    g.add_argument("--preset", default="both", choices=["both", "wood", "sandpaper"],
                   help="(a, b) fitted in the paper (default both: 0.581, 0.464)")
    g.add_argument("--a", type=_finite, default=None, help="weight of Ip (overrides --preset)")
    g.add_argument("--b", type=_finite, default=None, help="weight of Ia (overrides --preset)")
    return p


def _ab(args: argparse.Namespace) -> tuple[float, float]:
    from hostd.perception.indices import PRESETS

    a, b = PRESETS[args.preset]
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
            ("--decimal-comma", getattr(args, "decimal_comma", False)),
            ("--y-unit", getattr(args, "y_unit", "um") != "um")) if given]
        if ignored:
            warn(command, f"{', '.join(ignored)} ignored for {spec} (synthetic profiles are "
                 "generated in µm at 0.5 µm spacing)")
        prof = synth.from_spec(spec)
        return cut_patch(prof.heights_um, prof.spacing_um, load_opts(args, length_mm), spec)
    return load_profile(spec, load_opts(args, length_mm))


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
    from hostd.codec import ratecontrol, stream, stream2, transform
    from hostd.errors import CodecError
    from hostd.perception import thresholds
    from hostd.quality import score_stream

    prof = read_profile(args.profile, args)
    curve = thresholds.resolve(args.thresholds)
    geom = transform.Geometry(prof.n, prof.length_mm, args.speed, args.fmax)
    if args.format == "v2" and args.coder != "auto":
        raise CodecError("--coder applies to --format v1 only (v2 has one entropy coder, the "
                         "adaptive range coder)")
    if args.format == "v1" and args.method == "shaped":
        raise CodecError("--method shaped needs --format v2 (the default)")
    value_bits = args.value_bits if args.value_bits is not None else (16 if args.format == "v2" else 0)
    chosen = None
    if args.target_iobj is not None:
        res = ratecontrol.search(prof.heights_um, geom, curve, args.target_iobj, method=args.method,
                                 fmt=args.format, guard_db=None if args.no_guard else args.guard_db,
                                 ssnr_db=None if args.no_guard else args.guard_ssnr_db,
                                 ab=_ab(args))
        for note in res.notes:
            warn("encode", note)
        data = res.best.data
        chosen = res.best.describe()
        print(f"chose {chosen} after {res.encodes} encodes in "
              f"{res.seconds * 1e3:.0f} ms CPU", file=sys.stderr)
    elif args.method is None:
        raise CodecError("give --method shaped|quant|cut (or --target-iobj X)")
    else:
        for opt, val, method in (("--b0", args.b0, "quant"), ("--b0", args.b0, "shaped"),
                                 ("--levels", args.levels, "cut"), ("--levels", args.levels, "shaped"),
                                 ("--g", getattr(args, "g", None), "quant"),
                                 ("--g", getattr(args, "g", None), "cut"),
                                 ("--value-bits", args.value_bits or None, "quant")):
            if val is not None and args.method == method:
                warn("encode", f"{opt} is ignored with --method {method}")
        if args.format == "v2":
            data = stream2.encode_profile(prof.heights_um, geom, curve, method=args.method,
                                          g_db=args.g, levels=args.levels, b0_db=args.b0,
                                          value_bits=value_bits)
        else:
            data = stream.encode_profile(
                prof.heights_um, geom, curve, method=args.method, levels=args.levels,
                b0_db=args.b0, value_bits=value_bits, coder=args.coder,
            )
    _write_bytes_atomic(args.output, data)
    s = stream.decode(data)
    kept = int(np.count_nonzero(s.coefficients))
    if kept == 0:
        rms = float(np.sqrt(np.mean(prof.heights_um ** 2)))
        warn("encode", f"the stream keeps no component (every amplitude was quantized or cut to 0; "
             f"the profile's RMS is {rms:.3g} µm): check --y-unit (heights are read as "
             f"{getattr(args, 'y_unit', 'um')}), or ask for more levels / a lower --b0 / a smaller "
             "--target-iobj")
    sc = score_stream(s, a=_ab(args)[0], b=_ab(args)[1])
    if args.json:
        _dump({"output": args.output, "method": s.method, "levels": s.levels, "b0_db": s.b0_db,
               "value_bits": s.value_bits, "chosen": chosen, "n": s.n, "n_keep": s.n_keep,
               "kept": kept, "bytes": s.nbytes, "ratio_coeffs": s.ratio_coeffs,
               "ratio_profile": s.ratio_profile, "Ip": float(sc.Ip), "Ia": float(sc.Ia),
               "Iobj": float(sc.Iobj), "a": float(sc.a), "b": float(sc.b)})
        return 0
    print(
        f"{args.output}: v{s.version} {s.method}, N={s.n}, N'={s.n_keep}, {s.nbytes} bytes "
        f"({100 * s.ratio_coeffs:.1f}% of 16-bit coefficients, "
        f"{100 * s.ratio_profile:.2f}% of the 16-bit profile), Iobj {float(sc.Iobj):.4f}",
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
    s = _read_stream(stream_path)
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

        mismatch = reference_mismatch(s, out["P"], out["A"])
        out["reference_mismatch"] = mismatch is not None
        if mismatch:
            warn("iobj", mismatch)
    from hostd.codec import transform
    from hostd.perception import peer

    if ref is None:
        out["peer_note"] = "peer metrics (ST-SIM, SPQI) need the original: pass REFERENCE_PROFILE"
    elif not peer.available():
        out["peer_note"] = peer.NOTE_MISSING
    else:
        out.update(peer.peer_scores(transform.analyze(ref, s.n_keep), s.coefficients, s.n,
                                    s.length_mm, s.speed_mm_s) or {})
    out.update(bytes=s.nbytes, ratio_coeffs=s.ratio_coeffs, ratio_profile=s.ratio_profile,
               method=s.method)
    if args.json:
        _dump(out)
    else:
        for k, v in out.items():
            print(f"{k:>14}: {v}")
    return 0


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
    sign = "-" if res.b < 0 else "+"
    print(f"Iobj = {res.a:.4f} Ip {sign} {abs(res.b):.4f} Ia   ({res.n_used} stimuli"
          f"{', a, b >= 0' if res.nonnegative else ''})")
    pct = f"{100 * res.ci_level:g}%"
    for name, v, se, ci in (("a", res.a, res.se_a, res.ci_a), ("b", res.b, res.se_b, res.ci_b)):
        se_s = "n/a" if se is None else f"{se:.4f}"
        ci_s = "n/a" if ci is None else f"[{ci[0]:.4f}, {ci[1]:.4f}]"
        print(f"  {name} = {v:.4f}   standard error {se_s}   bootstrap {pct} interval {ci_s}")
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
    from hostd.perception import thresholds
    from hostd.report import rate_quality

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
                   help="rate control: the smallest stream whose Iobj <= X and which passes the "
                   "waveform guard (--guard-db and --guard-ssnr-db; only --method's knob when "
                   "given, else every method)")
    p.add_argument("--guard-db", type=_finite, default=25.0,
                   help="rate control's waveform guard, part 1: wSNR (SNR weighted by the "
                   "detection threshold b(f)) >= this, dB (default 25)")
    p.add_argument("--guard-ssnr-db", type=_finite, default=27.0,
                   help="waveform guard, part 2: sSNR (SNR weighted by the SPQI model's "
                   "threshold curve) >= this, dB (default 27: SPQI >= 0.9 on every texture "
                   "measured, see docs/benchmarks.md)")
    p.add_argument("--no-guard", action="store_true",
                   help="rate control on Iobj alone (can return a wrong waveform; see docs)")
    p.add_argument("--json", action="store_true",
                   help="print the result (setting, bytes, Ip, Ia, Iobj) as JSON on stdout")
    p.set_defaults(func=cmd_encode)

    p = sub.add_parser("decode", help="reconstruct heights (µm, one per line) from a stream")
    p.add_argument("stream")
    p.add_argument("-o", "--output", default=None, help="output file (default stdout)")
    p.set_defaults(func=cmd_decode)

    p = sub.add_parser("inspect", help="print a stream's header and coefficients")
    p.add_argument("stream")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_inspect)

    p = sub.add_parser("iobj", parents=[loader_parent(None), idx],
                       help="Ip, Ia, Iobj of a stream (against a profile or its header)")
    p.add_argument("first", metavar="[REFERENCE_PROFILE] STREAM")
    p.add_argument("stream", nargs="?", default=None, help=argparse.SUPPRESS)
    p.add_argument("--thresholds", default=None, metavar="CSV",
                   help="curve the stream was made with, if not embedded or shipped")
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
    rsub.required = True
    r = rsub.add_parser("rate-quality", parents=[loader, geom, idx],
                        help="sweep both methods: bytes vs Ip, Ia, Iobj (CSV, Markdown, PNG)")
    r.add_argument("profile", help="profile file or synthetic:wood[:SEED]")
    r.add_argument("-o", "--out", default="rate-quality", help="output directory")
    r.add_argument("--no-progress", action="store_true")
    r.add_argument("--json", action="store_true", help="print notes and every row as JSON")
    r.set_defaults(func=cmd_report_rate_quality)

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
