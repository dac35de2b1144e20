"""Issue 23, numerically hard inputs: scale invariance over float64's range, DCT round-off
treated as zero, and the (a, b) fit on ill-posed data, each against an independent
computation (exact rational arithmetic with `fractions`, or the mathematical identity)."""

import json
import math
from fractions import Fraction

import numpy as np
import pytest

from hostd import cli
from hostd.codec import methods, transform
from hostd.codec import stream as vtx
from hostd.codec.stream import v2 as stream2
from hostd.errors import FitError, QualityError
from hostd.perception import fit, guard, indices, thresholds
from hostd.texture import synth

CURVE = thresholds.default_curve()


# ---------------------------------------------------------------- the oracle: eq. 8-12 in exact rationals

def oracle_indices(c, cp, b, a_w=0.581, b_w=0.464):
    """Ip, Ia, Iobj of the paper's eq. 8-12 in exact rational arithmetic on the given floats
    (no scaling, no rounding until the end): right at any magnitude."""
    fb = [Fraction(float(x)) for x in b]
    P = sum((Fraction(float(x)) / bb) ** 2 for x, bb in zip(c, fb, strict=True))
    Pp = sum((Fraction(float(x)) / bb) ** 2 for x, bb in zip(cp, fb, strict=True))
    A = sum(abs(Fraction(float(x))) / bb for x, bb in zip(c, fb, strict=True))
    Ap = sum(abs(Fraction(float(x))) / bb for x, bb in zip(cp, fb, strict=True))

    def rel(x, y):
        return Fraction(0) if x + y == 0 else abs(x - y) / ((x + y) / 2)

    ip, ia = rel(P, Pp), rel(A, Ap)
    return float(ip), float(ia), float(Fraction(a_w) * ip + Fraction(b_w) * ia)


def oracle_snr_db(c, cp, b):
    """wSNR = 10 log10(sum (C/b)^2 / sum ((C - C')/b)^2), exactly, then in dB."""
    fb = [Fraction(float(x)) for x in b]
    sig = sum((Fraction(float(x)) / bb) ** 2 for x, bb in zip(c, fb, strict=True))
    noise = sum(((Fraction(float(x)) - Fraction(float(y))) / bb) ** 2
                for x, y, bb in zip(c, cp, fb, strict=True))
    # log10 of a ratio of huge rationals: through their integer parts' bit lengths
    r = sig / noise
    shift = r.numerator.bit_length() - r.denominator.bit_length()
    return 10 * (math.log10(float(r / Fraction(2) ** shift)) + shift * math.log10(2))


@pytest.fixture(scope="module")
def wood():
    prof = synth.wood(seed=1)
    geom = transform.Geometry(prof.n, prof.length_mm)
    c = transform.analyze(prof.heights_um, geom.n_keep)
    return c, methods.quantize(c, 6).values(), CURVE(geom.frequencies_hz())


def _close(x, y, rel=1e-12):
    return abs(x - y) <= rel * max(abs(y), 1e-300)


# ---------------------------------------------------------------- scale invariance

@pytest.mark.parametrize("factor", [1.0, 1e-300, 2.0 ** -1000, 1e150, 1e300])
def test_iobj_is_the_same_at_every_scale_of_the_heights(wood, factor):
    c, cp, b = wood
    got = indices.score(c * factor, cp * factor, b)
    ip, ia, iobj = oracle_indices(c * factor, cp * factor, b)
    assert _close(float(got.Ip), ip) and _close(float(got.Ia), ia) and _close(float(got.Iobj), iobj)
    assert _close(float(got.Iobj), float(indices.score(c, cp, b).Iobj))


@pytest.mark.parametrize("b_of", [lambda b: b * 1e200, lambda b: np.full_like(b, 5e-324),
                                  lambda b: np.full_like(b, 1e-310), lambda b: b * 1e-300])
def test_iobj_is_right_for_thresholds_anywhere_in_float64(wood, b_of):
    c, cp, b = wood
    bb = b_of(b)
    got = indices.score(c, cp, bb)
    ip, ia, iobj = oracle_indices(c, cp, bb)
    assert _close(float(got.Ip), ip) and _close(float(got.Ia), ia) and _close(float(got.Iobj), iobj)


def test_weighted_sums_keep_their_bits_where_nothing_overflows(wood, rng):
    """Stream headers carry P and A: the scaled computation must give the old bits exactly."""
    c, _, b = wood
    w2, w1 = 1.0 / b * (1.0 / b), 1.0 / b
    for cc in (c, c * 1e-30, c * 1e40, rng.normal(0, 1, c.size)):
        P, A = indices.weighted_sums(cc, b)
        assert float(P) == math.fsum((cc * cc * w2).tolist())
        assert float(A) == math.fsum((np.abs(cc) * w1).tolist())


@pytest.mark.parametrize("factor,where", [(1e-300, "below"), (1e160, "beyond")])
def test_a_header_sum_outside_float64_is_refused_with_one_line(wood, factor, where):
    c, _, b = wood
    with pytest.raises(QualityError, match=f"{where} float64's range") as e:
        indices.weighted_sums(c * factor, b)
    assert "\n" not in str(e.value) and "--y-unit" in str(e.value)


def test_encode_of_heights_times_1e_minus_300_exits_2_with_one_line(tmp_path, capsys):
    prof = synth.wood(seed=1)
    path = tmp_path / "tiny.txt"
    np.savetxt(path, prof.heights_um * 1e-300, fmt="%.17g")
    rc = cli.main(["encode", str(path), "--spacing", "0.5", "--method", "quant", "--levels", "6",
                   "-o", str(tmp_path / "t.vtx")])
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    # the error is one line; the only other line is the implausible-heights warning (--y-unit)
    errors = [ln for ln in lines if "warning" not in ln]
    assert rc == 2 and len(errors) == 1 and "float64" in errors[0], lines
    assert all("--y-unit" in ln for ln in lines if ln not in errors), lines
    assert not (tmp_path / "t.vtx").exists()


@pytest.mark.parametrize("factor", [1e-300, 1e150, 1e300])
def test_guard_snr_does_not_switch_itself_off_at_extreme_scales(wood, factor):
    c, cp, b = wood
    want = oracle_snr_db(c, cp, b)
    assert abs(guard.weighted_snr_db(c, cp, b) - want) < 1e-9
    cs, cps = c * factor, cp * factor
    assert abs(guard.weighted_snr_db(cs, cps, b) - oracle_snr_db(cs, cps, b)) < 1e-9
    assert abs(guard.weighted_snr_db(c, cp, b * factor) - oracle_snr_db(c, cp, b * factor)) < 1e-9
    assert abs(guard.weighted_snr_db(c * factor, cp * factor, b) - want) < 1e-6  # not 200 dB
    f = np.arange(1, c.size + 1) * 2.5
    v1, v2 = guard.check(c, cp, b, f), guard.check(c * factor, cp * factor, b, f)
    assert (v2.passed, round(v2.wsnr_db, 6), round(v2.ssnr_db, 6)) == (
        v1.passed, round(v1.wsnr_db, 6), round(v1.ssnr_db, 6))


def test_iobj_cli_scores_a_stream_encode_accepted_at_heights_times_1e150(tmp_path, capsys):
    prof = synth.wood(seed=1)
    y = prof.heights_um * 1e150
    ref = tmp_path / "big.txt"
    np.savetxt(ref, y, fmt="%.17g")
    out = tmp_path / "big.vtx"
    assert cli.main(["encode", str(ref), "--spacing", "0.5", "--method", "quant", "--levels", "6",
                     "-o", str(out)]) == 0
    capsys.readouterr()
    assert cli.main(["iobj", str(ref), str(out), "--spacing", "0.5", "--json"]) == 0
    got = json.loads(capsys.readouterr().out)
    s = vtx.decode(out.read_bytes())
    y_read = np.loadtxt(ref)
    c = transform.analyze(y_read, s.n_keep)
    _, _, iobj = oracle_indices(c, s.coefficients, CURVE(s.frequencies_hz))
    assert _close(got["Iobj"], iobj)
    assert all(v is None or math.isfinite(v) for v in got.values() if isinstance(v, float))


# ---------------------------------------------------------------- DCT round-off

@pytest.mark.parametrize("n", [19999, 20001, 30011])
def test_constant_profiles_have_no_signal(n):
    """The exact C_k (k >= 1) of a constant profile are 0 (sum_n cos(pi k (2n+1) / 2N) = 0):
    the FFT's round-off (1e-16 of the height) must not be taken for signal."""
    for h in (1.5, -7.3e-300, 2e150):
        assert not np.any(transform.analyze(np.full(n, h), n // 125))


@pytest.mark.parametrize("n", [19999, 30011])
def test_cut_of_a_constant_profile_scores_zero_and_rate_control_spends_a_header(tmp_path, capsys, n):
    path = tmp_path / "const.txt"
    path.write_text("1.5\n" * n)
    out = tmp_path / "c.vtx"
    args = [str(path), "--spacing", "0.5", "--length-mm", "100", "-o", str(out)]
    assert cli.main(["encode", *args, "--format", "v1", "--method", "cut", "--b0-db", "0", "--json"]) == 0
    # oracle: P = A = 0 and P' = A' = 0 (nothing to keep), and the relative error of two zeros is 0
    assert json.loads(capsys.readouterr().out)["Iobj"] == 0.0
    assert cli.main(["encode", *args, "--target-iobj", "0.05", "--json"]) == 0
    got = json.loads(capsys.readouterr().out)
    assert got["Iobj"] == 0.0 and got["bytes"] <= 16  # a header, no payload (134-193 before)


def test_the_roundoff_tolerance_keeps_a_tiny_real_component():
    """1e-6 µm of texture on a 1000 µm offset (1e-9 relative) is signal, far above 2^-43."""
    n = 4001
    k = np.arange(n)
    y = 1000.0 + 1e-6 * np.cos(np.pi * 7 * (2 * k + 1) / (2 * n))
    c = transform.analyze(y, 20)
    assert abs(c[6] - 1e-6) < 1e-9  # the direct sum gives 1e-6 exactly in exact arithmetic
    assert np.count_nonzero(c) >= 1


# ---------------------------------------------------------------- fit

def _stimuli(ip, ia, scores):
    return [fit.Stimulus("t", "m", str(i), float(s), float(p), float(a))
            for i, (p, a, s) in enumerate(zip(ip, ia, scores, strict=True))]


def oracle_fit(ip, ia, y):
    """The no-intercept least-squares (a, b) from the 2x2 normal equations, in exact rationals."""
    X = [(Fraction(float(p)), Fraction(float(q))) for p, q in zip(ip, ia, strict=True)]
    Y = [Fraction(float(v)) for v in y]
    s11 = sum(p * p for p, _ in X)
    s12 = sum(p * q for p, q in X)
    s22 = sum(q * q for _, q in X)
    t1 = sum(p * v for (p, _), v in zip(X, Y, strict=True))
    t2 = sum(q * v for (_, q), v in zip(X, Y, strict=True))
    det = s11 * s22 - s12 * s12
    return float((s22 * t1 - s12 * t2) / det), float((s11 * t2 - s12 * t1) / det)


@pytest.fixture
def well_posed(rng):
    ip = rng.uniform(0.05, 1.5, 12)
    ia = rng.uniform(0.05, 1.5, 12)
    return ip, ia, np.clip(0.6 * ip + 0.45 * ia + rng.normal(0, 0.1, 12), 0, 3)


def test_fit_matches_the_exact_normal_equations(well_posed):
    ip, ia, y = well_posed
    res = fit.fit(_stimuli(ip, ia, y), n_boot=0)
    a, b = oracle_fit(ip, ia, y)
    assert _close(res.a, a, 1e-10) and _close(res.b, b, 1e-10)
    assert all("collinear" not in w for w in res.warnings)


@pytest.mark.parametrize("scale", [1e-13, 1e200])
def test_fit_of_ip_of_any_magnitude_is_like_order_one(well_posed, scale):
    ip, ia, y = well_posed
    res = fit.fit(_stimuli(ip * scale, ia, y), n_boot=200)
    a, b = oracle_fit(ip * scale, ia, y)
    one = fit.fit(_stimuli(ip, ia, y), n_boot=0)
    assert _close(res.a, a, 1e-10) and _close(res.b, b, 1e-10)
    assert _close(res.a * scale, one.a, 1e-10) and _close(res.se_a * scale, one.se_a, 1e-8)
    assert _close(res.metrics["Ip"]["r2_pearson"], one.metrics["Ip"]["r2_pearson"], 1e-10)


def test_nearly_collinear_indices_fit_with_a_warning_not_a_traceback(rng):
    ip = rng.uniform(0.05, 1.5, 12)
    ia = 2 * ip + 1e-9 * rng.normal(size=12)
    y = np.clip(1.2 * ip + rng.normal(0, 0.1, 12), 0, 3)
    res = fit.fit(_stimuli(ip, ia, y), n_boot=200)
    assert any("nearly collinear" in w for w in res.warnings)
    a, b = oracle_fit(ip, ia, y)  # condition ~1e9: float64 keeps ~6 digits
    assert _close(res.a, a, 1e-4) and _close(res.b, b, 1e-4)
    assert res.se_a is None or (math.isfinite(res.se_a) and res.se_a > 0)


def test_negative_index_refused_and_repeats_warned(well_posed):
    ip, ia, y = well_posed
    bad = ip.copy()
    bad[3] = -0.1
    with pytest.raises(FitError, match="negative"):
        fit.fit(_stimuli(bad, ia, y))
    rep = fit.fit(_stimuli(np.repeat(ip[:2], 6), np.repeat(ia[:2], 6), np.repeat(y[:2], 6)), n_boot=0)
    assert any("2 distinct" in w for w in rep.warnings) and rep.se_a is None  # was 1.6e-15
    with pytest.raises(FitError, match="collinear"):
        fit.fit(_stimuli(ip, 3 * ip, y))


def test_fit_cli_nearly_collinear_exits_0_with_warnings(tmp_path, rng, capsys):
    ip = rng.uniform(0.05, 1.5, 12)
    ia = 2 * ip + 1e-9 * rng.normal(size=12)
    y = np.clip(1.2 * ip + rng.normal(0, 0.1, 12), 0, 3)
    p = tmp_path / "s.csv"
    rows = zip(ip, ia, y, strict=True)
    p.write_text("texture,method,level,score,Ip,Ia\n" + "".join(
        f"t,quant,{i},{float(s)!r},{float(a)!r},{float(b)!r}\n" for i, (a, b, s) in enumerate(rows)))
    assert cli.main(["fit", str(p), "--bootstrap", "100"]) == 0
    assert "nearly collinear" in capsys.readouterr().err
    p.write_text("texture,method,level,score,Ip,Ia\nt,quant,1,1.0,-0.5,0.2\nt,cut,2,2.0,0.4,0.9\n")
    assert cli.main(["fit", str(p)]) == 2
    err = capsys.readouterr().err
    assert "negative" in err and len(err.strip().splitlines()) == 1


def test_v2_stream_of_a_constant_profile_decodes_to_silence():
    n = 20001
    geom = transform.Geometry(n, n * 0.5e-3)
    data = stream2.encode_profile(np.full(n, 3.25), geom, CURVE, method="quant", levels=8)
    assert not np.any(vtx.decode(data).coefficients)
