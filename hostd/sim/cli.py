"""`hostd sim SCENE.toml [--json] [--plot DIR] [--only EFFECT ...]`"""

from __future__ import annotations

import json
import sys


def run_label(effects: list[str], width: int = 40) -> str:
    """The table's label of a run: its effects joined by '+', or 'all N effects' when that does not
    fit the column (the list follows the table)."""
    label = "+".join(effects) or "(none)"
    return label if len(label) <= width else f"all {len(effects)} effects"


def add_parser(sub) -> None:
    p = sub.add_parser("sim", help="simulate a scene (only the effects it names); quality per effect")
    p.add_argument("scene", help="scene TOML, or a shipped scene's name (ideal, worst-case, "
                   "usb-jitter, clock-drift, paper-experiment)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--plot", metavar="DIR", help="write stroke and error-spectrum PNGs here")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_sim)


def cmd_sim(args) -> int:
    from pathlib import Path

    from hostd.extras import need

    need("finufft", "sim", "hostd sim")  # before any work: the series fits of every run
    if args.plot:
        need("matplotlib", "plot", "hostd sim --plot")

    from hostd.paths import find
    from hostd.sim import scene

    path = Path(args.scene)
    if not path.exists() and not path.suffix:
        path = find("scenes", f"{args.scene}.toml")
    sc = scene.load(path)
    progress = not (args.quiet or args.json) and sc.duration_s > 3 and sys.stderr.isatty()
    result = scene.report(sc, progress=progress)
    plots = scene.plot(result, args.plot) if args.plot else []
    out = scene.strip(result)
    if args.json:
        out["plots"] = [str(p) for p in plots]
        json.dump(out, sys.stdout, indent=1)
        print()
        return 0
    print(f"scene {out['scene']}: {out['description']} ({out['duration_s']:g} s, seed {out['seed']}); "
          f"codec-only Iobj {out['codec_iobj']:.4f}")
    print(f"  {'effects':<40} {'Ip':>8} {'Ia':>8} {'Iobj':>8} {'RMS err µm':>10} {'Δspec µm':>9} "
          f"{'underruns':>9} {'latency ms':>10}")
    combined = []
    for r in out["runs"]:
        label = run_label(r["effects"])
        if label != "+".join(r["effects"]) and r["effects"]:
            combined.append(f"  {label}: {', '.join(r['effects'])}")
        print(f"  {label:<40} {r['Ip']:>8.4f} {r['Ia']:>8.4f} {r['Iobj']:>8.4f} "
              f"{r['rms_error_um']:>10.4f} {r['spectrum_change_um']:>9.5f} {r['underruns']:>9} "
              f"{r['latency_ms']:>10.2f}")
    for line in combined:  # a combined row's effects, below the table so the columns stay aligned
        print(line)
    for p in plots:
        print(f"  plot: {p}")
    return 0
