"""The VectorialWave and Transient bands of MPEG-I Haptics (.hjif), evaluated as the reference
Synthesizer evaluates them, so hostd reads what the reference Encoder writes from AHAP and IVS
input (and those elements of an OHM input) without running the reference software.

A port of the reference software's evaluation (MPEGGroup/HapticReferenceSoftware 2de9ff1, BSD:
Types/src/Band.cpp EvaluationBand, EvaluationSwitch; Types/src/Effect.cpp EvaluateVectorial,
EvaluateTransient, computeBaseSignal; Tools/src/Tools.cpp linearInterpolation,
chirpInterpolation), vectorized over the output samples. Its quirks are kept: frequency
keyframes accumulate phase as if ticks were milliseconds, a chirp's time restarts at its first
keyframe, amplitudes are float32, a transient lasts 22 ms. What the port does not cover (effects
other than Basis, keyframes out of order, a keyframe without a position, a transient keyframe
without an amplitude) returns None, and the caller falls back to the reference Synthesizer (only
when the user opted in). tests/test_hjif_rm.py checks the port against the Synthesizer.

Ported from software under this licence, whose notice a port retains:

Copyright (c) 2010-2022, ISO/IEC. All rights reserved.
Redistribution and use in source and binary forms, with or without modification, are permitted
provided that the following conditions are met: Redistributions of source code must retain the
above copyright notice, this list of conditions and the following disclaimer. Redistributions in
binary form must reproduce the above copyright notice, this list of conditions and the following
disclaimer in the documentation and/or other materials provided with the distribution. Neither the
name of the ISO/IEC nor the names of its contributors may be used to endorse or promote products
derived from this software without specific prior written permission.
THIS SOFTWARE IS PROVIDED BY THE COPYRIGHT HOLDERS AND CONTRIBUTORS "AS IS" AND ANY EXPRESS OR
IMPLIED WARRANTIES, INCLUDING, BUT NOT LIMITED TO, THE IMPLIED WARRANTIES OF MERCHANTABILITY AND
FITNESS FOR A PARTICULAR PURPOSE ARE DISCLAIMED. IN NO EVENT SHALL THE COPYRIGHT HOLDER OR
CONTRIBUTORS BE LIABLE FOR ANY DIRECT, INDIRECT, INCIDENTAL, SPECIAL, EXEMPLARY, OR CONSEQUENTIAL
DAMAGES (INCLUDING, BUT NOT LIMITED TO, PROCUREMENT OF SUBSTITUTE GOODS OR SERVICES; LOSS OF USE,
DATA, OR PROFITS; OR BUSINESS INTERRUPTION) HOWEVER CAUSED AND ON ANY THEORY OF LIABILITY, WHETHER
IN CONTRACT, STRICT LIABILITY, OR TORT (INCLUDING NEGLIGENCE OR OTHERWISE) ARISING IN ANY WAY OUT
OF THE USE OF THIS SOFTWARE, EVEN IF ADVISED OF THE POSSIBILITY OF SUCH DAMAGE.
"""

from __future__ import annotations

import math

import numpy as np

from hostd.errors import ProfileError

MS_2_S = 0.001
TRANSIENT_MS = 22.0
BASE_SIGNALS = ("Sine", "Square", "Triangle", "SawToothUp", "SawToothDown")
MAX_KEYFRAMES = 100_000  # of one effect
MAX_AMPLITUDE = 1e3  # as hostd.texture.hjif's: the format's amplitudes are -1..1
MAX_PHASE = 1e6
# samples evaluated for one band, summed over its effects (and a Transient band's keyframes): a
# file whose effects all span the whole signal would otherwise cost effects x samples
MAX_WORK = 1 << 27


def _int(v) -> int | None:
    return v if isinstance(v, int) and not isinstance(v, bool) and -(2**31) <= v < 2**31 else None


def _effects(band: dict) -> list[tuple[int, dict, np.ndarray, list, list]] | None:
    """[(position, effect, keyframe positions, amplitudes (float32 or None), frequencies (int or
    None))] of the band, or None when the port does not cover it."""
    effects = band.get("effects")
    if not isinstance(effects, list):
        return None
    out = []
    for e in effects:
        if not isinstance(e, dict) or e.get("effect_type", "Basis") != "Basis":
            return None
        pos = _int(e.get("position"))
        kfs = e.get("keyframes", [])
        if pos is None or not isinstance(kfs, list) or len(kfs) > MAX_KEYFRAMES:
            return None
        rel, amp, freq = [], [], []
        for k in kfs:
            if not isinstance(k, dict) or _int(k.get("relative_position")) is None:
                return None
            rel.append(k["relative_position"])
            a = k.get("amplitude_modulation")
            ok = isinstance(a, int | float) and not isinstance(a, bool) and math.isfinite(a)
            amp.append(float(np.float32(a)) if ok and abs(a) <= MAX_AMPLITUDE else float(a) if ok else None)
            freq.append(_int(k.get("frequency_modulation")))
        r = np.array(rel, dtype=np.int64)
        if r.size and np.any(np.diff(r) < 0):
            return None
        out.append((pos, e, r, amp, freq))
    return out


def _c_round(x: np.ndarray) -> np.ndarray:
    """C's round: halves away from zero."""
    return np.sign(x) * np.floor(np.abs(x) + 0.5)


def _base(kind: str, time: np.ndarray, freq: np.ndarray, phase: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        time = np.where(freq != 0, time + phase / (2 * math.pi * freq), time)
    tf = time * freq
    if kind == "Sine":
        return np.sin(2 * math.pi * tf)
    if kind == "Square":
        return 1 - 2 * _c_round(tf - np.floor(tf))
    if kind == "Triangle":
        return 1 - 4 * np.abs(_c_round(tf - 0.25) - (tf - 0.25))
    if kind == "SawToothUp":
        return 2 * (tf - np.floor(tf + 0.5))
    return 2 * (np.floor(tf + 0.5) - tf)


def _vectorial(e: dict, rel_kf: np.ndarray, amp: list, freq: list, rel: np.ndarray, limits: tuple[int, int],
               timescale: int) -> np.ndarray:
    """EvaluateVectorial at relative positions `rel` (all within the effect)."""
    ia = [i for i, a in enumerate(amp) if a is not None]
    am = np.ones(rel.size)
    if ia:
        ra = rel_kf[ia].astype(np.float64)
        va = np.array([amp[i] for i in ia])
        j = np.searchsorted(ra, rel, side="left")  # first amplitude keyframe at or after
        past = j >= ra.size
        am[past] = va[-1]
        first = j == 0
        am[first] = va[0]
        mid = ~past & ~first
        jm = j[mid]
        t0, t1, a0, a1, x = ra[jm - 1], ra[jm], va[jm - 1], va[jm], rel[mid]
        with np.errstate(divide="ignore", invalid="ignore"):
            y = (a0 * (t1 - x) + a1 * (x - t0)) / (t1 - t0)
        am[mid] = np.where(x < t0, a0, np.where(x > t1, a1, y))
    ph = e.get("phase", 0.0)
    phi0 = float(np.float32(ph)) if isinstance(ph, int | float) and not isinstance(ph, bool) else 0.0
    ifr = [i for i, f in enumerate(freq) if f is not None]
    fq = np.zeros(rel.size)
    phi = np.full(rel.size, phi0)
    t_eval = rel.copy()
    if ifr:
        rf = rel_kf[ifr]
        vf = np.array([freq[i] for i in ifr], dtype=np.int64)
        inc = np.zeros(rf.size)
        for m in range(rf.size):  # the phase each keyframe adds once passed
            if m >= 1:
                inc[m] = math.pi * int(rf[m] - rf[m - 1]) * MS_2_S * float(vf[m - 1] + vf[m])
            elif rf[m] > 0:
                inc[m] = 2 * math.pi * int(rf[m]) * MS_2_S * float(vf[m])
        cum = np.concatenate([[0.0], np.cumsum(inc)])
        j = np.searchsorted(rf.astype(np.float64), rel, side="left")  # first with position >= rel
        phi = phi0 + cum[j]
        past = j >= rf.size
        fq[past] = float(vf[-1])
        first = j == 0
        fq[first] = float(vf[0])
        mid = ~past & ~first
        jm = j[mid]
        t0, t1 = rf[jm - 1].astype(np.float64), rf[jm].astype(np.float64)
        f0, f1 = vf[jm - 1].astype(np.float64), vf[jm].astype(np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            ch = np.where(t0 == t1, f1, ((f1 - f0) / (t1 - t0)) / 2 * (rel[mid] - t0) + f0)
        fq[mid] = np.clip(ch, *limits)
        t_eval[mid] = rel[mid] - t0
    base = e.get("base_signal", "Sine")
    return am * _base(base if base in BASE_SIGNALS else "Sine", t_eval / timescale, fq, phi)


def covers(band: dict) -> bool:
    """Whether the port evaluates this band (else only the reference software does)."""
    if band.get("band_type") not in ("VectorialWave", "Transient"):
        return False
    if _int(band.get("lower_frequency_limit")) is None or _int(band.get("upper_frequency_limit")) is None:
        return False
    effects = _effects(band)
    if effects is None:
        return False
    # a transient keyframe without an amplitude makes the reference software loop for ever
    return band["band_type"] != "Transient" or all(a is not None for *_, amp, _f in effects for a in amp)


def render_band(band: dict, timescale: int, rate: int, count: int, where: str, path) -> np.ndarray:
    """The `count` samples at `rate` of a band the port covers (covers(band)), as the reference
    Synthesizer plays them. Work past MAX_WORK samples is a one-line refusal."""
    kind = band["band_type"]
    effects = _effects(band) or []
    for k, (_p, e, _r, amp, _f) in enumerate(effects):
        big = [a for a in amp if a is not None and not abs(a) <= MAX_AMPLITUDE]
        ph = e.get("phase", 0.0)
        if big or (isinstance(ph, int | float) and not abs(ph) <= MAX_PHASE):
            what = (f"an amplitude of {big[0]:g} (at most {MAX_AMPLITUDE:g})" if big
                    else f"a phase of {ph:g} (at most {MAX_PHASE:g})")
            raise ProfileError(f"{path}: {where}.effects[{k}]: {what} is absurd")
    limits = (band["lower_frequency_limit"], band["upper_frequency_limit"])
    pos = timescale * (np.arange(count, dtype=np.float64) / float(rate) - 0.0)
    y = np.zeros(count)
    td = TRANSIENT_MS / (1000.0 / timescale)
    windows = []
    for p0, e, rel_kf, amp, freq in effects:
        if rel_kf.size == 0:
            continue
        length = float(rel_kf[-1]) + (td if kind == "Transient" else 0.0)
        a, b = np.searchsorted(pos, p0, side="left"), np.searchsorted(pos, p0 + length, side="right")
        if kind == "Transient":  # each keyframe sounds for td only
            ka = np.searchsorted(pos, p0 + rel_kf, side="left")
            kb = np.searchsorted(pos, p0 + rel_kf + td, side="right")
            work = int(np.sum(kb - ka))
        else:
            ka = kb = None
            work = int(b - a)
        windows.append((p0, e, rel_kf, amp, freq, a, b, ka, kb, work))
    total = sum(w[-1] for w in windows)
    if total > MAX_WORK:
        raise ProfileError(f"{path}: {where}: its effects span {total} samples in all, more than the "
                           f"{MAX_WORK} hostd evaluates of one band (hostd.texture.hjif_vectorial.MAX_WORK)")
    for p0, e, rel_kf, amp, freq, a, b, ka, kb, _ in windows:
        if b <= a:
            continue
        if kind == "VectorialWave":
            y[a:b] += _vectorial(e, rel_kf, amp, freq, pos[a:b] - p0, limits, timescale)
            continue
        for r, am, i, j in zip(rel_kf.tolist(), amp, ka.tolist(), kb.tolist(), strict=True):
            if j > i:
                y[i:j] += np.sin(4 * math.pi * (pos[i:j] - p0 - r) / td) * am
    return y
