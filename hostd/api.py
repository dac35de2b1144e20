"""The public Python API of hostd, for notebooks and scripts.

Everything here takes and returns plain Python and numpy objects: dicts of floats, lists of
dicts (records) and 1-D numpy arrays, so that ``pandas.DataFrame(result)`` or
``pandas.DataFrame.from_records(rows)`` needs no glue. Units are in the names: ``_um``
(micrometres), ``_mm``, ``_mm_s`` (mm per second), ``_hz``, ``_s``.

Functions
---------
load_profile      a profile file or ``synthetic:KIND[:SEED]`` -> heights in µm on a uniform grid
encode            heights -> ``.vtx`` stream bytes (linear quantization or threshold cut)
decode            stream bytes -> :class:`hostd.codec.stream.Stream`
score             Ip, Ia, Iobj of a stream (from its header, or against its original)
fit               fit (a, b) of Iobj = a Ip + b Ia to subjective scores
render_stroke     the displacement a hand moving at constant speed feels (offline)
run_scene         a scene simulation: delivered quality per effect

See docs/api.md for a worked example.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np

from hostd.codec.stream import Stream
from hostd.texture.load import Profile

__all__ = ["Profile", "Stream", "decode", "encode", "fit", "load_profile", "render_stroke",
           "run_scene", "score"]


def load_profile(source: str | Path, *, x_unit: str = "um", y_unit: str = "um",
                 spacing: float | None = None, length_mm: float | None = 10.0,
                 offset_mm: float = 0.0, detrend: str = "none",
                 columns: tuple[int, ...] | None = None, decimal_comma: bool = False) -> Profile:
    """Load a height profile as micrometres on a uniform grid, cut to a patch.

    Parameters
    ----------
    source : str or Path
        A text file (one column of heights, or two columns x, height; instrument preambles
        are skipped), a ``.npy`` file, or ``"synthetic:wood[:SEED]"`` /
        ``"synthetic:sandpaper[:SEED]"`` (generated in µm at 0.5 µm spacing).
    x_unit, y_unit : {"m", "mm", "um", "nm"}
        Units of the x column (and of `spacing`) and of the heights in the file.
    spacing : float, optional
        Sample spacing in `x_unit`: needed for one-column files; for two-column files the
        grid to resample onto (default: the mean spacing of the x column).
    length_mm : float or None
        Patch length L in mm (default 10; None = the whole profile). N = round(L / dx).
    offset_mm : float
        Where the patch starts, mm.
    detrend : {"none", "mean", "linear"}
    columns : tuple of int, optional
        0-based columns (x, height) or (height,) of a text file.
    decimal_comma : bool
        Numbers written with a decimal comma (``1,5``).

    Returns
    -------
    Profile
        ``heights_um`` (float64 array of N heights, µm), ``spacing_um``, ``n``, ``length_mm``.
    """
    from hostd.texture import synth
    from hostd.texture.load import LoadOptions, cut_patch
    from hostd.texture.load import load_profile as _load

    opts = LoadOptions(x_unit=x_unit, y_unit=y_unit, spacing=spacing, length_mm=length_mm,
                       offset_mm=offset_mm, detrend=detrend,
                       columns=tuple(columns) if columns is not None else None,
                       decimal_comma=decimal_comma)
    if synth.is_spec(str(source)):
        prof = synth.from_spec(str(source))
        return cut_patch(prof.heights_um, prof.spacing_um, opts, str(source))
    return _load(source, opts)


def _heights(profile: Profile | np.ndarray, length_mm: float | None) -> tuple[np.ndarray, float]:
    if isinstance(profile, Profile):
        return profile.heights_um, profile.length_mm
    y = np.asarray(profile, dtype=np.float64)
    if length_mm is None:
        raise ValueError("give length_mm with a bare array of heights (or pass a Profile)")
    return y, float(length_mm)


def encode(profile: Profile | np.ndarray, *, method: str, levels: int | None = None,
           b0_db: float | None = None, value_bits: int = 0, length_mm: float | None = None,
           speed_mm_s: float = 50.0, fmax_hz: float = 400.0,
           thresholds: str | None = None) -> bytes:
    """Compress heights into a ``.vtx`` stream (paper eq. 5-7).

    The patch's DCT-II amplitudes C_k = (2/N) sum_n y_n cos(pi k (2n+1) / (2N)) are kept for
    k = 1..N' with f_k = k v / (2L) <= fmax_hz at v = speed_mm_s. ``method="quant"``
    quantizes them linearly into `levels` steps (eq. 5, 6); ``method="cut"`` zeroes those
    below the detection threshold shifted by `b0_db` (eq. 7).

    Parameters
    ----------
    profile : Profile or array of float
        Heights in µm (an array needs `length_mm`).
    method : {"quant", "cut"}
    levels : int
        Quantization steps L (quant).
    b0_db : float
        Threshold shift b0 in dB (cut).
    value_bits : {0, 8, 16, 32}
        Cut survivors: 0 = exact float64, else integers of this width.
    speed_mm_s, fmax_hz : float
        Reference hand speed v_ref (mm/s) and band limit at v_ref (Hz).
    thresholds : str, optional
        A threshold-curve CSV (default: config/thresholds/default.csv).

    Returns
    -------
    bytes
        The stream (header with the reference sums P and A, payload, CRC).
    """
    from hostd.codec import stream, transform
    from hostd.perception import thresholds as th

    y, length = _heights(profile, length_mm)
    geom = transform.Geometry(y.size, length, speed_mm_s, fmax_hz)
    return stream.encode_profile(y, geom, th.resolve(thresholds), method=method, levels=levels,
                                 b0_db=b0_db, value_bits=value_bits)


def decode(data: bytes | str | Path) -> Stream:
    """Parse and validate a stream (bytes, or the path of a ``.vtx`` file).

    Returns
    -------
    Stream
        ``coefficients`` (C'_1..C'_N', µm), ``n``, ``n_keep``, ``length_mm``, ``speed_mm_s``,
        ``fmax_hz``, ``frequencies_hz``, ``ref_P``, ``ref_A``; ``reconstruct()`` gives the N
        heights (µm) y'_n = sum_k C'_k cos(pi k (2n+1) / (2N)); ``summary()`` a dict.
    """
    from hostd.codec import stream

    if isinstance(data, str | Path):
        data = Path(data).read_bytes()
    return stream.decode(bytes(data))


def score(stream: Stream | bytes, reference: Profile | np.ndarray | None = None, *,
          a: float = 0.581, b: float = 0.464) -> dict:
    """Quality of a stream: Iobj = a Ip + b Ia (paper eq. 8-12).

    With the threshold b(f_k) of the stream's curve, P = sum (C_k / b_k)^2 and
    A = sum |C_k| / b_k over the reference and P', A' over the stream's C'_k;
    Ip = |P - P'| / P and Ia = |A - A'| / A (dimensionless).

    Parameters
    ----------
    stream : Stream or bytes
    reference : Profile or array, optional
        The original heights (µm, N samples). Default: the P and A in the stream's header.
    a, b : float
        Weights (default: the paper's fit over both materials).

    Returns
    -------
    dict
        P, A, P_prime, A_prime, Ip, Ia, Iobj, a, b (floats) and ``reference_mismatch``
        (True when a given reference is not the stream's original: its P, A differ from
        the header's).
    """
    from hostd.quality import reference_mismatch, score_stream

    s = stream if isinstance(stream, Stream) else decode(stream)
    ref = None
    if reference is not None:
        ref = reference.heights_um if isinstance(reference, Profile) else np.asarray(reference, float)
    out = score_stream(s, reference_um=ref, a=a, b=b).as_dict()
    out["reference_mismatch"] = ref is not None and reference_mismatch(s, out["P"], out["A"]) is not None
    return out


def fit(records: Iterable[Mapping] | Mapping[str, Iterable], *, nonnegative: bool = False,
        scale_min: float = 0.0, scale_max: float = 3.0, exclude_saturated: bool = False,
        n_boot: int = 2000) -> dict:
    """Fit (a, b) of Iobj = a Ip + b Ia to subjective scores by least squares without
    intercept (paper eq. 13-15).

    Parameters
    ----------
    records : list of dicts, or a dict of columns (e.g. ``DataFrame.to_dict("list")``)
        Each stimulus: ``score`` and ``Ip``, ``Ia``; optionally ``texture``, ``method``,
        ``level``. ``df.to_dict("records")`` works as is.
    nonnegative : bool
        Constrain a, b >= 0.
    scale_min, scale_max : float
        The rating scale; scores outside are refused.
    n_boot : int
        Bootstrap resamples for the intervals (0 = none).

    Returns
    -------
    dict
        a, b, se_a, se_b (standard errors), ci_a, ci_b (bootstrap 95 % intervals), n_used,
        warnings, metrics (r2_pearson and r2_fit of Iobj, Ip, Ia), excluded.
    """
    from hostd.perception import fit as _fit

    if isinstance(records, Mapping):
        keys = list(records)
        cols = [list(records[k]) for k in keys]
        records = [dict(zip(keys, row, strict=True)) for row in zip(*cols, strict=True)]
    stimuli = [_fit.Stimulus(str(r.get("texture", "")), str(r.get("method", "")), str(r.get("level", "")),
                             float(r["score"]), float(r["Ip"]), float(r["Ia"])) for r in records]
    res = _fit.fit(stimuli, nonnegative=nonnegative, scale_min=scale_min, scale_max=scale_max,
                   exclude_saturated=exclude_saturated, n_boot=n_boot)
    return res.as_dict()


def render_stroke(stream: Stream | bytes, *, speed_mm_s: float = 50.0, seconds: float = 1.0,
                  rate_hz: float = 3000.0, x0_mm: float = 0.0) -> dict[str, np.ndarray]:
    """The displacement a hand moving at constant speed feels on an ideal display (offline).

    h(t) = sum_k g_k(v) C'_k cos(k theta(x0 + v t)), theta(x) = pi (x/dx + 1/2) / N (the
    patch's mirror-even series, hostd.render.series), with the renderer's speed-aware band
    gains g_k(v) at the output rate (1 up to 400 Hz, a raised-cosine fade to 0.8 x rate/2).
    Synthesized with one chirp-z transform.

    Parameters
    ----------
    stream : Stream or bytes
    speed_mm_s : float
        Hand speed v (mm/s); negative moves backwards.
    seconds : float
        Duration (s).
    rate_hz : float
        Sample rate (Hz): 3000 for the device, 44100 or 48000 for an audio interface.
    x0_mm : float
        Start position (mm).

    Returns
    -------
    dict
        ``t_s``, ``x_mm``, ``height_um`` (float64 arrays of round(seconds * rate_hz)).
    """
    from hostd.render import series
    from hostd.render.height import BandLimitConfig, band_gains

    s = stream if isinstance(stream, Stream) else decode(stream)
    if not (np.isfinite(speed_mm_s) and np.isfinite(seconds) and seconds > 0 and rate_hz > 0):
        raise ValueError("speed_mm_s must be finite, seconds and rate_hz > 0")
    count = round(seconds * rate_hz)
    k = np.arange(1, s.n_keep + 1, dtype=np.float64)
    g = band_gains(k, speed_mm_s, s.length_mm, BandLimitConfig(sample_rate_hz=rate_hz))
    theta0 = float(series.phase_rad(x0_mm, s.n, s.length_mm))
    dtheta = np.pi * speed_mm_s / (s.length_mm / s.n * s.n * rate_hz)  # phase per sample
    h = series.evaluate_uniform(s.coefficients * g, theta0, dtheta, count)
    t = np.arange(count) / rate_hz
    return {"t_s": t, "x_mm": x0_mm + speed_mm_s * t, "height_um": h}


def run_scene(scene: str | Path, *, only: list[str] | None = None) -> dict:
    """Simulate a scene (a TOML file or a shipped name such as ``"worst-case"``).

    Returns
    -------
    dict
        ``scene``, ``codec_iobj``, and ``runs``: one record per run (no effect, each effect
        alone, all together; or just the effects in `only`) with effects, ip, ia, iobj,
        rms_error_um, rms_texture_um, underruns, latency_ms, spectrum_change_um.
        ``pandas.DataFrame(result["runs"])`` gives the table.
    """
    from hostd.paths import scenes_dir
    from hostd.sim import scene as sc_mod

    p = Path(scene)
    if not p.exists() and not p.suffix:
        p = scenes_dir() / f"{scene}.toml"
    sc = sc_mod.load(p)
    if only is None:
        return sc_mod.strip(sc_mod.report(sc, progress=False))
    r = sc_mod.run(sc, list(only))
    return {"scene": sc.name, "codec_iobj": r["codec_iobj"],
            "runs": [{k: v for k, v in r.items() if not k.startswith("_")}]}
