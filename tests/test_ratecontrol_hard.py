"""Issue 23's numerically hard inputs of rate control, and the Python API's rate control and
scoring: each compared with an independent computation or asserting the one-line error."""

from __future__ import annotations

import decimal
import math
import re

import numpy as np
import pytest

from hostd import api
from hostd.cli import main
from hostd.codec import ratecontrol, transform
from hostd.codec import stream as vtx
from hostd.codec.stream import v2 as stream2
from hostd.errors import CodecError
from hostd.perception import thresholds
from hostd.quality import score_stream

CURVE = thresholds.default_curve()
N = 20000


def _flat_spectrum():
    n = np.arange(N)
    return np.cos(np.pi * np.outer(2 * n + 1, np.arange(1, 161)) / (2 * N)).sum(axis=1)


def _wood():
    from hostd.texture import synth

    return synth.make("wood", seed=3).heights_um


def _one_line_error(capsys, argv):
    code = main(argv)
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.startswith("hostd")]
    assert "Traceback" not in err
    return code, lines


def _vibromaf_or_own_spqi(data, y):
    from hostd.perception import peer

    s = vtx.decode(data)
    c = transform.analyze(y, s.n_keep)
    try:
        from vibromaf.metrics.spqi import spqi
    except ImportError:
        from hostd.perception.spqi import spqi
    return float(spqi(peer.played_signal(s.coefficients, s.n, s.length_mm, s.speed_mm_s),
                      peer.played_signal(c, s.n, s.length_mm, s.speed_mm_s)))


def test_peak_db_stays_finite_where_the_ratio_overflows():
    """Thresholds of 5e-324 µm: |C_k| / b_k is inf in float64 (the old OverflowError in
    _knobs); the dB value equals the one computed in decimal arithmetic."""
    c = np.array([3.0, -7.5, 0.0, 1e-3])
    b = np.full(4, 5e-324)
    ctx = decimal.Context(prec=30)
    lb = ctx.log10(decimal.Decimal(float(b[0])))  # the float's exact value
    want = max(float(20 * (ctx.log10(decimal.Decimal(abs(x))) - lb)) for x in c if x != 0)
    assert ratecontrol.peak_db(c, b) == pytest.approx(want, rel=1e-12)
    from hostd.codec import formats

    for fmt, f in formats.FORMATS.items():
        for m in f.methods:
            for knob in ratecontrol._knobs(fmt, m, c, b):  # no OverflowError; a finite range
                assert knob.lo <= knob.hi and knob.setting(knob.lo) and knob.setting(knob.hi)


def test_threshold_curve_of_5e_324_um_with_target_iobj_is_no_traceback(tmp_path, capsys):
    csv = tmp_path / "tiny.csv"
    csv.write_text("frequency_hz,threshold_um\n1,5e-324\n1000,5e-324\n")
    out = tmp_path / "a.vtx"
    code, lines = _one_line_error(capsys, ["encode", "synthetic:wood:1", "--thresholds", str(csv),
                                           "--target-iobj", "0.05", "-o", str(out)])
    if code == 2:
        assert len(lines) == 1 and "--thresholds" in lines[0]
    else:  # where the sums are computed scale-invariantly, a verified stream is fine too
        assert code == 0 and float(score_stream(vtx.decode(out.read_bytes())).Iobj) <= 0.05


def test_a_method_that_cannot_code_the_input_is_skipped_not_fatal():
    """All-equal C_k: linear quantization refuses ("coefficient range too narrow") or codes
    nothing useful, yet the shaped quantizer codes it: rate control returns that stream,
    Iobj and SPQI checked independently."""
    y = _flat_spectrum()
    geom = transform.Geometry(N, 10.0)
    r = ratecontrol.search(y, geom, CURVE, 0.05)
    assert r.best.method == "shaped" and r.waveform_verified
    assert float(score_stream(vtx.decode(r.best.data)).Iobj) <= 0.05
    assert _vibromaf_or_own_spqi(r.best.data, y) >= 0.9


def test_rate_control_goes_on_when_one_method_raises(monkeypatch):
    real = stream2.encode_coefficients

    def cut_raises(c, g, curve, **s):
        if s["method"] == "cut":
            raise CodecError("cut refuses this input")
        return real(c, g, curve, **s)

    monkeypatch.setattr(stream2, "encode_coefficients", cut_raises)
    y = _wood()
    r = ratecontrol.search(y, transform.Geometry(N, 10.0), CURVE, 0.05)
    assert r.best.method in ("shaped", "quant") and r.waveform_verified
    assert any("cut skipped" in n for n in r.notes)

    def all_raise(c, g, curve, **s):
        raise CodecError("refused")

    monkeypatch.setattr(stream2, "encode_coefficients", all_raise)
    with pytest.raises(CodecError, match="no method can code"):
        ratecontrol.search(y, transform.Geometry(N, 10.0), CURVE, 0.05)


def test_huge_heights_do_not_ask_for_a_g_nobody_gave(tmp_path, capsys):
    y = np.cumsum(np.random.default_rng(0).standard_normal(N)) * 1e150
    prof = tmp_path / "big.npy"
    np.save(prof, y)
    out = tmp_path / "big.vtx"
    code, lines = _one_line_error(capsys, ["encode", str(prof), "--spacing", "0.5", "--target-iobj",
                                           "0.05", "-o", str(out)])
    if code == 2:
        assert len(lines) == 1
        assert "--g-db" not in lines[0] and "--y-unit" in lines[0]
    else:
        assert code == 0 and float(score_stream(vtx.decode(out.read_bytes())).Iobj) <= 0.05


def test_a_tiny_speed_prints_a_readable_n_keep(capsys):
    code, lines = _one_line_error(capsys, ["encode", "synthetic:wood:1", "--ref-speed-mm-s", "1e-300",
                                           "--target-iobj", "0.05", "-o", "/dev/null"])
    assert code == 2 and len(lines) == 1
    assert not re.search(r"\d{13,}", lines[0]), lines[0]
    assert "8e+303" in lines[0] and "--ref-speed-mm-s" in lines[0]


# ---------------------------------------------------------------- the Python API


def test_api_errors_name_api_arguments_not_cli_flags():
    prof = api.load_profile("synthetic:wood:1")
    with pytest.raises(CodecError) as e:
        api.encode(prof, target_iobj=-1.0)
    assert "target_iobj=" in str(e.value) and "--" not in str(e.value)
    with pytest.raises(CodecError) as e:
        api.encode(prof, method="shaped")
    assert "g_db=" in str(e.value) and "--g-db" not in str(e.value)
    with pytest.raises(CodecError) as e:
        api.encode(prof, method="shaped", format="v1", g_db=0.0)
    assert "format=" in str(e.value) and "--format" not in str(e.value)
    with pytest.raises(CodecError) as e:
        api.encode(prof, method="cut", target_iobj=0.0)
    assert "target_iobj=" in str(e.value) and "--" not in str(e.value)


def test_api_score_documents_and_computes_the_mean_normalized_relative_error():
    doc = api.score.__doc__
    assert "Ip = |P - P'| / P" not in doc and "Ip = |P - P'| / ((P + P') / 2)" in doc
    prof = api.load_profile("synthetic:wood:1")
    enc = api.encode(prof, method="shaped", g_db=-6.0)
    q = api.score(enc, reference=prof)
    assert q["Ip"] == pytest.approx(abs(q["P"] - q["P_prime"]) / ((q["P"] + q["P_prime"]) / 2), rel=1e-12)
    assert q["Ia"] == pytest.approx(abs(q["A"] - q["A_prime"]) / ((q["A"] + q["A_prime"]) / 2), rel=1e-12)
    assert q["spqi"] == pytest.approx(_vibromaf_or_own_spqi(enc["stream"], prof.heights_um), abs=1e-12)
    assert q["spqi"] == enc["spqi"]
    for k in ("wsnr_db", "ssnr_db", "st_sim"):
        assert k in q
    header_only = api.score(enc["stream"])
    assert "spqi" not in header_only and header_only["wsnr_db"] is not None


def test_api_encode_with_rate_control_returns_the_clis_report():
    prof = api.load_profile("synthetic:sandpaper:2")
    enc = api.encode(prof, method="shaped", format="v2", target_iobj=0.05)
    assert enc["method"] == "shaped" and enc["bytes"] == len(enc["stream"])
    assert enc["Iobj"] <= 0.05 and enc["spqi"] >= 0.9 and enc["waveform_verified"] is True
    assert enc["size_set_by"] in ("Iobj", "waveform") and enc["spqi_min"] == 0.9
    loose = api.encode(prof, method="shaped", target_iobj=0.05, spqi_min=None)
    assert loose["waveform_verified"] is None and loose["bytes"] <= enc["bytes"]
    floors = api.encode(prof, target_iobj=0.05, guard_db=25.0, ssnr_db=27.0)
    assert floors["wsnr_db"] >= 25.0 and floors["ssnr_db"] >= 27.0 and floors["spqi"] >= 0.9
    assert math.isfinite(enc["search_cpu_s"])


def test_when_spqi_cannot_be_computed_rate_control_says_so(monkeypatch, tmp_path, capsys):
    """waveform_verified is false (never a silent promise) and the proxy floors decide."""
    import json

    from hostd.errors import QualityError
    from hostd.perception import guard, peer

    def unmeasurable(*a, **k):
        raise QualityError("the played signal is not finite")

    monkeypatch.setattr(peer, "played_spqi", unmeasurable)
    r = ratecontrol.search(_wood(), transform.Geometry(N, 10.0), CURVE, 0.05)
    assert r.waveform_verified is False and r.best.spqi is None
    assert r.best.wsnr_db >= guard.DEFAULT_GUARD_DB and r.best.ssnr_db >= guard.DEFAULT_SSNR_DB
    assert any("could not be computed" in n for n in r.notes)
    out = tmp_path / "w.vtx"
    assert main(["encode", "synthetic:wood:3", "--target-iobj", "0.05", "-o", str(out), "--json"]) == 0
    cap = capsys.readouterr()
    assert json.loads(cap.out)["waveform_verified"] is False
    assert "could not be computed" in cap.err


def test_the_guard_snrs_do_not_switch_off_at_extreme_scales():
    """Heights x1e-300 or thresholds of 1e200 µm: the squares underflowed, both sums were 0 and
    a 6-level quantization reported wSNR 200 dB. Now the SNRs equal the written-out definition
    at scale 1 (exactly for powers of two, to 1e-9 dB otherwise)."""
    from hostd.codec.methods import quantize
    from hostd.perception import guard

    rng = np.random.default_rng(7)
    f = np.arange(1, 161) * 2.5
    b = CURVE(f)
    c = rng.normal(size=160) * b * 10
    qz = quantize(c, 6)
    d = qz.q * qz.step_um
    w = guard.spqi_curve_weights(f)
    want_w = 10 * np.log10(np.sum((c / b) ** 2) / np.sum(((c - d) / b) ** 2))
    want_s = 10 * np.log10(np.sum(w * c**2) / np.sum(w * (c - d) ** 2))
    base = guard.check(c, d, b, f)
    assert base.wsnr_db == pytest.approx(want_w, abs=1e-9) and base.ssnr_db == pytest.approx(want_s, abs=1e-9)
    assert base.wsnr_db < 30
    for hs, bs in ((2.0**-1000, 1.0), (1e-300, 1.0), (1.0, 1e200), (1e150, 1.0), (1.0, 1e-300)):
        v = guard.check(c * hs, d * hs, b * bs, f)
        assert v.wsnr_db == pytest.approx(want_w, abs=1e-9) and v.ssnr_db == pytest.approx(want_s, abs=1e-9)
        assert v.passed == base.passed
        assert guard.weighted_snr_db(c * hs, d * hs, b * bs) == pytest.approx(want_w, abs=1e-9)
