"""The public Python API of hostd, for notebooks and scripts.

Everything here takes and returns plain Python and numpy objects: dicts of floats, lists of
dicts (records) and 1-D numpy arrays, so that ``pandas.DataFrame(result)`` or
``pandas.DataFrame.from_records(rows)`` needs no glue. Units are in the names: ``_um``
(micrometres), ``_mm``, ``_mm_s`` (mm per second), ``_hz``, ``_s``.

Functions
---------
load_profile      a profile file or ``synthetic:KIND[:SEED]`` -> heights in µm on a uniform grid
encode            heights -> a ``.vtx`` stream and its report (rate control by default method
                  set: Iobj and SPQI verified on the returned bytes), as ``hostd encode --json``
decode            stream bytes -> :class:`hostd.codec.stream.Stream`
score             Ip, Ia, Iobj of a stream (from its header, or against its original), and
                  SPQI, ST-SIM, wSNR, sSNR where they can be computed
fit               fit (a, b) of Iobj = a Ip + b Ia to subjective scores
render_stroke     the displacement a hand moving at constant speed feels (offline)
run_scene         a scene simulation: delivered quality per effect
run_corpus        textures x codecs x settings -> a results table (resumable store; BD-rate
                  reports with `hostd corpus report`); needs the ``corpus`` extra

Errors are hostd.errors classes that are also the built-in exceptions: a missing file raises
FileNotFoundError, bad input or a bad argument ValueError (one-line messages naming this module's
keyword arguments). What the CLI prints as a note comes back in the result's ``notes`` and as a
``hostd.errors.HostdWarning`` (a UserWarning that can be filtered on its own).

See docs/api.md for a worked example.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np

from hostd.codec.stream import Stream
from hostd.errors import HostdError
from hostd.texture.load import Profile

__all__ = ["Profile", "Stream", "decode", "encode", "fit", "load_profile", "render_stroke",
           "run_corpus", "run_scene", "score"]


def load_profile(source: str | Path, *, x_unit: str = "um", y_unit: str = "um",
                 spacing: float | None = None, length_mm: float | None = 10.0,
                 offset_mm: float = 0.0, detrend: str = "none",
                 columns: tuple[int, ...] | None = None, decimal_comma: bool = False,
                 var: str | None = None) -> Profile:
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
    var : str, optional
        A MATLAB ``.mat`` file's variable holding the profile (needed when it holds several
        arrays), or ``"X,Y"``: an x and a height vector.

    Returns
    -------
    Profile
        ``heights_um`` (float64 array of N heights, µm), ``spacing_um``, ``n``, ``length_mm``,
        ``note`` (what the CLI prints about the file, e.g. which ``.mat`` variable it read; also
        raised as a HostdWarning).
    """
    from hostd.texture import synth
    from hostd.texture.load import LoadOptions, cut_patch
    from hostd.texture.load import load_profile as _load

    opts = LoadOptions(x_unit=x_unit, y_unit=y_unit, spacing=spacing, length_mm=length_mm,
                       offset_mm=offset_mm, detrend=detrend,
                       columns=tuple(columns) if columns is not None else None,
                       decimal_comma=decimal_comma, member=var)
    if synth.is_spec(str(source)):
        prof = synth.from_spec(str(source))
        return cut_patch(prof.heights_um, prof.spacing_um, opts, str(source))
    prof = _load(source, opts)
    if prof.note:  # what the CLI prints about the file (which .mat variable, what an .hjif held)
        _warn([f"{source}: {prof.note}"])
    return prof


def _heights(profile: Profile | np.ndarray, length_mm: float | None) -> tuple[np.ndarray, float]:
    if isinstance(profile, Profile):
        return profile.heights_um, profile.length_mm
    y = np.asarray(profile, dtype=np.float64)
    if length_mm is None:
        raise ValueError("give length_mm with a bare array of heights (or pass a Profile)")
    return y, float(length_mm)


# CLI option -> the keyword argument of this module that means the same (errors raised below
# this layer name CLI options; `_python_names` renames them for Python callers).
_ARG_NAMES = (("--target-iobj", "target_iobj="), ("--guard-ssnr-db", "ssnr_db="), ("--guard-db", "guard_db="),
              ("--spqi-min", "spqi_min="), ("--no-guard", "spqi_min=None"), ("--method", "method="),
              ("--format", "format="), ("--levels", "levels="), ("--value-bits", "value_bits="),
              ("--b0-db", "b0_db="), ("--g-db", "g_db="), ("--coder", "coder="),
              ("--ref-speed-mm-s", "speed_mm_s="), ("--fmax-hz", "fmax_hz="), ("--length-mm", "length_mm="),
              ("--thresholds", "thresholds="),
              ("--y-unit", "y_unit= of load_profile"), ("--x-unit", "x_unit= of load_profile"),
              ("--a", "a="), ("--b", "b="))
_ARG_RE = None


def _python_text(text: str) -> str:
    """A message with CLI options renamed to this API's keyword arguments."""
    import re

    global _ARG_RE
    if _ARG_RE is None:
        _ARG_RE = re.compile("|".join(re.escape(f) + r"(?![\w-])" for f, _ in _ARG_NAMES))
    table = dict(_ARG_NAMES)
    return _ARG_RE.sub(lambda m: table[m.group(0)], text)


def _python_names(exc: Exception) -> Exception:
    """The same error with CLI options renamed to this API's keyword arguments."""
    return type(exc)(_python_text(str(exc)))


def encode(profile: Profile | np.ndarray, *, method: str | None = None, format: str = "v2",
           target_iobj: float | None = None, spqi_min: float | None = 0.9,
           guard_db: float | None = None, ssnr_db: float | None = None,
           g_db: float | None = None, levels: int | None = None, b0_db: float | None = None,
           value_bits: int | None = None, coder: str = "auto", length_mm: float | None = None,
           speed_mm_s: float = 50.0, fmax_hz: float = 400.0, thresholds: str | None = None,
           a: float = 0.581, b: float = 0.464) -> dict:
    """Compress heights into a ``.vtx`` stream: the default codec with rate control, or one
    method at one setting. The same function `hostd encode` runs; returns what its ``--json``
    prints, plus the stream's bytes.

    The patch's DCT-II amplitudes C_k = (2/N) sum_n y_n cos(pi k (2n+1) / (2N)) are kept for
    k = 1..N' with f_k = k v / (2L) <= fmax_hz at v = speed_mm_s, then coded by one method:
    ``"shaped"`` (v2 only) quantizes C_k with the step 10^(g/20) b(f_k); ``"quant"`` quantizes
    linearly into `levels` steps (paper eq. 5, 6); ``"cut"`` zeroes those below the detection
    threshold shifted by `b0_db` (eq. 7).

    With `target_iobj` (rate control, hostd.codec.ratecontrol), the smallest stream of the
    format (every method, or only `method`) that meets, measured on its own bytes,
    Iobj <= target_iobj (against the header's sums, as `score` computes it) and
    SPQI >= spqi_min (the played signal against the original's, as `score(stream, profile)`
    reports it; spqi_min=None: Iobj alone); `guard_db` / `ssnr_db` add wSNR / sSNR floors.

    Parameters
    ----------
    profile : Profile or array of float
        Heights in µm (an array needs `length_mm`).
    method : {"shaped", "quant", "cut"}, optional
        Required without `target_iobj`; with it, restricts the search to this method.
    format : {"v2", "v1"}
        Stream format (v1: the original 84-byte header, quant and cut only).
    target_iobj : float, optional
        Rate control's Iobj target (e.g. 0.05).
    spqi_min : float or None
        Rate control's waveform criterion (default 0.9).
    guard_db, ssnr_db : float, optional
        Extra floors on wSNR and sSNR (dB); off by default.
    g_db, levels, b0_db : float, int, float
        The setting of `method` without rate control: shaped step g (dB, multiple of 0.25),
        quantization steps L, cut shift b0 (dB).
    value_bits : {0, 8, 16, 32}, optional
        Cut survivors: 0 = exact float64 (v1 only, its default), else integers (v2 default 16).
    coder : {"auto", "none", "deflate"}
        v1's entropy stage.
    speed_mm_s, fmax_hz : float
        Reference hand speed v_ref (mm/s) and band limit at v_ref (Hz).
    thresholds : str, optional
        A threshold-curve CSV (default: config/thresholds/default.csv).
    a, b : float
        Iobj's weights (default: the paper's fit over both materials).

    Returns
    -------
    dict
        ``stream`` (bytes), ``method``, ``levels``, ``b0_db``, ``value_bits``, ``chosen``,
        ``n``, ``n_keep``, ``kept``, ``bytes``, ``ratio_coeffs``, ``ratio_profile``, ``Ip``,
        ``Ia``, ``Iobj``, ``a``, ``b``, ``spqi``, ``wsnr_db``, ``ssnr_db``, ``notes`` (what the
        CLI prints as warnings and notes, each also raised as a ``hostd.errors.HostdWarning``,
        a UserWarning: ``warnings.simplefilter("ignore", HostdWarning)`` silences them); with
        `target_iobj` also ``target_iobj``, ``spqi_min``,
        ``waveform_verified`` (True: SPQI >= spqi_min measured on this stream; False: SPQI
        could not be computed, see notes), ``size_set_by`` ("Iobj" or "waveform": which
        criterion kept a smaller stream out; ``size_note`` says so when it was the waveform),
        ``binding`` (that criterion in words: "SPQI >= 0.9" or "Iobj <= 0.05"),
        ``encodes`` and ``search_cpu_s``.
    """
    y, length = _heights(profile, length_mm)
    try:
        res = encode_heights(y, length, method=method, fmt=format, target_iobj=target_iobj,
                             spqi_min=spqi_min, guard_db=guard_db, ssnr_db=ssnr_db, g_db=g_db,
                             levels=levels, b0_db=b0_db, value_bits=value_bits, coder=coder,
                             speed_mm_s=speed_mm_s, fmax_hz=fmax_hz, thresholds=thresholds,
                             ab=(a, b))
    except HostdError as exc:
        raise _python_names(exc) from None
    if res.get("size_note"):
        res["size_note"] = _python_text(res["size_note"])
    res["notes"] = [_python_text(n) for n in res["notes"]] + ([res["size_note"]] if res.get("size_note")
                                                               else [])
    _warn(res["notes"])
    return res


def _warn(notes: Iterable[str]) -> None:
    """Each note the CLI would print, as a HostdWarning (filter with warnings.simplefilter)."""
    import warnings

    from hostd.errors import HostdWarning

    for n in notes:
        warnings.warn(n, HostdWarning, stacklevel=3)


def encode_heights(y_um: np.ndarray, length_mm: float, *, method: str | None, fmt: str,
                   target_iobj: float | None, spqi_min: float | None, guard_db: float | None,
                   ssnr_db: float | None, g_db: float | None, levels: int | None,
                   b0_db: float | None, value_bits: int | None, coder: str, speed_mm_s: float,
                   fmax_hz: float, thresholds: str | None, ab: tuple[float, float]) -> dict:
    """`encode` and `hostd encode`'s one code path (errors name the CLI's options)."""
    from hostd.codec import formats, ratecontrol, stream, transform
    from hostd.errors import CodecError
    from hostd.perception import calibration, guard, peer
    from hostd.quality import score_stream

    curve = calibration.resolve_curve(thresholds)
    geom = transform.Geometry(y_um.size, length_mm, speed_mm_s, fmax_hz)
    fm = formats.get(fmt)
    if coder != "auto" and "--coder" not in fm.options:
        with_it = [f.name for f in formats.FORMATS.values() if "--coder" in f.options]
        raise CodecError(f"--coder applies to --format {' or '.join(with_it)} only ({fmt} has one "
                         "entropy coder of its own, the adaptive range coder)")
    if method is not None and method not in fm.methods:
        with_it = [f.name for f in formats.FORMATS.values() if method in f.methods]
        if not with_it:
            known = sorted({m for f in formats.FORMATS.values() for m in f.methods})
            raise CodecError(f"unknown method {method!r}: use {', '.join(known)}")
        raise CodecError(f"--method {method} needs --format {' or '.join(with_it)}"
                         + (" (the default)" if formats.DEFAULT in with_it else ""))
    notes: list[str] = []
    out: dict = {}
    if target_iobj is not None:
        res = ratecontrol.search(y_um, geom, curve, target_iobj, method=method, fmt=fmt,
                                 spqi_min=spqi_min, guard_db=guard_db, ssnr_db=ssnr_db, ab=ab)
        notes += res.notes
        data = res.best.data
        out.update(target_iobj=target_iobj, spqi_min=res.spqi_min,
                   waveform_verified=res.waveform_verified, size_set_by=res.size_set_by,
                   binding=(f"SPQI >= {res.spqi_min:g}" if res.size_set_by == "waveform"
                            else f"Iobj <= {target_iobj:g}"),  # what set the size, as the CLI leads with it
                   chosen=res.best.describe(), encodes=res.encodes, search_cpu_s=res.seconds)
    elif method is None:
        raise CodecError("give --method shaped|quant|cut (or --target-iobj X)")
    else:
        for opt, val, m in (("--b0-db", b0_db, "quant"), ("--b0-db", b0_db, "shaped"),
                            ("--levels", levels, "cut"), ("--levels", levels, "shaped"),
                            ("--g-db", g_db, "quant"), ("--g-db", g_db, "cut"),
                            ("--value-bits", value_bits or None, "quant")):
            if val is not None and method == m:
                notes.append(f"{opt} is ignored with --method {method}")
        knobs = {"g_db": g_db} if "shaped" in fm.methods else {}
        extra = {"coder": coder} if "--coder" in fm.options else {}
        data = stream.encode_profile(y_um, geom, curve, format=fmt, method=method, levels=levels,
                                     b0_db=b0_db, **knobs, **extra,
                                     value_bits=value_bits if value_bits is not None else fm.value_bits)
        out.update(chosen=None)
    s = stream.decode(data)
    kept = int(np.count_nonzero(s.coefficients))
    if kept == 0:
        rms = float(np.sqrt(np.mean(np.square(y_um))))
        notes.append(f"the stream keeps no component (every amplitude was quantized or cut to 0; "
                     f"the profile's RMS is {rms:.3g} µm): check --y-unit (heights are read in "
                     "that unit), or ask for more levels / a lower --b0 / a smaller --target-iobj")
    sc = score_stream(s, curve=curve, a=ab[0], b=ab[1])
    c = transform.analyze(y_um, s.n_keep)
    try:
        sp = peer.played_spqi(c, s.coefficients, s.n, s.length_mm, s.speed_mm_s)
    except HostdError as exc:
        sp = None
        notes.append(f"SPQI not computed: {exc}")
    if out.get("size_set_by") == "waveform":
        out["size_note"] = (f"the waveform criterion (SPQI >= {out['spqi_min']:g}), not Iobj, set the "
                            f"size: Iobj {float(sc.Iobj):.4f} is under --target-iobj {target_iobj:g}; a "
                            "lower --spqi-min (or --no-guard, Iobj alone) gives a smaller stream")
    out = {"stream": data, "method": s.method, "levels": s.levels, "b0_db": s.b0_db,
           "value_bits": s.value_bits, "n": s.n, "n_keep": s.n_keep, "kept": kept,
           "bytes": s.nbytes, "ratio_coeffs": s.ratio_coeffs, "ratio_profile": s.ratio_profile,
           "Ip": float(sc.Ip), "Ia": float(sc.Ia), "Iobj": float(sc.Iobj), "a": float(sc.a),
           "b": float(sc.b), "spqi": sp,
           "wsnr_db": guard.weighted_snr_db(c, s.coefficients, curve(s.frequencies_hz)),
           "ssnr_db": guard.spectral_snr_db(c, s.coefficients, s.frequencies_hz),
           **out, "notes": notes}
    return out


def decode(data: bytes | str | Path | Mapping) -> Stream:
    """Parse and validate a stream (bytes, the path of a ``.vtx`` file, or `encode`'s result).

    Returns
    -------
    Stream
        ``coefficients`` (C'_1..C'_N', µm), ``n``, ``n_keep``, ``length_mm``, ``speed_mm_s``,
        ``fmax_hz``, ``frequencies_hz``, ``ref_P``, ``ref_A``; ``reconstruct()`` gives the N
        heights (µm) y'_n = sum_k C'_k cos(pi k (2n+1) / (2N)); ``summary()`` a dict.
    """
    from hostd.codec import stream

    if isinstance(data, Mapping):  # what `encode` returns
        data = data["stream"]
    if isinstance(data, str | Path):  # a missing file: FileNotFoundError (hostd's StreamNotFound)
        from hostd.fileio import read_stream

        return read_stream(data)
    return stream.decode(bytes(data))


def score(stream: Stream | bytes | Mapping, reference: Profile | np.ndarray | None = None, *,
          a: float = 0.581, b: float = 0.464) -> dict:
    """Quality of a stream: Iobj = a Ip + b Ia (paper eq. 8-12), and the waveform measures.

    With the threshold b(f_k) of the stream's curve, P = sum (C_k / b_k)^2 and
    A = sum |C_k| / b_k over the reference and P', A' over the stream's C'_k;
    Ip = |P - P'| / ((P + P') / 2) and Ia = |A - A'| / ((A + A') / 2) (dimensionless; the
    relative error against the mean of the two sums, as hostd.perception.indices computes
    it and docs/conventions.md defines it: symmetric, at most 2, 0 when both sums are 0).

    Against the original (`reference` given), also the waveform: SPQI and ST-SIM of the
    signal a hand at the stream's v_ref feels for 1 s (8 kHz) against the original's (1 =
    identical; SPQI is hostd's own, ST-SIM needs the ``peer`` extra), and the waveform
    guard's wSNR and sSNR (dB). These are exactly what ``hostd iobj REF STREAM --json``
    reports, and SPQI is the criterion rate control (`encode(target_iobj=...)`) verifies.

    Parameters
    ----------
    stream : Stream, bytes, or `encode`'s result
    reference : Profile or array, optional
        The original heights (µm, N samples). Default: the P and A in the stream's header
        (then only wSNR, from a v2 header, of the waveform measures is known).
    a, b : float
        Weights (default: the paper's fit over both materials).

    Returns
    -------
    dict
        P, A, P_prime, A_prime, Ip, Ia, Iobj, a, b (floats), ``reference_mismatch`` (True
        when a given reference is not the stream's original: its P, A differ from the
        header's), ``wsnr_db`` (None when unknown) and, with a reference, ``ssnr_db``,
        ``nmr_max_db``, ``spqi`` and ``st_sim`` (None without the ``peer`` extra).
    """
    from hostd.codec import transform
    from hostd.perception import peer
    from hostd.quality import guard_report, reference_mismatch, score_stream

    s = stream if isinstance(stream, Stream) else decode(stream)
    ref = None
    if reference is not None:
        ref = reference.heights_um if isinstance(reference, Profile) else np.asarray(reference, float)
    try:
        out = score_stream(s, reference_um=ref, a=a, b=b).as_dict()
        mismatch = reference_mismatch(s, out["P"], out["A"]) if ref is not None else None
        out["reference_mismatch"] = mismatch is not None
        out["notes"] = [_python_text(mismatch)] if mismatch else []
        g = guard_report(s, reference_um=ref)
        out.update({k: v for k, v in g.items() if k != "guard_source"})
        if ref is not None:
            out.update({"st_sim": None, **peer.peer_scores(transform.analyze(ref, s.n_keep),
                                                           s.coefficients, s.n, s.length_mm,
                                                           s.speed_mm_s)})
    except HostdError as exc:
        raise _python_names(exc) from None
    _warn(out["notes"])
    return out


def fit(records: Iterable[Mapping] | Mapping[str, Iterable] | str | Path, *, nonnegative: bool = False,
        scale_min: float = 0.0, scale_max: float = 3.0, exclude_saturated: bool = False,
        n_boot: int = 2000) -> dict:
    """Fit (a, b) of Iobj = a Ip + b Ia to subjective scores by least squares without
    intercept (paper eq. 13-15).

    Parameters
    ----------
    records : list of dicts, a dict of columns (e.g. ``DataFrame.to_dict("list")``), or the
        path of a scores CSV (as ``hostd fit`` reads it; stream rows scored with µm profiles)
        Each stimulus: ``score`` and ``Ip``, ``Ia`` (or ``ip``, ``ia``); optionally ``texture``,
        ``method``, ``level``. A control (``method="none"``, the reference against itself) may
        leave out Ip and Ia: they are 0. ``df.to_dict("records")`` works as is.
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
    from hostd.errors import FitError
    from hostd.perception import fit as _fit

    if isinstance(records, str | Path):  # a scores CSV; a missing one is FileNotFoundError
        from hostd.quality import score_stream

        def score_one(stream_path, profile_spec):
            st = decode(stream_path)
            ref = None if profile_spec is None else load_profile(profile_spec, length_mm=st.length_mm)
            sc = score_stream(st, reference_um=None if ref is None else ref.heights_um)
            return float(sc.Ip), float(sc.Ia)

        try:
            stimuli = _fit.read_scores(records, score_one)
        except HostdError as exc:
            raise _python_names(exc) from None
        records = [{"texture": s.texture, "method": s.method, "level": s.level, "score": s.score,
                    "Ip": s.Ip, "Ia": s.Ia} for s in stimuli]
    if isinstance(records, Mapping):
        keys = list(records)
        cols = [list(records[k]) for k in keys]
        records = [dict(zip(keys, row, strict=True)) for row in zip(*cols, strict=True)]
    stimuli = []
    try:
        for i, r in enumerate(records):
            where = f"record {i}"
            if "score" not in r:
                raise FitError(f"{where}: no score")
            idx = _fit.indices_of(r, where)
            if idx is None:
                raise FitError(f"{where}: no Ip and Ia (only a control, method 'none', may leave them out)")
            try:
                score = float(r["score"])
            except (TypeError, ValueError):
                raise FitError(f"{where}: score must be a number, not {r['score']!r:.20}") from None
            stimuli.append(_fit.Stimulus(str(r.get("texture", "")), str(r.get("method", "")),
                                         str(r.get("level", "")), score, *idx))
    except HostdError as exc:
        raise _python_names(exc) from None
    res = _fit.fit(stimuli, nonnegative=nonnegative, scale_min=scale_min, scale_max=scale_max,
                   exclude_saturated=exclude_saturated, n_boot=n_boot)
    out = res.as_dict()
    _warn(out.get("warnings", []))
    return out


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
    from hostd.render.stroke import at_constant_speed

    s = stream if isinstance(stream, Stream) else decode(stream)
    if not (np.isfinite(speed_mm_s) and np.isfinite(seconds) and seconds > 0 and rate_hz > 0):
        raise ValueError("speed_mm_s must be finite, seconds and rate_hz > 0")
    count = round(seconds * rate_hz)
    h = at_constant_speed(s.coefficients, s.n, s.length_mm, speed_mm_s, rate_hz, count, x0_mm=x0_mm)
    t = np.arange(count) / rate_hz
    return {"t_s": t, "x_mm": x0_mm + speed_mm_s * t, "height_um": h}


def run_scene(scene: str | Path, *, only: list[str] | None = None) -> dict:
    """Simulate a scene (a TOML file or a shipped name such as ``"worst-case"``).

    Returns
    -------
    dict
        ``scene``, ``codec_iobj``, and ``runs``: one record per run (no effect, each effect
        alone, all together; or just the effects in `only`) with effects, Ip, Ia, Iobj,
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


def run_corpus(inputs: str | Path | Iterable[str | Path], store: str | Path, *,
               codecs: Iterable[str] = ("hostd-v2",), settings: Mapping[str, Iterable[Mapping]] | None = None,
               methods: Iterable[str] | None = None, g_db: Iterable[float] | None = None,
               levels: Iterable[int] | None = None, b0_db: Iterable[float] | None = None,
               target_iobj: Iterable[float] = (), speeds_mm_s: Iterable[float] = (50.0,),
               fmaxs_hz: Iterable[float] = (400.0,), x_unit: str = "um", y_unit: str = "um",
               spacing: float | None = None, length_mm: float | None = 10.0, offset_mm: float = 0.0,
               detrend: str = "none", workers: int | None = None, dask: str | None = None,
               batch: int | None = None, timeout_s: float = 60.0, spqi: bool = True,
               retry_errors: bool = False, progress: bool | None = None, as_pandas: bool | None = None,
               calibration: str | Path | None = None):
    """Evaluate codecs over a corpus: the same run as ``hostd corpus run`` (docs/corpus.md).

    Every (texture, codec, setting, speed, fmax) is one row of `store` (SQLite), keyed by a
    content hash: rows already there are not computed again, so calling this again after an
    interruption goes on where it stopped. Jobs run on every core (`workers`), in this
    process (`workers=1`) or on a Dask cluster (`dask="tcp://host:8786"` or ``"local"``).

    Parameters
    ----------
    inputs : path, ``synthetic:KIND[:SEED]`` or a list of them
        Directories of profiles, manifests (.toml / .csv), profile files, synthetic names.
    store : path
        The SQLite results file (created or resumed).
    codecs : names
        ``"hostd-v2"``, ``"hostd-v1"``, or external codecs ``"module:attr"`` following the
        protocol of hostd.corpus.codecs.
    settings : {codec name: [setting dict, ...]}, optional
        Sweeps for external codecs (default: each codec's own ``settings``).
    methods, g_db, levels, b0_db, target_iobj
        The sweep of hostd's codecs (None: the defaults of hostd.corpus.hostdcodec).
    speeds_mm_s, fmaxs_hz
        Geometries: every speed x every band limit.
    x_unit, y_unit, spacing, length_mm, offset_mm, detrend
        Loader options for profiles that a manifest does not describe.
    as_pandas : bool, optional
        Return a pandas DataFrame (default: when pandas is installed); else a pyarrow Table.
    calibration : path, optional
        A display's calibration file (`hostd experiment calibration`): rows scored with its
        (a, b) and threshold curve (part of each row's key and its ``scoring`` column).

    Returns
    -------
    pyarrow.Table or pandas.DataFrame
        Every row of the store (the schema of docs/corpus.md), not only this call's. The run's
        summary (counts by failure reason, interrupted) is in ``.attrs["summary"]`` of a
        DataFrame, or in the Table's schema metadata ``b"summary"`` (JSON).
    """
    import json

    from hostd.corpus import run as crun
    from hostd.corpus import store as cstore
    from hostd.corpus.jobs import Scoring
    from hostd.texture.load import LoadOptions

    if isinstance(inputs, str | Path):
        inputs = [inputs]
    opts = LoadOptions(x_unit=x_unit, y_unit=y_unit, spacing=spacing, length_mm=length_mm,
                       offset_mm=offset_mm, detrend=detrend)
    textures = crun.textures_from([str(i) for i in inputs], opts)
    plan = crun.make_plan(list(codecs), speeds_mm_s=list(speeds_mm_s), fmaxs_hz=list(fmaxs_hz),
                          methods=None if methods is None else list(methods),
                          g_db=None if g_db is None else list(g_db),
                          levels=None if levels is None else list(levels),
                          b0_db=None if b0_db is None else list(b0_db), target_iobj=list(target_iobj),
                          settings={k: list(v) for k, v in (settings or {}).items()})
    cstore._pyarrow()  # before the run: the result is a pyarrow table
    if calibration is not None:
        from hostd.perception.calibration import load as load_calibration

        scoring = Scoring.calibrated(load_calibration(calibration), spqi=spqi, timeout_s=timeout_s)
    else:
        scoring = Scoring(spqi=spqi, timeout_s=timeout_s)
    summ = crun.run(textures, plan, store, scoring=scoring, dask=dask,
                    workers=workers, batch=batch, progress=progress, retry_errors=retry_errors)
    table = cstore.to_arrow(store)
    table = table.replace_schema_metadata({b"summary": json.dumps(summ.as_dict()).encode()})
    if as_pandas is None:
        try:
            import pandas  # noqa: F401

            as_pandas = True
        except ImportError:
            as_pandas = False
    if not as_pandas:
        return table
    df = table.to_pandas()
    df.attrs["summary"] = summ.as_dict()
    return df
