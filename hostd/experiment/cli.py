"""`hostd experiment threshold|similarity|calibration|bench` (docs/experiments.md)."""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from pathlib import Path

from hostd.errors import ExperimentError


def _freqs(v: str) -> list[float]:
    try:
        out = [float(x) for x in v.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{v!r}: frequencies in Hz, comma-separated") from None
    if not out or any(not f > 0 for f in out) or len(set(out)) != len(out):
        raise argparse.ArgumentTypeError(f"{v!r}: distinct frequencies > 0 Hz, comma-separated")
    return out


def add_parser(sub, parents=()) -> None:
    p = sub.add_parser("experiment", help="calibrate Iobj on your display: thresholds, similarity test")
    esub = p.add_subparsers(dest="experiment", metavar="EXPERIMENT")
    from hostd.cliopts import needs_subcommand, renamed

    p.set_defaults(func=needs_subcommand(p, "an experiment"))

    session = argparse.ArgumentParser(add_help=False)
    g = session.add_argument_group("session")
    g.add_argument("-o", "--output", dest="out", required=True, metavar="DIR",
                   help="where the session store and results go (made 0700; its files 0600)")
    renamed(g, "--output", "--out")
    g.add_argument("--participant", default=None, metavar="ID",
                   help="the participant's id: names the session in the store (one session per id); not in "
                   "the page's address. Default: session-N")
    g.add_argument("--token", dest="participant_token", default=None, metavar="ID",
                   help="deprecated: the same as --participant (a label that grants nothing; the page's "
                   "address carries a secret hostd makes)")
    g.add_argument("--resume", action="store_true",
                   help="resume the session of --participant (default: the store's one unfinished session)")
    g.add_argument("--port", type=int, default=None,
                   help="loopback port of the participant's page (default: any free one; --resume: the "
                   "session's own, so an open page goes on)")
    g.add_argument("--plan", default=None, metavar="TOML",
                   help="the session plan: instructions, consent, practice, breaks, blocks, end page "
                   "(default: the plan shipped with hostd, experiment-plan.toml among its data files)")
    g.add_argument("--display", default="sim", metavar="sim|daemon",
                   help="sim: the simulated display (default); daemon: the running hostd's display (for "
                   "thresholds its config needs [experiment] stimuli = true)")
    g.add_argument("--socket", default=None, metavar="PATH",
                   help="--display daemon: hostd's control socket (default: $HOSTD_SOCKET, else "
                   "control.socket of --config)")
    g.add_argument("--config", default=None, help="hostd config (output limits, actuator, control socket)")
    g.add_argument("--simulate", choices=["weibull", "logistic", "linear"], default=None,
                   help="answer with a simulated observer instead of the page (a dry run)")

    t = esub.add_parser("threshold", parents=[session], help="detection thresholds (QUEST+, n-AFC)")
    t.add_argument("--frequencies", type=_freqs, default=None, metavar="HZ,...",
                   help="default: those of the shipped b(f) table (hostd's default thresholds)")
    t.add_argument("--prior", default=None, metavar="CSV",
                   help="the prior's centre per frequency (default: the shipped b(f))")
    t.add_argument("--afc", type=int, choices=[2, 3], default=3,
                   help="intervals per trial (default 3: within ±2 dB in 30 trials more often than 2)")
    t.add_argument("--trials", type=int, default=None,
                   help="trial budget per frequency (default: per-frequency, stop on the 95%% interval's "
                   "width within 60; joint, 15: the total is this x the frequencies, as much again on "
                   "a misfit)")
    from hostd.experiment.procedure import PROCEDURES

    t.add_argument("--procedure", choices=list(PROCEDURES), default="per-frequency",
                   help="per-frequency: one QUEST+ per frequency, interleaved (default); joint: the whole "
                   "curve at once (prior curve + offset, tilt, curvature over log f)")
    t.add_argument("--joint", dest="procedure", action="store_const", const="joint",
                   help="the same as --procedure joint")
    t.add_argument("--stop-width-db", type=float, default=None,
                   help="stop a frequency once its 95%% interval is this narrow, dB (default without "
                   "--trials: 2AFC 5.25, 3AFC 4.5; with --trials: 0, the budget only)")
    t.add_argument("--min-trials", type=int, default=None,
                   help="trials per frequency before the width can stop it (default: 2AFC 12, 3AFC 40)")
    t.add_argument("--seed", type=int, default=0)
    t.set_defaults(func=cmd_threshold)

    s = esub.add_parser("similarity", parents=[session],
                        help="the paper's similarity test from a design file")
    s.add_argument("design", help="design TOML: textures x methods x settings x repetitions")
    s.add_argument("--thresholds", default=None, metavar="CSV",
                   help="the curve the stimuli are encoded with (a thresholds CSV or a calibration)")
    s.set_defaults(func=cmd_similarity)

    c = esub.add_parser("calibration", help="write a calibration file: thresholds + (a, b) + provenance")
    c.add_argument("-o", "--output", required=True, help="the calibration file (.toml)")
    c.add_argument("--thresholds", required=True, metavar="CSV", help="thresholds CSV (experiment threshold)")
    c.add_argument("--fit", metavar="JSON", help="`hostd fit --json` output giving a and b")
    c.add_argument("--a", type=float, default=None)
    c.add_argument("--b", type=float, default=None)
    c.add_argument("--name", default=None, help="one word (default: the file's stem)")
    c.add_argument("--note", default="", help="free text for the provenance (display, participants, ...)")
    c.add_argument("--json", action="store_true", help="the calibration written (file, label, a, b) as JSON")
    c.set_defaults(func=cmd_calibration)

    from hostd.experiment.bench import add_parser as add_bench

    add_bench(esub)


def _display(args):
    from hostd.experiment.display import DaemonDisplay, Reach, SimDisplay
    from hostd.service.config import load

    cfg = load(args.config)
    if args.display == "sim":
        return SimDisplay(Reach(cfg.render_config()), realtime=args.simulate is None), cfg
    if args.display == "daemon":
        import os

        return DaemonDisplay(args.socket or os.environ.get("HOSTD_SOCKET") or cfg.control.socket), cfg
    raise ExperimentError(f"--display {args.display}: sim or daemon")


def _private_files(cmd):
    """Run a session command with umask 077, so that every file it writes (results, streams,
    SQLite's -wal/-shm) is 0600, and give the caller's umask back after it (the command may run
    inside another program: hostd.cli.main called by a script or a test)."""
    import functools
    import os

    @functools.wraps(cmd)
    def run(args) -> int:
        old = os.umask(0o077)
        try:
            return cmd(args)
        finally:
            os.umask(old)

    return run


def _open_session(args, out: Path, kind: str, make_plan):
    """The store (the folder made 0700, files 0600), the session's label and its plan: a new
    session (make_plan() -> plan) or, with --resume, the stored one."""

    from hostd.experiment.session import Store

    if args.participant_token:
        print("hostd experiment: --token is deprecated: it is now only the session's label, the same as "
              "--participant (the page's address carries a secret hostd makes)", file=sys.stderr)
    label = args.participant or args.participant_token
    store = Store(out / "session.sqlite")
    if args.resume:
        if label is None:
            open_ = [t for t, k, st in store.sessions() if k == kind and st not in ("done", "declined")]
            if len(open_) != 1:
                raise ExperimentError(f"{len(open_)} unfinished {kind} sessions in {out / 'session.sqlite'} "
                                      f"({', '.join(open_) or 'none'}): name one with --participant")
            label = open_[0]
        return store, label, store.load(label, kind)
    if label is None:
        label = f"session-{len(store.sessions()) + 1}"
    plan = make_plan()
    store.create(label, kind, plan)
    return store, label, plan


def _simulated(store, label: str) -> str | None:
    """The simulated observer's kind if any answer of the session was simulated."""
    kinds = [e["detail"] for e in store.events(label) if e["kind"] == "simulated"]
    return ", ".join(dict.fromkeys(kinds)) if kinds else None


def _sim_mark(simulated: str | None) -> str:
    """The first line of every file a simulated session writes."""
    if not simulated:
        return ""
    return f"# SIMULATED: answered by a simulated {simulated} observer (--simulate), not a participant\n"


def _drive(sess, args, out: Path) -> str:
    """Serve the page (or answer by simulation) until the session ends: done, declined, aborted
    (Ctrl-C) or failed (the store could not take a write: one line here, a plain message on the page)."""
    from hostd.experiment.runner import run_simulated

    if sess.phase == "end":  # every answer was in (a resumed session whose done mark failed)
        return "done"
    if args.simulate:
        sess.store.event(sess.token, "simulated", args.simulate)
        sess.steps = {**sess.steps, "practice": {**sess.steps["practice"], "trials": 0}}  # (for people)
        run_simulated(sess, _observer(sess, args.simulate))
    else:
        _serve(sess, args, out)
    if sess.failure is not None:
        print(f"hostd experiment: stopped: {sess.failure_detail}", file=sys.stderr)
        return "failed"
    if sess.phase == "declined":
        print("hostd experiment: the participant declined: the session ended, only the decline is recorded",
              file=sys.stderr)
        return "declined"
    return "done" if sess.phase == "end" else "aborted"


def _observer(sess, kind: str):
    import numpy as np

    from hostd.experiment.observers import LogisticObserver, WeibullObserver
    from hostd.experiment.threshold import db

    rng = np.random.default_rng(12345)

    def choose(t: dict) -> int:
        if sess.kind == "threshold":
            centre = db(float(np.interp(t["frequency_hz"], sess.cfg.frequencies_hz, sess.cfg.prior_um)))
            obs = (WeibullObserver if kind == "weibull" else LogisticObserver)(centre, n_afc=t["n_afc"])
            ok = rng.random() < obs.p_correct(t["level_db"])
            return t["target"] if ok else t["target"] % t["n_afc"] + 1
        v = 0.0 if t["method"] == "none" else 0.6 * t["Ip"] + 0.4 * t["Ia"]
        return int(np.clip(np.rint(v + rng.normal(0, 0.5)), 0, 3))

    return choose


def _serve(sess, args, out: Path) -> None:
    from hostd.experiment.server import ExperimentServer, new_capability

    store = sess.store
    access = store.access(sess.token)
    if access is None:
        import secrets

        access = {"capability": new_capability(), "csrf_key": secrets.token_bytes(32), "port": 0}
    port = args.port if args.port is not None else access["port"]
    srv = ExperimentServer(sess, port, access["capability"], access["csrf_key"],
                           report=lambda line: print(f"hostd experiment: {line}", file=sys.stderr))
    store.set_access(sess.token, access["capability"], access["csrf_key"], srv.port)
    srv.start()
    print(srv.url, flush=True)  # the participant's address: here only (stdout), never in a log
    print(f"hostd experiment: session {sess.token}: open the address above (stdout) in the participant's "
          f"browser on this computer; progress below; Ctrl-C aborts (resume later with --resume)",
          file=sys.stderr)
    last = None
    try:
        while True:
            p = sess.progress()
            line = f"{p['answered']}/{p['total']} answered, {sess.phase}" \
                   f"{' (paused)' if sess.paused else ''}" \
                   f"{f', display lost {sess.display_lost}x' if sess.display_lost else ''}"
            if line != last:
                print(f"hostd experiment: {line}", file=sys.stderr)
                last = line
            if sess.finished() or store.state(sess.token) == "aborted":
                time.sleep(1.0)  # the page fetches its last state
                return
            time.sleep(0.2)
    except KeyboardInterrupt:
        sess.abort()
        print(f"hostd experiment: aborted at {sess.answered()} answers; every answer is kept in "
              f"{out / 'session.sqlite'}: resume with --resume --participant {sess.token}", file=sys.stderr)
    finally:
        srv.close()


def _finish_logs(write) -> None:
    """The logs beside the results after a session that stopped: best effort (the disk may be full)."""
    try:
        write()
    except OSError:
        pass


@_private_files
def cmd_threshold(args) -> int:
    from hostd.extras import need

    need("questplus", "experiment", "hostd experiment threshold")
    from hostd.experiment.plan import read_plan
    from hostd.experiment.runner import ThresholdSession
    from hostd.experiment.threshold import ThresholdConfig, thresholds_csv
    from hostd.perception import calibration
    from hostd.perception import thresholds as th

    out = Path(args.out)
    display, _cfg = _display(args)
    steps = read_plan(args.plan)

    def make_plan() -> dict:
        prior = calibration.resolve_curve(args.prior)
        freqs = args.frequencies or [float(f) for f in th.default_curve().freq_hz]
        reach = [display.reach.reach_um(f) for f in freqs]  # (the daemon's: its config's bound)
        for f, r in zip(freqs, reach, strict=True):
            if not r > 0:
                raise ExperimentError(f"the display cannot play {f:g} Hz (its reach there is {r:.3g} µm): "
                                      "leave that frequency out (--frequencies)")
        cfg = ThresholdConfig(freqs, [float(prior(f)) for f in freqs], reach, n_afc=args.afc,
                              max_trials=args.trials, stop_width_db=args.stop_width_db, seed=args.seed,
                              procedure=args.procedure, min_trials=args.min_trials)
        from dataclasses import asdict

        return {"config": asdict(cfg), "prior": str(args.prior or "shipped"), "steps": steps}

    store, label, plan = _open_session(args, out, "threshold", make_plan)
    cfg = ThresholdConfig.stored(plan["config"])
    sess = ThresholdSession(store, label, display, cfg, plan.get("steps", steps))
    if args.resume:
        sess.resume()
    status = _drive(sess, args, out)
    sim = _simulated(store, label)
    if status != "done":
        _finish_logs(lambda: _write_trial_log(sess, out / "trials.csv", sim))
        return 0 if status == "declined" else 1
    _results(out / "trials.csv", lambda: _write_trial_log(sess, out / "trials.csv", sim), store)
    res = sess.run.results()
    prov = (f"session {label}, {cfg.n_afc}AFC, {cfg.procedure}, {sess.answered()} trials, "
            f"seed {cfg.seed}, "
            f"questplus {_version('questplus')}, {time.strftime('%Y-%m-%d %H:%M:%S %z')}")
    if sim:
        prov = _sim_mark(sim)[2:] + prov
    notes = sess.run.notes()  # the joint mode's check: did the curve fit?
    text = thresholds_csv(res, "\n".join([prov, *notes]))
    _results(out / "thresholds.csv", lambda: _write(out / "thresholds.csv", text), store)
    for note in notes:
        print(f"hostd experiment: {note}", file=sys.stderr)
    for r in res:
        flag = "" if r.status == "ok" else \
            f"  ABOVE THE DISPLAY'S REACH ({r.reach_um:.3g} µm): not in the curve"
        print(f"{r.frequency_hz:>7g} Hz  {r.threshold_um:.4g} µm  [{r.ci_low_um:.4g}, {r.ci_high_um:.4g}]  "
              f"{r.trials} trials{flag}")
    print(f"wrote {out / 'thresholds.csv'} and {out / 'trials.csv'}{' (SIMULATED)' if sim else ''}",
          file=sys.stderr)
    return 0


def _results(path: Path, write, store) -> None:
    """Write one result file; a disk that cannot take it is one line (the answers are in the store)."""
    try:
        write()
    except OSError as e:
        raise ExperimentError(f"cannot write {path}: {e.strerror or e}. Every answer is kept in "
                              f"{store.path}: free space, then run the same command with --resume") from None


def _write_trial_log(sess, path: Path, simulated: str | None = None) -> None:
    rows = sess.store.answers(sess.token)
    with open(path, "w", newline="", encoding="utf-8") as fh:
        if simulated:
            fh.write(_sim_mark(simulated))
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(["trial", "frequency_hz", "amplitude_um", "level_db", "target", "answer", "correct",
                    "presented_at", "answered_at"])
        for a in rows:
            s = a["stimulus"]
            w.writerow([a["trial"], s["frequency_hz"], f"{s['amplitude_um']:.6g}", f"{s['level_db']:.3f}",
                        s["target"], a["answer"], int(a["answer"] == s["target"]), a["presented_at"],
                        a["answered_at"]])
        for e in sess.store.events(sess.token):
            fh.write(f"# event {e['at']:.3f} {e['kind']} {e['detail']}\n")


@_private_files
def cmd_similarity(args) -> int:
    from hostd.experiment.plan import read_plan
    from hostd.experiment.runner import SimilaritySession, similarity_scores
    from hostd.experiment.similarity import make_plan, read_design, scores_csv

    if args.simulate not in (None, "linear"):
        raise ExperimentError(f"similarity --simulate {args.simulate}: a grading observer is linear (grades "
                              "from Ip and Ia); weibull and logistic are detection observers (threshold)")
    out = Path(args.out)
    display, _cfg = _display(args)
    steps = read_plan(args.plan)
    store, label, plan = _open_session(args, out, "similarity", lambda: {
        **make_plan(read_design(args.design), out, args.thresholds), "steps": steps})
    sess = SimilaritySession(store, label, display, plan, plan.get("steps", steps))
    if args.resume:
        sess.resume()
    status = _drive(sess, args, out)
    sim = _simulated(store, label)
    mark = _sim_mark(sim)

    def answers_csv() -> None:
        with open(out / "answers.csv", "w", newline="", encoding="utf-8") as fh:
            fh.write(mark)
            w = csv.writer(fh, lineterminator="\n")
            w.writerow(["trial", "texture", "method", "level", "rep", "grade", "answered_at"])
            for a in store.answers(label):
                s = a["stimulus"]
                w.writerow([a["trial"], s["texture"], s["method"], s["level"], s["rep"], a["answer"],
                            a["answered_at"]])

    if status != "done":
        _finish_logs(answers_csv)
        return 0 if status == "declined" else 1
    _results(out / "answers.csv", answers_csv, store)
    rows = similarity_scores(sess)
    _results(out / "scores.csv", lambda: _write(out / "scores.csv", mark + scores_csv(rows)), store)
    print(f"wrote {out / 'scores.csv'} (hostd fit reads it) and {out / 'answers.csv'}"
          f"{' (SIMULATED)' if sim else ''}", file=sys.stderr)
    return 0


def _says_simulated(path: str) -> bool:
    """A file --simulate wrote (its comment lines say SIMULATED; a fit's JSON, its source's)."""
    try:
        text = Path(path).read_text(encoding="utf-8", errors="replace")
    except OSError:
        return False
    if any(line.startswith("# SIMULATED") for line in text.splitlines()):
        return True
    try:
        src = json.loads(text).get("scores") or json.loads(text).get("path")
    except (ValueError, AttributeError):
        return False
    return isinstance(src, str) and src != path and Path(src).is_file() and _says_simulated(src)


def cmd_calibration(args) -> int:
    from hostd.perception import calibration
    from hostd.perception import thresholds as th

    curve = calibration.load_curve(args.thresholds)
    if args.fit:
        try:
            fit = json.loads(Path(args.fit).read_text())
            a, b = float(fit["a"]), float(fit["b"])
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise ExperimentError(f"--fit {args.fit}: not `hostd fit --json` output ({e})") from None
    elif args.a is not None and args.b is not None:
        a, b = args.a, args.b
    else:
        raise ExperimentError("give --fit FIT.json (hostd fit --json) or both --a and --b")
    name = args.name or Path(args.output).stem
    prov = {"thresholds": f"{args.thresholds} ({curve.curve_id})",
            "weights": f"{args.fit}" if args.fit else "given by hand (--a, --b)",
            "created": time.strftime("%Y-%m-%d %H:%M:%S %z")}
    if args.note:
        prov["note"] = args.note
    sims = [f for f in (args.thresholds, args.fit) if f and _says_simulated(f)]
    if sims:
        prov["simulated"] = f"yes: {', '.join(sims)} came from a simulated observer (--simulate)"
        print(f"hostd experiment calibration: {', '.join(sims)} came from --simulate: the calibration "
              "says so", file=sys.stderr)
    named = th.ThresholdCurve(curve.freq_hz, curve.threshold_um, name=name)
    cal = calibration.Calibration(named, a, b, name, prov)
    calibration.write(args.output, cal)
    if args.json:
        print(json.dumps({"file": str(args.output), "label": cal.label, "thresholds": int(curve.freq_hz.size),
                          "a": a, "b": b}))
        return 0
    print(f"{args.output}: calibration {cal.label}: {curve.freq_hz.size} thresholds, "
          f"a = {a:.4g}, b = {b:.4g}")
    return 0


def _write(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text(text, encoding="utf-8")
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)


def _version(mod: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(mod)
    except PackageNotFoundError:
        return "?"
