"""Linear quantization (eq. 5, 6) and threshold-cut (eq. 7) against direct formulas."""

import numpy as np
import pytest

from hostd.codec import methods, transform
from hostd.errors import CodecError
from hostd.perception.thresholds import default_curve
from hostd.texture import synth


def test_quantize_matches_eq5_eq6(rng):
    c = rng.normal(0, 1, 160)
    for levels in (2, 4, 14, 255):
        d = (c.max() - c.min()) / (levels - 1)
        expect = np.rint(c / d) * d
        got = methods.quantize(c, levels).values()
        assert np.max(np.abs(got - expect)) <= 1e-12 * np.max(np.abs(c))
        assert np.max(np.abs(got - c)) <= d / 2 * (1 + 1e-12)


def test_two_levels_is_the_coarsest(rng):
    c = rng.normal(0, 1, 50)
    q = methods.quantize(c, 2)
    assert q.step_um == pytest.approx(np.ptp(c))
    assert np.unique(q.q).size <= 3
    with pytest.raises(CodecError, match=">= 2"):
        methods.quantize(c, 1)
    with pytest.raises(CodecError):
        methods.quantize(c, 0)


def test_equal_coefficients_do_not_divide_by_zero():
    for val in (0.0, 3.5, -2.0):
        q = methods.quantize(np.full(10, val), 14)
        assert np.all(np.isfinite(q.values()))
        assert np.array_equal(q.values(), np.full(10, val))


def test_threshold_cut_matches_eq7_log_form():
    prof = synth.sandpaper(seed=3)
    g = transform.Geometry(prof.n, prof.length_mm)
    c = transform.analyze(prof.heights_um, g.n_keep)
    b = default_curve()(g.frequencies_hz())
    for b0 in (-12.0, -4.0, 0.0, 4.0, 12.0):
        keep = methods.threshold_cut(c, b, b0)
        with np.errstate(divide="ignore"):
            expect_zero = np.log10(np.abs(c)) < np.log10(b) + b0 / 20
        assert np.array_equal(keep, ~expect_zero)


def test_huge_b0_cuts_everything_and_zero_coefficients_are_cut():
    c = np.array([0.0, 1e3, -1e3])
    b = np.ones(3)
    assert not methods.threshold_cut(c, b, 200.0).any()
    assert methods.threshold_cut(c, b, 0.0).tolist() == [False, True, True]


def test_non_finite_b0_rejected():
    with pytest.raises(CodecError):
        methods.threshold_cut(np.ones(3), np.ones(3), float("nan"))
