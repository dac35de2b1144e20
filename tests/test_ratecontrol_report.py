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
        assert np.isfinite(float(r["Iobj"])) and int(r["bytes"]) > vtx.HEADER_SIZE
    png = (tmp_path / "rate_quality.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    assert "| series |" in (tmp_path / "rate_quality.md").read_text()
