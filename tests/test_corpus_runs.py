"""hostd corpus: runs that cannot hang, leak or fail silently. A job past --timeout ends as a
`timeout` row whatever it does (its worker is killed and replaced); the local pool dies with its
driver; the API works in a plain script; failed jobs make a non-zero exit; rows of lost workers
run again next time."""

from __future__ import annotations

import json
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hostd.procstat import descendants

ROOT = Path(__file__).resolve().parent.parent
FIX = "tests.corpus_codec_fixture"


def _env(**extra) -> dict:
    return {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""), **extra}


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state != "Z"


def test_a_job_that_no_signal_reaches_ends_as_a_timeout_row_and_the_run_goes_on(tmp_path):
    """A codec that blocks SIGALRM and waits in C (the in-process time limit never fires): the
    driver kills its worker after the limit, writes the `timeout` row, and every other job of the
    run (in the same task, and in the task the other worker lost with the pool) gets its row."""
    db = tmp_path / "r.sqlite"
    sweep = tmp_path / "s.toml"
    sweep.write_text(f'[codec."{FIX}:Misbehaving"]\nsettings = [' + ", ".join(
        f'{{step_um = {s}, fault = "{f}"}}' for s, f in ((1.0, "none"), (0.5, "deaf"), (0.25, "none"),
                                                          (2.0, "none"))) + "]\n")
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-m", "hostd", "corpus", "run", "synthetic:wood:1-2", "--codec",
                        f"{FIX}:Misbehaving", "--sweep", str(sweep), "--length-mm", "2", "--no-spqi",
                        "--workers", "2", "--timeout", "1", "--no-progress", "-o", str(db), "--json"],
                       capture_output=True, text=True, env=_env(), cwd=ROOT, timeout=120)
    took = time.monotonic() - t0
    assert r.returncode == 1 and "2 of 8 jobs failed" in r.stderr, r.stderr
    summ = json.loads(r.stdout)
    assert summ["written"] == 8 and summ["ok"] == 6 and summ["failed_by_reason"] == {"timeout": 2}
    c = sqlite3.connect(db)
    rows = list(c.execute("SELECT setting, error_reason, error, curve FROM results"))
    c.close()
    bad = [x for x in rows if x[1] is not None]
    assert len(bad) == 2 and all('"deaf"' in x[0] and x[1] == "timeout" and "killed" in x[2]
                                 and x[3] == "misbehaving" for x in bad)
    assert took < 60, took


@pytest.mark.parametrize("where", [["--workers", "2"], ["--dask", "local", "--workers", "2"]],
                         ids=["local-pool", "dask-local"])
def test_sigkill_of_the_driver_leaves_no_process_of_its_pool(tmp_path, where):
    """The local pool's fork server, resource tracker and workers (they outlived a SIGKILLed
    driver by 27 min), and a --dask local cluster's worker processes (Dask's own parent watch)."""
    if "--dask" in where:
        pytest.importorskip("distributed")
        pytest.importorskip("cryptography")
    gate = tmp_path / "gate"
    gate.mkdir()  # never opened: one encode passes (the run is going), the rest wait
    p = subprocess.Popen([sys.executable, "-m", "hostd", "corpus", "run", "synthetic:wood:1-3", "--codec",
                          f"{FIX}:Gated", "--length-mm", "2", "--no-spqi", *where, "--no-progress",
                          "-o", str(tmp_path / "r.sqlite")], env=_env(HOSTD_TEST_GATE=f"{gate}:1"), cwd=ROOT,
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        deadline = time.monotonic() + 90
        tree: set[int] = set()
        while time.monotonic() < deadline and (len(tree) < 4 or not (gate / "pass-0").exists()):
            time.sleep(0.1)  # workers and their helpers started, a job has run
            tree = descendants(p.pid)
        assert len(tree) >= 4 and (gate / "pass-0").exists(), tree
        time.sleep(0.5)
        tree = descendants(p.pid) - {p.pid}
        os.kill(p.pid, signal.SIGKILL)
        p.wait()
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and any(_alive(q) for q in tree):
            time.sleep(0.05)
        left = sorted(q for q in tree if _alive(q))
    finally:
        try:
            os.killpg(p.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    assert not left, [Path(f"/proc/{q}/cmdline").read_bytes()[:80] for q in left if _alive(q)]


def test_the_api_works_in_a_plain_script(tmp_path):
    """The docs' lines saved as a script without `if __name__ == "__main__":` (every job was
    `worker_lost`, exit 0, and the failed rows kept the corrected script from running them)."""
    script = tmp_path / "plain.py"
    script.write_text(
        "from hostd import api\n"
        f"df = api.run_corpus('synthetic:wood:1-2', {str(tmp_path / 'r.sqlite')!r},\n"
        f"                    codecs=['{FIX}:uniform'],\n"
        "                    length_mm=2.0, spqi=False, workers=2, progress=False)\n"
        "print('summary', df.attrs['summary']['ok'], df.attrs['summary']['failed'])\n")
    r = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=_env(),
                       cwd=tmp_path, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip().splitlines() == ["summary 10 0"], r.stdout
    assert "Traceback" not in r.stderr


def test_rows_of_lost_workers_run_again_on_the_next_run(tmp_path):
    from hostd.corpus import jobs
    from hostd.corpus import run as crun
    from hostd.texture.load import LoadOptions

    tex = crun.textures_from(["synthetic:wood:1"], LoadOptions(length_mm=2.0))
    plan = crun.make_plan([f"{FIX}:uniform"])
    db = tmp_path / "r.sqlite"
    sc = jobs.Scoring(spqi=False)

    def lose(task):
        return [{**jobs.empty_row(task.texture, j), "error": "lost", "error_reason": "worker_lost"}
                for j in task.jobs]

    first = crun.run(tex, plan, db, workers=1, scoring=sc, task_fn=lose)
    assert first.failed == {"worker_lost": 5}
    again = crun.run(tex, plan, db, workers=1, scoring=sc)
    assert again.skipped == 0 and again.written == again.ok == 5
    c = sqlite3.connect(db)
    assert c.execute("SELECT COUNT(*), COUNT(error) FROM results").fetchone() == (5, 0)
    c.close()
