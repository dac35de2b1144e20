"""`hostd export X -o Y.hjif`: a texture (a profile or a .vtx stream) as MPEG-I Haptics .hjif
(hostd.texture.hjif writes it; docs/interchange.md says what maps to what)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from hostd.cliopts import _positive, geometry_parent, index_parent, loader_parent, read_profile

if TYPE_CHECKING:
    import numpy as np


def played_um(coeffs_um: np.ndarray, n: int, length_mm: float, speed_mm_s: float,
              rate_hz: float) -> np.ndarray:
    """One crossing of the patch (L / v seconds from x = 0) as hostd renders it (`hostd render`,
    hostd.api.render_stroke): the series with the renderer's band gains at rate_hz."""
    from hostd.render.stroke import at_constant_speed, crossing_count

    return at_constant_speed(coeffs_um, n, length_mm, speed_mm_s, rate_hz,
                             crossing_count(length_mm, speed_mm_s, rate_hz, minimum=3))


def _is_stream(spec: str) -> bool:
    p = Path(spec)
    if p.suffix.lower() == ".vtx":
        return True
    try:
        with p.open("rb") as fh:
            return fh.read(3) == b"VTX"
    except OSError:
        return False


def texture_export(spec: str, args: argparse.Namespace):
    """The hjif.Export of a profile or a stream, with hostd's provenance."""
    from hostd import __version__
    from hostd.codec import transform
    from hostd.texture import hjif

    prov: dict = {"tool": f"hostd {__version__}", "source": Path(spec).name}
    if _is_stream(spec):
        from hostd.fileio import read_stream
        from hostd.quality import score_stream

        s = read_stream(spec)
        heights, spacing, coeffs, n, length = s.reconstruct(), s.spacing_um, s.coefficients, s.n, s.length_mm
        setting = (f"g_db={s.g_db}" if s.method == "shaped" else f"levels={s.levels}" if s.method == "quant"
                   else f"b0_db={s.b0_db},value_bits={s.value_bits}")
        prov.update(codec=f"hostd vtx v{s.version} {s.method}", setting=setting,
                    Iobj=float(f"{float(score_stream(s).Iobj):.6g}"), bytes=s.nbytes,
                    v_ref_mm_s=s.speed_mm_s, fmax_hz=s.fmax_hz, n_keep=s.n_keep)
        speed_ref = s.speed_mm_s
    else:
        prof = read_profile(spec, args)
        heights, spacing, n, length = prof.heights_um, prof.spacing_um, prof.n, prof.length_mm
        n_keep = min(n - 1, transform.n_keep_for(length, args.speed, args.fmax))
        if n_keep < 1:
            from hostd.errors import ProfileError

            raise ProfileError(f"{spec}: the patch is {length:.3g} mm long ({n} samples every {spacing:.3g} "
                               f"µm): no component of it lies at or below --fmax {args.fmax:g} Hz at --speed "
                               f"{args.speed:g} mm/s, so there is nothing to play; check the profile's x "
                               "unit (--x-unit, --spacing) or the patch length (--length-mm)")
        coeffs = transform.analyze(heights, n_keep)
        prov.update(codec="none", setting="", Iobj=0.0, v_ref_mm_s=args.speed, fmax_hz=args.fmax,
                    n_keep=n_keep)
        speed_ref = args.speed
    speed = args.speed_mm_s if args.speed_mm_s is not None else speed_ref
    cal = getattr(args, "calibration", None)  # --calibration FILE (the index options): NAME@ID
    cal = None if cal is None else cal.label
    # None: hostd's streams and profiles carry no actuator calibration; last, as the first key
    # dropped should the description run past 255 bytes
    prov["calibration"] = cal
    played = played_um(coeffs, n, length, speed, args.rate_hz)
    full_scale = args.full_scale_um
    if full_scale is None and Path(spec).suffix.lower() in (".hjif", ".hmpg"):
        # an MPEG file in, an MPEG file out: amplitude 1.0 keeps its meaning (the scale the source
        # states, else 1 --y-unit), unless the texture as played would exceed it
        from hostd.texture.load import UNITS_TO_UM

        stated = hjif.read_channel(Path(spec), getattr(args, "member", None)).full_scale_um
        full_scale = stated if stated is not None else UNITS_TO_UM[args.y_unit]
        import numpy as np

        full_scale = max(full_scale, float(np.max(np.abs(heights))), float(np.max(np.abs(played))))
    return hjif.Export(heights_um=heights, spacing_um=spacing, coeffs_um=coeffs, n=n, length_mm=length,
                       played_um=played, speed_mm_s=float(speed),
                       rate_hz=int(args.rate_hz), provenance=prov, full_scale_um=full_scale,
                       perceptions=args.perceptions, compact=args.compact)


def cmd_export(args: argparse.Namespace) -> int:
    from hostd.errors import ConfigError
    from hostd.fileio import write_output
    from hostd.render.stroke import crossing_count
    from hostd.texture import hjif

    if not str(args.output).lower().endswith(".hjif"):
        raise ConfigError(f"-o {args.output}: hostd exports .hjif (an .hmpg is made from it by the "
                          "reference Encoder: Encoder -f X.hjif -o X.hmpg -b)")
    if args.rate_hz != int(args.rate_hz):
        raise ConfigError(f"--rate-hz must be a whole number, got {args.rate_hz:g}")
    ex = texture_export(args.source, args)
    doc = hjif.build(ex)
    write_output(args.output, hjif.dumps(doc))
    by_id = {p["id"]: p for p in doc["perceptions"]}

    tex, tim = by_id.get(0), by_id.get(1)
    m = hjif._FULL_SCALE.search(doc["perceptions"][0]["description"])
    info = {"output": args.output, "perceptions": [p["perception_modality"] for p in doc["perceptions"]],
            "spatial_positions": tex and crossing_count(ex.length_mm, ex.speed_mm_s, doc["timescale"],
                                                        minimum=3),
            "unit_exponent": tex and tex["unit_exponent"], "timescale": doc["timescale"],
            "tick_um": tex and ex.speed_mm_s * 1e3 / doc["timescale"],
            "played_samples": tim and tim["channels"][0]["sample_count"], "rate_hz": ex.rate_hz,
            "speed_mm_s": ex.speed_mm_s, "full_scale_um": float(m.group(1)) if m else None,
            "spacing_um": float(ex.spacing_um)}
    if args.json:
        print(json.dumps(info, allow_nan=False))
    else:
        parts = []
        if tex is not None:
            parts.append(f"texture ({ex.n} samples every {info['spacing_um']:g} µm) along one stroke at "
                         f"{ex.speed_mm_s:g} mm/s: {info['spatial_positions']} positions every "
                         f"{info['tick_um']:.5g} µm (1/{doc['timescale']} s)")
        if tim is not None:
            parts.append(f"played at {ex.speed_mm_s:g} mm/s: {info['played_samples']} samples at "
                         f"{ex.rate_hz} Hz")
        print(f"{args.output}: {'; '.join(parts)}; full scale {info['full_scale_um']:.4g} µm",
              file=sys.stderr)
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser("export", parents=[loader_parent(), geometry_parent(), index_parent()],
                       help="a texture (profile or .vtx stream) as MPEG-I Haptics .hjif",
                       description="Write a texture as MPEG-I Haptics (ISO/IEC 23090-31) .hjif: a "
                       "'Vibrotactile Texture' perception (the heights over space) and a 'Vibrotactile' "
                       "perception (the texture as played at --speed-mm-s), with hostd's provenance.")
    p.add_argument("source", help="a profile (csv/txt/npy/hjif, synthetic:wood[:SEED]) or a .vtx stream")
    p.add_argument("-o", "--output", required=True, help="output .hjif file")
    p.add_argument("--speed-mm-s", type=_positive, default=None,
                   help="the stroke speed both perceptions play at in the reference Synthesizer, mm/s: the "
                   "time-domain one is the texture as played at it, the spatial one's positions are "
                   "ticks of the timescale at it (default: the stream's v_ref, or --ref-speed-mm-s)")
    p.add_argument("--rate-hz", type=_positive, default=8000.0,
                   help="sample rate of the time-domain perception, Hz (default 8000, the reference "
                   "Synthesizer's; at most 48000)")
    p.add_argument("--perceptions", choices=["both", "texture", "time"], default="both",
                   help="both (default), the texture over space only, or the texture as played only "
                   "(the reference Encoder/Decoder at 2de9ff1 carry only this one through .hmpg)")
    p.add_argument("--compact", action="store_true",
                   help="each perception as one VectorialWave band, a sinusoid per non-zero term of the "
                   "texture's series, instead of a keyframe per sample (needs the terms' frequencies at "
                   "--speed-mm-s, k v / 2L, to be whole numbers of Hz; hostd says which speeds work)")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_export)
