"""`hostd bench [accuracy|pipeline|codec|scoring|all]` (also `./run bench`, `python -m benchmarks`)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from hostd.cliopts import renamed, warn_once


class _Minutes(argparse.Action):
    """bench soak's old --minutes M: --seconds 60 M, with a note."""

    def __call__(self, parser, namespace, values, option_string=None):
        warn_once("hostd: --minutes is deprecated: use --seconds (the old spelling goes in the next release)")
        namespace.seconds = float(values) * 60.0


def add_parser(sub, parents) -> None:
    p = sub.add_parser("bench", help="benchmarks: what accuracy costs in time, and what each part costs",
                       description="Benchmarks. Figures are medians/percentiles measured in one run "
                       "on this machine; compare ratios, not absolute numbers, across machines.")
    bsub = p.add_subparsers(dest="bench", metavar="WHAT")
    a = bsub.add_parser("accuracy", parents=parents,
                        help="every render knob: RMS error vs CPU ms per second of output")
    a.add_argument("--json", action="store_true", help="print the rows as JSON")
    a.add_argument("--plot", metavar="FILE.png", help="write error against CPU time, one point per setting")
    a.add_argument("--seconds", dest="duration", type=float, default=4.8, metavar="S",
                   help="simulated seconds per setting and texture (default 4.8 = two metronome cycles)")
    renamed(a, "--seconds", "--duration")
    a.add_argument("--profile", action="append", default=[], metavar="FILE",
                   help="a real profile to include (repeatable; loader options apply); default: the "
                   "bundled instrument profile when present")
    a.add_argument("--quiet", action="store_true", help="no progress bar")
    a.add_argument("--repeats", type=int, default=3, metavar="N",
                   help="runs per host setting and texture: the CPU median and its min-max (default 3)")
    _check_opt(a, "every rendering mode within 1 %% RMS of the ideal display on every texture, host "
               "rendering within 5 %% of a core; runs only the render_at rows")
    q = bsub.add_parser("pipeline", help="time per 1 ms batch at default settings (p50/p99/p99.9)")
    q.add_argument("--json", action="store_true")
    q.add_argument("--seconds", dest="duration", type=float, default=60.0, metavar="S",
                   help="simulated seconds (default 60)")
    renamed(q, "--seconds", "--duration")
    q.add_argument("--host-cycle-ms", type=int, default=1, metavar="MS",
                   help="one batch of MS x 3 samples per wake-up, as the pump's [device] host_cycle_ms "
                        "(1..10, default 1); reports the accuracy it costs")
    q.add_argument("--texture", default="wood", help="synthetic texture (default wood)")
    lat = bsub.add_parser("latency", help="encoder change to first DAC sample, through the firmware on a pty")
    lat.add_argument("--json", action="store_true")
    lat.add_argument("--seconds", dest="duration", type=float, default=8.0, metavar="S",
                     help="seconds per run (default 8)")
    renamed(lat, "--seconds", "--duration")
    lat.add_argument("--target-fill", type=int, default=12, metavar="SAMPLES",
                     help="the device buffer's target fill (default 12 = 4 ms)")
    lat.add_argument("--runs", type=int, default=None, metavar="N",
                     help="runs per setting, medians reported (default 1; --check 10, --check ci 5, "
                          "--sweep 3)")
    lat.add_argument("--load", action="store_true", help="a CPU hog per core meanwhile")
    lat.add_argument("--sched-fifo", type=int, default=None, metavar="PRIO",
                     help="the pump SCHED_FIFO at PRIO (0: SCHED_OTHER), as the daemon's [realtime] "
                          "sched_fifo_priority (default: the daemon's default, 10)")
    lat.add_argument("--sweep", action="store_true",
                     help="what latency costs: fixed fill targets 2..12 ms against underruns per minute "
                          "and played fraction, quiet and beside a CPU hog per core")
    _check_opt(lat, "p50 <= 3.83 ms (3.5 ms on a STATUS tick + the mean 1/3 ms wait for one), no "
               "underrun of the link's own in 10 runs at the default; "
               "`ci`: 5 runs, p50 <= 7 ms, a median of 6 per minute, 99 %% played")
    so = bsub.add_parser("soak", help="the daemon playing for minutes on the firmware's host port: "
                         "played fraction, underruns, silences from the DAC log")
    so.add_argument("--json", action="store_true")
    so.add_argument("--load", action="store_true", help="a CPU hog on the other core meanwhile")
    so.add_argument("--host-cycle-ms", type=int, default=1, metavar="MS",
                    help="the daemon's [device] host_cycle_ms (1..10, default 1)")
    so.add_argument("--seconds", type=float, default=600.0, metavar="S",
                    help="how long each run lasts (default 600; the device-mode goal: --runs 3 "
                    "--seconds 40)")
    so.add_argument("--minutes", action=_Minutes, help=argparse.SUPPRESS)  # the old spelling
    _check_opt(so, "device rendering: PSS <= 60 MB, <= 12 threads, <= 0.15 %% of a core for daemon + pump, "
               "pump wake-ups <= its loop runs")
    cy = bsub.add_parser("cycle", help="the host-rendering pump's CPU time per cycle on the firmware's "
                         "host port: the Python reference part by part, then the compiled cycle")
    cy.add_argument("--json", action="store_true")
    cy.add_argument("--seconds", type=float, default=8.0, metavar="S", help="how long (default 8)")
    cy.add_argument("--host-cycle-ms", type=int, default=1, metavar="MS", help="pump cycle (1..10)")
    cy.add_argument("--compiled-only", action="store_true",
                    help="only the compiled cycle (the guarded figure)")
    _check_opt(cy, "the compiled cycle <= 50 µs of thread CPU per 1 ms cycle, its step's median <= 15 µs")
    cl = bsub.add_parser("cli", help="CPU time of a command-line call (hostd encode --target-iobj), "
                         "median of runs")
    cl.add_argument("--json", action="store_true")
    cl.add_argument("--runs", type=int, default=5, metavar="N", help="runs (default 5)")
    _check_opt(cl, "hostd encode synthetic:wood:3 --target-iobj 0.05 <= 0.4 s CPU")
    so.add_argument("--render", choices=["host", "device", "auto"], default="auto",
                    help="who renders: [render] where for the run (default auto: the display, protocol v2)")
    so.add_argument("--runs", type=int, default=1, metavar="N", help="repeat N times, report medians")
    sb = bsub.add_parser("sim", help="scene simulation speed vs number of effects and duration")
    sb.add_argument("--json", action="store_true")
    ob = bsub.add_parser("offline", help="goals: shipped scenes at N'=1600 < 5 s, rate-quality "
                         "report at N'=160 < 3 s (CPU time of the working thread)")
    ob.add_argument("--json", action="store_true")
    cb = bsub.add_parser("corpus", help="hostd corpus: machinery overhead per job vs the bare codec call, "
                         "parallel efficiency, driver memory over 10^4 jobs (Dask: the corpus extra)")
    cb.add_argument("--json", action="store_true")
    cb.add_argument("--jobs", type=int, default=10_000, metavar="N", help="jobs of the memory run (10^4)")
    cb.add_argument("--workers", type=int, default=None, metavar="N", help="pool size (default every core)")
    cb.add_argument("--batch", type=int, default=None, metavar="JOBS",
                    help="at most JOBS per task (default as `hostd corpus run`: 256)")
    cb.add_argument("--heights", type=int, default=2000, metavar="N",
                    help="heights per texture of the tiny jobs (default 2000 = 1 mm; at most 20000, the "
                    "synthetic textures' 10 mm)")
    cb.add_argument("--spqi", action="store_true", help="score the tiny jobs with SPQI too")
    cb.add_argument("--repeats", type=int, default=7, metavar="N",
                    help="rounds of 1 and W workers per job size, medians reported (7: a round is ~1 s, "
                    "single rounds spread ±20 %%)")
    cb.add_argument("--no-typical", action="store_true",
                    help="skip the typical jobs (20 000 heights, hostd-v2's default sweep, SPQI)")
    cb.add_argument("--no-dask", action="store_true", help="skip the Dask LocalCluster run")
    _check_opt(cb, "overhead <= 1 ms per job on the local pool, parallel efficiency >= 0.85 on a quiet "
               "machine, driver RSS growth <= 50 MB from job 10^3 to the last")
    lb = bsub.add_parser("load", help="reading a large two-column CSV against np.loadtxt (goal <= 1.5x)")
    lb.add_argument("--lines", type=int, default=2_000_000)
    lb.add_argument("--json", action="store_true")
    for name, hlp in (("codec", "encode/decode times; v2 vs v1 bytes at Iobj <= 0.05 with the guard"),
                      ("scoring", "index scoring throughput"),
                      ("all", "pipeline, codec and scoring (accuracy is run on its own)")):
        b = bsub.add_parser(name, help=hlp)
        b.add_argument("--json", action="store_true")
        if name == "scoring":
            _check_opt(b, ">= 1 M scores per second at every batch size")
        if name == "codec":
            b.add_argument("--tune-deadzone", action="store_true",
                           help="only the shaped quantizer's dead-zone / reconstruction table")
            b.add_argument("--guard-calibration", action="store_true",
                           help="only SPQI against the guard's wSNR and sSNR on 32 textures "
                           "(the guard's defaults; takes minutes)")
            b.add_argument("--holdout", action="store_true",
                           help="only rate control's defaults on the held-out textures (not the "
                           "guard's calibration set): bytes, Iobj, SPQI, CPU time")
            b.add_argument("--peers", metavar="DIR", default=None, nargs="?", const="",
                           help="only v2 against the peer codecs (MPEG-I Haptics RM, VC-PWQ: a "
                           "research codec, CC BY-NC) built under DIR (or named by HOSTD_PEER_* "
                           "variables; the RM also from its build.sh cache, DIR optional): bytes "
                           "for SPQI >= 0.9")
    from hostd.cliopts import needs_subcommand

    p.set_defaults(func=needs_subcommand(p, "a benchmark (all: pipeline, codec and scoring)"))
    for b in bsub.choices.values():
        b.set_defaults(func=cmd_bench)


def _check_opt(p, goal: str) -> None:
    p.add_argument("--check", nargs="?", const="goal", choices=["goal", "ci"], default=None,
                   help=f"exit 1 past the goal ({goal}); `--check ci`: the CI bound (about twice a "
                   "CPU-time goal; the goal itself for memory, threads and counts)")


def _print_rows(rows: list[dict]) -> None:
    for r in rows:
        print("  ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in r.items()))


def _textures(args) -> dict:
    from hostd.texture import synth

    tex = {"wood": synth.make("wood", seed=1), "sandpaper": synth.make("sandpaper", seed=1)}
    if args.profile:
        from hostd.cliopts import read_profile

        for path in args.profile:
            prof = read_profile(path, args, length_mm=args.length_mm)
            tex[Path(path).stem] = prof
    else:
        from hostd.texture.load import bundled_profile

        found = bundled_profile()
        if found is not None:
            tex[Path(found.source).stem or "real"] = found
    return tex


def _peer_env() -> bool:
    """True when a HOSTD_PEER_* variable names a peer executable."""
    import os

    from hostd.bench import peers

    return any(os.environ.get(v) for v in (peers.VCPWQ_ENV, peers.MPEG_ENCODER_ENV,
                                           peers.MPEG_SYNTH_ENV))


def cmd_bench(args: argparse.Namespace) -> int:
    from hostd.bench import accuracy, common, micro, pipeline
    from hostd.errors import HostdError

    what = args.bench
    if what == "accuracy":
        if not (0.5 <= args.duration <= 600):
            raise SystemExit("hostd bench: error: --seconds must be 0.5..600 s")
        if not 1 <= args.repeats <= 50:
            raise SystemExit("hostd bench: error: --repeats must be 1..50")
        level = args.check
        if args.plot:
            from hostd.plotting import check_image_path

            check_image_path(args.plot, "--plot")
        rows = accuracy.run(_textures(args), args.duration, progress=not (args.quiet or args.json),
                            repeats=args.repeats, knobs=("render_at",) if level else None,
                            firmware_cost=not level)
        if args.plot:
            accuracy.plot(rows, args.plot)
        if args.json:
            json.dump(rows, sys.stdout, indent=1, default=float)
            print()
        else:
            print(f"machine: {common.machine()}")
            print(accuracy.table(rows))
            if args.plot:
                print(f"plot: {args.plot}")
        return _check(what, rows, level) if level else 0
    rows: list[dict] = []
    if what == "latency":
        from hostd.bench import latency

        if not (1.0 <= args.duration <= 3600 and 1 <= args.target_fill <= 200
                and (args.runs is None or 1 <= args.runs <= 100)
                and (args.sched_fifo is None or 0 <= args.sched_fifo <= 99)):
            raise SystemExit("hostd bench latency: error: --seconds 1..3600, --target-fill 1..200, "
                             "--runs 1..100, --sched-fifo 0..99")
        try:
            if args.sweep:
                sums = latency.sweep(args.runs or 3, args.duration, sched_fifo=args.sched_fifo)
            else:
                runs = args.runs or (latency.CHECK_RUNS[args.check] if args.check else 1)
                sums = [latency.repeat(runs, args.duration, args.target_fill, load=args.load,
                                       sched_fifo=args.sched_fifo)]
        except (RuntimeError, HostdError) as e:
            raise SystemExit(f"hostd bench latency: error: {e}") from None
        bad = latency.check(sums[0], args.check) if args.check else []
        if args.json:
            print(json.dumps({"machine": common.machine(), "rows": sums,
                              "check": {"ok": not bad, "failed": bad} if args.check else None}, indent=1))
        else:
            print(f"machine: {common.machine()}")
            print(latency.table(sums))
            if args.check:
                print("check: " + ("ok" if not bad else "FAILED: " + "; ".join(bad)))
        return 1 if bad else 0
    if what == "soak":
        from hostd.bench import soak

        try:
            if not 1 <= args.host_cycle_ms <= 10:
                raise SystemExit("hostd bench soak: error: --host-cycle-ms must be 1..10")
            if not 1 <= args.runs <= 100:
                raise SystemExit("hostd bench soak: error: --runs must be 1..100")
            if not 1 <= args.seconds <= 24 * 3600:
                raise SystemExit("hostd bench soak: error: --seconds must be 1..86400")
            rows.append(soak.run_many(args.runs, minutes=args.seconds / 60, load=args.load,
                                      progress=not args.json, render=args.render,
                                      host_cycle_ms=args.host_cycle_ms, seconds=args.seconds))
        except (RuntimeError, HostdError) as e:
            raise SystemExit(f"hostd bench soak: error: {e}") from None
    if what == "cycle":
        from hostd.bench import cycle

        if not (1.0 <= args.seconds <= 3600 and 1 <= args.host_cycle_ms <= 10):
            raise SystemExit("hostd bench cycle: error: --seconds must be 1..3600 and --host-cycle-ms 1..10")
        try:
            rows += ([cycle.run(args.seconds, args.host_cycle_ms, compiled=True)] if args.compiled_only
                     else cycle.run_both(args.seconds, args.host_cycle_ms))
        except (RuntimeError, HostdError) as e:
            raise SystemExit(f"hostd bench cycle: error: {e}") from None
    if what == "corpus":
        from hostd.bench import corpus as corpus_bench

        if (args.jobs < 1000 or (args.workers is not None and args.workers < 1)
                or (args.batch is not None and args.batch < 1) or not 1 <= args.repeats <= 50
                or not 16 <= args.heights <= 20_000):
            raise SystemExit("hostd bench corpus: error: --jobs must be >= 1000, --workers and --batch >= 1, "
                             "--repeats 1..50, --heights 16..20000 (a synthetic texture's length)")
        try:
            rows.append(corpus_bench.run(jobs_scale=args.jobs, dask=not args.no_dask, workers=args.workers,
                                         batch=args.batch, heights=args.heights, spqi=args.spqi,
                                         repeats=args.repeats, typical=not args.no_typical))
        except (RuntimeError, HostdError) as e:
            raise SystemExit(f"hostd bench corpus: error: {e}") from None
    if what == "cli":
        from hostd.bench import clicost

        if not 1 <= args.runs <= 100:
            raise SystemExit("hostd bench cli: error: --runs must be 1..100")
        rows.append(clicost.run(args.runs))
    if what == "sim":
        from hostd.bench import simbench

        rows += simbench.run()
    show = not args.json and sys.stderr.isatty()
    if what == "load":
        with common.progress(5, "bench load", show) as bar:
            rows += micro.bench_load(args.lines, step=lambda: bar.update(1))
    if what == "offline":
        from hostd.bench import simbench

        rows += simbench.run_offline()
    if what in ("pipeline", "all"):
        cycle = getattr(args, "host_cycle_ms", 1)
        if not 1 <= cycle <= 10:
            raise SystemExit("hostd bench pipeline: error: --host-cycle-ms must be 1..10")
        texture = getattr(args, "texture", "wood")
        extra = {k: v for k, v in (("texture", texture), ("host_cycle_ms", cycle))
                 if v != {"texture": "wood", "host_cycle_ms": 1}[k]}  # `bench all`: the defaults
        rows.append(pipeline.run(getattr(args, "duration", 60.0), **extra))
    if what == "codec" and args.tune_deadzone:
        from hostd.bench import codec2

        rows += codec2.tune_deadzone_rows()
    elif what == "codec" and args.holdout:
        from hostd.bench import holdout

        rows += holdout.rows()
    elif what == "codec" and args.guard_calibration:
        from hostd.bench import codec2

        rows += codec2.guard_calibration_rows()
    elif what == "codec" and (args.peers is not None or _peer_env()):
        from hostd.bench import codec2

        rows += codec2.peer_rows(Path(args.peers) if args.peers else None)
    elif what in ("codec", "all"):
        from hostd.bench import codec2
        from hostd.bench.codec2 import textures

        with common.progress(4 + 1 + len(textures()), "bench codec", show) as bar:
            rows += micro.bench_codec(step=lambda: bar.update(1))
            rows += codec2.time_rows()
            bar.update(1)
            rows += codec2.rate_rows(step=lambda: bar.update(1))
    if what in ("scoring", "all"):
        rows += micro.bench_scoring()
    if args.json:
        print(json.dumps({"machine": common.machine(), "rows": rows}, indent=1))
    else:
        print(f"machine: {common.machine()}")
        _print_rows(rows)
    level = getattr(args, "check", None)
    return _check(what, rows, level) if level else 0


def _check(what: str, rows: list[dict], level: str) -> int:
    """--check: the guarded figures of this bench against their goal or CI bound (bench.guards)."""
    from hostd.bench import guards as g

    if what == "soak":
        device = [r for r in rows if r.get("render_at") == "device"]
        if len(device) != len(rows):
            print("hostd bench soak: --check holds device rendering to its goals: run it with --render "
                  "device (or auto on a v2 display)", file=sys.stderr)
            return 1
        return g.check(rows, [g.DEVICE_PSS_MB, g.DEVICE_THREADS, g.DEVICE_CPU_SHARE,
                              g.DEVICE_WAKEUPS_PER_RUN, g.FLEET_CPU_SHARE, g.FLEET_PSS_MB,
                              g.FLEET_CPU_MS_PER_COMMIT], level, "soak")
    if what == "cycle":
        compiled = [r for r in rows if r.get("cycle") == "compiled"]
        if not compiled:
            print("hostd bench cycle: --check needs the compiled cycle, which is not built here",
                  file=sys.stderr)
            return 1
        return g.check(compiled, [g.CYCLE_US, g.CYCLE_STEP_P50_US], level, "cycle")
    if what == "cli":
        return g.check(rows, [g.CLI_ENCODE_CPU_S], level, "cli encode")
    if what == "scoring":
        return g.check(rows, [g.SCORING_PER_S], level, "scoring")
    if what == "corpus":
        return g.check(rows, [g.CORPUS_OVERHEAD_MS, g.CORPUS_EFFICIENCY, g.CORPUS_EFFICIENCY_CPU,
                              g.CORPUS_RSS_GROWTH_MB], level, "corpus")
    if what == "accuracy":
        modes = [r for r in rows if r["knob"] == "render_at"]
        if {r["setting"] for r in modes} != {"host", "device"}:
            print("hostd bench accuracy: --check needs the render_at rows (host and device)", file=sys.stderr)
            return 1
        bad = 0
        for r in modes:
            guards = [g.ACCURACY_RMS_PCT] + ([g.ACCURACY_HOST_CPU_MS_PER_S] if r["setting"] == "host" else [])
            bad |= g.check([r], guards, level, f"accuracy render_at={r['setting']} ({r['worst_texture']})")
        return bad
    return 0
