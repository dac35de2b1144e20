"""hostd corpus (issue 30): the codec protocol, the store's keys and resume, bad input as rows,
BD-rate on constructed cases, the CLI and API, a real Dask LocalCluster of worker processes
(equal rows; a worker SIGKILLed mid-run), and kill -9 of the driver then the same command."""

from __future__ import annotations

import json
import math
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from hostd.corpus import codecs, jobs, report
from hostd.corpus import run as crun
from hostd.corpus.store import Store
from hostd.texture.load import LoadOptions

ROOT = Path(__file__).resolve().parent.parent
FIX = "tests.corpus_codec_fixture"
SHORT = LoadOptions(length_mm=2.0)  # 4000 heights: cheap jobs
NO_SPQI = jobs.Scoring(spqi=False, timeout_s=30.0)


def _env() -> dict:
    return {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}


def _rows(path) -> list[dict]:
    st = Store(path)
    try:
        return st.rows("ORDER BY key")
    finally:
        st.close()


def _without_timings(rows):
    return [{k: v for k, v in r.items() if k not in jobs.TIMING_COLUMNS} for r in rows]


# ----------------------------------------------------------------------------- protocol


def test_external_codec_goes_through_the_protocol_and_is_scored_like_hostds(tmp_path):
    from tests.corpus_codec_fixture import UniformZlib

    tex = crun.textures_from(["synthetic:wood:1"], SHORT)
    plan = crun.make_plan([f"{FIX}:uniform", "hostd-v2"], methods=["shaped"], g_db=[0.0, 12.0])
    summ = crun.run(tex, plan, tmp_path / "r.sqlite", workers=1, scoring=jobs.Scoring(timeout_s=30))
    assert summ.total == summ.written == summ.ok == len(UniformZlib.settings) + 2
    rows = {r["setting"]: r for r in _rows(tmp_path / "r.sqlite")}
    from hostd.texture import synth

    whole = synth.from_spec("synthetic:wood:1")
    y = whole.heights_um[:4000]
    codec = UniformZlib()
    for s in UniformZlib.settings:
        r = rows[codecs.setting_json(s)]
        data = codec.encode(y, 0.5, **s)
        assert r["bytes"] == len(data)  # the rate is the codec's own bytes
        assert r["codec"] == "uniform-zlib" and r["codec_version"] == "1" and r["curve"] == "uniform-zlib"
        assert r["bits_per_mm"] == pytest.approx(8 * len(data) / 2.0)
        assert r["bits_per_s"] == pytest.approx(8 * len(data) * 50.0 / 2.0)
        assert 0 < r["spqi"] <= 1 and r["Iobj"] >= 0 and r["error"] is None
    # a finer step costs bytes, and the finest is far better than the coarsest
    ext = [rows[codecs.setting_json(s)] for s in UniformZlib.settings]  # coarse to fine
    assert [r["bytes"] for r in ext] == sorted(r["bytes"] for r in ext)
    assert ext[-1]["Iobj"] < ext[0]["Iobj"] / 10
    v2 = [r for r in rows.values() if r["codec"] == "hostd-v2"]
    assert {r["curve"] for r in v2} == {"hostd-v2/shaped"}
    # hostd's own codec scored from its reconstruction equals its stream's own Iobj (header sums)
    from hostd import api

    enc = api.encode(y, length_mm=2.0, method="shaped", g_db=12.0, spqi_min=None)
    against_original = api.score(enc, reference=y)
    r = rows[codecs.setting_json({"method": "shaped", "g_db": 12.0})]
    assert r["bytes"] == enc["bytes"]
    assert r["Iobj"] == pytest.approx(against_original["Iobj"], rel=1e-9, abs=1e-12)
    assert r["spqi"] == pytest.approx(against_original["spqi"], abs=1e-9)


def test_codec_names_resolve_or_say_what_is_wrong(tmp_path):
    assert codecs.resolve("v2").name == "hostd-v2"
    f = tmp_path / "mycodec.py"
    f.write_text("from tests.corpus_codec_fixture import UniformZlib as C\n")
    assert codecs.resolve(f"{f}:C").name == "uniform-zlib"  # a file path, the class called
    # the peers by their short names, each labelled where the report shows it
    assert [codecs.resolve(n).name for n in ("mpeg-rm", "mpeg-rm-cf0", "vc-pwq")] == list(codecs.PEERS)
    notes = report.about(["vc-pwq", "mpeg-rm", "hostd-v2/shaped", f"{FIX}:uniform"])
    assert list(notes) == ["mpeg-rm", "vc-pwq"] and "standard's codec" in notes["mpeg-rm"]
    assert "research codec (CC BY-NC" in notes["vc-pwq"]
    for bad, says in (("nope", "module:attr"), ("no_such_module_xyz:f", "cannot be loaded"),
                      (f"{FIX}:struct", "not a codec"), (f"{tmp_path}/missing.py:C", "no file")):
        with pytest.raises(codecs.HostdError, match=says):
            codecs.resolve(bad)


# ----------------------------------------------------------------------------- bad input


def test_bad_input_and_misbehaving_codecs_become_rows_and_the_run_goes_on(tmp_path):
    garbage = tmp_path / "garbage.txt"
    garbage.write_text("not a number\nat all\n")
    good = tmp_path / "good.txt"
    rng = np.random.default_rng(1)
    good.write_text("\n".join(f"{0.5 * i:.3f} {h:.5f}" for i, h in enumerate(rng.normal(0, 5, 4000))))
    man = tmp_path / "m.csv"
    man.write_text("file,name,units,y_unit,length_mm\n"
                   f"{garbage.name},garbage,um,,2\n"
                   f"{good.name},good,um,,2\n"
                   f"{good.name},metres,um,m,2\n"  # heights read as metres: 5e6 µm
                   f"{good.name},xmetres,m,,2\n"  # x read as metres: 0.5 m apart
                   "missing.txt,missing,um,,2\n")
    tex = crun.textures_from([str(man)], SHORT)
    plan = crun.make_plan([f"{FIX}:Misbehaving", f"{FIX}:NotInstalled"])
    summ = crun.run(tex, plan, tmp_path / "r.sqlite", workers=1,
                    scoring=jobs.Scoring(spqi=False, timeout_s=0.5))
    per_tex = plan.per_texture
    assert summ.written == summ.total == 5 * per_tex
    rows = _rows(tmp_path / "r.sqlite")
    by = {(r["texture"], r["codec"], json.loads(r["setting"]).get("fault")): r for r in rows}
    for t in ("garbage", "missing"):
        assert {r["error_reason"] for r in rows if r["texture"] == t} == {"unreadable_profile"}
    for t in ("metres", "xmetres"):
        assert {r["error_reason"] for r in rows if r["texture"] == t} == {"implausible_units"}, t
    want = {"none": None, "raise": "codec_error", "hang": "timeout", "short": "wrong_length",
            "nan": "nonfinite", "str": "bad_output"}
    for fault, reason in want.items():
        assert by[("good", "misbehaving", fault)]["error_reason"] == reason, fault
    assert "always fails" in by[("good", "misbehaving", "raise")]["error"]
    assert by[("good", "misbehaving", "none")]["Iobj"] is not None
    assert {r["error_reason"] for r in rows if r["codec"] == "not-installed" and r["texture"] == "good"} \
        == {"unavailable"}
    assert summ.ok == 1 and sum(summ.failed.values()) == summ.written - 1
    assert summ.failed["unavailable"] == 5 and summ.failed["timeout"] == 1  # 5 settings on "good"
    assert report.failures(rows)["unreadable_profile"] == 2 * per_tex


def test_resume_skips_known_keys_and_a_new_codec_version_is_a_new_key(tmp_path, monkeypatch):
    tex = crun.textures_from(["synthetic:wood:1", "synthetic:sandpaper:2"], SHORT)
    plan = crun.make_plan([f"{FIX}:uniform"])
    db = tmp_path / "r.sqlite"
    first = crun.run(tex, plan, db, workers=1, scoring=NO_SPQI)
    assert first.written == first.total == 10
    again = crun.run(tex, plan, db, workers=1, scoring=NO_SPQI)
    assert again.written == 0 and again.skipped == 10
    from tests.corpus_codec_fixture import UniformZlib

    monkeypatch.setattr(UniformZlib, "version", "2")
    codecs.resolve.cache_clear()
    try:
        bumped = crun.run(tex, plan, db, workers=1, scoring=NO_SPQI)
    finally:
        codecs.resolve.cache_clear()
    assert bumped.written == 10 and len(_rows(db)) == 20


def test_the_drivers_fast_keys_are_job_keys_bytes_and_tasks_are_guided(tmp_path):
    """The keys iter_tasks builds from pre-encoded parts equal job_key's (stores made before
    stay valid), with non-ASCII text in a setting; every job is handed out once, in order; a
    texture is one task while more than a texture per worker remains, and the last ones are cut
    into shrinking tasks down to single jobs."""
    tex = crun.textures_from([f"synthetic:wood:{k}" for k in range(1, 6)], SHORT)
    fx = f"{FIX}:uniform"
    plan = crun.make_plan(["hostd-v2", fx], methods=["shaped"], g_db=[-6.0, 0.0, 6.0],
                          speeds_mm_s=[50.0, 100.0],
                          settings={fx: [{"step_um": 1.0}, {"step_um": 0.5, "note": "µm – ü"}]})
    assert plan.per_texture == 10
    sc = jobs.Scoring(spqi=False)
    ver = crun.versions(plan)
    skipped = []
    two = list(crun.iter_tasks(tex, plan, sc, 256, lambda keys: set(), skipped.append, 2))
    for t in two:
        for j in t.jobs:
            name, version = ver[j.codec]
            assert j.key == jobs.job_key(t.texture, name, version, j.setting, j.speed_mm_s, j.fmax_hz, sc)
    assert [len(t.jobs) for t in two] == [10, 10, 10, 10, 5, 3, 1, 1]  # 50 jobs, 2 workers
    assert [t.texture.name for t in two][:4] == [x.name for x in tex[:4]] and not skipped
    keys = [j.key for t in two for j in t.jobs]
    assert len(set(keys)) == len(keys) == 50
    # one worker: whole textures, at most `batch` jobs per task; known keys are left out
    one = list(crun.iter_tasks(tex, plan, sc, 4, lambda ks: set(ks[:3]), skipped.append, 1))
    assert [len(t.jobs) for t in one] == [4, 3] * 5 and skipped == [3] * 5
    left = [k for i in range(5) for k in keys[10 * i + 3 : 10 * i + 10]]
    assert [j.key for t in one for j in t.jobs] == left
    # the driver's cap (from how long jobs take) is read as each task is made
    caps = iter([64, 64] + [3] * 18)
    capped = list(crun.iter_tasks(tex, plan, sc, 256, lambda keys: set(), skipped.append, 1,
                                  lambda: next(caps)))
    assert [len(t.jobs) for t in capped] == [10, 10] + [3, 3, 3, 1] * 3


def test_manifest_csv_and_toml_give_each_entry_its_own_units(tmp_path):
    from hostd.errors import ProfileError
    from hostd.texture import manifest

    (tmp_path / "a.txt").write_text("1\n2\n3\n")
    csv_m = tmp_path / "m.csv"
    csv_m.write_text("# corpus\nfile,name,x_unit,y_unit,spacing,columns,offset_mm,length_mm\n"
                     "a.txt,A,mm,nm,0.001,1,0,all\nsynthetic:wood:2,,,,,,,5\n")
    es = manifest.read(csv_m)
    assert [e.name for e in es] == ["A", "synthetic:wood:2"]
    assert es[0].options.x_unit == "mm" and es[0].options.y_unit == "nm" and es[0].options.spacing == 0.001
    assert es[0].options.columns == (0,) and es[0].options.length_mm is None
    assert es[0].source == str((tmp_path / "a.txt").resolve()) and es[1].options.length_mm == 5.0
    toml_m = tmp_path / "m.toml"
    toml_m.write_text('[defaults]\nunits = "mm"\n[[texture]]\nfile = "a.txt"\n[[texture]]\n'
                      'file = "a.txt"\nname = "b"\ny_unit = "um"\n')
    es = manifest.read(toml_m)
    assert [(e.options.x_unit, e.options.y_unit) for e in es] == [("mm", "mm"), ("mm", "um")]
    bad = tmp_path / "bad.csv"
    bad.write_text("file,unit\na.txt,mm\n")
    with pytest.raises(ProfileError, match="row 2: unknown key"):
        manifest.read(bad)
    assert manifest.is_manifest(csv_m) and not manifest.is_manifest(tmp_path / "a.txt")


# ----------------------------------------------------------------------------- BD-rate


def _curve(scale=1.0, n=6):
    q = np.linspace(5.0, 20.0, n)  # quality (dB)
    return 100.0 * 10 ** (q / 10.0) * scale, q


@pytest.mark.parametrize("method", ["pchip", "akima"])
def test_bd_rate_of_constructed_curves_has_the_known_answer(method):
    rate, q = _curve()
    assert report.bd_rate((rate, q), (0.9 * rate, q), method)[0] == pytest.approx(-10.0, abs=1e-9)
    assert report.bd_rate((rate, q), (1.25 * rate, q), method)[0] == pytest.approx(25.0, abs=1e-9)
    assert report.bd_rate((rate, q), (rate, q), method)[0] == pytest.approx(0.0, abs=1e-9)
    # a constant quality gain of 3 dB on this curve (log-rate slope 1/10 per dB) = rate x 10^-0.3
    val, note = report.bd_rate((rate, q), (rate, q + 3.0), method)
    assert val == pytest.approx((10 ** -0.3 - 1) * 100, abs=1e-6) and "overlap" in note  # 80 % overlap


def test_bd_rate_uses_the_pareto_front_and_says_why_there_is_no_value():
    rate, q = _curve()
    noisy_r = np.concatenate([0.9 * rate, [1e9, 2e9]])  # points beaten in rate and in quality
    noisy_q = np.concatenate([q, [6.0, 6.0]])
    pr, pq = report.pareto(noisy_r, noisy_q)
    assert np.all(np.diff(pr) > 0) and np.all(np.diff(pq) > 0) and 1e9 not in pr
    val, _ = report.bd_rate((rate, q), (noisy_r, noisy_q))
    assert val == pytest.approx(-10.0, abs=1e-9)
    val, note = report.bd_rate((rate, q), (rate[:1], q[:1]))
    assert math.isnan(val) and "too few points" in note
    val, note = report.bd_rate((rate, q), (rate, q + 100.0))
    assert math.isnan(val) and "do not overlap" in note


def test_report_writes_tables_that_name_the_transform(tmp_path):
    db = tmp_path / "r.sqlite"
    rate, q = _curve()
    rows = []
    for tex in ("t1", "t2"):
        for curve, scale in (("hostd-v2/shaped", 1.0), ("mine", 0.9 if tex == "t1" else 1.2)):
            for r, qq in zip(rate * scale, q, strict=True):
                row = dict.fromkeys(jobs.COLUMNS)
                row.update(key=f"{tex}{curve}{qq}", texture=tex, curve=curve, codec=curve, speed_mm_s=50.0,
                           fmax_hz=400.0, bytes=round(r), iobj_db=qq, Iobj=10 ** (-qq / 10),
                           spqi=qq / 30.0)
                rows.append(row)
    st = Store(db)
    st.write(rows)
    st.close()
    res = report.report(db, tmp_path / "out", plots=True, max_plots=1)
    s = {(x["metric"], x["curve"]): x for x in res["summary"]}
    iobj = s[("iobj_db", "mine")]
    assert iobj["textures"] == 2 and iobj["wins"] == 1
    assert iobj["worst_pct"] == pytest.approx(20.0, abs=0.5)  # t2: 1.2 x the rate
    assert iobj["mean_pct"] == pytest.approx(5.0, abs=0.5)  # (-10 + 20) / 2
    md = (tmp_path / "out" / "report.md").read_text()
    assert "Iobj in dB = -10·log10(Iobj)" in md and "SPQI (as is)" in md and "pchip" in md
    assert (tmp_path / "out" / "bdrate.csv").read_text().count("\n") == 1 + 2 * 2
    assert len([f for f in res["files"] if f.endswith(".png")]) == 1


# ----------------------------------------------------------------------------- CLI and API


def test_api_returns_a_table_of_the_store(tmp_path):
    pa = pytest.importorskip("pyarrow")
    from hostd import api

    t = api.run_corpus("synthetic:wood:1", tmp_path / "r.sqlite", codecs=[f"{FIX}:uniform"], length_mm=2.0,
                       workers=1, spqi=False, as_pandas=False)
    assert isinstance(t, pa.Table) and t.num_rows == 5 and t.column_names == list(jobs.COLUMNS)
    assert json.loads(t.schema.metadata[b"summary"])["written"] == 5
    df = api.run_corpus("synthetic:wood:1", tmp_path / "r.sqlite", codecs=[f"{FIX}:uniform"], length_mm=2.0,
                        workers=1, spqi=False, as_pandas=True)
    assert len(df) == 5 and df.attrs["summary"]["skipped"] == 5
    import pyarrow.parquet as pq

    from hostd.corpus import store

    out = store.export_parquet(tmp_path / "r.sqlite", tmp_path / "r.parquet", chunk_rows=2)  # 3 row groups
    assert pq.read_table(out).equals(store.to_arrow(tmp_path / "r.sqlite"))


def test_the_daemon_and_other_commands_do_not_import_the_corpus_dependencies():
    code = ("import sys, hostd.cli, hostd.api; hostd.cli.build_parser(); "
            "import hostd.corpus.cli; "
            "print(sorted(m for m in ('dask', 'distributed', 'pyarrow', 'bjontegaard', 'hostd.corpus.run') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=_env(), check=True)
    assert out.stdout.strip() == "[]"


def _sigint_default() -> None:
    """In the child: Ctrl-C as a terminal's foreground job gets it. A runner started in the
    background (`cmd &` in a script) hands its children SIGINT ignored, and Python then keeps it
    ignored (no KeyboardInterrupt): the Ctrl-C test then saw a run finish with exit 0."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _cli(args, gate: str | None = None, **kw):
    env = _env() if gate is None else {**_env(), "HOSTD_TEST_GATE": gate}
    return subprocess.Popen([sys.executable, "-m", "hostd", "corpus", *args], env=env, cwd=ROOT,
                            preexec_fn=_sigint_default,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            **kw)


def _count(db: Path) -> int:
    try:
        with sqlite3.connect(db, timeout=5) as c:
            return int(c.execute("SELECT COUNT(*) FROM results").fetchone()[0])
    except sqlite3.Error:
        return 0


def test_kill_9_of_the_driver_then_the_same_command_resumes_with_nothing_lost_or_twice(tmp_path):
    db = tmp_path / "r.sqlite"
    # 6 textures x 4 settings = 24 jobs, batches of 2, on 2 workers; 4 encodes pass, the rest
    # wait behind the gate until the resumed run: the run is surely going when it is killed. (A
    # batch's rows come together, and a worker may take a second batch's tokens before the other
    # took its first's: one whole batch, 2 rows, is what the 4 tokens guarantee.)
    gate = tmp_path / "gate"
    gate.mkdir()
    args = ["run", "synthetic:wood:1-3", "synthetic:sandpaper:1-3", "--codec", f"{FIX}:Gated",
            "--length-mm", "2", "--no-spqi", "--workers", "2", "--batch", "2", "-o", str(db), "--json"]
    p = _cli(args, gate=f"{gate}:4")
    deadline = time.monotonic() + 120
    while _count(db) < 2 and p.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    assert p.poll() is None, "the run ended before it could be killed: " + p.stderr.read()
    os.kill(p.pid, signal.SIGKILL)
    p.wait()
    try:
        os.killpg(p.pid, signal.SIGKILL)  # the dead driver's own pool workers, if still there
    except ProcessLookupError:
        pass
    before = {r["key"]: r for r in _rows(db)}
    assert 2 <= len(before) < 24
    (gate / "open").touch()
    q = _cli(args, gate=f"{gate}:4")
    out, err = q.communicate(timeout=180)
    assert q.returncode == 0, err
    summ = json.loads(out)
    assert summ["skipped"] == len(before) and summ["written"] == 24 - len(before)
    after = _rows(db)
    assert len(after) == len({r["key"] for r in after}) == 24
    assert all(r["error"] is None for r in after), [r["error"] for r in after if r["error"]][:3]
    for r in after:  # the rows written before the kill are untouched
        if r["key"] in before:
            assert r == before[r["key"]]


def test_ctrl_c_stops_the_run_and_keeps_the_finished_rows(tmp_path):
    db = tmp_path / "r.sqlite"
    gate = tmp_path / "gate"  # 2 encodes pass, the rest wait for the gate: Ctrl-C comes mid-run
    gate.mkdir()
    p = _cli(["run", "synthetic:wood:1-4", "--codec", f"{FIX}:Gated", "--length-mm", "2", "--no-spqi",
              "--workers", "2", "--batch", "1", "-o", str(db)], gate=f"{gate}:2")
    deadline = time.monotonic() + 120
    while _count(db) < 2 and p.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    assert p.poll() is None, "the run ended before Ctrl-C: " + p.stderr.read()
    os.kill(p.pid, signal.SIGINT)
    (gate / "open").touch()  # (the jobs in the workers' hands may end or be stopped)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 130 and "interrupted: the rows above are kept" in err
    kept = _rows(db)
    assert 2 <= len(kept) < 16 and all(r["error"] is None for r in kept)


def test_cli_report_and_export(tmp_path, capsys):
    from hostd.cli import main

    db = tmp_path / "r.sqlite"
    for args in (["run", "synthetic:wood:1", "--codec", f"{FIX}:uniform", "--codec", "hostd-v2", "--methods",
                  "shaped", "--g-db=-12,-6,0,6", "--length-mm", "2", "--no-spqi", "--workers", "1", "-o",
                  str(db), "--no-progress"],
                 ["report", str(db), "-o", str(tmp_path / "rep"), "--anchor", "hostd-v2/shaped",
                  "--interpolation", "akima", "--no-plots"],
                 ["export", str(db), "-o", str(tmp_path / "r.csv")]):
        assert main(["corpus", *args]) == 0, capsys.readouterr().err
    assert "akima" in (tmp_path / "rep" / "report.md").read_text()
    assert (tmp_path / "r.csv").read_text().count("\n") == 1 + 9
    capsys.readouterr()
    # run and report in one command (--report): the same table as `hostd corpus report` prints
    run = ["corpus", "run", "synthetic:wood:1", "--codec", f"{FIX}:uniform", "--codec", "hostd-v2",
           "--methods", "shaped", "--g-db=-12,-6,0,6", "--length-mm", "2", "--no-spqi", "--workers", "1",
           "-o", str(db), "--no-progress"]
    assert main([*run, "--report", str(tmp_path / "one")]) == 0
    out = capsys.readouterr().out
    assert main(["corpus", "report", str(db), "-o", str(tmp_path / "two"), "--no-plots"]) == 0
    assert [ln for ln in out.splitlines() if " vs hostd-v2/shaped: " in ln] == [
        ln for ln in capsys.readouterr().out.splitlines() if " vs hostd-v2/shaped: " in ln] != []
    assert (tmp_path / "one" / "bdrate.csv").read_text() == (tmp_path / "two" / "bdrate.csv").read_text()
    assert main([*run, "--report", str(tmp_path / "one"), "--json"]) == 0
    both = json.loads(capsys.readouterr().out)
    assert both["run"]["skipped"] == 9 and both["report"]["anchor"] == "hostd-v2/shaped"
    assert main(["corpus", "report", str(db), "-o", str(tmp_path / "rep"), "--anchor", "nope"]) == 2
    err = capsys.readouterr().err
    assert "anchor 'nope' is not a curve" in err and len(err.strip().splitlines()) == 1


# ----------------------------------------------------------------------------- Dask, for real


@pytest.fixture(scope="module")
def cluster():
    """One LocalCluster of 2 worker processes x 1 thread for the module (its start costs seconds);
    the test that SIGKILLs a worker comes last, and the nanny restarts the worker anyway."""
    distributed = pytest.importorskip("distributed")
    c = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None)
    try:
        yield c
    finally:
        c.close()


def test_dask_worker_processes_give_the_local_pools_rows(tmp_path, cluster):
    """Equal rows, error rows included: a codec that hangs is stopped by SIGALRM in the pool's
    worker processes and by an asynchronous exception in Dask's worker threads."""
    tex = crun.textures_from(["synthetic:wood:1", "synthetic:sandpaper:1"], SHORT)
    bad = f"{FIX}:Misbehaving"
    plan = crun.make_plan(["hostd-v2", f"{FIX}:uniform", bad], methods=["shaped", "quant"], g_db=[-6.0, 6.0],
                          levels=[8], speeds_mm_s=[50.0],
                          settings={f"{FIX}:uniform": [{"step_um": 1.0}, {"step_um": 0.25}],
                                    bad: [{"step_um": 1.0, "fault": f} for f in ("hang", "nan")]})
    sc = jobs.Scoring(spqi=True, timeout_s=1.5)
    local = crun.run(tex, plan, tmp_path / "local.sqlite", workers=2, scoring=sc, batch=3)
    dask = crun.run(tex, plan, tmp_path / "dask.sqlite", dask=cluster.scheduler_address, workers=2,
                    scoring=sc, batch=3)
    assert local.written == dask.written == 2 * (3 + 2 + 2) and dask.executor.startswith("dask")
    a, b = _rows(tmp_path / "local.sqlite"), _rows(tmp_path / "dask.sqlite")
    assert _without_timings(a) == _without_timings(b)
    assert all(r["error"] is None and r["spqi"] is not None for r in b if r["codec"] != "misbehaving")
    reasons = sorted(r["error_reason"] for r in b if r["codec"] == "misbehaving")
    assert reasons == ["nonfinite"] * 2 + ["timeout"] * 2


def test_dask_a_job_no_exception_reaches_ends_as_a_timeout_row(tmp_path, cluster):
    """A codec that blocks SIGALRM and waits in C (the asynchronous exception never lands, as
    with a ctypes spin, time.sleep or a waited-for child): its worker logs the job and kills
    itself, the driver writes the `timeout` row and runs the task's other jobs again."""
    tex = crun.textures_from(["synthetic:wood:1"], SHORT)
    bad = f"{FIX}:Misbehaving"
    plan = crun.make_plan([bad], settings={bad: [{"step_um": s, "fault": f} for s, f in
                                                ((1.0, "none"), (0.5, "deaf"), (0.25, "none"))]})
    t0 = time.monotonic()
    summ = crun.run(tex, plan, tmp_path / "r.sqlite", dask=cluster.scheduler_address, workers=2,
                    scoring=jobs.Scoring(spqi=False, timeout_s=1.0), batch=3)
    assert time.monotonic() - t0 < 60
    rows = _rows(tmp_path / "r.sqlite")
    assert summ.written == len(rows) == 3 and summ.ok == 2 and summ.failed == {"timeout": 1}
    (bad_row,) = [r for r in rows if r["error"] is not None]
    assert '"deaf"' in bad_row["setting"] and "killed" in bad_row["error"]


def test_dask_worker_sigkilled_mid_run_every_row_exactly_once(tmp_path, cluster):
    from distributed import Client

    tex = crun.textures_from([f"synthetic:wood:{k}" for k in range(1, 7)], SHORT)
    plan = crun.make_plan([f"{FIX}:Slow"])  # 24 jobs of >= 50 ms, batches of 2
    client = Client(cluster)
    killed = []

    def kill_a_busy_worker(rows):
        if killed:
            return
        busy = [w for w, tasks in client.processing().items() if tasks]
        if busy:
            pid = client.run(os.getpid, workers=[busy[0]])[busy[0]]
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)

    try:
        summ = crun.run(tex, plan, tmp_path / "r.sqlite", dask=cluster.scheduler_address, workers=2,
                        scoring=NO_SPQI, batch=2, on_rows=kill_a_busy_worker)
    finally:
        client.close()
    assert killed, "no worker was busy to kill"
    rows = _rows(tmp_path / "r.sqlite")
    assert summ.written == len(rows) == len({r["key"] for r in rows}) == 24
    assert all(r["error"] is None for r in rows)
    # and the summary says what was lost and redone (retried_tasks stayed 0: Dask redid them)
    assert summ.workers_lost == 1 and summ.redone_by_dask >= 1
    assert any("1 Dask worker(s) died" in line for line in summ.lines())


_BLOCK = """
import importlib.abc, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in ("dask", "distributed", "pyarrow", "bjontegaard"):
            raise ImportError(f"blocked {name}")
sys.meta_path.insert(0, Block())
from hostd.cli import main
raise SystemExit(main(sys.argv[1:]))
"""


def test_without_the_corpus_extra_runs_work_and_the_rest_names_the_extra(tmp_path):
    def hostd(*args):
        return subprocess.run([sys.executable, "-c", _BLOCK, "corpus", *args], capture_output=True, text=True,
                              env=_env(), cwd=ROOT, timeout=300)

    db = str(tmp_path / "r.sqlite")
    r = hostd("run", "synthetic:wood:1", "--codec", f"{FIX}:uniform", "--length-mm", "2", "--no-spqi",
              "--workers", "1", "-o", db)
    assert r.returncode == 0 and "5 rows written" in r.stdout, r.stderr
    for args in (["report", db, "-o", str(tmp_path / "rep")],
                 ["export", db, "-o", str(tmp_path / "r.parquet")],
                 ["run", "synthetic:wood:1", "--dask", "local", "-o", db]):
        r = hostd(*args)
        from hostd.extras import pip_install

        assert r.returncode == 2 and pip_install("corpus") in r.stderr, (args, r.stderr)
        assert len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "rep").exists()
