"""The paper's Section IV similarity test from a design file, into a session plan.

Design (TOML):

    seconds = 5             # each texture's presentation (the paper: 5 s)
    repetitions = 4         # each stimulus' presentations (the paper: 4)
    length_mm = 10          # the patch of each profile
    seed = 1                # the randomised order
    participants = 8        # planned (default 8): the design check's answers per stimulus
    [textures]              # name = a profile file (relative to the design) or synthetic:KIND[:SEED]
    wood = "synthetic:wood:1"
    [[methods]]
    method = "quant"        # quant: settings are levels L; cut: settings are b0 in dB
    settings = [14, 12, 10, 8, 6, 4]
    [[methods]]
    method = "cut"
    settings = [-12, -8, -4, 0, 4, 8]
    textures = ["wood"]     # optional: the textures this method applies to (default: all)

Every texture also gets the uncompressed control (method none: the reference twice), with the
same repetitions. Stimuli are hostd streams encoded into OUT/streams/, scored (Ip, Ia against
their reference) once at planning; the trial order is randomised once with the seed and kept
in the session, so a resumed session meets the same order.

The design check: at planning, the (Ip, Ia) of the design's stimuli are simulated as labs of
`participants` x `repetitions` grades per stimulus at the paper's (a, b) and per-answer noise
0.15..0.8 (hostd.perception.fit.design_check), and the plan keeps the coverage and bias of the
intervals `hostd fit` would state; below 90 % it says so on stderr before the session starts.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from hostd.errors import ExperimentError, HostdError

METHODS = {"quant": "levels", "cut": "b0_db"}
REFERENCE_LEVELS = 4096
KEYS = {"seconds", "repetitions", "length_mm", "seed", "textures", "methods", "gap_s", "participants"}


def read_design(path: str | Path) -> dict:
    from hostd.tomlfile import read

    p = Path(path)
    doc = read(p, "design file", "see hostd experiment similarity --help", exc=ExperimentError)
    unknown = set(doc) - KEYS
    if unknown:
        raise ExperimentError(f"{p}: unknown key(s) {', '.join(sorted(unknown))} (expected "
                              f"{', '.join(sorted(KEYS))})")
    tex = doc.get("textures")
    if not isinstance(tex, dict) or not tex or not all(isinstance(v, str) for v in tex.values()):
        raise ExperimentError(f"{p}: [textures] must name at least one texture: name = \"profile\"")
    for name in tex:
        if not name.replace("-", "").replace("_", "").isalnum():
            raise ExperimentError(f"{p}: texture name {name!r}: letters, digits, - and _ only")
    methods = doc.get("methods")
    if not isinstance(methods, list) or not methods:
        raise ExperimentError(f"{p}: give at least one [[methods]] table (method, settings)")
    for i, m in enumerate(methods, start=1):
        where = f"{p}: methods #{i}"
        if not isinstance(m, dict) or m.get("method") not in METHODS:
            raise ExperimentError(f"{where}: method must be one of {', '.join(METHODS)} (the control, "
                                  "method none, is added for every texture)")
        extra = set(m) - {"method", "settings", "textures"}
        if extra:
            raise ExperimentError(f"{where}: unknown key(s) {', '.join(sorted(extra))}")
        st = m.get("settings")
        if not isinstance(st, list) or not st:
            raise ExperimentError(f"{where}: settings must be a non-empty list")
        for v in st:
            is_int = isinstance(v, int) and not isinstance(v, bool)
            if m["method"] == "quant" and not (is_int and 2 <= v <= 4096):
                raise ExperimentError(f"{where}: quant setting {v!r}: a number of levels L, "
                                      "an integer 2..4096")
            if m["method"] == "cut" and not (isinstance(v, int | float) and not isinstance(v, bool)
                                             and math.isfinite(v) and -60 <= v <= 60):
                raise ExperimentError(f"{where}: cut setting {v!r}: a shift b0 in dB, -60..60")
        if len(set(st)) != len(st):
            raise ExperimentError(f"{where}: a setting is listed twice")
        for t in m.get("textures", list(tex)):
            if t not in tex:
                raise ExperimentError(f"{where}: unknown texture {t!r} (the design's textures: "
                                      f"{', '.join(tex)})")
    for key, lo, hi in (("seconds", 0.5, 60), ("repetitions", 1, 100), ("length_mm", 0.1, 1000),
                        ("gap_s", 0, 60), ("participants", 1, 1000)):
        v = doc.get(key)
        if v is not None and (not isinstance(v, int | float) or isinstance(v, bool) or not lo <= v <= hi):
            raise ExperimentError(f"{p}: {key} must be a number {lo:g}..{hi:g}")
    return {"path": str(p), "seconds": float(doc.get("seconds", 5.0)),
            "repetitions": int(doc.get("repetitions", 4)), "length_mm": float(doc.get("length_mm", 10.0)),
            "seed": int(doc.get("seed", 1)), "gap_s": float(doc.get("gap_s", 1.0)),
            "participants": int(doc.get("participants", 8)),
            "textures": dict(tex), "methods": methods}


def make_plan(design: dict, out_dir: str | Path, thresholds: str | None = None) -> dict:
    """Encode every stimulus into out_dir/streams, score it, and randomise the trials."""
    from hostd import api
    from hostd.texture import synth

    out = Path(out_dir)
    sdir = out / "streams"
    sdir.mkdir(parents=True, exist_ok=True)
    base = Path(design["path"]).parent
    stimuli = []
    for name, spec in design["textures"].items():
        src = spec if synth.is_spec(spec) else str((base / spec).resolve())
        try:
            prof = api.load_profile(src, length_mm=design["length_mm"])
        except (HostdError, OSError, ValueError) as e:
            raise ExperimentError(f"{design['path']}: texture {name}: {e}") from None
        ref = sdir / f"{name}-reference.vtx"
        try:
            # the reference: the finest quantization hostd codes (the daemon plays streams only)
            ref.write_bytes(api.encode(prof, method="quant", levels=REFERENCE_LEVELS,
                                       thresholds=thresholds)["stream"])
        except (HostdError, ValueError) as e:
            raise ExperimentError(f"{design['path']}: texture {name}: cannot encode the reference: "
                                  f"{e}") from None
        stimuli.append({"texture": name, "method": "none", "level": "", "stream": "", "stream_rel": "",
                        "reference": str(ref), "profile": spec, "Ip": None, "Ia": None})
        for m in design["methods"]:
            if name not in m.get("textures", list(design["textures"])):
                continue
            for v in m["settings"]:
                kw = {METHODS[m["method"]]: v}
                try:
                    res = api.encode(prof, method=m["method"], thresholds=thresholds, **kw)
                except (HostdError, ValueError) as e:
                    raise ExperimentError(f"{design['path']}: {name} {m['method']} {v}: {e}") from None
                f = sdir / f"{name}-{m['method']}-{v}.vtx"
                f.write_bytes(res["stream"])
                sc = api.score(res["stream"], prof)  # with the curve the stream was made with
                stimuli.append({"texture": name, "method": m["method"], "level": str(v), "stream": str(f),
                                "stream_rel": f"streams/{f.name}", "reference": str(ref), "profile": spec,
                                "Ip": float(sc["Ip"]), "Ia": float(sc["Ia"])})
    check = design_check(stimuli, design["repetitions"] * design.get("participants", 8))
    trials = [dict(s, rep=r) for s in stimuli for r in range(design["repetitions"])]
    order = np.random.default_rng(design["seed"]).permutation(len(trials))
    trials = [dict(trials[int(j)], index=i) for i, j in enumerate(order)]
    return {"design": design, "seconds": design["seconds"], "gap_s": design["gap_s"], "trials": trials,
            "design_check": check}


def design_check(stimuli: list[dict], answers: int) -> dict:
    """The coverage and bias of (a, b)'s intervals on these stimuli (the control at Ip = Ia = 0),
    at the paper's weights, by simulation (hostd.perception.fit.design_check); a warning on
    stderr below 90 %."""
    from hostd.perception import fit
    from hostd.perception.indices import DEFAULT_AB

    ip = np.array([s["Ip"] or 0.0 for s in stimuli])
    ia = np.array([s["Ia"] or 0.0 for s in stimuli])
    if np.linalg.matrix_rank(np.column_stack([ip, ia])) < 2:
        return {"sims": 0, "why": "Ip and Ia are collinear over the design: (a, b) cannot be fitted"}
    d, warning = fit.design_check(ip, ia, *DEFAULT_AB, answers, fit.GRADE_NOISE_SDS)
    if warning:
        from hostd.cliopts import warn

        warn("experiment similarity", f"{warning} (the design file's participants = N sets the answers)")
    return d


def scores_csv(rows: list[dict]) -> str:
    """The scores CSV `hostd fit` reads as-is: Ip, Ia given (scored at planning), the stream
    beside them; control rows with method none and empty Ip, Ia and stream cells."""
    import csv
    import io

    out = io.StringIO()
    out.write("# Mean similarity grades (0 same .. 3 different) from hostd experiment similarity\n")
    w = csv.writer(out, lineterminator="\n")
    w.writerow(["texture", "method", "level", "score", "Ip", "Ia", "n", "stream", "profile"])
    for r in rows:
        ctl = r["method"] == "none"
        w.writerow([r["texture"], r["method"], r["level"], f"{r['score']:.6g}",
                    "" if ctl else repr(r["Ip"]), "" if ctl else repr(r["Ia"]), r["n"],
                    "" if ctl else r["stream"], r["profile"]])
    return out.getvalue()
