"""`hostd experiment bench`: the procedures' statistics on simulated observers and participants
with a known truth (docs/experiments.md, "How many trials and minutes"), and `--check`, the
goals they must keep (.ci/run). Every figure comes from the procedures' own code run on a batch
of seeded runs at once (threshold.ThresholdGrid, joint.JointBatch, fit.design_coverage)."""

from __future__ import annotations

import json
import sys
import time


def _sds(v: str) -> list[float]:
    import argparse

    try:
        out = [float(x) for x in v.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{v!r}: SDs in dB, comma-separated") from None
    if not out or any(not x >= 0 for x in out):
        raise argparse.ArgumentTypeError(f"{v!r}: SDs in dB >= 0, comma-separated")
    return out


def add_parser(esub) -> None:
    b = esub.add_parser("bench", help="simulated observers and participants: the procedures' statistics")
    b.add_argument("--runs", type=int, default=400,
                   help="seeded runs per per-frequency case (default 400)")
    b.add_argument("--trials", type=int, default=30,
                   help="the fixed budget per frequency compared with the default stop (default 30)")
    b.add_argument("--fit-sims", type=int, default=50)
    b.add_argument("--seed", type=int, default=2026,
                   help="the runs' seed (default 2026, the docs' figures; another gives independent runs)")
    b.add_argument("--oracle", action="store_true",
                   help="also the same runs answered to a grid Bayes that knows each observer's psychometric "
                   "function and has only its threshold to find: what the trials can carry at best")
    b.add_argument("--joint-runs", type=int, default=0, metavar="N",
                   help="also N seeded runs per case of --procedure joint over the shipped b(f)'s "
                   "frequencies (default 0: none; about 0.5 s CPU a run)")
    b.add_argument("--joint-wiggle-db", type=_sds, default=[0.0, 2.0], metavar="SD,...",
                   help="joint runs: each frequency's true threshold also deviates from a smooth curve by a "
                   "normal deviate of this SD, a case per SD (default 0,2: the model's form, and bumps)")
    b.add_argument("--joint-afc", type=int, choices=[2, 3], default=None,
                   help="joint runs: only this n-AFC (default both)")
    b.add_argument("--joint-trials", type=int, default=None,
                   help="joint runs' budget per frequency (default: the procedure's, 15)")
    b.add_argument("--check", action="store_true",
                   help="the goals, on the default seed: a line per goal missed, exit 1 (.ci/run)")
    b.add_argument("--json", action="store_true")
    b.set_defaults(func=cmd_bench)


def _rates(e, covered=None, trials=None) -> dict:
    import numpy as np

    r = {"within_2db": float(np.mean(np.abs(e) <= 2.0)), "bias_db": float(np.mean(e)),
         "p90_abs_err_db": float(np.percentile(np.abs(e), 90))}
    if covered is not None:
        r["ci95_covers"] = float(np.mean(covered))
    if trials is not None:
        r["median_trials"] = float(np.median(trials))
        r["max_trials"] = int(np.max(trials))
    return r


def per_frequency(runs: int, seed: int, trials: int) -> dict:
    """Every observer shape x 2/3-AFC: a fixed budget of `trials`, and the default stop."""
    from hostd.experiment import threshold as thr
    from hostd.experiment.observers import SHAPES, simulate_threshold_runs

    out = {}
    for kind in SHAPES:
        for n in (2, 3):
            t0 = time.process_time()
            f = simulate_threshold_runs(kind, n, runs, trials, seed=seed)
            d = simulate_threshold_runs(kind, n, runs, thr.MAX_TRIALS, seed=seed,
                                        stop_width_db=thr.STOP_WIDTH_DB[n])
            out[f"{n}AFC {kind}"] = {
                "fixed": _rates(f["errors_db"], f["covered"], f["trials"]),
                "default_stop": _rates(d["errors_db"], d["covered"], d["trials"]),
                "stop_width_db": thr.STOP_WIDTH_DB[n], "min_trials": thr.MIN_TRIALS_WIDTH[n],
                "cpu_s": time.process_time() - t0}
    return out


def oracle(runs: int, seed: int, trials: int) -> dict:
    import numpy as np

    from hostd.experiment import threshold as thr
    from hostd.experiment.observers import SHAPES, simulate_oracle

    out = {}
    for kind in SHAPES:
        for n in (2, 3):
            for t in sorted({trials, thr.MAX_TRIALS}):
                e = simulate_oracle(kind, n, runs, t, seed=seed)
                out[f"{n}AFC {kind}, {t} trials"] = {"within_2db": float(np.mean(np.abs(e) <= 2.0))}
    return out


def joint(runs: int, seed: int, sds: list[float], afc: int | None, trials: int | None) -> dict:
    import numpy as np

    from hostd.experiment.joint import simulate_joint
    from hostd.experiment.threshold import JOINT_TRIALS

    out = {}
    for sd in sds:
        for kind in ("weibull", "logistic"):
            for n in ((afc,) if afc else (2, 3)):
                t0 = time.process_time()
                r = simulate_joint(kind, n, runs, trials or JOINT_TRIALS, seed=seed, wiggle_db=sd)
                e, cov, mis = r["errors_db"], r["covered"], r["spent_more"]
                within = np.abs(e) <= 2.0
                d = _rates(e, cov, r["trials"])
                d.update({"worst_frequency_within_2db": float(np.min(np.mean(within, axis=0))),
                          "worst_frequency_ci95_covers": float(np.min(np.mean(cov, axis=0))),
                          "misfit_found": float(np.mean(mis)), "frequencies": r["frequencies"],
                          "ci95_covers_when_fit": float(np.mean(cov[~mis])) if (~mis).any() else None,
                          "ci95_covers_when_misfit": float(np.mean(cov[mis])) if mis.any() else None,
                          "cpu_s_per_run": (time.process_time() - t0) / runs})
                out[f"{n}AFC {kind}, bumps SD {sd:g} dB"] = d
    return out


def fit_figures(sims: int) -> dict:
    """hostd fit's intervals: per grade noise on the wood design, per plan size, and per design
    the coverage the simulation finds beside the coverage hostd fit estimates from one lab."""
    import numpy as np

    from hostd.experiment.observers import simulate_fit, wood_design
    from hostd.perception import fit

    out = {"noise": [simulate_fit(0.581, 0.464, sd, n_sims=sims) for sd in (0.3, 0.5, 0.8)],
           "plan": [simulate_fit(0.581, 0.464, 0.5, n_sims=sims, participants=p) for p in (2, 4, 8, 16, 32)]}
    designs = {"wood, 13 stimuli": wood_design(0)}
    ip0, ia0 = wood_design(0)
    ip1, ia1 = wood_design(1)
    designs["two textures, 26 stimuli"] = (np.r_[ip0, ip1], np.r_[ia0, ia1])
    designs["two textures, 26 stimuli, half the indices"] = (np.r_[ip0, ip1] / 2, np.r_[ia0, ia1] / 2)
    out["design"] = []
    for name, (ip, ia) in designs.items():
        for noise in (0.15, 0.3, 0.5):
            true = fit.design_coverage(ip, ia, 0.581, 0.464, noise, 32, sims=sims)
            est = []  # what hostd fit says of the design from each of 8 labs' own scores
            for lab in range(8):
                rng = np.random.default_rng([7, lab])
                g = np.rint(0.581 * ip + 0.464 * ia + rng.normal(0, noise, (32, ip.size)))
                y = np.clip(g, 0, 3).mean(axis=0)
                st = [fit.Stimulus("t", "m", str(k), float(y[k]), float(ip[k]), float(ia[k]), n=32)
                      for k in range(ip.size)]
                r = fit.fit(st, scale_min=0.0, scale_max=3.0, n_boot=1000, design_sims=100)
                if r.design and r.design.get("sims"):
                    est.append(r.design["coverage_both"])
            out["design"].append({"design": name, "noise_sd": noise, "coverage_both": true["coverage_both"],
                                  "bias_a": true["bias_a"], "bias_b": true["bias_b"],
                                  "hostd_fit_estimate_median": float(np.median(est)) if est else None,
                                  "hostd_fit_warned": float(np.mean(np.array(est) < fit.COVERAGE_WARN))
                                  if est else None})
    return out


CHECK_RUNS = 400  # per-frequency runs per case: 200 pin a rate of 90 % to ±2 points only
CHECK_JOINT_RUNS = 40


def check(seed: int) -> list[str]:
    """The goals (docs/experiments.md): a line per goal missed."""
    import numpy as np

    from hostd.experiment import threshold as thr
    from hostd.experiment.joint import simulate_joint
    from hostd.experiment.observers import simulate_threshold_runs, wood_design
    from hostd.perception import fit
    from hostd.perception import thresholds as th

    bad = []
    for kind in ("weibull", "logistic"):
        for n in (2, 3):
            d = simulate_threshold_runs(kind, n, CHECK_RUNS, thr.MAX_TRIALS, seed=seed,
                                        stop_width_db=thr.STOP_WIDTH_DB[n])
            r = _rates(d["errors_db"], d["covered"], d["trials"])
            if (r["within_2db"] < 0.9 or r["ci95_covers"] < 0.9 or r["median_trials"] > 40
                    or r["max_trials"] > 60):
                bad.append(f"per-frequency {n}AFC {kind}: {r} (want >= 90 % within ±2 dB and covered, "
                           "median <= 40 and max <= 60 trials)")
    # β = 2, below the goal of 90 %: 2AFC out of reach (an oracle reaches 89.5 % in 60 trials);
    # 3AFC 92.0 % on this seed but 89.5 % on 1000 runs, so its floor is what holds beyond a seed
    floors = {2: 0.76, 3: 0.88}
    covers = {2: 0.88, 3: 0.90}  # 2AFC: 90.0 % on this seed
    for n, floor in floors.items():
        d = simulate_threshold_runs("weibull-beta2", n, CHECK_RUNS, thr.MAX_TRIALS, seed=seed,
                                    stop_width_db=thr.STOP_WIDTH_DB[n])
        w, c = float(np.mean(np.abs(d["errors_db"]) <= 2)), float(np.mean(d["covered"]))
        m = float(np.median(d["trials"]))
        if w < floor or c < covers[n] or (n == 3 and m > 40):
            bad.append(f"per-frequency {n}AFC Weibull β = 2: {w:.1%} within ±2 dB (documented >= "
                       f"{floor:.0%}), 95 % intervals cover {c:.1%} (documented >= {covers[n]:.0%}), "
                       f"median {m:g} trials (3AFC: want <= 40)")
    curve = th.default_curve()
    cfg = thr.ThresholdConfig([float(f) for f in curve.freq_hz], [float(v) for v in curve.threshold_um],
                              [30.0] * curve.freq_hz.size, procedure="joint")
    if cfg.max_trials * curve.freq_hz.size != 195:
        bad.append(f"joint default budget: {cfg.max_trials} per frequency, not 15 (195 trials)")
    for n in (2, 3):  # a curve of the model's form: the budget, accurate, intervals that hold
        r = simulate_joint("weibull", n, CHECK_JOINT_RUNS, seed=seed)
        w, c = float(np.mean(np.abs(r["errors_db"]) <= 2)), float(np.mean(r["covered"]))
        m = float(np.median(r["trials"]))
        if w < 0.9 or c < 0.9 or m > 195:
            bad.append(f"joint {n}AFC Weibull, a curve of the model's form: {w:.1%} within ±2 dB, 95 % "
                       f"intervals cover {c:.1%} (want >= 90 % each), median {m:g} trials (want 195)")
    r = simulate_joint("weibull", 2, CHECK_JOINT_RUNS, seed=seed, wiggle_db=2.0)
    c, found = float(np.mean(r["covered"])), float(np.mean(r["spent_more"]))
    if c < 0.9 or found < 0.6:
        bad.append(f"joint 2AFC Weibull, bumps of SD 2 dB: 95 % intervals cover {c:.1%} (want >= 90 %), "
                   f"misfit found in {found:.0%} of runs (want >= 60 %; 79 % in the documented 200 runs)")
    ip, ia = wood_design(0)
    good = fit.design_coverage(ip, ia, 0.581, 0.464, 0.5, 32, sims=50)
    if good["coverage_both"] < 0.9:
        bad.append(f"hostd fit on the wood design, noise 0.5: covers both {good['coverage_both']:.0%} "
                   "(want >= 90 %)")
    ip1, ia1 = wood_design(1)
    ip2, ia2 = np.r_[ip, ip1] / 2, np.r_[ia, ia1] / 2
    poor = fit.design_coverage(ip2, ia2, 0.581, 0.464, 0.15, 32, sims=50)
    rng = np.random.default_rng([7, 0])
    y = np.clip(np.rint(0.581 * ip2 + 0.464 * ia2 + rng.normal(0, 0.15, (32, ip2.size))), 0, 3).mean(0)
    st = [fit.Stimulus("t", "m", str(k), float(y[k]), float(ip2[k]), float(ia2[k]), n=32)
          for k in range(ip2.size)]
    res = fit.fit(st, scale_min=0.0, scale_max=3.0, n_boot=1000, design_sims=100)
    if poor["coverage_both"] >= 0.9 or not any("simulated labs" in w for w in res.warnings):
        bad.append(f"a design that covers {poor['coverage_both']:.0%}: hostd fit did not warn "
                   f"({res.warnings})")
    return bad


def cmd_bench(args) -> int:
    if args.check:
        from hostd.bench.common import one_blas_thread

        # one BLAS thread: its work is small matrices, and a second thread spinning on a busy
        # machine's other core charged up to 12x the CPU (418 s against 34 s) for nothing
        t0, w0 = time.process_time(), time.monotonic()
        with one_blas_thread():
            bad = check(args.seed)
        for line in bad:
            print(f"hostd experiment bench --check: {line}", file=sys.stderr)
        print(f"hostd experiment bench --check: {'FAILED' if bad else 'ok'} "
              f"({time.process_time() - t0:.0f} s CPU, {time.monotonic() - w0:.0f} s)", file=sys.stderr)
        return 1 if bad else 0
    out = {"runs": args.runs, "seed": args.seed, "trials_per_frequency": args.trials}
    if args.runs > 0:
        out["threshold"] = per_frequency(args.runs, args.seed, args.trials)
        if args.oracle:
            out["oracle"] = oracle(args.runs, args.seed, args.trials)
    if args.joint_runs > 0:
        out["joint"] = joint(args.joint_runs, args.seed, args.joint_wiggle_db, args.joint_afc,
                             args.joint_trials)
    if args.fit_sims > 0:
        out["fit"] = fit_figures(args.fit_sims)
    if args.json:
        json.dump(out, sys.stdout, indent=1, default=float)
        print()
        return 0
    _print(out)
    return 0


def _pct(v) -> str:
    return "-" if v is None else f"{v:.1%}"


def _print(out: dict) -> None:
    for case, r in out.get("threshold", {}).items():
        f, d = r["fixed"], r["default_stop"]
        print(f"QUEST+ {case:<19} {out['trials_per_frequency']} trials: within ±2 dB "
              f"{_pct(f['within_2db'])}, "
              f"95% covers {_pct(f['ci95_covers'])}, bias {f['bias_db']:+.2f} dB | default stop "
              f"(95% width <= {r['stop_width_db']:g} dB after >= {r['min_trials']}): "
              f"within {_pct(d['within_2db'])}, covers "
              f"{_pct(d['ci95_covers'])}, trials median {d['median_trials']:g} max {d['max_trials']} "
              f"({r['cpu_s']:.1f} s CPU)")
    for case, r in out.get("oracle", {}).items():
        print(f"oracle (knows the observer's function) {case}: within ±2 dB {_pct(r['within_2db'])}")
    for case, r in out.get("joint", {}).items():
        print(f"joint {case}: within ±2 dB {_pct(r['within_2db'])} (worst frequency "
              f"{_pct(r['worst_frequency_within_2db'])}), 95% covers {_pct(r['ci95_covers'])} (worst "
              f"{_pct(r['worst_frequency_ci95_covers'])}; when the check passed "
              f"{_pct(r['ci95_covers_when_fit'])}, when it fired {_pct(r['ci95_covers_when_misfit'])}), "
              f"misfit found in {_pct(r['misfit_found'])} of runs, trials median {r['median_trials']:g} max "
              f"{r['max_trials']} ({r['cpu_s_per_run']:.2f} s CPU/run)")
    fit = out.get("fit")
    if not fit:
        return
    for f in fit["noise"]:
        print(f"hostd fit, (a, b) = (0.581, 0.464), grade noise {f['noise_sd']}, {f['sims']} labs of "
              f"{f['answers_per_stimulus']} answers x {f['stimuli']} stimuli: covers a "
              f"{f['coverage_a']:.0%}, "
              f"b {f['coverage_b']:.0%}, both {f['coverage_both']:.0%} (width a {f['mean_width_a']:.3f}, "
              f"b {f['mean_width_b']:.3f}); t interval covers both {f['se_t_interval_coverage_both']:.0%}")
    for f in fit["plan"]:
        print(f"plan: {f['answers_per_stimulus']:3d} answers per stimulus, grade noise 0.5: mean 95% width "
              f"a {f['mean_width_a']:.3f}, b {f['mean_width_b']:.3f}; covers both {f['coverage_both']:.0%}")
    for f in fit["design"]:
        print(f"design {f['design']}, grade noise {f['noise_sd']}: covers both {f['coverage_both']:.0%} "
              f"(bias a {f['bias_a']:+.3f}, b {f['bias_b']:+.3f}); hostd fit's estimate from one lab: "
              f"median {_pct(f['hostd_fit_estimate_median'])}, warns in "
              f"{_pct(f['hostd_fit_warned'])} of labs")
