"""A calibration file (thresholds + a, b + provenance): every command's --calibration and
--thresholds read it, the daemon's quality log records which calibration scored each row; the
thresholds CSV with intervals reads as-is, and a bad one is a one-line message."""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from hostd.cli import main
from hostd.errors import ConfigError, ThresholdError
from hostd.perception import calibration, thresholds
from hostd.service import qualitylog
from hostd.service.client import ClientError, request
from hostd.service.config import load
from tests.test_daemon import write_cfg


def _cal(tmp_path, a=0.9, b=0.2):
    curve = thresholds.ThresholdCurve(np.array([40.0, 100.0, 250.0, 400.0]), np.array([2.0, 0.5, 0.2, 0.3]))
    cal = calibration.Calibration(curve, a, b, "lab-a", {"thresholds": "test", "weights": "test"})
    p = tmp_path / "lab-a.toml"
    calibration.write(p, cal)
    return p, cal


def test_calibration_round_trips_and_its_id_is_its_numbers(tmp_path):
    p, cal = _cal(tmp_path)
    back = calibration.load(p)
    assert back.cal_id == cal.cal_id and back.label == f"lab-a@{cal.cal_id}" and back.a == 0.9
    assert np.array_equal(back.curve.threshold_um, cal.curve.threshold_um)
    other = calibration.Calibration(cal.curve, 0.9, 0.2000001, "lab-a")
    assert other.cal_id != cal.cal_id
    p.write_text(p.read_text().replace('format = "hostd-calibration-1"', 'format = "x"'))
    with pytest.raises(ThresholdError, match="not a hostd calibration"):
        calibration.load(p)


def test_every_command_takes_calibration(tmp_path, capsys):
    p, cal = _cal(tmp_path)
    csv = tmp_path / "curve.csv"
    csv.write_text("frequency_hz,threshold_um\n40,2\n100,0.5\n250,0.2\n400,0.3\n")
    s = tmp_path / "w.vtx"  # encoded for the lab's curve: a stream is scored with its own curve
    assert main(["encode", "synthetic:wood:2", "-o", str(s), "--method", "cut", "--b0-db", "0",
                 "--calibration", str(p)]) == 0
    capsys.readouterr()
    assert main(["inspect", str(s), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["threshold_id"] == cal.curve.curve_id
    assert main(["iobj", str(s), "--json", "--calibration", str(p)]) == 0
    with_cal = json.loads(capsys.readouterr().out)
    assert main(["iobj", str(s), "--json", "--thresholds", str(csv), "--a", "0.9", "--b", "0.2"]) == 0
    by_hand = json.loads(capsys.readouterr().out)
    assert with_cal["Iobj"] == by_hand["Iobj"] and with_cal["Ip"] == by_hand["Ip"]
    assert main(["iobj", str(s), "--json", "--thresholds", str(csv)]) == 0  # the paper's (a, b)
    assert json.loads(capsys.readouterr().out)["Iobj"] != with_cal["Iobj"]
    # --thresholds reads the calibration file as-is too
    assert main(["iobj", str(s), "--json", "--thresholds", str(p), "--a", "0.9", "--b", "0.2"]) == 0
    assert json.loads(capsys.readouterr().out)["Iobj"] == with_cal["Iobj"]
    with pytest.raises(SystemExit) as e:  # a usage error: argparse's exit 2, one line
        main(["iobj", str(s), "--calibration", str(tmp_path / "none.toml")])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip()
    assert "none.toml" in err and "\n" not in err


@pytest.mark.parametrize("text, needle", [
    ("frequency_hz,threshold_um,ci_low_um,ci_high_um\n100,,0.1,0.3\n", "missing threshold_um at 100 Hz"),
    ("frequency_hz,threshold_um\n100,0\n", "must be > 0"),
    ("frequency_hz,threshold_um\n100,-0.5\n", "must be > 0"),
    ("frequency_hz,threshold_um\n100,nan\n", "must be > 0"),
    ("frequency_hz,threshold_um,ci_low_um\n100,0.5\n", "expected 3 columns"),
])
def test_a_bad_thresholds_csv_is_one_line(tmp_path, capsys, text, needle):
    f = tmp_path / "t.csv"
    f.write_text(text)
    with pytest.raises(ThresholdError, match=needle):
        thresholds.load_csv(f)
    assert main(["encode", "synthetic:wood:2", "-o", str(tmp_path / "x.vtx"), "--thresholds", str(f)]) == 2
    err = capsys.readouterr().err.strip()
    assert needle.split()[0] in err and "t.csv:2" in err and "\n" not in err


def test_thresholds_csv_with_intervals_reads_by_column_name(tmp_path):
    f = tmp_path / "t.csv"
    f.write_text("# measured\nfrequency_hz,threshold_um,ci_low_um,ci_high_um,trials,status\n"
                 "40,3.0,2.5,3.6,30,ok\n250,0.1,0.08,0.12,30,ok\n")
    c = thresholds.load_csv(f)
    assert list(c.freq_hz) == [40.0, 250.0] and list(c.threshold_um) == [3.0, 0.1]


def test_config_calibration_key(tmp_path):
    p = _cal(tmp_path)[0]
    c = tmp_path / "c.toml"
    c.write_text(f'[quality]\ncalibration = "{p.name}"\n')
    q = load(c).quality
    assert (q.a, q.b) == (0.9, 0.2) and q.calibration == str(p)
    c.write_text(f'[quality]\ncalibration = "{p.name}"\na = 0.7\n')
    with pytest.raises(ConfigError, match=r"remove quality\.a"):
        load(c)
    c.write_text('[quality]\ncalibration = "nothere.toml"\n')
    with pytest.raises(ConfigError, match=r"quality\.calibration"):
        load(c)


def test_old_log_gains_the_column_and_old_readers_see_null(tmp_path):
    import sqlite3

    db = tmp_path / "q.sqlite"
    con = sqlite3.connect(db)
    con.executescript(qualitylog.SCHEMA.replace("    calibration TEXT,", ""))
    con.execute("INSERT INTO streams (sha256, name, received_at, scored_at, bytes, method, n, n_keep, "
                "length_mm, speed_mm_s, curve_id, ratio_coeffs, ratio_profile, ip, ia, iobj, a, b) "
                "VALUES ('x', 'old', 1, 1, 9, 'quant', 8, 4, 1, 50, '00', 1, 1, 0.1, 0.1, 0.1, 1, 1)")
    con.commit()
    con.close()
    ro = qualitylog.connect_readonly(db)
    assert qualitylog.query(ro)[0]["calibration"] is None  # read-only: not migrated, read as NULL
    ro.close()
    qualitylog.connect(db).close()  # the daemon's connection adds the column
    assert "calibration" in qualitylog._stream_columns(qualitylog.connect_readonly(db))


def test_daemon_records_the_calibration_of_each_row(tmp_path):
    p, cal = _cal(tmp_path)
    cfg = write_cfg(tmp_path, f'calibration = "{p.name}"\n')
    proc = subprocess.Popen([sys.executable, "-m", "hostd", "run", "--config", str(cfg)],
                            stderr=open(tmp_path / "log.txt", "w"), cwd=tmp_path)
    sock = str(tmp_path / "hostd.sock")
    try:
        s = tmp_path / "calibrated.vtx"
        assert main(["encode", "synthetic:wood:3", "-o", str(s), "--method", "quant", "--levels", "8",
                     "--calibration", str(p)]) == 0
        rows = []
        t_end = time.monotonic() + 90  # the daemon's start imports numpy/scipy: slow under load
        while time.monotonic() < t_end and not rows:
            try:
                if not (tmp_path / "spool" / "calibrated.vtx").exists() and not request(
                        sock, {"cmd": "list"}, timeout_s=2)["textures"]:
                    shutil.copy(s, tmp_path / "spool" / "calibrated.vtx")
                rows = request(sock, {"cmd": "quality"}, timeout_s=2)["rows"]
            except ClientError:
                pass
            time.sleep(0.1)
        assert rows, (tmp_path / "log.txt").read_text()
        assert rows[0]["calibration"] == cal.label and (rows[0]["a"], rows[0]["b"]) == (0.9, 0.2)
        from hostd.codec import stream as vtx
        from hostd.quality import score_stream

        sc = score_stream(vtx.decode(s.read_bytes()), curve=cal.curve, a=0.9, b=0.2)
        assert rows[0]["iobj"] == pytest.approx(float(sc.Iobj), rel=1e-12)
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(15)
