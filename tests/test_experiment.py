"""hostd experiment: safety of stimuli, the session store (one session per token, every answer
once), resume with the same plan, a display lost mid-trial, bad designs, and the outputs that
`--thresholds`, `hostd fit` and `--calibration` read as-is."""

from __future__ import annotations

import json
import re
import threading

import numpy as np
import pytest

pytest.importorskip("questplus")

from hostd.cli import main
from hostd.errors import ExperimentError
from hostd.experiment.display import Reach, SimDisplay, Sinusoid
from hostd.experiment.plan import check_plan
from hostd.experiment.runner import Refused, SimilaritySession, ThresholdSession
from hostd.experiment.session import Store
from hostd.experiment.threshold import ThresholdConfig, ThresholdRun, db, thresholds_csv
from hostd.perception import thresholds as th


@pytest.fixture(scope="module")
def reach():
    return Reach()


def test_the_host_refuses_any_stimulus_beyond_the_reach(reach):
    d = SimDisplay(reach)
    for f in (40.0, 250.0, 500.0):
        r = reach.reach_um(f)
        d.play(Sinusoid(f, r))  # at the reach: played, unlimited by the output stage
        assert np.max(np.abs(d.last_um)) <= reach.stage.limit_um
        with pytest.raises(ExperimentError, match="refused"):
            d.play(Sinusoid(f, r * 1.001))
    # the reach is what the output stage can play without limiting: 20 % past the margin it limits
    from hostd.render.output import OutputStage

    f = 40.0  # the displacement limit binds here
    cmd = Sinusoid(f, reach.reach_um(f) / 0.9 * 1.2).samples_um(reach.gain(f))
    st = OutputStage(reach.stage.cfg)
    st.start()
    st.envelope = 1.0
    assert not np.allclose(st.process(cmd), cmd)
    with pytest.raises(ExperimentError):
        d.play(Sinusoid(f, float("nan")))


def test_no_procedure_step_asks_beyond_the_reach_and_above_reach_is_reported(reach):
    # an observer who never detects anything: the staircase climbs to the top of its grid
    cfg = ThresholdConfig([250.0], [0.1], [0.5], n_afc=2, max_trials=25, seed=3)
    run = ThresholdRun(cfg)
    while (t := run.next_trial()) is not None:
        assert t.amplitude_um <= 0.5 * (1 + 1e-12)
        run.answer(t.index, t.target % 2 + 1)  # always wrong
    res = run.results()[0]
    assert res.status == "above_reach" and res.threshold_um > 0.5
    text = thresholds_csv(run.results())
    assert "ABOVE THE DISPLAY'S REACH" in text and "\n250," not in text  # not clipped into the curve


def test_the_joint_mode_never_asks_beyond_the_reach_and_reports_above_reach():
    from hostd.experiment.procedure import make_run

    freqs = [40.0, 100.0, 250.0, 500.0]
    reach = [0.5, 5.0, 5.0, 5.0]  # the first frequency's reach is below what this observer needs
    cfg = ThresholdConfig(freqs, [3.9, 0.62, 0.1, 0.32], reach, n_afc=2, max_trials=12, seed=5,
                          procedure="joint")
    run = make_run(cfg)
    levels = {f: [] for f in freqs}
    while (t := run.next_trial()) is not None:
        assert t.amplitude_um <= reach[freqs.index(t.frequency_hz)] * (1 + 1e-12)
        levels[t.frequency_hz].append(t.level_db)
        # an observer far less sensitive than the prior (+20 dB): 40 Hz is beyond the reach
        correct = t.level_db > db(cfg.prior_um[freqs.index(t.frequency_hz)]) + 20
        run.answer(t.index, t.target if correct else t.target % 2 + 1)
    # the budget, and as much again per frequency: a step 20 dB off the prior does not fit the curve
    assert run.index == 24 * len(freqs) == run.planned_trials and sum(map(len, levels.values())) == run.index
    assert "may not fit" in run.notes()[0]
    res = run.results()
    assert res[0].status == "above_reach" and res[0].threshold_um > 0.5
    text = thresholds_csv(res)
    assert "ABOVE THE DISPLAY'S REACH" in text and "\n40," not in text
    with pytest.raises(ExperimentError, match="at least 3"):
        ThresholdConfig(freqs[:2], [1.0, 1.0], [5.0, 5.0], procedure="joint")


def test_thresholds_csv_reads_as_is(tmp_path):
    cfg = ThresholdConfig([40.0, 250.0], [3.9, 0.1], [30.0, 20.0], max_trials=4, seed=1)
    run = ThresholdRun(cfg)
    while (t := run.next_trial()) is not None:
        run.answer(t.index, t.target)
    f = tmp_path / "t.csv"
    f.write_text(thresholds_csv(run.results()))
    c = th.load_csv(f)
    assert list(c.freq_hz) == [40.0, 250.0]
    assert np.allclose(c.threshold_um, [r.threshold_um for r in run.results()], rtol=1e-5)


def test_one_session_per_token_and_one_answer_per_trial(tmp_path):
    st = Store(tmp_path / "s.sqlite")
    st.create("abc", "threshold", {"x": 1})
    with pytest.raises(ExperimentError, match="participant abc is already"):
        st.create("abc", "similarity", {})
    with pytest.raises(ExperimentError, match="participant"):
        st.create("a b", "threshold", {})
    assert st.record("abc", 0, 1, {}, None) and not st.record("abc", 0, 2, {}, None)
    assert [a["answer"] for a in st.answers("abc")] == [1]
    import os

    assert os.stat(tmp_path / "s.sqlite").st_mode & 0o777 == 0o600
    shared = tmp_path / "shared"  # a folder others can enter, not made by hostd: refused, left as it is
    shared.mkdir()
    shared.chmod(0o755)
    with pytest.raises(ExperimentError, match="open to other accounts"):
        Store(shared / "s.sqlite")
    assert shared.stat().st_mode & 0o777 == 0o755 and not (shared / "s.sqlite").exists()


def _cfg():
    return ThresholdConfig([40.0, 250.0], [3.9, 0.1], [30.0, 20.0], n_afc=3, max_trials=6, seed=7)


NO_PRACTICE = check_plan({"practice": {"trials": 0}})


def _answer(sess, rng):
    """One trial as the page takes it: played whole, then answered (a lost display: retry)."""
    if sess.holder != "pg":
        sess.open("pg")
        sess.step("pg", "continue")
    if sess.finished():
        return {"done": True}
    sess.present("pg")
    sess.player.join()
    if sess.retry:
        return {"done": False, "retry": True}
    t = sess.current()
    sess.answer("pg", t["index"], t["target"] if rng.random() < 0.7 else t["target"] % 3 + 1)
    return {"done": sess.finished()}


def test_resume_meets_the_same_trials_and_a_lost_display_repeats_the_trial(tmp_path):
    rng = np.random.default_rng(0)
    st = Store(tmp_path / "s.sqlite")
    st.create("tok", "threshold", {})
    # the display disconnects during plays 4 and 5 (the second trial's stimulus, then its retry)
    d = SimDisplay(fail_on={4, 5})
    a = ThresholdSession(st, "tok", d, _cfg(), NO_PRACTICE)
    seen = []
    for _ in range(5):
        s = _answer(a, rng)
        seen.append(bool(s.get("retry")))
    assert any(seen)
    ev = [e["kind"] for e in st.events("tok")]
    assert ev.count("display_lost") >= 1
    rows = st.answers("tok")
    assert [r["trial"] for r in rows] == list(range(len(rows)))  # nothing twice, nothing skipped
    # a crash: a new process resumes from the store, with the same plan
    b = ThresholdSession(st, "tok", SimDisplay(), _cfg(), NO_PRACTICE)
    b.resume()
    assert b.answered() == len(rows)
    ref = ThresholdRun(_cfg())  # the same answers replayed by hand reach the same next trial
    for r in rows:
        t = ref.next_trial()
        assert t.level_db == r["stimulus"]["level_db"]
        ref.answer(t.index, r["answer"])
    assert ref.next_trial().as_dict() == b.current()
    b.open("pg")
    while not _answer(b, rng)["done"]:
        pass
    assert len(st.answers("tok")) == 12 and st.state("tok") == "done"


def test_a_session_stored_by_an_older_hostd_resumes(tmp_path):
    # 100 answers of a default-stop 3AFC session (three frequencies, one already stopped on its
    # interval's width after 39 trials) recorded by the hostd before the intervals' cells were
    # centred and 3AFC's default minimum was 40 trials: its stored config has no min_trials, so it
    # replays with the minimum it was run with, meets the same levels and stops, and goes on to
    # its end (with today's default minimum it would not match)
    from pathlib import Path

    from hostd.experiment.threshold import MAX_TRIALS

    data = Path(__file__).parent / "data" / "threshold-session-before-interval-fix.json"
    old = json.loads(data.read_text())
    assert "min_trials" not in old["config"]
    st = Store(tmp_path / "s.sqlite")
    st.create("tok", "threshold", {})
    for a in old["answers"]:
        assert st.record("tok", a["trial"], a["answer"], a["stimulus"], None)
    with pytest.raises(ExperimentError, match="does not match the plan"):
        ThresholdSession(st, "tok", SimDisplay(), ThresholdConfig(**old["config"]), NO_PRACTICE).resume()
    b = ThresholdSession(st, "tok", SimDisplay(), ThresholdConfig.stored(old["config"]), NO_PRACTICE)
    b.resume()
    assert b.answered() == len(old["answers"]) == 100
    stopped = [s.n for i, s in enumerate(b.run.stairs) if i not in b.run.running()]
    assert stopped and max(stopped) < MAX_TRIALS  # a stop on the width, replayed
    rng = np.random.default_rng(1)
    b.open("pg")
    while not _answer(b, rng)["done"]:
        pass
    assert st.state("tok") == "done" and len(st.answers("tok")) > 100


def test_resume_refuses_a_plan_that_no_longer_matches(tmp_path):
    st = Store(tmp_path / "s.sqlite")
    st.create("tok", "threshold", {})
    a = ThresholdSession(st, "tok", SimDisplay(), _cfg(), NO_PRACTICE)
    _answer(a, np.random.default_rng(0))
    other = ThresholdConfig([40.0, 250.0], [3.9, 0.1], [30.0, 20.0], n_afc=3, max_trials=6, seed=8)
    with pytest.raises(ExperimentError, match="does not match the plan"):
        ThresholdSession(st, "tok", SimDisplay(), other, NO_PRACTICE).resume()


DESIGN = """seconds = 1
repetitions = 2
length_mm = 1
seed = 3
[textures]
wood = "synthetic:wood:1"
[[methods]]
method = "quant"
settings = [4, 8, 16]
[[methods]]
method = "cut"
settings = [-4, 0, 8]
"""


@pytest.mark.parametrize("edit, needle", [
    (("settings = [4, 8, 16]", "settings = [4, 1.5]"), "quant setting 1.5"),
    (("settings = [-4, 0, 8]", "settings = [-4, 0, 8]\ntextures = [\"oak\"]"), "unknown texture 'oak'"),
    (('method = "cut"', 'method = "zip"'), "method must be one of"),
    (('wood = "synthetic:wood:1"', 'wood = "nothere.csv"'), "texture wood"),
    (("seed = 3", "sed = 3"), "unknown key(s) sed"),
])
def test_a_bad_design_is_one_line(tmp_path, capsys, edit, needle):
    d = tmp_path / "design.toml"
    d.write_text(DESIGN.replace(*edit))
    assert main(["experiment", "similarity", str(d), "-o", str(tmp_path / "o"), "--participant", "x",
                 "--simulate", "linear"]) == 2
    err = capsys.readouterr().err.strip()
    assert needle in err and "\n" not in err


def test_similarity_plan_scores_fit_and_calibration_end_to_end(tmp_path, capsys):
    d = tmp_path / "design.toml"
    d.write_text(DESIGN)
    out = tmp_path / "sim"
    assert main(["experiment", "similarity", str(d), "-o", str(out), "--participant", "s1",
                 "--simulate", "linear"]) == 0
    st = Store(out / "session.sqlite")
    plan = st.load("s1", "similarity")
    assert len(plan["trials"]) == 2 * (1 + 3 + 3)  # controls included
    order = [(t["method"], t["level"]) for t in plan["trials"]]
    assert order != sorted(order)  # randomised
    import csv

    rows = list(csv.DictReader(line for line in (out / "scores.csv").open() if not line.startswith("#")))
    ctl = [r for r in rows if r["method"] == "none"]
    assert len(ctl) == 1 and ctl[0]["stream"] == "" and ctl[0]["Ip"] == "" and ctl[0]["n"] == "2"
    assert all((out / r["stream"]).is_file() for r in rows if r["method"] != "none")
    capsys.readouterr()
    assert main(["fit", str(out / "scores.csv"), "--json", "--bootstrap", "100"]) == 0
    fit = json.loads(capsys.readouterr().out)
    assert fit["n_used"] == 7
    (tmp_path / "fit.json").write_text(json.dumps(fit))
    # the same participant again (through the deprecated --token: a label): refused, nothing overwritten
    before = (out / "scores.csv").read_bytes()
    assert main(["experiment", "similarity", str(d), "-o", str(out), "--token", "s1",
                 "--simulate", "linear"]) == 2
    err = capsys.readouterr().err
    assert "already" in err and "--token is deprecated" in err and (out / "scores.csv").read_bytes() == before
    # everything --simulate wrote says so
    for f in ("scores.csv", "answers.csv"):
        assert (out / f).read_text().startswith("# SIMULATED: answered by a simulated linear observer")
    tout = tmp_path / "thr"
    assert main(["experiment", "threshold", "-o", str(tout), "--participant", "t",
                 "--frequencies", "40,250", "--trials", "5", "--simulate", "weibull"]) == 0
    assert "# SIMULATED: answered by a simulated weibull" in (tout / "thresholds.csv").read_text()
    assert (tout / "trials.csv").read_text().startswith("# SIMULATED")
    jout = tmp_path / "thr-joint"  # the joint mode through the same session machinery
    assert main(["experiment", "threshold", "-o", str(jout), "--participant", "j",
                 "--frequencies", "40,100,250", "--trials", "4", "--joint", "--simulate", "weibull"]) == 0
    assert len(th.load_csv(jout / "thresholds.csv").freq_hz) == 3
    assert "joint" in (jout / "thresholds.csv").read_text()
    cal = tmp_path / "lab.toml"
    assert main(["experiment", "calibration", "-o", str(cal), "--thresholds", str(tout / "thresholds.csv"),
                 "--fit", str(tmp_path / "fit.json")]) == 0
    assert "simulated = \"yes: " in cal.read_text()  # the calibration's provenance says so
    capsys.readouterr()
    s = tmp_path / "x.vtx"
    assert main(["encode", "synthetic:wood:1", "--length-mm", "1", "-o", str(s), "--method", "cut",
                 "--b0-db", "0", "--calibration", str(cal),
                 "--json"]) == 0
    enc = json.loads(capsys.readouterr().out)
    assert (enc["a"], enc["b"]) == (fit["a"], fit["b"])


def test_similarity_session_answers_once_and_repeats_a_lost_texture(tmp_path):
    from hostd.experiment.similarity import make_plan, read_design

    d = tmp_path / "design.toml"
    d.write_text(DESIGN.replace("repetitions = 2", "repetitions = 1"))
    plan = make_plan(read_design(d), tmp_path / "o")
    st = Store(tmp_path / "s.sqlite")
    st.create("k", "similarity", plan)
    sess = SimilaritySession(st, "k", SimDisplay(fail_on={1}), plan, NO_PRACTICE)
    sess.open("pg")
    sess.step("pg", "continue")
    sess.present("pg")
    sess.player.join()
    assert sess.retry and st.events("k")[-1]["kind"] == "display_lost"
    sess.present("pg")
    sess.player.join()
    idx = sess.view("pg")["trial"]["index"]
    assert sess.answer("pg", idx, 2) == {"ok": True}
    with pytest.raises(Refused, match="not played on this page"):
        sess.answer("pg", idx, 3)  # a double click: that trial is no longer the one played
    assert [a["answer"] for a in st.answers("k")] == [2]


def test_similarity_simulate_takes_only_a_grading_observer(tmp_path, capsys):
    d = tmp_path / "design.toml"
    d.write_text(DESIGN)
    assert main(["experiment", "similarity", str(d), "-o", str(tmp_path / "o"),
                 "--simulate", "weibull"]) == 2
    assert "a grading observer is linear" in capsys.readouterr().err


def test_the_plan_is_data_checked_with_one_line_and_breaks_come_as_declared(tmp_path):
    from pathlib import Path

    from hostd.experiment.plan import break_due, default_path, read_plan

    plan = read_plan()  # the shipped default
    assert plan["consent"] is None and plan["practice"]["trials"] == 3
    docs = (Path(__file__).parents[1] / "docs" / "experiments.md").read_text()
    assert default_path().read_text().strip() in docs  # the docs show the very file
    for text, needle in [("[practice]\ntrials = -1\n", "not negative"), ("[brakes]\n", "unknown section"),
                         ("[end]\ncolour = 1\n", "unknown key(s) colour"),
                         ("[breaks]\nevery_trials = 1.5\n", "must be a whole number"),
                         ("[consent]\nagree = 'yes'\n", "needs text"),
                         ("[main]\nblocks = 0\n", "at least 1")]:
        f = tmp_path / "p.toml"
        f.write_text(text)
        with pytest.raises(ExperimentError, match=re.escape(needle)):
            read_plan(f)
    f.write_text("[consent]\ntext = 'Agree?'\n[breaks]\nevery_trials = 0\nevery_minutes = 5\n"
                 "[main]\nblocks = 3\n")
    p = read_plan(f)
    assert p["consent"] == {"text": "Agree?", "agree": "I agree", "decline": "I do not agree"}
    assert p["end"] == plan["end"]  # what a plan leaves out is the default plan's
    assert [n for n in range(1, 30) if break_due(p, n, 30, 0.0)] == [10, 20]  # blocks of 10
    assert break_due(p, 3, 30, 5.0) and not break_due(p, 3, 30, 4.9)  # every 5 minutes
    assert not break_due(p, 30, 30, 99.0)  # never after the last trial


def test_db_scale():
    assert db(1.0) == 0.0 and abs(db(0.1) + 20.0) < 1e-12


def test_the_daemon_and_encode_do_not_import_the_experiment_dependencies(tmp_path):
    import subprocess
    import sys

    code = ("import sys; from hostd.cli import main; from hostd.service import daemon; "
            f"main(['encode', 'synthetic:wood:1', '--length-mm', '1', '-o', {str(tmp_path / 'x.vtx')!r}, "
            "'--method', 'quant', '--levels', '8']); "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('questplus', 'xarray', 'selenium')))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().splitlines()[-1] == "[]"


def test_the_experimenters_terminal_shows_progress_aborts_and_resumes(tmp_path):
    """The command as an experimenter runs it: the page's address once on stdout (a secret, not
    the participant's id), the progress on stderr, Ctrl-C aborts keeping every answer, --resume
    goes on with the same plan."""
    import re
    import signal
    import subprocess
    import sys

    from tests.page_client import PageClient

    out = tmp_path / "o"
    plan = tmp_path / "plan.toml"
    plan.write_text("[practice]\ntrials = 0\n")
    args = [sys.executable, "-m", "hostd", "experiment", "threshold", "-o", str(out),
            "--participant", "p1", "--frequencies", "40,250", "--trials", "3", "--plan", str(plan)]
    # (SIGINT as a terminal's foreground job has it: a runner started in the background hands
    # its children SIGINT ignored, and the Ctrl-C below never arrived: a 300 s hang)
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        url = proc.stdout.readline().strip()
        assert re.fullmatch(r"http://127\.0\.0\.1:\d+/s/[A-Za-z0-9_-]{32}", url), url
        c = PageClient(url)
        c.to_main()
        for _ in range(2):
            t = c.play()["trial"]
            assert c.answer(t["index"], 1) == (200, {"ok": True})
        progress = ""
        while "2/6 answered" not in progress:
            progress += proc.stderr.readline()
        proc.send_signal(signal.SIGINT)
        err = proc.stderr.read()
        assert proc.wait(60) == 1 and "aborted at 2 answers" in err and "--resume" in err
        assert url.rsplit("/", 1)[1] not in progress + err  # the secret: stdout only
        assert proc.stdout.read() == ""  # printed once
    finally:
        if proc.poll() is None:
            proc.kill()
    st = Store(out / "session.sqlite")
    assert st.state("p1") == "aborted" and len(st.answers("p1")) == 2
    first = [a["stimulus"] for a in st.answers("p1")]
    r = subprocess.run([*args[:-4], "--resume", "--simulate", "weibull"], capture_output=True, text=True,
                       timeout=120)  # (--participant given, so the --plan is the stored one)
    assert r.returncode == 0, r.stderr
    rows = st.answers("p1")
    assert len(rows) == 6 and [a["stimulus"] for a in rows[:2]] == first
    assert th.load_csv(out / "thresholds.csv").freq_hz.size == 2


# ---------------------------------------------------------------------------- a full disk
def _run_main_in_thread(argv: list[str], capsys) -> tuple[threading.Thread, dict, str]:
    """`hostd ARGV` in a thread (the command serving its page); its address from stdout."""
    import time

    res: dict = {}
    th_ = threading.Thread(target=lambda: res.setdefault("rc", main(argv)), daemon=True)
    th_.start()
    out = ""
    t_end = time.monotonic() + 60
    while "http://" not in out and th_.is_alive() and time.monotonic() < t_end:
        out += capsys.readouterr().out
        time.sleep(0.02)
    m = re.search(r"http://127\.0\.0\.1:\d+/s/\S+", out)
    assert m, out
    return th_, res, m.group(0)


@pytest.mark.parametrize("moment", ["answer", "done", "results"])
def test_a_full_disk_stops_with_one_line_and_a_plain_message_and_resume_finishes(tmp_path, capsys,
                                                                                   monkeypatch, moment):
    """The session's folder on a 1 MiB tmpfs that fills up at one moment: an answer, the done
    mark, the results. Each ends in one line on the terminal and a plain message on the page (no
    path, no JSON dump); once space returns, the same command with --resume finishes the results
    from the stored answers, every answer once."""
    import subprocess

    from hostd.experiment import cli as ecli
    from tests.page_client import PageClient
    from tests.test_quality_full_disk import _fill, _mount_tmpfs

    fs = tmp_path / "fs"
    _mount_tmpfs(fs)
    filled: list = []

    def fill() -> None:
        if not filled:
            filled.append(_fill(fs))

    try:
        out = fs / "o"
        plan = tmp_path / "plan.toml"
        plan.write_text("[practice]\ntrials = 0\n")
        argv = ["experiment", "threshold", "-o", str(out), "--participant", "p1", "--frequencies", "40",
                "--trials", "3", "--afc", "2", "--plan", str(plan)]
        if moment == "done":
            real = Store.set_state
            monkeypatch.setattr(Store, "set_state",
                                lambda self, tok, state: (fill() if state == "done" else None,
                                                          real(self, tok, state))[1])
        if moment == "results":
            real_log = ecli._write_trial_log
            monkeypatch.setattr(ecli, "_write_trial_log", lambda *a: (fill(), real_log(*a))[1])
        th_, res, url = _run_main_in_thread(argv, capsys)
        c = PageClient(url)
        c.to_main()
        replies = []
        for i in range(3):
            if moment == "answer" and i == 2:
                fill()
            t = c.play()["trial"]
            replies.append(c.answer(t["index"], 1))
        th_.join(60)
        err = capsys.readouterr().err
        assert not th_.is_alive() and res["rc"] in (1, 2) and "Traceback" not in err
        said = [line for line in err.splitlines() if "--resume" in line and "space" in line.lower()]
        assert len(said) == 1, err
        if moment in ("answer", "done"):
            code, rep = replies[-1]
            assert code == 507 and "tell the experimenter" in rep["error"] and "/" not in rep["error"], rep
        else:
            assert replies[-1] == (200, {"ok": True})
        assert not (out / "thresholds.csv").exists()
        stored = len(Store(out / "session.sqlite").answers("p1"))
        assert stored == (2 if moment == "answer" else 3)
        # space returns: the same command, --resume
        for f in filled[0]:
            f.unlink()
        for f in fs.glob("tail*"):
            f.unlink()
        filled.append("freed")
        monkeypatch.undo()
        if moment == "answer":
            th_, res, url2 = _run_main_in_thread([*argv, "--resume"], capsys)
            assert url2 == url
            c = PageClient(url)
            c.open()
            t = c.play()["trial"]
            assert c.answer(t["index"], 2) == (200, {"ok": True})
            th_.join(60)
            assert res["rc"] == 0
        else:
            assert main([*argv, "--resume"]) == 0  # nothing left to answer: no page served
        st = Store(out / "session.sqlite")
        assert [a["trial"] for a in st.answers("p1")] == [0, 1, 2] and st.state("p1") == "done"
        assert th.load_csv(out / "thresholds.csv").freq_hz.size == 1
    finally:
        subprocess.run(["umount", "-l", str(fs)], capture_output=True)


def test_a_session_command_gives_the_callers_umask_back(tmp_path):
    """The session's files are 0600 (umask 077 while it runs); a script or a test that calls
    hostd.cli.main gets its own umask back (it leaked: later files of the caller were 0600)."""
    import os

    old = os.umask(0o022)
    try:
        assert main(["experiment", "threshold", "-o", str(tmp_path / "t"), "--participant", "u",
                     "--frequencies", "40", "--trials", "2", "--simulate", "weibull"]) == 0
        assert os.umask(0o022) == 0o022
        assert (tmp_path / "t" / "thresholds.csv").stat().st_mode & 0o077 == 0
    finally:
        os.umask(old)
