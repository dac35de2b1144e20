"""Held-out textures for rate control: none is in the guard's calibration set.

`hostd bench codec --holdout` runs `--target-iobj 0.05` with the defaults on every texture here
and reports bytes, Iobj, SPQI and the CPU time of the search; tests/test_holdout.py checks a
representative subset with an independent scorer. The calibration set
(hostd.bench.codec2.calibration_textures) holds synthetic wood and sandpaper seeds 0-5 at the
paper's geometry and the real profiles in a few windows at a few speeds; this set takes other
windows, offsets, detrendings, speeds and band limits of the real profiles (including
recordings with hundreds to a thousand components), and synthetic textures of a character
the calibration never saw. Every synthetic texture is N = 20000 heights at 0.5 µm (a 10 mm
patch, the paper's geometry unless a speed or fmax is given), seeded and documented here:

- spikes:       40 isolated one-sample spikes of ±(2..10) µm at uniformly random positions on 0
- single spike: one 10 µm spike at x = 3.3 mm on 0
- flat-spectrum: all C_k equal: y_n = sum_{k=1..160} cos(pi k (2n+1) / (2N)) µm (issue 23)
- square grating: a ±20 µm square wave of period 0.8 mm (odd harmonics 1/h)
- sine grating: 5 µm at period 0.37 mm plus its 3rd harmonic at 1 µm
- brownian:     cumulative sum of white Gaussian steps (1/f^2 power), scaled to 10 µm RMS
- fbm H=0.3:    fractional Brownian surface by spectral synthesis, power ~ f^-(2H+1), 3 µm RMS
- band noise:   white noise band-passed (FFT mask) to 100-300 Hz at 50 mm/s, 2 µm RMS
- steps:        piecewise-constant terraces, 25 random step edges of ±(1..8) µm
- mixture:      square grating (5 µm) + brownian (3 µm RMS) + one 15 µm spike
- chirp:        a linear chirp from period 2 mm to 0.1 mm, 4 µm amplitude
- vibration:    a vibration-like signal of a finger stroke, 20000 samples at 0.5 µm, std 5 µm:
                damped resonances (AR(2) at 80 and 230 Hz at 50 mm/s) excited by Poisson
                impacts under a stroke envelope (rise, hold, decay)
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import scipy.fft
import scipy.signal

from hostd.codec import transform

N = 20000
DX_UM = 0.5
LENGTH_MM = N * DX_UM / 1000.0


def _x_mm() -> np.ndarray:
    return np.arange(N) * DX_UM / 1000.0


def _spikes(seed: int = 11) -> np.ndarray:
    rng = np.random.default_rng(seed)
    y = np.zeros(N)
    y[rng.choice(N, 40, replace=False)] = rng.choice([-1.0, 1.0], 40) * rng.uniform(2, 10, 40)
    return y


def _single_spike() -> np.ndarray:
    y = np.zeros(N)
    y[round(3.3 / LENGTH_MM * N)] = 10.0
    return y


def _flat_spectrum() -> np.ndarray:
    n = np.arange(N)
    k = np.arange(1, 161)
    return np.cos(np.pi * np.outer(2 * n + 1, k) / (2 * N)).sum(axis=1)


def _square_grating(amp_um: float = 20.0, period_mm: float = 0.8) -> np.ndarray:
    return amp_um * np.sign(np.sin(2 * np.pi * _x_mm() / period_mm + 0.3))


def _sine_grating() -> np.ndarray:
    x = _x_mm()
    return 5.0 * np.sin(2 * np.pi * x / 0.37) + 1.0 * np.sin(2 * np.pi * 3 * x / 0.37 + 1.0)


def _brownian(seed: int = 12, rms_um: float = 10.0) -> np.ndarray:
    y = np.cumsum(np.random.default_rng(seed).standard_normal(N))
    y -= y.mean()
    return rms_um * y / np.std(y)


def _fbm(seed: int = 13, hurst: float = 0.3, rms_um: float = 3.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    f = scipy.fft.rfftfreq(N, d=DX_UM)
    amp = np.zeros_like(f)
    amp[1:] = f[1:] ** (-(2 * hurst + 1) / 2)
    y = scipy.fft.irfft(amp * (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size)), N)
    return rms_um * y / np.std(y)


def _band_noise(seed: int = 14, lo_hz: float = 100.0, hi_hz: float = 300.0,
                speed_mm_s: float = 50.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    spec = scipy.fft.rfft(rng.standard_normal(N))
    f_hz = scipy.fft.rfftfreq(N, d=DX_UM / 1000.0) * speed_mm_s  # cycles/mm * mm/s
    spec[(f_hz < lo_hz) | (f_hz > hi_hz)] = 0
    y = scipy.fft.irfft(spec, N)
    return 2.0 * y / np.std(y)


def _steps(seed: int = 15) -> np.ndarray:
    rng = np.random.default_rng(seed)
    jumps = np.zeros(N)
    at = rng.choice(np.arange(1, N), 25, replace=False)
    jumps[at] = rng.choice([-1.0, 1.0], 25) * rng.uniform(1, 8, 25)
    y = np.cumsum(jumps)
    return y - y.mean()


def _mixture() -> np.ndarray:
    y = _square_grating(5.0, 0.8) + _brownian(16, 3.0)
    y[round(7.1 / LENGTH_MM * N)] += 15.0
    return y


def _chirp() -> np.ndarray:
    x = _x_mm()
    f0, f1 = 1 / 2.0, 1 / 0.1  # cycles per mm
    return 4.0 * np.sin(2 * np.pi * (f0 * x + (f1 - f0) * x**2 / (2 * LENGTH_MM)))


def _vibration(seed: int = 17) -> np.ndarray:
    rng = np.random.default_rng(seed)
    fs = 50.0 / (DX_UM / 1000.0)  # samples per second at 50 mm/s (100 kHz)
    exc = np.zeros(N)
    hits = rng.random(N) < 0.004
    exc[hits] = rng.standard_normal(hits.sum())
    exc += 0.05 * rng.standard_normal(N)
    y = np.zeros(N)
    for f0, r, g in ((80.0, 0.9995, 1.0), (230.0, 0.999, 0.6)):
        a1, a2 = 2 * r * np.cos(2 * np.pi * f0 / fs), -r * r
        y += g * scipy.signal.lfilter([1.0], [1.0, -a1, -a2], exc)
    t = np.arange(N) / N
    env = np.minimum(1.0, t / 0.1) * np.where(t > 0.7, np.exp(-(t - 0.7) / 0.1), 1.0)
    y *= env
    y -= y.mean()
    return 5.0 * y / np.std(y)


SYNTHETIC = {
    "spikes": (_spikes, 50.0, 400.0),
    "single spike": (_single_spike, 50.0, 400.0),
    "flat spectrum (all C_k equal)": (_flat_spectrum, 50.0, 400.0),
    "square grating 0.8 mm": (_square_grating, 50.0, 400.0),
    "sine grating 0.37 mm": (_sine_grating, 50.0, 400.0),
    "brownian": (_brownian, 50.0, 400.0),
    "brownian @20 fmax 800": (_brownian, 20.0, 800.0),
    "fbm H=0.3": (_fbm, 50.0, 400.0),
    "band noise 100-300 Hz": (_band_noise, 50.0, 400.0),
    "band noise @50 fmax 1000": (_band_noise, 50.0, 1000.0),
    "steps": (_steps, 50.0, 400.0),
    "mixture": (_mixture, 50.0, 400.0),
    "chirp": (_chirp, 50.0, 400.0),
    "vibration (0.5 µm, std 5 µm)": (_vibration, 50.0, 400.0),
}

# Real profiles (units from shared/data/profiles/README.md; xy-1's and xy-4's unknown units
# read as µm and mm, as everywhere in the project): windows, offsets, detrendings, speeds and
# band limits that are not in the calibration set.
_UM = {"x_unit": "um", "y_unit": "um"}
_XY4 = {"x_unit": "mm", "y_unit": "um"}
_OPDX = {"x_unit": "m", "y_unit": "m"}
REAL = (
    ("dektak-1.csv", {**_UM, "length_mm": 1.0, "offset_mm": 0.3}, 30.0, 400.0, "[1 mm at 0.3]@30"),
    ("dektak-1.csv", {**_UM, "length_mm": None, "detrend": "mean"}, 15.0, 400.0, "[whole, mean]@15"),
    ("dektak-1.csv", {**_UM, "length_mm": 0.25, "offset_mm": 1.2}, 10.0, 400.0, "[0.25 mm at 1.2]@10"),
    ("dektak-1.csv", {**_UM, "length_mm": None, "detrend": "linear"}, 5.0, 1000.0,
     "[whole, linear]@5 fmax 1000"),
    ("xy-4.txt", {**_XY4, "length_mm": None}, 5.0, 400.0, "[whole]@5"),
    ("xy-4.txt", {**_XY4, "length_mm": None, "detrend": "linear"}, 2.0, 1000.0,
     "[whole, linear]@2 fmax 1000"),
    ("xy-4.txt", {**_XY4, "length_mm": 0.4, "offset_mm": 0.5}, 20.0, 400.0, "[0.4 mm at 0.5]@20"),
    ("xy-1.txt", {**_UM}, 3.0, 400.0, "@3"),
    ("opdx-3.txt", {**_OPDX, "length_mm": None}, 0.5, 400.0, "@0.5"),
    ("opdx-3.txt", {**_OPDX, "length_mm": None, "detrend": "linear"}, 0.1, 1000.0, "[linear]@0.1 fmax 1000"),
    ("opdx-3.txt", {**_OPDX, "length_mm": 0.025, "offset_mm": 0.02}, 0.25, 400.0, "[25 µm at 20 µm]@0.25"),
)

# The subset tests/test_holdout.py checks (one of each character, and high-N' real ones).
FAST = ("spikes", "single spike", "flat spectrum (all C_k equal)", "square grating 0.8 mm",
        "fbm H=0.3", "steps", "vibration (0.5 µm, std 5 µm)", "dektak-1.csv[whole, mean]@15",
        "xy-4.txt[whole, linear]@2 fmax 1000", "opdx-3.txt@0.5")


def profiles_dir() -> Path:
    env = os.environ.get("HOSTD_PROFILES_DIR")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[3] / "shared" / "data" / "profiles"


def textures(names: tuple[str, ...] | None = None) -> list[tuple[str, np.ndarray, transform.Geometry]]:
    """(name, heights in µm, geometry) of the held-out set (or of `names` in it); real ones
    only where shared/data/profiles is present."""
    from hostd.texture.load import LoadOptions, load_profile

    out = []
    for name, (gen, speed, fmax) in SYNTHETIC.items():
        if names is None or name in names:
            out.append((name, gen(), transform.Geometry(N, LENGTH_MM, speed, fmax)))
    d = profiles_dir()
    for fname, opts, speed, fmax, tag in REAL:
        name = fname + tag
        if (names is None or name in names) and (d / fname).exists():
            p = load_profile(d / fname, LoadOptions(**opts))
            out.append((name, p.heights_um, transform.Geometry(p.n, p.length_mm, speed, fmax)))
    return out


def rows(repeat: int = 3) -> list[dict]:
    """`hostd bench codec --holdout`: per texture, the stream `--target-iobj 0.05` returns with
    the defaults (bytes, method, Iobj, SPQI by hostd and by vibromaf where installed, which
    criterion set the size, encodes, the search's CPU time: median of `repeat` runs, thread
    time) and with the previous default (the proxy guard wSNR >= 25 dB, sSNR >= 27 dB); then
    a summary row."""
    import statistics

    from hostd.bench.codec2 import PROXY_GUARD
    from hostd.codec import ratecontrol
    from hostd.codec import stream as vtx
    from hostd.perception import peer, thresholds

    curve = thresholds.default_curve()
    try:
        from vibromaf.metrics.spqi import spqi as vibromaf_spqi
    except ImportError:
        vibromaf_spqi = None
    out = []
    for name, y, geom in textures():
        runs = [ratecontrol.search(y, geom, curve, 0.05) for _ in range(repeat)]
        r = runs[0]
        s = vtx.decode(r.best.data)
        c = transform.analyze(y, s.n_keep)
        row: dict = {"bench": "codec_holdout", "texture": name, "n_keep": s.n_keep,
                     "bytes": r.best.nbytes, "method": r.best.method, "Iobj": round(r.best.Iobj, 4),
                     "spqi": round(r.best.spqi, 4), "size_set_by": r.size_set_by,
                     "encodes": r.encodes,
                     "search_ms": round(statistics.median(x.seconds for x in runs) * 1e3, 1)}
        if vibromaf_spqi is not None:
            import warnings

            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                row["spqi_vibromaf"] = round(float(vibromaf_spqi(
                    peer.played_signal(s.coefficients, s.n, s.length_mm, s.speed_mm_s),
                    peer.played_signal(c, s.n, s.length_mm, s.speed_mm_s))), 4)
        old = ratecontrol.search(y, geom, curve, 0.05, **PROXY_GUARD)
        so = vtx.decode(old.best.data)
        row.update(prev_bytes=old.best.nbytes, prev_spqi=round(peer.played_spqi(
            c, so.coefficients, so.n, so.length_mm, so.speed_mm_s), 4))
        out.append(row)
    out.append({"bench": "codec_holdout_summary", "textures": len(out),
                "max_Iobj": max(r["Iobj"] for r in out), "min_spqi": min(r["spqi"] for r in out),
                "bytes": sum(r["bytes"] for r in out), "prev_bytes": sum(r["prev_bytes"] for r in out),
                "prev_below_0.9": sum(r["prev_spqi"] < 0.9 for r in out),
                "search_ms_median": statistics.median(r["search_ms"] for r in out),
                "search_ms_max": max(r["search_ms"] for r in out),
                "size_set_by_waveform": sum(r["size_set_by"] == "waveform" for r in out)})
    return out
