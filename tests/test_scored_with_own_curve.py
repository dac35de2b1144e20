"""Every accepted stream gets its quality row under a calibration: a stream made with another
curve than the lab's (the default one) is scored with its own curve and the weights that go with
it, and the row says which curve and which weights scored it (curve_id, a, b, calibration NULL);
a stream made with the lab's curve gets the lab's weights and its label. `hostd iobj
--calibration` follows the same rule and says which one it applied."""

from __future__ import annotations

import json
import threading

import pytest

from hostd.cli import main
from hostd.codec import stream as vtx
from hostd.perception.indices import DEFAULT_AB
from hostd.quality import score_stream
from hostd.service import qualitylog
from tests.daemon_helpers import wait_for
from tests.test_calibration import _cal
from tests.test_daemon_own_edges import _close, _daemon


def _streams(tmp_path, lab) -> tuple[bytes, bytes]:
    """The same texture encoded with the default curve, and with the lab's."""
    plain, labbed = tmp_path / "plain.vtx", tmp_path / "lab.vtx"
    assert main(["encode", "synthetic:wood:3", "-o", str(plain), "--method", "quant", "--levels", "8"]) == 0
    assert main(["encode", "synthetic:wood:3", "-o", str(labbed), "--method", "quant", "--levels", "8",
                 "--calibration", str(lab)]) == 0
    return plain.read_bytes(), labbed.read_bytes()


def test_the_daemon_scores_a_stream_of_another_curve_with_its_own_and_says_so(tmp_path, caplog):
    lab, cal = _cal(tmp_path)
    plain, labbed = _streams(tmp_path, lab)
    d = _daemon(tmp_path, quality=f'calibration = "{lab}"\n')
    worker = threading.Thread(target=d.quality_worker, daemon=True)
    worker.start()
    try:
        d.accept("plain", plain, "test")
        d.accept("lab", labbed, "test")
        wait_for(lambda: len(_rows(tmp_path)) == 2, 30, "both rows")
    finally:
        _close(d)
        worker.join(10)
    rows = _rows(tmp_path)
    own = vtx.decode(plain)
    assert rows["plain"]["curve_id"] == own.threshold_id.hex() != cal.curve.curve_id
    assert (rows["plain"]["a"], rows["plain"]["b"], rows["plain"]["calibration"]) == (*DEFAULT_AB, None)
    want = score_stream(own, a=DEFAULT_AB[0], b=DEFAULT_AB[1])
    assert rows["plain"]["iobj"] == pytest.approx(float(want.Iobj), rel=1e-12)
    assert rows["lab"]["curve_id"] == cal.curve.curve_id
    assert (rows["lab"]["a"], rows["lab"]["b"], rows["lab"]["calibration"]) == (0.9, 0.2, cal.label)
    said = [r.getMessage() for r in caplog.records if r.getMessage().startswith("quality plain: the stream")]
    assert len(said) == 1 and cal.label in said[0] and "its own curve" in said[0], said


def _rows(tmp_path) -> dict:
    con = qualitylog.connect_readonly(tmp_path / "q.sqlite")
    try:
        return {r["name"]: r for r in qualitylog.query(con)}
    finally:
        con.close()


def test_iobj_with_a_calibration_scores_a_stream_of_another_curve_with_its_own_and_says_which(
        tmp_path, capsys):
    lab, cal = _cal(tmp_path)
    plain, _ = _streams(tmp_path, lab)
    capsys.readouterr()
    assert main(["iobj", str(tmp_path / "plain.vtx"), "--json", "--calibration", str(lab)]) == 0
    cap = capsys.readouterr()
    out = json.loads(cap.out)
    own = vtx.decode(plain)
    assert out["curve_id"] == own.threshold_id.hex() and out["calibration"] is None
    assert (out["a"], out["b"]) == DEFAULT_AB and out["scored_with"] == "the stream's own curve"
    assert out["Iobj"] == float(score_stream(own).Iobj) and "its own curve" in out["scoring_note"]
    assert "its own curve" in cap.err and cap.err.count("\n") == 1
    # the lab's own stream: the lab's curve and weights, and its label
    assert main(["iobj", str(tmp_path / "lab.vtx"), "--json", "--calibration", str(lab)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert (out["a"], out["b"], out["calibration"]) == (0.9, 0.2, cal.label) and out["scoring_note"] is None
    assert out["scored_with"] == f"calibration {cal.label}" and out["curve_id"] == cal.curve.curve_id
    # text: the same fields
    assert main(["iobj", str(tmp_path / "plain.vtx"), "--calibration", str(lab), "--a", "0.7"]) == 0
    text = capsys.readouterr().out
    assert "scored_with: the stream's own curve" in text and "a: 0.7" in text
