"""`hostd corpus run | report | export`: the parser and its handlers (docs/corpus.md)."""

from __future__ import annotations

import argparse
import json
import sys


def _floats(v: str) -> list[float]:
    try:
        out = [float(t) for t in v.split(",") if t.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a comma-separated list of numbers: {v!r}") from None
    if not out:
        raise argparse.ArgumentTypeError("an empty list")
    return out


def _ints(v: str) -> list[int]:
    vals = _floats(v)
    if any(x != int(x) for x in vals):
        raise argparse.ArgumentTypeError(f"whole numbers only: {v!r}")
    return [int(x) for x in vals]


def add_parser(sub, parents) -> None:
    from hostd.cliopts import needs_subcommand, renamed

    p = sub.add_parser("corpus", help="evaluate codecs over a texture database: sweep, results store, "
                       "BD-rate (needs the corpus extra)",
                       description="Corpus-scale codec evaluation: every texture x codec x "
                       "setting x geometry -> one row in a resumable SQLite store; BD-rate reports.")
    csub = p.add_subparsers(dest="corpus", metavar="WHAT")
    p.set_defaults(func=needs_subcommand(p, "run, report or export"))

    r = csub.add_parser("run", parents=parents, help="run the sweep (skips rows already in the store)")
    r.add_argument("inputs", nargs="+", metavar="INPUT",
                   help="a directory of profiles, a manifest (.toml, or .csv whose header starts with "
                   "'file'), a profile file, or synthetic:KIND[:SEED] / synthetic:KIND:FIRST-LAST")
    r.add_argument("-o", "--output", dest="out", default="corpus.sqlite", metavar="FILE.sqlite",
                   help="the results store (default corpus.sqlite); created, or resumed")
    renamed(r, "--output", "--out")
    r.add_argument("--codec", action="append", default=None, metavar="NAME",
                   help="hostd-v2 (default), hostd-v1, mpeg-rm / mpeg-rm-cf0 (the MPEG-I Haptics "
                   "reference software: the standard's codec), vc-pwq (a research codec, CC BY-NC), or "
                   "module:attr / file.py:attr (repeatable)")
    r.add_argument("--sweep", metavar="FILE.toml",
                   help="settings for the codecs given with --codec: [codec.\"NAME\"] settings = [{...}, "
                   "...], NAME as given to --codec or the codec's name (a sweep never loads a codec)")
    r.add_argument("--methods", type=lambda v: [t.strip() for t in v.split(",") if t.strip()],
                   help="hostd codecs: methods to sweep (shaped,quant,cut; default all of the format)")
    r.add_argument("--g-db", dest="g", type=_floats, help="shaped step g in dB, comma list (default -18..18 "
                   "by 6; a list that starts negative needs '=': --g-db=-12,0,12)")
    renamed(r, "--g-db", "--g")
    r.add_argument("--levels", type=_ints, help="quant levels, comma list (default 4..128)")
    r.add_argument("--b0-db", dest="b0", type=_floats,
                   help="cut shift b0 in dB, comma list (default -18..12 by 6; --b0-db=-6,0,6)")
    renamed(r, "--b0-db", "--b0")
    r.add_argument("--target-iobj", type=_floats, default=[],
                   help="rate-control points of hostd codecs (comma list, e.g. 0.02,0.05,0.1)")
    r.add_argument("--ref-speed-mm-s", dest="speed", type=_floats, default=[50.0],
                   help="reference speeds v_ref, mm/s (comma list; 50)")
    renamed(r, "--ref-speed-mm-s", "--speed")
    r.add_argument("--fmax-hz", dest="fmax", type=_floats, default=[400.0],
                   help="band limits, Hz (comma list; 400)")
    renamed(r, "--fmax-hz", "--fmax")
    r.add_argument("--workers", type=int, default=None, metavar="N",
                   help="processes (default: every core; 1 = in this process)")
    r.add_argument("--dask", metavar="ADDRESS",
                   help="run on a Dask cluster: tcp://HOST:8786, or 'local' (a LocalCluster of worker "
                   "processes)")
    r.add_argument("--batch", type=int, default=None, metavar="JOBS",
                   help="at most JOBS per task (default 256; a texture's jobs go in one task of at most "
                   "~2 s, the last textures' in shrinking tasks)")
    r.add_argument("--timeout", type=float, default=60.0, metavar="S",
                   help="per-job limit: a codec still running after S seconds is an error row (60)")
    r.add_argument("--no-spqi", action="store_true", help="skip SPQI (faster; the SPQI column stays empty)")
    from hostd.cliopts import CalibrationAction

    r.add_argument("--calibration", action=CalibrationAction, default=None, metavar="FILE",
                   help="score with a display's calibration (hostd experiment calibration): its (a, b) and "
                   "threshold curve; part of every row's key and its `scoring` column")
    r.add_argument("--retry-errors", action="store_true", help="run again the jobs whose row is an error")
    r.add_argument("--parquet", metavar="FILE.parquet", help="also export the whole store as Parquet")
    r.add_argument("--no-progress", action="store_true", help="no progress bar (default: on a terminal)")
    r.add_argument("--report", metavar="DIR",
                   help="then write the BD-rate report there and print its summary, as `hostd corpus "
                   "report` does (anchor hostd-v2/shaped when present; no PNGs)")
    r.add_argument("--json", action="store_true", help="print the summary as JSON")
    r.set_defaults(func=cmd_run)

    rep = csub.add_parser("report", help="BD-rate tables (CSV, Markdown) and rate-quality PNGs")
    rep.add_argument("store", help="the results store of `hostd corpus run`")
    rep.add_argument("-o", "--output", dest="out", default="corpus-report",
                     help="output directory (default corpus-report)")
    renamed(rep, "--output", "--out")
    rep.add_argument("--anchor", help="the curve to compare against (default hostd-v2/shaped when present)")
    rep.add_argument("--interpolation", choices=["pchip", "akima"], default="pchip",
                     help="BD-rate interpolation (default pchip, as the video standards' spreadsheets)")
    rep.add_argument("--no-plots", action="store_true", help="no PNGs")
    rep.add_argument("--max-plots", type=int, default=20, metavar="N",
                     help="at most N PNGs (default 20; 0 = one per texture and geometry); the summary says "
                     "how many it left out")
    rep.add_argument("--min-overlap", type=float, default=0.5, metavar="F",
                     help="summaries leave out a BD-rate over less than F of the anchor's quality range "
                     "(default 0.5; 0 keeps all), saying which")
    rep.add_argument("--latest", action="store_true",
                     help="when a curve has rows of several codec versions, loader options or scorings, "
                     "compare the latest run's (default: refuse, saying what differs)")
    rep.add_argument("--json", action="store_true", help="print the summary as JSON")
    rep.set_defaults(func=cmd_report)

    cmp = csub.add_parser("compare", help="BD-rate of each curve of one store or run against the same "
                          "curve of another")
    cmp.add_argument("base", metavar="BASE", help="a store, or STORE@RUN: the rows that run wrote")
    cmp.add_argument("test", metavar="TEST", help="a store, or STORE@RUN")
    cmp.add_argument("-o", "--output", dest="out", default="corpus-compare",
                     help="output directory (default corpus-compare)")
    cmp.add_argument("--interpolation", choices=["pchip", "akima"], default="pchip")
    cmp.add_argument("--latest", action="store_true", help="as for report")
    cmp.add_argument("--min-overlap", type=float, default=0.5, metavar="F", help="as for report")
    cmp.add_argument("--json", action="store_true", help="print the summary as JSON")
    cmp.set_defaults(func=cmd_compare)

    rs = csub.add_parser("runs", help="the runs of a store: number, start, hostd version, rows")
    rs.add_argument("store")
    rs.add_argument("--json", action="store_true", help="the runs as a JSON list")
    rs.set_defaults(func=cmd_runs)

    ex = csub.add_parser("export", help="the store as Parquet or CSV")
    ex.add_argument("store")
    ex.add_argument("-o", "--output", dest="out", required=True, metavar="FILE",
                    help="FILE.parquet or FILE.csv")
    renamed(ex, "--output", "--out")
    ex.set_defaults(func=cmd_export)


def _sweep_file(path: str) -> dict[str, list[dict]]:
    import tomllib

    from hostd.errors import ConfigError

    try:
        with open(path, "rb") as fh:
            doc = tomllib.load(fh)
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"cannot read the sweep {path}: {exc}") from None
    out = {}
    for name, tbl in doc.get("codec", {}).items():
        sets = tbl.get("settings") if isinstance(tbl, dict) else None
        if not isinstance(sets, list) or not all(isinstance(s, dict) for s in sets):
            raise ConfigError(f"{path}: [codec.\"{name}\"] needs settings = [{{...}}, ...]")
        out[name] = sets
    extra = set(doc) - {"codec"}
    if extra:
        raise ConfigError(f"{path}: unknown key(s) {', '.join(sorted(extra))}; only [codec.\"NAME\"] tables")
    return out


def cmd_run(args: argparse.Namespace) -> int:
    from hostd.cliopts import load_opts
    from hostd.corpus import run, store
    from hostd.corpus.jobs import Scoring
    from hostd.errors import HostdError

    if args.workers is not None and args.workers < 1:
        raise HostdError("--workers must be >= 1")
    if not (args.timeout > 0):
        raise HostdError("--timeout must be > 0 seconds")
    settings = _sweep_file(args.sweep) if args.sweep else {}
    codec_specs = args.codec or ["hostd-v2"]  # a sweep file names settings, never a codec to load
    textures = run.textures_from(args.inputs, load_opts(args))
    plan = run.make_plan(codec_specs, speeds_mm_s=args.speed, fmaxs_hz=args.fmax, methods=args.methods,
                         g_db=args.g, levels=args.levels, b0_db=args.b0, target_iobj=args.target_iobj,
                         settings=settings)
    if args.calibration is not None:
        scoring = Scoring.calibrated(args.calibration, spqi=not args.no_spqi, timeout_s=args.timeout)
    else:
        scoring = Scoring(spqi=not args.no_spqi, timeout_s=args.timeout)
    summ = run.run(textures, plan, args.out, scoring=scoring, dask=args.dask, workers=args.workers,
                   batch=args.batch, progress=False if (args.no_progress or args.json) else None,
                   retry_errors=args.retry_errors)
    if args.parquet and not summ.interrupted:
        store.export_parquet(args.out, args.parquet)
    if not args.json or summ.interrupted:
        for line in summ.lines():
            print(line, file=sys.stderr if summ.interrupted else sys.stdout)
    if summ.interrupted:
        return 130
    failed = summ.hard_failures()
    status = 0
    if failed:
        every = "every job" if not summ.ok and not summ.skipped else f"{failed} of {summ.written} jobs"
        print(f"hostd corpus run: error: {every} failed (see the reasons above and the rows' `error`; "
              "rerun with --retry-errors after a fix)", file=sys.stderr)
        status = 1
    if args.report is None or (failed and not summ.ok and not summ.skipped):
        if args.json:
            print(json.dumps(summ.as_dict(), indent=1))
        return status
    from hostd.corpus import report

    res = report.report(args.out, args.report, plots=False, latest=True)
    if args.json:
        print(json.dumps({"run": summ.as_dict(), "report": res}, indent=1, default=str))
    else:
        _print_report(res, "hostd corpus run")
    return status


def _print_report(res: dict, prog: str) -> None:
    if res["warnings"]:
        print(f"{prog}: note: {len(res['warnings'])} BD-rate values have a note (small quality overlap, or "
              f"why there is no value): the `note` column of {res['files'][0]}", file=sys.stderr)
    for line in res.get("left_out", ()):
        print(f"left out: {line}")
    if res["summary"]:
        print(f"summaries over textures whose BD-rate covers >= {100 * res['min_overlap']:.0f} % of the "
              "anchor's quality range (--min-overlap); mean [95 % bootstrap interval over textures]")
    for s in res["summary"]:
        ci = f" [{s['ci95_lo_pct']:+.1f}, {s['ci95_hi_pct']:+.1f}]" if s["textures"] >= 2 else ""
        ratios = {k: s.get(f"{k}_time_ratio") for k in ("encode", "decode")}
        times = "".join(f", {k} time x{v:.2g}" for k, v in ratios.items() if v is not None and v == v)
        print(f"{s['transform']:<32} {s['curve']:<24} vs {s['anchor']}: mean {s['mean_pct']:+.1f} %{ci}, "
              f"median {s['median_pct']:+.1f} %, worst {s['worst_pct']:+.1f} %, "
              f"wins {s['wins']}/{s['textures']}"
              + (f", excluded {s['excluded']} ({', '.join(s['excluded_textures'][:3])}"
                 + (", ..." if len(s["excluded_textures"]) > 3 else "") + ")" if s["excluded"] else "")
              + (f", no value {s['no_value']}" if s["no_value"] else "") + times)
    for s in res.get("groups", ()):
        print(f"  group {s['group']:<20} {s['metric']:<8} {s['curve']:<24} mean {s['mean_pct']:+.1f} %, "
              f"median {s['median_pct']:+.1f} %, wins {s['wins']}/{s['textures']}"
              + (f", excluded {s['excluded']}" if s["excluded"] else ""))
    for name, text in res.get("about", {}).items():
        print(f"{name}: {text}")
    if res.get("failed_by_reason"):
        print("failed rows: " + ", ".join(f"{k} {v}" for k, v in res["failed_by_reason"].items()))
    pngs = len([f for f in res["files"] if f.endswith(".png")])
    tables = [f for f in res["files"] if not f.endswith(".png")]
    of = res.get("plots", {}).get("of", 0)
    more = f" (of {of} textures x geometries: --max-plots N, 0 = all)" if of > pngs else ""
    print("wrote " + ", ".join(tables) + (f" and {pngs} PNGs{more}" if pngs else ""))


def cmd_report(args: argparse.Namespace) -> int:
    from hostd.corpus import report

    res = report.report(args.store, args.out, anchor=args.anchor, method=args.interpolation,
                        plots=not args.no_plots, max_plots=args.max_plots, latest=args.latest,
                        min_overlap=args.min_overlap)
    if args.json:
        for w in res["warnings"]:
            print(f"hostd corpus report: warning: {w}", file=sys.stderr)
        print(json.dumps(res, indent=1, default=str))
        return 0
    _print_report(res, "hostd corpus report")
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    from pathlib import Path

    from hostd.corpus import store
    from hostd.errors import HostdError

    out = Path(args.out)
    if out.suffix.lower() == ".parquet":
        store.export_parquet(args.store, out)
    elif out.suffix.lower() == ".csv":
        import csv

        from hostd.corpus.jobs import COLUMNS

        st = store.Store(args.store, create=False)
        try:
            tmp = out.with_name(out.name + ".part")
            with open(tmp, "w", newline="", encoding="utf-8") as fh:
                w = csv.DictWriter(fh, fieldnames=list(COLUMNS))
                w.writeheader()
                w.writerows(st.rows("ORDER BY texture, codec, curve, key"))
            tmp.replace(out)
        finally:
            st.close()
    else:
        raise HostdError(f"{out}: give a .parquet or .csv file name")
    print(f"wrote {out}")
    return 0


def cmd_compare(args: argparse.Namespace) -> int:
    from hostd.corpus import report

    res = report.compare(args.base, args.test, args.out, method=args.interpolation, latest=args.latest,
                         min_overlap=args.min_overlap)
    if args.json:
        print(json.dumps(res, indent=1, default=str))
        return 0
    _print_report(res, "hostd corpus compare")
    return 0


def cmd_runs(args: argparse.Namespace) -> int:
    import time

    from hostd.corpus import store

    st = store.Store(args.store, create=False)
    try:
        counts = dict(st.db.execute("SELECT run, COUNT(*) FROM results GROUP BY run").fetchall())
        if args.json:
            print(json.dumps([{**r, "rows": counts.get(r["run"], 0)} for r in st.runs()]))
            return 0
        for r in st.runs():
            when = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(r["started_at"])) if r["started_at"] \
                else "-"
            n = counts.get(r["run"], 0)
            print(f"{r['run']:>4}  {when:<23}  hostd {r['hostd_version']:<12}  {n} rows")
    finally:
        st.close()
    return 0
