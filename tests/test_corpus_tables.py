"""hostd corpus: tables that cannot mislead. A curve is one codec version + one set of loader
and scoring options: a store holding several is refused by `report` (or --latest picks the latest),
two runs compare in one command; identical bytes under two names each get rows; a file fixed
since shows its current rows only; --calibration changes the rows."""

from __future__ import annotations

import json
import sqlite3

import numpy as np
import pytest

from hostd.cli import main
from hostd.corpus import codecs

FIX = "tests.corpus_codec_fixture"
BASE = ["--length-mm", "2", "--no-spqi", "--workers", "1", "--no-progress"]
SMALL_V2 = ["--codec", "hostd-v2", "--methods", "shaped", "--g-db=-12,-6,0,6,12"]


@pytest.fixture
def fresh_codecs():
    codecs.resolve.cache_clear()
    yield
    codecs.resolve.cache_clear()


def _err_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


def test_two_codec_versions_in_one_store_are_never_averaged_and_compare_in_one_command(
        tmp_path, capsys, monkeypatch, fresh_codecs):
    """v2 of a codec pays 1.25x the bytes of v1 for the same heights: the report over the store
    holding both refuses (naming the codec versions and --latest); --latest reports v2's;
    `compare STORE@1 STORE@2` gives +25 %; a --length-mm 5 run added is named as loader options."""
    from tests.corpus_codec_fixture import UniformZlib

    db = tmp_path / "s.sqlite"
    tex = ["synthetic:wood:1", "synthetic:sandpaper:1"]
    assert main(["corpus", "run", *tex, *SMALL_V2, "--codec", f"{FIX}:uniform", *BASE, "-o", str(db)]) == 0
    monkeypatch.setattr(UniformZlib, "version", "2")
    monkeypatch.setattr(UniformZlib, "pad", 0.25)
    codecs.resolve.cache_clear()
    assert main(["corpus", "run", *tex, *SMALL_V2, "--codec", f"{FIX}:uniform", *BASE, "-o", str(db)]) == 0
    capsys.readouterr()
    assert main(["corpus", "report", str(db), "-o", str(tmp_path / "rep"), "--no-plots"]) == 2
    err = _err_line(capsys)
    assert "uniform-zlib: codec versions" in err and "--latest" in err and "hostd corpus compare" in err
    assert main(["corpus", "report", str(db), "-o", str(tmp_path / "rep"), "--no-plots", "--latest",
                 "--json"]) == 0
    latest = json.loads(capsys.readouterr().out)
    assert "rows of earlier sets left out" in latest["left_out"][0]
    assert latest["rows"] == 2 * (5 + 5)
    # run 1 wrote v1's rows and hostd-v2's; run 2 only v2's (hostd-v2's were there)
    assert main(["corpus", "compare", f"{db}@1", f"{db}@2", "-o", str(tmp_path / "cmp"), "--json"]) == 0
    cmp = json.loads(capsys.readouterr().out)
    s = {(x["metric"], x["curve"]): x for x in cmp["summary"]}
    assert set(s) == {("iobj_db", "uniform-zlib")} and s[("iobj_db", "uniform-zlib")]["textures"] == 2
    assert s[("iobj_db", "uniform-zlib")]["mean_pct"] == pytest.approx(25.0, abs=0.5)
    # two stores compare alike
    other = tmp_path / "other.sqlite"
    assert main(["corpus", "run", *tex, "--codec", f"{FIX}:uniform", *BASE, "-o", str(other)]) == 0
    assert main(["corpus", "compare", f"{db}@1", str(other), "-o", str(tmp_path / "cmp2"), "--json"]) == 0
    out = capsys.readouterr().out
    assert json.loads(out[out.index("{"):])["summary"][0]["mean_pct"] == pytest.approx(25.0, abs=0.5)
    # another loader option (the patch's length) in the same store: named too
    assert main(["corpus", "run", *tex, *SMALL_V2, *BASE, "--length-mm", "1.5", "-o", str(db)]) == 0
    capsys.readouterr()
    assert main(["corpus", "report", str(db), "-o", str(tmp_path / "rep"), "--no-plots"]) == 2
    assert "hostd-v2/shaped: loader options" in _err_line(capsys)


def test_identical_bytes_under_two_names_each_get_their_rows_and_the_counts_add_up(tmp_path, capsys):
    d = tmp_path / "db"
    d.mkdir()
    rng = np.random.default_rng(3)
    text = "\n".join(f"{0.5 * i:.1f} {h:.4f}" for i, h in enumerate(np.cumsum(rng.normal(0, 1, 4000))))
    (d / "a.txt").write_text(text)
    (d / "b.txt").write_text(text)
    db = tmp_path / "r.sqlite"
    assert main(["corpus", "run", str(d), "--codec", f"{FIX}:uniform", *BASE, "-o", str(db), "--json"]) == 0
    summ = json.loads(capsys.readouterr().out)
    assert summ["total"] == summ["written"] == summ["ok"] == 10 and summ["skipped"] == 0
    c = sqlite3.connect(db)
    assert dict(c.execute("SELECT texture, COUNT(*) FROM results GROUP BY texture")) == {"a": 5, "b": 5}
    c.close()


def test_a_file_fixed_since_shows_its_current_rows_only(tmp_path, capsys):
    d = tmp_path / "db"
    d.mkdir()
    (d / "t.txt").write_text("not a profile\n")
    db = tmp_path / "r.sqlite"
    run = ["corpus", "run", str(d), *SMALL_V2, *BASE, "-o", str(db)]
    assert main(run) == 1  # every job failed
    rng = np.random.default_rng(4)
    (d / "t.txt").write_text("\n".join(f"{0.5 * i:.1f} {h:.4f}"
                                       for i, h in enumerate(np.cumsum(rng.normal(0, 1, 4000)))))
    assert main(run) == 0
    capsys.readouterr()
    assert main(["corpus", "report", str(db), "-o", str(tmp_path / "rep"), "--no-plots", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["failed_by_reason"] == {} and res["rows"] == 5
    assert "5 rows of files changed since left out" in res["left_out"][0]


def test_calibration_is_taken_by_corpus_run_and_changes_the_rows(tmp_path, capsys):
    from hostd.perception import calibration, thresholds

    d = thresholds.default_curve()
    cal = calibration.Calibration(thresholds.ThresholdCurve(d.freq_hz, 2.0 * d.threshold_um, name="lab"),
                                  0.7, 0.3, "lab")
    f = tmp_path / "lab.toml"
    calibration.write(f, cal)
    db = tmp_path / "r.sqlite"
    run = ["corpus", "run", "synthetic:wood:1", *SMALL_V2, *BASE, "-o", str(db)]
    assert main(run) == 0 and main([*run, "--calibration", str(f)]) == 0
    c = sqlite3.connect(db)
    rows = {}
    for scoring, setting, iobj in c.execute("SELECT scoring, setting, Iobj FROM results"):
        rows.setdefault(json.loads(scoring).get("calibration"), {})[setting] = iobj
    c.close()
    assert set(rows) == {None, cal.label} and len(rows[None]) == len(rows[cal.label]) == 5
    assert all(rows[None][s] != pytest.approx(rows[cal.label][s], rel=1e-3) for s in rows[None])
    capsys.readouterr()
    assert main(["corpus", "report", str(db), "-o", str(tmp_path / "rep"), "--no-plots"]) == 2
    assert "scorings" in _err_line(capsys)
    pytest.importorskip("pyarrow")
    from hostd import api

    t = api.run_corpus("synthetic:wood:1", db, codecs=["hostd-v2"], methods=["shaped"],
                       g_db=[-12, -6, 0, 6, 12], length_mm=2.0, workers=1, spqi=False, calibration=f,
                       as_pandas=False)
    assert json.loads(t.schema.metadata[b"summary"])["skipped"] == 5  # the same keys as the command's
