"""Seeded, material-like synthetic height profiles for demos and tests.

wood:      1/f^beta roughness (energy at low spatial frequency) plus fibre grain: narrow-band
           quasi-periodic grooves with a jittered pitch and random depth.
sandpaper: a random field of abrasive grains (half-ellipsoid bumps) whose mean size and spacing
           follow the grit (FEPA P-grade) median particle size; broadband.
"""

from __future__ import annotations

import numpy as np

from hostd import pocketfft
from hostd.errors import ProfileError
from hostd.texture.load import Profile

# FEPA P-grade median grain size, µm (FEPA 43-2:2017, abridged).
GRIT_UM = {
    80: 201.0, 120: 125.0, 180: 82.0, 240: 58.5, 320: 46.2, 400: 35.0, 600: 25.8,
    800: 21.8, 1000: 18.3, 1200: 15.3, 1500: 12.6, 2000: 10.3, 2500: 8.4,
}


def _colored_noise(rng: np.random.Generator, n: int, dx_um: float, beta: float,
                   corner_um: float) -> np.ndarray:
    """Gaussian noise with power ~ 1/(1 + (lambda_c f)^2)^(beta/2): 1/f^beta above a corner."""
    f = np.fft.rfftfreq(n, d=dx_um)  # cycles per µm (scipy.fft.rfftfreq is numpy's)
    shape = (1.0 + (corner_um * f) ** 2) ** (-beta / 4.0)
    shape[0] = 0.0
    spec = shape * (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size))
    y = pocketfft.irfft(spec, n)
    return y / (np.std(y) or 1.0)


def wood(
    seed: int = 0,
    n: int = 20000,
    spacing_um: float = 0.5,
    rms_um: float = 6.0,
    beta: float = 2.0,
    corner_um: float = 2000.0,
    grain_pitch_um: float = 180.0,
    grain_depth_um: float = 2.5,
    grain_jitter: float = 0.25,
) -> Profile:
    """Wood-like texture: 1/f^beta roughness of rms_um plus grooves every ~grain_pitch_um."""
    rng = np.random.default_rng(seed)
    y = rms_um * _colored_noise(rng, n, spacing_um, beta, corner_um)
    x = np.arange(n) * spacing_um
    pos = rng.uniform(0, grain_pitch_um)
    while pos < x[-1]:
        width = grain_pitch_um * rng.uniform(0.15, 0.35)
        depth = grain_depth_um * rng.uniform(0.4, 1.6)
        y -= depth * np.exp(-0.5 * ((x - pos) / (0.3 * width)) ** 2)
        pos += grain_pitch_um * (1.0 + grain_jitter * rng.standard_normal())
        pos = max(pos, 0.0) + 1e-9
    y -= y.mean()
    return Profile(heights_um=y, spacing_um=spacing_um, source=f"synthetic:wood:seed={seed}")


def sandpaper(
    seed: int = 0,
    n: int = 20000,
    spacing_um: float = 0.5,
    grit: int = 1500,
    coverage: float = 0.7,
    backing_rms_um: float = 0.5,
) -> Profile:
    """Sandpaper-like texture: grains of the grit's median size d, ~coverage / d per µm.

    Grain heights protrude 0.2..0.6 d above the backing; widths scatter around d.
    """
    if grit not in GRIT_UM:
        raise ProfileError(f"unknown grit P{grit}: use one of {sorted(GRIT_UM)}")
    d = GRIT_UM[grit]
    rng = np.random.default_rng(seed)
    x = np.arange(n) * spacing_um
    count = rng.poisson(coverage * x[-1] / d)
    centres = rng.uniform(0, x[-1], count)
    sizes = d * rng.lognormal(0.0, 0.25, count)
    heights = sizes * rng.uniform(0.2, 0.6, count)
    y = backing_rms_um * _colored_noise(rng, n, spacing_um, 1.0, 5 * d)
    for c, s, h in zip(centres, sizes, heights, strict=True):
        lo = np.searchsorted(x, c - s / 2)
        hi = np.searchsorted(x, c + s / 2)
        u = (x[lo:hi] - c) / (s / 2)
        y[lo:hi] = np.maximum(y[lo:hi], h * np.sqrt(np.clip(1 - u * u, 0, None)))
    y -= y.mean()
    return Profile(heights_um=y, spacing_um=spacing_um, source=f"synthetic:sandpaper:P{grit}:seed={seed}")


GENERATORS = {"wood": wood, "sandpaper": sandpaper}


def make(kind: str, seed: int = 0, **kw) -> Profile:
    try:
        gen = GENERATORS[kind]
    except KeyError:
        raise ProfileError(f"unknown synthetic texture {kind!r}: use wood or sandpaper") from None
    return gen(seed=seed, **kw)


SPEC_PREFIX = "synthetic:"
SPEC_HELP = "synthetic:KIND[:SEED] with KIND wood or sandpaper and SEED an integer >= 0"


def is_spec(spec: str) -> bool:
    """True for a 'synthetic:...' profile name (which is not a file)."""
    return str(spec).startswith(SPEC_PREFIX)


def parse_spec(spec: str) -> tuple[str, int]:
    """'synthetic:KIND[:SEED]' -> (KIND, SEED); the one parser of that syntax (CLI, scenes, API)."""
    parts = str(spec).split(":")
    if parts[0] + ":" != SPEC_PREFIX or not 2 <= len(parts) <= 3 or not parts[1]:
        raise ProfileError(f"bad synthetic profile {spec!r}: use {SPEC_HELP}")
    kind = parts[1]
    if kind not in GENERATORS:
        raise ProfileError(f"unknown synthetic texture {kind!r}: use wood or sandpaper")
    seed = 0
    if len(parts) == 3:
        try:
            seed = int(parts[2])
        except ValueError:
            raise ProfileError(f"bad seed {parts[2]!r} in {spec!r}: use {SPEC_HELP}") from None
        if seed < 0:
            raise ProfileError(f"bad seed {seed} in {spec!r}: the seed must be an integer >= 0")
    return kind, seed


def from_spec(spec: str) -> Profile:
    """The whole synthetic profile a 'synthetic:KIND[:SEED]' name stands for (µm, 0.5 µm spacing)."""
    kind, seed = parse_spec(spec)
    return make(kind, seed)
