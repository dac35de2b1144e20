"""DCT-II amplitudes, frequencies and the band-limited inverse against the paper's formulas."""

import numpy as np
import pytest

from hostd.codec import transform
from hostd.errors import CodecError
from hostd.texture import synth
from hostd.texture.load import LoadOptions, load_profile
from tests.conftest import REAL, real_profile_path

REL = 1e-9


def rel_err(a, b):
    return np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300)


@pytest.mark.parametrize("n", [2, 3, 17, 1000, 4096])
def test_amplitudes_match_direct_sum_on_random_profiles(rng, n):
    y = rng.normal(0, 5, n)
    k = np.arange(n)
    assert rel_err(transform.amplitudes(y), transform.direct_amplitudes(y, k)) <= REL


@pytest.mark.parametrize("name", list(REAL))
def test_amplitudes_and_synthesis_match_direct_sums_on_real_profiles(name):
    prof = load_profile(real_profile_path(name), LoadOptions(length_mm=None, **REAL[name]))
    y = prof.heights_um[:3000]
    k = np.arange(1, 121)
    c = transform.analyze(y, 120)
    assert rel_err(c, transform.direct_amplitudes(y, k)) <= REL
    assert rel_err(transform.synthesize(c, y.size), transform.direct_synthesis(c, y.size)) <= REL


def test_synthesis_matches_direct_sum_on_random_coefficients(rng):
    c = rng.normal(0, 1, 160)
    assert rel_err(transform.synthesize(c, 20000), transform.direct_synthesis(c, 20000)) <= REL


def test_full_band_synthesis_inverts_analysis_up_to_dc(rng):
    y = rng.normal(0, 1, 512)
    c = transform.analyze(y, 511)
    assert np.max(np.abs(transform.synthesize(c, 512) - (y - y.mean()))) <= 1e-12


def test_paper_geometry_keeps_160_components():
    g = transform.Geometry(n=20000, length_mm=10.0, speed_mm_s=50.0, fmax_hz=400.0)
    assert g.n_keep == 160
    assert g.spacing_um == 0.5
    f = g.frequencies_hz()
    assert f[0] == 2.5 and f[-1] == 400.0


def test_frequency_is_half_cycles_over_patch():
    # A cosine of k half-cycles over L, played at v, has frequency k v / (2 L).
    n, length_mm, v = 4000, 10.0, 50.0
    x = (np.arange(n) + 0.5) / n
    y = np.cos(np.pi * 37 * x)
    c = transform.amplitudes(y)
    assert np.argmax(np.abs(c)) == 37
    assert abs(c[37] - 1.0) < 1e-12
    assert transform.frequencies_hz(37, length_mm, v) == pytest.approx(37 * v / (2 * length_mm))


def test_constant_profile_has_all_zero_amplitudes():
    c = transform.analyze(np.full(1000, 42.0), 100)
    assert np.max(np.abs(c)) <= 1e-12 * 42


def test_n_keep_not_below_n():
    with pytest.raises(CodecError, match="N' must be < N"):
        _ = transform.Geometry(n=100, length_mm=10.0, fmax_hz=400.0).n_keep
    with pytest.raises(CodecError):
        transform.analyze(np.zeros(10), 10)
    with pytest.raises(CodecError):
        transform.synthesize(np.zeros(10), 10)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_heights_rejected(bad):
    y = np.zeros(100)
    y[7] = bad
    with pytest.raises(CodecError, match="NaN or Inf"):
        transform.analyze(y, 10)


@pytest.mark.parametrize("scale", [1e-30, 1e6])
def test_tiny_and_huge_amplitudes_stay_exact(scale):
    prof = synth.wood(seed=2, n=4000)
    y = prof.heights_um * scale
    c = transform.analyze(y, 160)
    assert np.all(np.isfinite(c))
    assert rel_err(c, transform.direct_amplitudes(y, np.arange(1, 161))) <= REL
    assert rel_err(transform.synthesize(c, y.size), transform.direct_synthesis(c, y.size)) <= REL
