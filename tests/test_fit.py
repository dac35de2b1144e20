"""Fitting (a, b) to subjective scores (eq. 13-15)."""

import numpy as np
import pytest

from hostd.errors import FitError
from hostd.perception import fit


def _stimuli(ip, ia, scores):
    return [fit.Stimulus("t", "m", str(i), float(s), float(p), float(a))
            for i, (p, a, s) in enumerate(zip(ip, ia, scores, strict=True))]


def test_fit_recovers_known_coefficients_like_lstsq(rng):
    ip = rng.uniform(0, 1.5, 40)
    ia = rng.uniform(0, 1.5, 40)
    scores = 0.7 * ip + 0.4 * ia + rng.normal(0, 0.01, 40)
    res = fit.fit(_stimuli(ip, ia, scores))
    ref = np.linalg.lstsq(np.column_stack([ip, ia]), scores, rcond=None)[0]
    assert res.a == pytest.approx(ref[0], rel=1e-10) and res.b == pytest.approx(ref[1], rel=1e-10)
    assert abs(res.a - 0.7) < 0.02 and abs(res.b - 0.4) < 0.02
    assert res.metrics["Iobj"]["r2_fit"] > 0.99
    assert res.metrics["Iobj"]["r2_pearson"] > 0.99


def test_nonnegative_fit_clamps_a_negative_weight(rng):
    ip = rng.uniform(0, 1, 30)
    ia = rng.uniform(0, 1, 30)
    scores = -0.3 * ip + 0.9 * ia
    assert fit.fit(_stimuli(ip, ia, scores)).a < 0
    res = fit.fit(_stimuli(ip, ia, scores), nonnegative=True)
    assert res.a >= 0 and res.b >= 0


def test_saturated_stimuli_are_excluded_and_flagged(rng):
    ip = rng.uniform(0, 1, 10)
    ia = rng.uniform(0, 1, 10)
    scores = np.minimum(ip + ia, 3.0)
    scores[3] = 3.0
    res = fit.fit(_stimuli(ip, ia, scores), scale_max=3.0, exclude_saturated=True)
    assert res.n_used == 9 and len(res.excluded) == 1 and "saturated" in res.excluded[0]["why"]
    assert fit.fit(_stimuli(ip, ia, scores), scale_max=3.0).n_used == 10


@pytest.mark.parametrize("ip,ia,scores,msg", [
    ([0.1], [0.2], [1.0], "at least 2"),
    ([0.1, 0.2, 0.3], [0.2, 0.1, 0.5], [1.0, 1.0, 1.0], "every score is equal"),
    ([0.1, 0.2, 0.3], [0.2, 0.4, 0.6], [1.0, 2.0, 2.5], "collinear"),
])
def test_degenerate_data_gives_a_clear_message(ip, ia, scores, msg):
    with pytest.raises(FitError, match=msg):
        fit.fit(_stimuli(ip, ia, scores))


def test_csv_reading_needs_the_documented_columns(tmp_path):
    p = tmp_path / "s.csv"
    p.write_text("texture,method,score\nw,quant,1\n")
    with pytest.raises(FitError, match="missing column"):
        fit.read_scores(p)
    p.write_text("texture,method,level,score,Ip,Ia\nw,quant,4,x,0.1,0.2\n")
    with pytest.raises(FitError, match="must be numbers"):
        fit.read_scores(p)
