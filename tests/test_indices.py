"""P, A, Ip, Ia, Iobj (eq. 8-12) against direct re-computation; zero cases; receiver path."""

import math

import numpy as np
import pytest

from hostd.codec import stream as vtx
from hostd.codec import transform
from hostd.errors import QualityError
from hostd.perception import indices, thresholds
from hostd.quality import score_stream
from hostd.texture import synth
from hostd.texture.load import LoadOptions, load_profile
from tests.conftest import REAL, REAL_SPEED, real_profile_path

CURVE = thresholds.default_curve()


def direct(c, cp, b, a_w, b_w):
    # Exact sums (fsum): Ip of a near-lossless variant is a difference of nearly equal sums,
    # which a naive left-to-right sum would get wrong in the 12th digit.
    P = math.fsum(ck * ck / (bk * bk) for ck, bk in zip(c, b, strict=True))
    A = math.fsum(abs(ck) / bk for ck, bk in zip(c, b, strict=True))
    Pp = math.fsum(ck * ck / (bk * bk) for ck, bk in zip(cp, b, strict=True))
    Ap = math.fsum(abs(ck) / bk for ck, bk in zip(cp, b, strict=True))
    ip = abs(P - Pp) / ((P + Pp) / 2)
    ia = abs(A - Ap) / ((A + Ap) / 2)
    return P, A, Pp, Ap, ip, ia, a_w * ip + b_w * ia


def _close(x, y):
    return abs(x - y) <= 1e-12 * max(abs(y), 1e-300)


def _check(c, cp, b):
    s = indices.score(c, cp, b, 0.581, 0.464)
    for got, want in zip((s.P, s.A, s.P_prime, s.A_prime, s.Ip, s.Ia, s.Iobj),
                         direct(c, cp, b, 0.581, 0.464), strict=True):
        assert _close(float(got), want)


def test_indices_match_direct_formulas_on_random_spectra(rng):
    b = CURVE(np.linspace(2.5, 400, 160))
    for _ in range(20):
        c = rng.normal(0, 1, 160)
        _check(c, c + rng.normal(0, 0.1, 160), b)


@pytest.mark.parametrize("name", list(REAL))
def test_indices_match_direct_formulas_on_real_profiles(name):
    prof = load_profile(real_profile_path(name), LoadOptions(**REAL[name]))
    geom = transform.Geometry(prof.n, prof.length_mm, speed_mm_s=REAL_SPEED[name])
    c = transform.analyze(prof.heights_um, geom.n_keep)
    s = vtx.decode(vtx.v1.encode_profile(prof.heights_um, geom, CURVE, method="quant", levels=5))
    _check(c, s.coefficients, CURVE(geom.frequencies_hz()))


def test_identical_and_silent_textures_score_zero_not_nan():
    b = np.ones(4)
    z = np.zeros(4)
    s = indices.score(z, z, b)
    assert float(s.Ip) == 0.0 and float(s.Ia) == 0.0 and float(s.Iobj) == 0.0
    c = np.array([1.0, -2.0, 0.0, 3.0])
    assert float(indices.score(c, c, b).Iobj) == 0.0


def test_everything_removed_gives_the_maximum_relative_error_of_two():
    c = np.array([1.0, 2.0])
    s = indices.score(c, np.zeros(2), np.ones(2))
    assert float(s.Ip) == 2.0 and float(s.Ia) == 2.0


def test_non_finite_input_refused():
    b = np.ones(3)
    with pytest.raises(QualityError, match="NaN or Inf"):
        indices.score(np.array([1.0, np.nan, 0]), np.ones(3), b)
    with pytest.raises(QualityError):
        indices.score(np.ones(3), np.ones(3), np.array([1.0, 0.0, 1.0]))
    with pytest.raises(QualityError):
        indices.scores_from_sums(1.0, 1.0, 1.0, 1.0, a=math.inf)


def test_vectorized_scores_equal_one_at_a_time(rng):
    b = CURVE(np.linspace(2.5, 400, 160))
    c = rng.normal(0, 1, 160)
    variants = c + rng.normal(0, 0.2, (50, 160))
    many = indices.score(c, variants, b)
    for i in range(50):
        one = indices.score(c, variants[i], b)
        assert _close(float(many.Iobj[i]), float(one.Iobj))


def test_presets_are_the_papers_fits():
    assert indices.PRESETS == {"both": (0.581, 0.464), "wood": (0.67, 0.44),
                               "sandpaper": (0.52, 0.58)}
    assert indices.DEFAULT_AB == (0.581, 0.464)


@pytest.mark.parametrize("kw", [dict(method="quant", levels=6), dict(method="cut", b0_db=0.0),
                                dict(method="cut", b0_db=-8.0, value_bits=16)])
def test_receiver_with_only_the_stream_scores_like_the_sender(kw):
    prof = synth.sandpaper(seed=9)
    geom = transform.Geometry(prof.n, prof.length_mm)
    s = vtx.decode(vtx.v1.encode_profile(prof.heights_um, geom, CURVE, **kw))
    receiver = score_stream(s)
    sender = score_stream(s, reference_um=prof.heights_um)
    for k in ("P", "A", "Ip", "Ia", "Iobj"):
        assert _close(float(getattr(receiver, k)), float(getattr(sender, k)))
