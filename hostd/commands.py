"""The toolkit's commands (encode, decode, inspect, iobj, render, demo, fit, report, completion,
manpage): each `cmd_*` takes the parsed arguments and returns the exit code. Their options are
declared in hostd/parser.py; hostd/cli.py runs them."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from hostd.cliopts import _ab, read_profile, warn


def _dump(obj) -> None:
    print(json.dumps(obj, indent=None, allow_nan=False))


def _read_stream(path: str):
    from hostd.fileio import read_stream

    return read_stream(path)


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
    if "binding" in res and not args.json:  # rate control: what set the size leads, then the slack
        other = (f"Iobj {res['Iobj']:.4f}, under --target-iobj {res['target_iobj']:g}; a lower --spqi-min "
                 "gives a smaller stream" if res["size_set_by"] == "waveform" else
                 "no SPQI asked: --no-guard" if res["spqi_min"] is None else
                 f"SPQI {res['spqi']:.3f} >= --spqi-min {res['spqi_min']:g}" if res["spqi"] is not None
                 else f"SPQI >= --spqi-min {res['spqi_min']:g} by the proxy guard")
        print(f"{args.output}: {res['bytes']} bytes, the smallest stream with {res['binding']}: the "
              f"constraint that set its size ({other})", file=sys.stderr)
    if res["chosen"] is not None:
        print(f"chose {res['chosen']} after {res['encodes']} encodes in "
              f"{res['search_cpu_s'] * 1e3:.0f} ms CPU", file=sys.stderr)
    if args.json:  # rate control: the binding constraint first (binding, size_set_by)
        lead = {"binding": res["binding"], "size_set_by": res["size_set_by"]} if "binding" in res else {}
        _dump({**lead, "output": args.output, **res})
        return 0
    sp = "" if res["spqi"] is None else f", SPQI {res['spqi']:.3f}"
    print(
        f"{args.output}: {args.format} {res['method']}, N={res['n']}, N'={res['n_keep']}, "
        f"{res['bytes']} bytes ({100 * res['ratio_coeffs']:.1f}% of 16-bit coefficients, "
        f"{100 * res['ratio_profile']:.2f}% of the 16-bit profile), Iobj {res['Iobj']:.4f}{sp}",
        file=sys.stderr,
    )
    return 0


DECODE_TEXT_SUFFIXES = ("", ".csv", ".txt", ".dat", ".asc", ".tsv")  # one height per line


def cmd_decode(args: argparse.Namespace) -> int:
    """Heights (µm) one per line, or a .npy array: what the output's extension names; any other
    extension (out.wav) is refused before the stream is read."""
    from hostd.errors import ConfigError

    suffix = "" if args.output in (None, "-") else Path(args.output).suffix.lower()
    if suffix not in (*DECODE_TEXT_SUFFIXES, ".npy"):
        raise ConfigError(f"-o {args.output}: hostd decode writes heights as text (one per line: .csv, .txt) "
                          f"or a NumPy .npy array, not {suffix}: name it "
                          f"{Path(args.output).with_suffix('.csv').name}")
    s = _read_stream(args.stream)
    y = s.reconstruct()
    if suffix == ".npy":
        import io

        import numpy as np

        buf = io.BytesIO()
        np.save(buf, np.asarray(y, dtype=np.float64))
        _write_bytes_atomic(args.output, buf.getvalue())
        return 0
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
    from hostd.perception import calibration
    from hostd.quality import score_stream

    if args.stream is None:
        stream_path, ref_spec = args.first, None
    else:
        stream_path, ref_spec = args.stream, args.first
    decoded = _decoded_profile(stream_path, ref_spec, args)
    if decoded is not None:
        return _iobj_of_profiles(ref_spec, decoded, args)
    s = _read_iobj_stream(stream_path, ref_spec)
    for opt, given, header, unit in (("--speed", args.speed, s.speed_mm_s, "mm/s"),
                                     ("--fmax", args.fmax, s.fmax_hz, "Hz")):
        if given is not None and not math.isclose(given, header, rel_tol=1e-9):
            warn("iobj", f"{opt} {given:g} ignored: the stream was made for {header:g} {unit} (its "
                 "header's geometry defines the components scored)")
    curve = calibration.load_curve(args.thresholds) if args.thresholds else None
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


def _decoded_profile(path: str, ref_spec: str | None, args: argparse.Namespace):
    """`hostd iobj REFERENCE DECODED`: the second file when it is a profile, not a stream (another
    codec's output, an .hjif back from the reference software); None when it is a stream, or
    when the two look swapped or it is no profile (then the stream's message is the one given)."""
    from hostd.errors import StreamError
    from hostd.texture import synth

    if ref_spec is None or Path(path).suffix.lower() == ".vtx":
        return None  # a stream (or a broken one: the stream's message)
    if not (synth.is_spec(path) or Path(path).is_file()):
        return None
    try:
        _read_stream(path)
        return None
    except StreamError:
        pass
    try:
        _read_stream(ref_spec)
        return None  # REFERENCE is the stream: arguments swapped (the stream's message says so)
    except (StreamError, OSError):
        pass
    ref = read_profile(ref_spec, args)
    return ref, read_profile(path, args, length_mm=ref.length_mm)


def _iobj_of_profiles(ref_spec: str, profiles, args: argparse.Namespace) -> int:
    """Ip, Ia, Iobj (and SPQI) of a decoded profile against its reference: the N' DCT amplitudes
    of each (N' from --speed and --fmax, default 50 mm/s and 400 Hz), as for a stream."""
    import numpy as np

    from hostd.codec import transform
    from hostd.errors import ProfileError
    from hostd.perception import calibration, guard, indices, peer, thresholds

    ref, dec = profiles
    if dec.n != ref.n or not math.isclose(dec.spacing_um, ref.spacing_um, rel_tol=1e-9):
        raise ProfileError(f"{args.stream}: {dec.n} samples every {dec.spacing_um:g} µm, the reference "
                           f"{ref_spec} {ref.n} every {ref.spacing_um:g} µm: load both with the same "
                           "options (--length-mm, --spacing, units)")
    speed = args.speed if args.speed is not None else 50.0
    fmax = args.fmax if args.fmax is not None else 400.0
    n_keep = max(1, min(ref.n - 1, transform.n_keep_for(ref.length_mm, speed, fmax)))
    curve = calibration.load_curve(args.thresholds) if args.thresholds else thresholds.default_curve()
    b_k = curve(transform.frequencies_hz(np.arange(1, n_keep + 1), ref.length_mm, speed))
    c_ref = transform.analyze(ref.heights_um, n_keep)
    c_dec = transform.analyze(dec.heights_um, n_keep)
    a, b = _ab(args)
    out = indices.score(c_ref, c_dec, b_k, a, b).as_dict()
    out.update(reference="profile", decoded="profile", n=ref.n, n_keep=n_keep, spacing_um=ref.spacing_um,
               length_mm=ref.length_mm, speed_mm_s=speed, fmax_hz=fmax,
               wsnr_db=guard.weighted_snr_db(c_ref, c_dec, b_k))
    out.update(peer.peer_scores(c_ref, c_dec, ref.n, ref.length_mm, speed))
    for k in ("st_sim", "spqi"):
        if out.get(k) is not None and not math.isfinite(out[k]):
            out[k] = None
    if args.json:
        _dump(out)
    else:
        print(format_fields(out))
    return 0


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
    for name, v, se, ci, ti in (("a", res.a, res.se_a, res.ci_a, res.t_interval_a),
                                ("b", res.b, res.se_b, res.ci_b, res.t_interval_b)):
        se_s = "n/a" if se is None else num(se)
        ci_s = "n/a" if ci is None else f"[{num(ci[0])}, {num(ci[1])}]"
        ti_s = "" if ti is None else f"   t {pct} interval [{num(ti[0])}, {num(ti[1])}]"
        print(f"  {name} = {num(v)}   standard error {se_s}   bootstrap {pct} interval {ci_s}{ti_s}")
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
    from hostd.perception import calibration
    from hostd.report import rate_quality

    need("matplotlib", "plot", "hostd report rate-quality (its PNG)")  # before the sweep
    prof = read_profile(args.profile, args)
    curve = calibration.resolve_curve(args.thresholds)
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

    _check_wav_name(args.output)
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


def _check_wav_name(output: str) -> None:
    """hostd render writes WAV: a file named for another format (out.mp3) is refused before any
    work; '-' (stdout), a device or a FIFO take the WAV bytes as they are."""
    import stat

    from hostd.errors import ConfigError

    if output == "-" or Path(output).suffix.lower() == ".wav":
        return
    try:
        if not stat.S_ISREG(Path(output).stat().st_mode):
            return
    except OSError:
        pass
    suffix = Path(output).suffix or "no extension"
    wav = Path(output).with_suffix(".wav").name
    raise ConfigError(f"-o {output}: hostd render writes WAV files only ({suffix} is not .wav): name it "
                      f"{wav}, and convert it afterwards for another format (e.g. ffmpeg -i {wav} "
                      f"{Path(output).name})")


def cmd_demo(args: argparse.Namespace) -> int:
    from hostd.demo import codec_demo, daemon_demo

    if args.codec_only:
        return codec_demo(out_dir=args.out)
    return daemon_demo(out_dir=args.out, seconds_per_texture=args.seconds, force_sim=args.sim,
                       render_at=args.render)


def cmd_completion(args: argparse.Namespace) -> int:
    from hostd.docgen import completion

    sys.stdout.write(completion(args.shell, args.root_parser))
    return 0


def cmd_manpage(args: argparse.Namespace) -> int:
    from hostd.docgen import man_page

    sys.stdout.write(man_page(args.root_parser))
    return 0
