"""Rate control and the rate-quality report."""

import csv

import numpy as np
import pytest

from hostd.codec import ratecontrol, transform
from hostd.codec import stream as vtx
from hostd.errors import CodecError
from hostd.perception import thresholds
from hostd.quality import score_stream
from hostd.report import rate_quality
from hostd.texture import synth
from hostd.texture.load import LoadOptions, load_profile
from tests.conftest import real_profile_path

CURVE = thresholds.default_curve()


@pytest.fixture(scope="module")
def wood():
    p = synth.wood(seed=4)
    return p.heights_um, transform.Geometry(p.n, p.length_mm)


@pytest.fixture(scope="module")
def cands(wood):
    return ratecontrol.candidates(*wood, CURVE)


@pytest.mark.parametrize("target", [0.0, 0.05, 0.3, 1.0])
def test_rate_control_picks_the_smallest_stream_within_target(wood, cands, target):
    choice = ratecontrol.smallest_within(*wood, CURVE, target)
    assert choice.Iobj <= target
    assert float(score_stream(vtx.decode(choice.data), reference_um=wood[0]).Iobj) == \
        pytest.approx(choice.Iobj, abs=1e-15)
    assert all(c.nbytes >= choice.nbytes for c in cands if c.Iobj <= target)
    assert {c.method for c in cands} == {"quant", "cut"}


def test_rate_control_refuses_a_negative_target(wood):
    with pytest.raises(CodecError):
        ratecontrol.smallest_within(*wood, CURVE, -0.1)


def test_looser_targets_never_cost_more_bytes(wood):
    sizes = [ratecontrol.smallest_within(*wood, CURVE, t).nbytes for t in (0.02, 0.1, 0.5, 2.0)]
    assert sizes == sorted(sizes, reverse=True)


@pytest.mark.parametrize("source", ["wood", "sandpaper", "real"])
def test_rate_quality_report_writes_table_and_plot(tmp_path, source):
    if source == "real":
        prof = load_profile(real_profile_path("dektak-1.csv"), LoadOptions())
    else:
        prof = synth.make(source, seed=2)
    geom = transform.Geometry(prof.n, prof.length_mm)
    res = rate_quality(prof.heights_um, geom, CURVE, tmp_path, source, progress=False)
    rows = list(csv.DictReader((tmp_path / "rate_quality.csv").open()))
    assert len(rows) == len(res["rows"])
    levels = {int(r["levels"]) for r in rows if r["method"] == "quant"}
    b0s = {float(r["b0_db"]) for r in rows if r["method"] == "cut"}
    assert {14, 12, 10, 8, 6, 5, 4} <= levels and {-12, -8, -4, 0, 4, 8, 12} <= b0s
    for r in rows:
        assert np.isfinite(float(r["Iobj"])) and np.isfinite(float(r["wsnr_db"]))
        assert np.isfinite(float(r["ssnr_db"]))
        if r["version"] == "1":
            assert int(r["bytes"]) > vtx.HEADER_SIZE
    v2 = [r for r in rows if r["series"] == "v2 shaped"]
    assert len(v2) >= 20 and {float(r["g_db"]) for r in v2} >= {-12.0, 0.0, 6.0}
    png = (tmp_path / "rate_quality.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    assert "| series |" in (tmp_path / "rate_quality.md").read_text()


# ---------------------------------------------------------------- bisection with the waveform guard


def _independent_spqi(ref_heights, s):
    """SPQI of the decoded stream's played signal, by vibromaf when installed (the definition's
    reference implementation), else by hostd's own."""
    from hostd.perception import peer

    c = transform.analyze(ref_heights, s.n_keep)
    ref = peer.played_signal(c, s.n, s.length_mm, s.speed_mm_s)
    dist = peer.played_signal(s.coefficients, s.n, s.length_mm, s.speed_mm_s)
    try:
        from vibromaf.metrics.spqi import spqi
    except ImportError:
        from hostd.perception.spqi import spqi
    return float(spqi(dist, ref))


@pytest.mark.parametrize("fmt,method", [("v2", "shaped"), ("v2", "quant"), ("v1", "quant"),
                                        ("v2", "cut")])
def test_search_returns_a_stream_meeting_target_and_spqi_measured(wood, fmt, method):
    r = ratecontrol.search(*wood, CURVE, 0.05, method=method, fmt=fmt)  # default: SPQI >= 0.9
    s = vtx.decode(r.best.data)
    assert s.method == method and s.version == int(fmt[1])
    sc = score_stream(s)  # as a receiver scores it: from the header
    assert float(sc.Iobj) <= 0.05
    spqi = _independent_spqi(wood[0], s)
    assert spqi >= 0.9 and r.best.spqi == pytest.approx(spqi, abs=1e-12)
    assert r.waveform_verified is True
    assert r.encodes <= 25  # a bisection, not every candidate


def test_search_only_searches_the_given_method_and_finds_the_exhaustive_optimum(wood):
    """Neither quality nor bytes are strictly monotone in L (here L = 136 passes, 137..150 do
    not): the bisection returns a passing boundary L within a few percent of the exhaustive
    optimum, in a fraction of the encodes."""
    from hostd.perception import guard

    r = ratecontrol.search(*wood, CURVE, 0.05, method="quant", fmt="v1", spqi_min=None,
                           guard_db=25.0, ssnr_db=27.0)  # the proxy floors as explicit criteria
    c = transform.analyze(wood[0], wood[1].n_keep)
    f = wood[1].frequencies_hz()
    b = CURVE(f)
    passing = {}
    for L in range(2, ratecontrol.MAX_L + 1):
        s = vtx.decode(vtx.encode_coefficients(c, wood[1], CURVE, method="quant", levels=L))
        if float(score_stream(s).Iobj) <= 0.05 and guard.check(c, s.coefficients, b, f).passed:
            passing[L] = s.nbytes
    L = r.best.setting["levels"]
    assert L in passing and L - 1 not in passing
    assert r.best.nbytes <= 1.05 * min(passing.values())
    assert r.encodes <= 20


def test_the_waveform_criterion_rejects_what_iobj_alone_accepts(wood):
    loose = ratecontrol.search(*wood, CURVE, 0.05, spqi_min=None)
    strict = ratecontrol.search(*wood, CURVE, 0.05)
    assert loose.waveform_verified is None and strict.waveform_verified is True
    assert _independent_spqi(wood[0], vtx.decode(loose.best.data)) < 0.9
    assert _independent_spqi(wood[0], vtx.decode(strict.best.data)) >= 0.9
    assert loose.best.nbytes < strict.best.nbytes and strict.size_set_by == "waveform"
    # explicit proxy floors are still honoured on top
    floors = ratecontrol.search(*wood, CURVE, 0.05, guard_db=25.0, ssnr_db=27.0)
    assert floors.best.wsnr_db >= 25.0 and floors.best.ssnr_db >= 27.0 and floors.best.spqi >= 0.9


def test_degenerate_and_unreachable_targets_are_reported(wood):
    r = ratecontrol.search(*wood, CURVE, 5.0)
    assert r.notes and "degenerate" in r.notes[0]
    with pytest.raises(CodecError, match="no cut stream reaches"):
        ratecontrol.search(*wood, CURVE, 0.0, method="cut")
    with pytest.raises(CodecError, match="not available"):
        ratecontrol.search(*wood, CURVE, 0.05, method="shaped", fmt="v1")
