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
    from hostd.cliopts import needs_subcommand

    p.set_defaults(func=needs_subcommand(p, "an experiment"))

    session = argparse.ArgumentParser(add_help=False)
    g = session.add_argument_group("session")
    g.add_argument("--out", required=True, metavar="DIR", help="where the session store and results go")
    g.add_argument("--token", required=True, help="this session's token (one session per token)")
    g.add_argument("--resume", action="store_true", help="resume the session of --token where it stopped")
    g.add_argument("--port", type=int, default=0,
                   help="loopback port of the participant's page (0: any free)")
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


def _drive(sess, args, out: Path) -> bool:
    """Serve the page (or answer by simulation) until done or aborted; True when done."""
    if args.simulate:
        import numpy as np

        from hostd.experiment.observers import LogisticObserver, WeibullObserver
        from hostd.experiment.threshold import db

        rng = np.random.default_rng(12345)
        while not (st := sess.state())["done"]:
            if st.get("retry"):
                continue
            t = sess.current()
            if sess.kind == "threshold":
                centre = db(float(np.interp(t["frequency_hz"], sess.cfg.frequencies_hz, sess.cfg.prior_um)))
                kind = WeibullObserver if args.simulate == "weibull" else LogisticObserver
                obs = kind(centre, n_afc=t["n_afc"])
                ok = rng.random() < obs.p_correct(t["level_db"])
                sess.answer(t["index"], t["target"] if ok else t["target"] % t["n_afc"] + 1)
            else:
                v = 0.0 if t["method"] == "none" else 0.6 * t["Ip"] + 0.4 * t["Ia"]
                sess.answer(t["index"], int(np.clip(np.rint(v + rng.normal(0, 0.5)), 0, 3)))
        return True
    from hostd.experiment.server import ExperimentServer

    srv = ExperimentServer(sess, args.port).start()
    print(f"hostd experiment: the participant's page: {srv.url}", file=sys.stderr)
    print("hostd experiment: progress below; Ctrl-C aborts (resume later with --resume)", file=sys.stderr)
    last = None
    try:
        while True:
            p = sess.progress()
            state = sess.store.state(sess.token)
            line = f"{p['answered']}/{p['total']} answered{' (paused)' if sess.paused else ''}" \
                   f"{f', display lost {sess.display_lost}x' if sess.display_lost else ''}"
            if line != last:
                print(f"hostd experiment: {line}", file=sys.stderr)
                last = line
            if state in ("done", "aborted"):
                return state == "done"
            time.sleep(0.5)
    except KeyboardInterrupt:
        sess.abort()
        print(f"hostd experiment: aborted at {sess.answered()} answers; every answer is kept in "
              f"{out / 'session.sqlite'}: resume with --resume --token {sess.token}", file=sys.stderr)
        return False
    finally:
        srv.close()


def cmd_threshold(args) -> int:
    from hostd.extras import need

    need("questplus", "experiment", "hostd experiment threshold")
    from hostd.experiment.runner import ThresholdSession
    from hostd.experiment.session import Store
    from hostd.experiment.threshold import ThresholdConfig, thresholds_csv
    from hostd.perception import calibration
    from hostd.perception import thresholds as th

    out = Path(args.out)
    store = Store(out / "session.sqlite")
    display, _cfg = _display(args)
    if args.resume:
        plan = store.load(args.token, "threshold")
        cfg = ThresholdConfig(**plan["config"])
    else:
        prior = calibration.resolve_curve(args.prior)
        freqs = args.frequencies or [float(f) for f in th.default_curve().freq_hz]
        reach = [display.reach.reach_um(f) for f in freqs]  # (the daemon's: its config's bound)
        for f, r in zip(freqs, reach, strict=True):
            if not r > 0:
                raise ExperimentError(f"the display cannot play {f:g} Hz (its reach there is {r:.3g} µm): "
                                      "leave that frequency out (--frequencies)")
        cfg = ThresholdConfig(freqs, [float(prior(f)) for f in freqs], reach, n_afc=args.afc,
                              max_trials=args.trials, stop_width_db=args.stop_width_db, seed=args.seed,
                              procedure=args.procedure)
        from dataclasses import asdict

        store.create(args.token, "threshold", {"config": asdict(cfg), "prior": str(args.prior or "shipped")})
    sess = ThresholdSession(store, args.token, display, cfg)
    if args.resume:
        sess.resume()
    done = _drive(sess, args, out)
    _write_trial_log(sess, out / "trials.csv")
    if not done:
        return 1
    res = sess.run.results()
    prov = (f"session {args.token}, {cfg.n_afc}AFC, {cfg.procedure}, {sess.answered()} trials, "
            f"seed {cfg.seed}, "
            f"questplus {_version('questplus')}, {time.strftime('%Y-%m-%d %H:%M:%S %z')}")
    notes = sess.run.notes()  # the joint mode's check: did the curve fit?
    _write(out / "thresholds.csv", thresholds_csv(res, "\n".join([prov, *notes])))
    for note in notes:
        print(f"hostd experiment: {note}", file=sys.stderr)
    for r in res:
        flag = "" if r.status == "ok" else \
            f"  ABOVE THE DISPLAY'S REACH ({r.reach_um:.3g} µm): not in the curve"
        print(f"{r.frequency_hz:>7g} Hz  {r.threshold_um:.4g} µm  [{r.ci_low_um:.4g}, {r.ci_high_um:.4g}]  "
              f"{r.trials} trials{flag}")
    print(f"wrote {out / 'thresholds.csv'} and {out / 'trials.csv'}", file=sys.stderr)
    return 0


def _write_trial_log(sess, path: Path) -> None:
    rows = sess.store.answers(sess.token)
    with open(path, "w", newline="", encoding="utf-8") as fh:
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


def cmd_similarity(args) -> int:
    from hostd.experiment.runner import SimilaritySession, similarity_scores
    from hostd.experiment.session import Store
    from hostd.experiment.similarity import make_plan, read_design, scores_csv

    out = Path(args.out)
    store = Store(out / "session.sqlite")
    display, _cfg = _display(args)
    if args.resume:
        plan = store.load(args.token, "similarity")
    else:
        design = read_design(args.design)
        plan = make_plan(design, out, args.thresholds)
        store.create(args.token, "similarity", plan)
    sess = SimilaritySession(store, args.token, display, plan)
    if args.resume:
        sess.resume()
    done = _drive(sess, args, out)
    rows = similarity_scores(sess)
    with open(out / "answers.csv", "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(["trial", "texture", "method", "level", "rep", "grade", "answered_at"])
        for a in store.answers(args.token):
            s = a["stimulus"]
            w.writerow([a["trial"], s["texture"], s["method"], s["level"], s["rep"], a["answer"],
                        a["answered_at"]])
    if not done:
        return 1
    _write(out / "scores.csv", scores_csv(rows))
    print(f"wrote {out / 'scores.csv'} (hostd fit reads it) and {out / 'answers.csv'}", file=sys.stderr)
    return 0


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
    named = th.ThresholdCurve(curve.freq_hz, curve.threshold_um, name=name)
    cal = calibration.Calibration(named, a, b, name, prov)
    calibration.write(args.output, cal)
    print(f"{args.output}: calibration {cal.label}: {curve.freq_hz.size} thresholds, "
          f"a = {a:.4g}, b = {b:.4g}")
    return 0


def _write(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(path)


def _version(mod: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(mod)
    except PackageNotFoundError:
        return "?"
