"""`hostd corpus report`: BD-rate tables of every codec curve against an anchor, per texture and
summarised, and rate-quality PNGs, from a results store.

BD-rate (Bjøntegaard delta rate, the `bjontegaard` package): the average difference in
log10(rate) between two rate-quality curves over the quality range both cover, as a percentage
of the anchor's rate (-10 % = the test needs 10 % fewer bytes for the same quality). The
curves are interpolated by `pchip` (default; it reproduces the video standards' reference
spreadsheets) or `akima`. BD-rate needs a quality axis where higher is better:
- "Iobj in dB" = -10 log10(Iobj) (Iobj is a loss; 0 is lossless, so an Iobj of 0 is left out),
- "SPQI" as is (0..1, 1 = identical played signal).
Each curve is first reduced to its Pareto front (the points no other point of the curve beats
in both rate and quality), sorted by quality, because interpolation needs a quality that
increases with rate. A curve with fewer than 2 such points, or curves that do not overlap in
quality, give no BD-rate (NaN with the reason); the package's own warnings (small overlap) are
passed on in the `note` column and on stderr, not hidden.

Rate: bytes of the coded texture (per texture and geometry bits per mm and per second of
stroke are proportional to it, so the percentage is the same).
"""

from __future__ import annotations

import csv
import math
import statistics
import warnings
from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hostd.errors import HostdError

METRICS = {"iobj_db": "Iobj in dB = -10·log10(Iobj)", "spqi": "SPQI (as is)"}
INTERPOLATIONS = ("pchip", "akima")


def pareto(rate: Sequence[float], quality: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """The points not beaten in both rate and quality, sorted by quality (strictly increasing
    in quality and in rate); non-finite and non-positive rates are dropped."""
    pts = sorted((float(q), float(r)) for r, q in zip(rate, quality, strict=True)
                 if r is not None and q is not None and math.isfinite(r) and math.isfinite(q) and r > 0)
    keep_q: list[float] = []
    keep_r: list[float] = []
    # from the best quality down: keep a point when it is cheaper than every better one
    best_rate = math.inf
    for q, r in sorted(pts, key=lambda p: (-p[0], p[1])):
        if r < best_rate and (not keep_q or q < keep_q[-1]):
            keep_q.append(q)
            keep_r.append(r)
            best_rate = r
    return np.array(keep_r[::-1]), np.array(keep_q[::-1])


MIN_OVERLAP = 0.5  # default: a BD-rate over less of the anchor's quality range is left out of summaries


def overlap(anchor_q: np.ndarray, test_q: np.ndarray) -> float:
    """The part of the anchor's quality range that the test curve covers too (0..1; NaN when
    the anchor's range is a point)."""
    span = float(anchor_q.max() - anchor_q.min())
    if not span > 0:
        return math.nan
    both = min(anchor_q.max(), test_q.max()) - max(anchor_q.min(), test_q.min())
    return max(0.0, float(both)) / span


def bd_rate(anchor: tuple[Sequence[float], Sequence[float]], test: tuple[Sequence[float], Sequence[float]],
            method: str = "pchip", with_overlap: bool = False):
    """BD-rate (%) of test against anchor, each (rates, qualities); and a note (why NaN, or the
    quality overlap when small); with_overlap: and the overlap (the anchor's range covered)."""
    val, note, ov = _bd_rate(anchor, test, method)
    return (val, note, ov) if with_overlap else (val, note)


def _bd_rate(anchor, test, method: str) -> tuple[float, str, float]:
    from hostd.extras import need

    bjontegaard = need("bjontegaard", "corpus", "BD-rate (hostd corpus report)")
    if method not in INTERPOLATIONS:
        raise HostdError(f"interpolation {method!r}: use pchip or akima")
    ra, qa = pareto(*anchor)
    rt, qt = pareto(*test)
    if ra.size < 2 or rt.size < 2:
        return math.nan, f"too few points on the Pareto front (anchor {ra.size}, test {rt.size}; need 2)", \
            math.nan
    ov = overlap(qa, qt)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            val = float(bjontegaard.bd_rate(ra, qa, rt, qt, method=method, require_matching_points=False))
        except (ValueError, ZeroDivisionError) as exc:
            return math.nan, f"bjontegaard: {exc}", ov
    # the package's overlap warning (its measure, and a hint naming its own argument): ours instead
    notes = [str(w.message) for w in caught if "overlap" not in str(w.message).lower()]
    if not ov > 0:
        notes.insert(0, "the curves do not overlap in quality")
        val = math.nan
    elif any("overlap" in str(w.message).lower() for w in caught):
        notes.insert(0, f"small quality overlap: {100 * ov:.0f} % of the anchor's range")
    return val, "; ".join(notes), ov


@dataclass
class BDRow:
    metric: str
    texture: str
    speed_mm_s: float
    fmax_hz: float
    anchor: str
    curve: str
    bd_rate_pct: float
    note: str
    overlap: float = math.nan  # the part of the anchor's quality range both curves cover


def curves(rows: Iterable[dict], metric: str) -> dict[tuple, dict[str, tuple[list, list]]]:
    """(texture, speed, fmax) -> curve label -> (bytes, quality) of the rows without error."""
    out: dict[tuple, dict[str, tuple[list, list]]] = defaultdict(lambda: defaultdict(lambda: ([], [])))
    for r in rows:
        if r.get("error") is not None or r.get(metric) is None or r.get("bytes") is None:
            continue
        c = out[(r["texture"], r["speed_mm_s"], r["fmax_hz"])][r["curve"]]
        c[0].append(float(r["bytes"]))
        c[1].append(float(r[metric]))
    return out


def bd_table(rows: Sequence[dict], anchor: str, metric: str, method: str = "pchip") -> list[BDRow]:
    """BD-rate of every curve against `anchor`, per texture and geometry."""
    if metric not in METRICS:
        raise HostdError(f"quality axis {metric!r}: use {' or '.join(METRICS)}")
    out = []
    for (tex, v, f), by_curve in sorted(curves(rows, metric).items()):
        for label in sorted(by_curve):
            if label == anchor:
                continue
            if anchor not in by_curve:
                out.append(BDRow(metric, tex, v, f, anchor, label, math.nan, "the anchor has no result here"))
                continue
            val, note, ov = bd_rate(by_curve[anchor], by_curve[label], method, with_overlap=True)
            out.append(BDRow(metric, tex, v, f, anchor, label, val, note, ov))
    return out


def bootstrap_ci(vals: Sequence[float], n: int = 2000, level: float = 0.95,
                 seed: int = 0) -> tuple[float, float]:
    """Percentile bootstrap interval of the mean over textures (resampling textures; seeded, so
    the same table gives the same interval). NaN with fewer than 2 values."""
    x = np.asarray(vals, dtype=np.float64)
    if x.size < 2:
        return math.nan, math.nan
    rng = np.random.default_rng(seed)
    means = x[rng.integers(0, x.size, size=(n, x.size))].mean(axis=1)
    lo, hi = np.quantile(means, [(1 - level) / 2, (1 + level) / 2])
    return float(lo), float(hi)


def summarise(table: Sequence[BDRow], min_overlap: float = MIN_OVERLAP) -> list[dict]:
    """Per (metric, curve): mean (with a 95 % bootstrap interval over textures), median, worst
    (largest) BD-rate over the textures whose value covers at least `min_overlap` of the anchor's
    quality range, how many of those it wins (BD-rate < 0), how many were left out for a smaller
    overlap (`excluded`, and which), and how many gave no value."""
    groups: dict[tuple[str, str], list[BDRow]] = defaultdict(list)
    for r in table:
        groups[(r.metric, r.curve)].append(r)
    out = []
    for (metric, curve), rs in sorted(groups.items()):
        finite = [r for r in rs if math.isfinite(r.bd_rate_pct)]
        kept = [r for r in finite if not (r.overlap < min_overlap)]  # (NaN overlap: kept)
        vals = [r.bd_rate_pct for r in kept]
        lo, hi = bootstrap_ci(vals)
        out.append({"metric": metric, "transform": METRICS[metric], "curve": curve, "anchor": rs[0].anchor,
                    "textures": len(vals), "no_value": len(rs) - len(finite),
                    "excluded": len(finite) - len(kept),
                    "excluded_textures": sorted({r.texture for r in finite if r not in kept}),
                    "min_overlap": min_overlap,
                    "mean_pct": statistics.fmean(vals) if vals else math.nan,
                    "ci95_lo_pct": lo, "ci95_hi_pct": hi,
                    "median_pct": statistics.median(vals) if vals else math.nan,
                    "worst_pct": max(vals) if vals else math.nan,
                    "wins": sum(1 for x in vals if x < 0),
                    "warnings": sum(1 for r in rs if r.note)})
    return out


def group_summaries(rows: Sequence[dict], table: Sequence[BDRow],
                    min_overlap: float = MIN_OVERLAP) -> list[dict]:
    """summarise() within each group of textures (the manifests' `group` column, the rows'
    `texture_group`), each entry with its "group"; [] when no texture has a group."""
    group = {r["texture"]: r["texture_group"] for r in rows if r.get("texture_group")}
    out = []
    for g in sorted(set(group.values())):
        for x in summarise([b for b in table if group.get(b.texture) == g], min_overlap):
            out.append({"group": g, **x})
    return out


def group_markdown(by_group: Sequence[dict]) -> str:
    if not by_group:
        return ""
    lines = ["", "## Per group (the manifests' `group` column)", "",
             "| group | quality axis | curve | textures | mean [95 % CI] | median | worst | wins "
             "| excluded |",
             "|---|---|---|---:|---:|---:|---:|---:|---:|"]
    for s in by_group:
        lines.append(f"| {s['group']} | {s['transform']} | `{s['curve']}` | {s['textures']} | "
                     f"{_fmt(s['mean_pct'])} {_ci(s)} | {_fmt(s['median_pct'])} | {_fmt(s['worst_pct'])} | "
                     f"{s['wins']} | {s['excluded']} |")
    return "\n".join(lines) + "\n"


def time_ratios(rows: Sequence[dict], anchor: str) -> dict[str, dict[str, float]]:
    """Per curve: the median over textures and geometries of (the curve's median encode CPU time
    per job / the anchor's there), and the same for decoding (NaN when not measured)."""
    per: dict[tuple, dict[str, list[list[float]]]] = defaultdict(lambda: defaultdict(lambda: [[], []]))
    for r in rows:
        if r.get("error") is None and r.get("curve"):
            e = per[(r["texture"], r["speed_mm_s"], r["fmax_hz"])][r["curve"]]
            for i, c in enumerate(("encode_cpu_s", "decode_cpu_s")):
                if r.get(c) is not None and r[c] > 0:
                    e[i].append(float(r[c]))
    ratios: dict[str, list[list[float]]] = defaultdict(lambda: [[], []])
    for by_curve in per.values():
        if anchor not in by_curve:
            continue
        for label, times in by_curve.items():
            for i in (0, 1):
                a = by_curve[anchor][i]
                if times[i] and a:
                    ratios[label][i].append(statistics.median(times[i]) / statistics.median(a))
    return {label: {"encode_time_ratio": statistics.median(v[0]) if v[0] else math.nan,
                    "decode_time_ratio": statistics.median(v[1]) if v[1] else math.nan}
            for label, v in ratios.items() if label != anchor}


def about(labels: Iterable[str]) -> dict[str, str]:
    """What each peer codec among the curves is (hostd.corpus.peercodecs.ABOUT: the standard's
    reference software, or a research codec and its licence), by codec name."""
    from hostd.corpus.peercodecs import ABOUT

    names = {label.split("/")[0] for label in labels}
    return {n: ABOUT[n] for n in sorted(names) if n in ABOUT}


# ----------------------------------------------------------------------------- which rows


IDENTITY = ("codec_version", "loader", "scoring")  # with the curve and geometry: one curve's rows
_OPTION = {"codec_version": "codec versions", "loader": "loader options (units, patch, ...)",
           "scoring": "scorings (SPQI, a, b, --calibration)"}


def _run(r: dict) -> int:
    return int(r["run"]) if r.get("run") is not None else -1


def current(rows: Sequence[dict]) -> tuple[list[dict], int]:
    """The rows of each named texture's current file: those with the bytes (input_sha256) of its
    latest run; rows of a file that has since changed (a broken file fixed) are left out.
    Returns (rows, how many were left out)."""
    latest: dict[str, tuple[int, str]] = {}
    for r in rows:
        t = r["texture"]
        if t not in latest or _run(r) > latest[t][0]:
            latest[t] = (_run(r), r["input_sha256"])
    keep = [r for r in rows if r["input_sha256"] == latest[r["texture"]][1]]
    return keep, len(rows) - len(keep)


def one_set_per_curve(rows: Sequence[dict], latest: bool = False,
                      what: str = "the store") -> tuple[list[dict], str]:
    """A curve's identity is one codec version, one set of loader options and one scoring, at
    one geometry, per texture. When a store holds several such sets for a curve, BD-rates over
    their union mislead: refuse, naming what differs and the options that pick one; with
    `latest`, keep the set of the latest run of each. Returns (rows, a note on what was left out)."""
    sets: dict[tuple, dict[tuple, int]] = defaultdict(dict)
    for r in rows:
        if r.get("curve") is None or r.get("codec_version") is None:
            continue
        k = (r["texture"], r["speed_mm_s"], r["fmax_hz"], r["curve"])
        ident = tuple(r.get(c) for c in IDENTITY)
        sets[k][ident] = max(sets[k].get(ident, -1), _run(r))
    several = {k: v for k, v in sets.items() if len(v) > 1}
    if not several:
        return list(rows), ""
    differ: dict[str, set[str]] = defaultdict(set)
    for (_, _, _, curve), v in several.items():
        idents = list(v)
        for i, c in enumerate(IDENTITY):
            if len({x[i] for x in idents}) > 1:
                differ[curve].add(c)
    what_differs = "; ".join(f"{curve}: {', '.join(_OPTION[c] for c in IDENTITY if c in cs)}"
                             for curve, cs in sorted(differ.items()))
    if not latest:
        raise HostdError(f"{what} holds several sets of rows for a curve ({what_differs}): give --latest to "
                         "compare the latest run of each, or compare two runs with `hostd corpus compare "
                         "STORE@RUN STORE@RUN` (`hostd corpus runs STORE` lists them)")
    keep_ident = {k: max(v, key=v.get) for k, v in several.items()}
    out = []
    for r in rows:
        k = (r["texture"], r["speed_mm_s"], r["fmax_hz"], r["curve"])
        if k in keep_ident and r.get("codec_version") is not None \
                and tuple(r.get(c) for c in IDENTITY) != keep_ident[k]:
            continue
        out.append(r)
    return out, (f"{len(rows) - len(out)} rows of earlier sets left out (--latest; {what_differs})")


def default_anchor(rows: Sequence[dict]) -> str:
    labels = sorted({r["curve"] for r in rows if r.get("curve") and r.get("error") is None})
    if not labels:
        raise HostdError("the store holds no successful row: nothing to compare")
    for pref in ("hostd-v2/shaped", "hostd-v2/quant", "hostd-v1/quant"):
        if pref in labels:
            return pref
    return labels[0]


def failures(rows: Sequence[dict]) -> dict[str, int]:
    out: dict[str, int] = defaultdict(int)
    for r in rows:
        if r.get("error") is not None:
            out[r.get("error_reason") or "error"] += 1
    return dict(sorted(out.items(), key=lambda kv: -kv[1]))


# ----------------------------------------------------------------------------- outputs


def _fmt(x: float) -> str:
    return "—" if not math.isfinite(x) else f"{x:+.1f} %"


def _ci(s: dict) -> str:
    lo, hi = s.get("ci95_lo_pct", math.nan), s.get("ci95_hi_pct", math.nan)
    return f"[{lo:+.1f}, {hi:+.1f}]" if math.isfinite(lo) and math.isfinite(hi) else ""


def _ratio(x: float | None) -> str:
    return "—" if x is None or not math.isfinite(x) else f"{x:.2g}"


def markdown(summary: Sequence[dict], table: Sequence[BDRow], method: str, fails: dict[str, int],
             total_rows: int, notes: dict[str, str] | None = None, left_out: Sequence[str] = ()) -> str:
    lines = [f"# Corpus BD-rate report ({total_rows} rows)", ""]
    lines.append(f"Interpolation: {method}. Rate: bytes. Negative = fewer bytes than the anchor for the "
                 "same quality. Each curve reduced to its Pareto front first.")
    if left_out:
        lines += ["", "Left out: " + "; ".join(left_out) + "."]
    if notes:
        lines += ["", "Codecs:", ""] + [f"- `{n}`: {text}" for n, text in notes.items()]
    if fails:
        lines.append("")
        lines.append("Failed rows: " + ", ".join(f"{k} {v}" for k, v in fails.items()))
    for metric, transform in METRICS.items():
        summ = [s for s in summary if s["metric"] == metric]
        if not summ:
            continue
        lines += ["", f"## Quality axis: {transform}", "",
                  f"Anchor: `{summ[0]['anchor']}`. Quality axis: {transform}.", "",
                  "Summaries over the textures whose BD-rate covers at least "
                  f"{100 * summ[0]['min_overlap']:.0f} % "
                  "of the anchor's quality range (`--min-overlap`); the others are counted as "
                  "excluded and listed below the table. Mean with a 95 % bootstrap interval over textures; "
                  "encode/decode: median CPU time per job against the anchor's.", "",
                  "| curve | textures | mean [95 % CI] | median | worst | wins | excluded | no value "
                  "| encode × | decode × |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for s in summ:
            lines.append(f"| `{s['curve']}` | {s['textures']} | {_fmt(s['mean_pct'])} {_ci(s)} "
                         f"| {_fmt(s['median_pct'])} | {_fmt(s['worst_pct'])} | {s['wins']} "
                         f"| {s['excluded']} | {s['no_value']} | {_ratio(s.get('encode_time_ratio'))} "
                         f"| {_ratio(s.get('decode_time_ratio'))} |")
        for s in summ:
            if s["excluded_textures"]:
                lines.append(f"\n`{s['curve']}` excluded (overlap below the minimum): "
                             + ", ".join(s["excluded_textures"]))
        per = [r for r in table if r.metric == metric]
        lines += ["", f"Per texture ({transform}; BD-rate against `{summ[0]['anchor']}`):", "",
                  "| texture | speed mm/s | fmax Hz | curve | BD-rate | overlap | note |",
                  "|---|---:|---:|---|---:|---:|---|"]
        for r in per:
            ov = f"{100 * r.overlap:.0f} %" if math.isfinite(r.overlap) else "—"
            lines.append(f"| {r.texture} | {r.speed_mm_s:g} | {r.fmax_hz:g} | `{r.curve}` | "
                         f"{_fmt(r.bd_rate_pct)} | {ov} | {r.note.replace('|', '/')} |")
    return "\n".join(lines) + "\n"


def html_page(summary: Sequence[dict], table: Sequence[BDRow], method: str, fails: dict[str, int],
              total_rows: int, pngs: dict[tuple, str], left_out: Sequence[str] = ()) -> str:
    """report.html: the summary tables, then per texture and geometry its BD-rates beside its
    rate-quality plot (as the codec field's dashboards show them)."""
    from html import escape as e

    def cell(x: float) -> str:
        return f"<td class=n>{e(_fmt(x))}</td>"

    out = ["<!doctype html><html><head><meta charset=utf-8><title>Corpus BD-rate report</title>",
           "<style>body{font-family:sans-serif;margin:1.5em}table{border-collapse:collapse;margin:.5em 0}"
           "td,th{border:1px solid #ccc;padding:2px 6px}.n{text-align:right}.tex{display:flex;gap:1em;"
           "align-items:flex-start;margin:1em 0}img{max-width:60%}</style></head><body>",
           f"<h1>Corpus BD-rate report ({total_rows} rows)</h1>",
           f"<p>Interpolation: {e(method)}. Rate: bytes. Negative = fewer bytes than the anchor for the same "
           "quality. Pareto fronts. Summaries over textures whose BD-rate covers at least "
           f"{100 * (summary[0]['min_overlap'] if summary else MIN_OVERLAP):.0f} % of the anchor's quality "
           "range; mean with a 95 % bootstrap interval over textures.</p>"]
    if left_out:
        out.append("<p>Left out: " + e("; ".join(left_out)) + ".</p>")
    if fails:
        out.append("<p>Failed rows: " + e(", ".join(f"{k} {v}" for k, v in fails.items())) + "</p>")
    for metric, transform in METRICS.items():
        summ = [s for s in summary if s["metric"] == metric]
        if not summ:
            continue
        out.append(f"<h2>{e(transform)}: against <code>{e(summ[0]['anchor'])}</code></h2><table><tr><th>curve"
                   "<th>textures<th>mean<th>95 % CI<th>median<th>worst<th>wins<th>excluded<th>no value"
                   "<th>encode ×<th>decode ×</tr>")
        for s in summ:
            out.append(f"<tr><td><code>{e(s['curve'])}</code><td class=n>{s['textures']}{cell(s['mean_pct'])}"
                       f"<td class=n>{e(_ci(s))}{cell(s['median_pct'])}{cell(s['worst_pct'])}"
                       f"<td class=n>{s['wins']}<td class=n title='{e(', '.join(s['excluded_textures']))}'>"
                       f"{s['excluded']}<td class=n>{s['no_value']}"
                       f"<td class=n>{e(_ratio(s.get('encode_time_ratio')))}"
                       f"<td class=n>{e(_ratio(s.get('decode_time_ratio')))}</tr>")
        out.append("</table>")
    out.append("<h2>Per texture</h2>")
    by_key: dict[tuple, list[BDRow]] = defaultdict(list)
    for r in table:
        by_key[(r.texture, r.speed_mm_s, r.fmax_hz)].append(r)
    for key in sorted(by_key):
        tex, v, f = key
        rows = "".join(f"<tr><td>{e(METRICS[r.metric].split(' =')[0])}<td><code>{e(r.curve)}</code>"
                       f"{cell(r.bd_rate_pct)}<td class=n>"
                       f"{'' if not math.isfinite(r.overlap) else f'{100 * r.overlap:.0f} %'}"
                       f"<td>{e(r.note)}</tr>" for r in by_key[key])
        img = f"<img src='{e(pngs[key])}' alt='rate-quality plot of {e(tex)}'>" if key in pngs else ""
        out.append(f"<div class=tex><div><h3>{e(tex)} <small>v = {v:g} mm/s, fmax = {f:g} Hz</small></h3>"
                   f"<table><tr><th>axis<th>curve<th>BD-rate<th>overlap<th>note</tr>{rows}</table></div>{img}</div>")
    out.append("</body></html>")
    return "\n".join(out) + "\n"


def _write_csv(path: Path, rows: Sequence[dict]) -> None:
    tmp = path.with_name(path.name + ".part")
    with open(tmp, "w", newline="", encoding="utf-8") as fh:
        if rows:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
    tmp.replace(path)


def _plot_keys(rows: Sequence[dict], max_plots: int) -> list[tuple]:
    keys = sorted(curves(rows, "iobj_db"))
    return keys[:max_plots] if max_plots > 0 else keys


def log_axis_labels(axis) -> None:
    """Labels of a log axis (call it once the data are plotted) that never overprint: within a
    decade at most 5 plain numbers (the axis is nearly linear there), over a few decades at 1, 2
    and 5 times powers of ten, over more at the powers only; none on minor ticks (matplotlib
    labels minor ticks when the data span less than a decade, and those ran into each other)."""
    from matplotlib.ticker import FuncFormatter, LogLocator, MaxNLocator, NullFormatter

    lo, hi = sorted(axis.get_view_interval())
    ratio = hi / lo if lo > 0 else math.inf
    if ratio < 10:
        axis.set_major_locator(MaxNLocator(nbins=4, steps=[1, 2, 2.5, 5, 10]))
    else:
        axis.set_major_locator(LogLocator(base=10.0, subs=(1.0, 2.0, 5.0) if ratio < 1000 else (1.0,)))
    axis.set_major_formatter(FuncFormatter(lambda x, _pos: f"{x:g}"))
    axis.set_minor_formatter(NullFormatter())


def plot(rows: Sequence[dict], out_dir: Path, anchor: str, max_plots: int = 20) -> list[Path]:
    """One PNG per texture and geometry: bytes against Iobj in dB and against SPQI, every curve."""
    from hostd.extras import need

    matplotlib = need("matplotlib", "plot", "the rate-quality PNGs (or --no-plots)")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    by_metric = {m: curves(rows, m) for m in METRICS}
    keys = _plot_keys(rows, max_plots)
    paths = []
    for key in keys:
        tex, v, f = key
        fig, axes = plt.subplots(1, 2, figsize=(10, 4))
        for ax, metric in zip(axes, METRICS, strict=True):
            for label, (r, q) in sorted(by_metric[metric].get(key, {}).items()):
                pr, pq = pareto(r, q)
                style = {"lw": 2.5} if label == anchor else {"lw": 1.2}
                ax.plot(pr, pq, marker="o", ms=3, label=label, **style)
            ax.set_xscale("log")
            ax.set_xlabel("bytes")
            ax.set_ylabel(METRICS[metric])
            ax.grid(True, which="both", alpha=0.3)
        for ax in axes:
            log_axis_labels(ax.xaxis)
        axes[0].legend(fontsize=7)
        fig.suptitle(f"{tex}  (v = {v:g} mm/s, fmax = {f:g} Hz; Pareto fronts)")
        fig.tight_layout()
        safe = "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in f"{tex}_v{v:g}_f{f:g}")
        p = out_dir / f"rq_{safe}.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        paths.append(p)
    return paths


def load(spec: str | Path, latest: bool = False) -> tuple[list[dict], list[str]]:
    """The rows a report compares from `spec` = STORE or STORE@RUN (the rows run RUN wrote): each
    texture's current file, one set per curve (one_set_per_curve); and notes on what was left out."""
    from hostd.corpus.store import Store

    path, run = str(spec), None
    head, sep, tail = path.rpartition("@")
    if sep and tail.isdigit() and not Path(path).exists():
        path, run = head, int(tail)
    st = Store(path, create=False)
    try:
        rows = st.rows("WHERE run = ?", (run,)) if run is not None else st.rows()
        runs = [r["run"] for r in st.runs()]
    finally:
        st.close()
    if not rows:
        if run is not None:
            raise HostdError(f"{path} holds no rows of run {run} (its runs: {', '.join(map(str, runs))})")
        raise HostdError(f"{path} holds no rows: run `hostd corpus run` first")
    notes = []
    rows, stale = current(rows)
    if stale:
        notes.append(f"{stale} rows of files changed since left out (each texture's current file is shown)")
    rows, note = one_set_per_curve(rows, latest, str(spec))
    if note:
        notes.append(note)
    return rows, notes


def report(store_path: str | Path, out_dir: str | Path, *, anchor: str | None = None,
           method: str = "pchip", plots: bool = True, max_plots: int = 20, latest: bool = False,
           min_overlap: float = MIN_OVERLAP) -> dict:
    """Write bdrate.csv, bdrate_summary.csv, report.md (and PNGs) under out_dir; return the summary."""
    rows, left_out = load(store_path, latest)
    from hostd.extras import need

    need("bjontegaard", "corpus", "BD-rate (hostd corpus report)")
    anchor = anchor or default_anchor(rows)
    known = {r["curve"] for r in rows if r.get("curve")}
    if anchor not in known:
        raise HostdError(f"anchor {anchor!r} is not a curve of this store: use one of "
                         f"{', '.join(sorted(known))}")
    out = Path(out_dir)
    if not 0 <= min_overlap <= 1:
        raise HostdError(f"--min-overlap {min_overlap:g}: give a fraction of the anchor's quality range, "
                         "0..1")
    out.mkdir(parents=True, exist_ok=True)
    table = [r for m in METRICS for r in bd_table(rows, anchor, m, method)]
    summ = summarise(table, min_overlap)
    times = time_ratios(rows, anchor)
    for x in summ:
        x.update(times.get(x["curve"], {"encode_time_ratio": math.nan, "decode_time_ratio": math.nan}))
    by_group = group_summaries(rows, table, min_overlap)
    fails = failures(rows)
    _write_csv(out / "bdrate.csv", [{**r.__dict__, "transform": METRICS[r.metric], "interpolation": method}
                                    for r in table])
    _write_csv(out / "bdrate_summary.csv", [{**s, "interpolation": method} for s in summ])
    if by_group:
        _write_csv(out / "bdrate_groups.csv", [{**s, "interpolation": method} for s in by_group])
    notes = about(r["curve"] for r in rows if r.get("curve"))
    md = markdown(summ, table, method, fails, len(rows), notes, left_out) + group_markdown(by_group)
    tmp = out / "report.md.part"
    tmp.write_text(md, encoding="utf-8")
    tmp.replace(out / "report.md")
    pngs = plot(rows, out, anchor, max_plots) if plots else []
    n_plots = len(curves(rows, "iobj_db"))
    png_of = {k: p.name for k, p in zip(_plot_keys(rows, max_plots), pngs, strict=False)}
    page = html_page(summ, table, method, fails, len(rows), png_of, left_out)
    tmp = out / "report.html.part"
    tmp.write_text(page, encoding="utf-8")
    tmp.replace(out / "report.html")
    return {"anchor": anchor, "interpolation": method, "rows": len(rows), "failed_by_reason": fails,
            "summary": summ, "groups": by_group, "about": notes, "left_out": left_out,
            "min_overlap": min_overlap,
            "plots": {"written": len(pngs), "of": n_plots if plots else 0},
            "warnings": [f"{r.texture} {r.curve} ({r.metric}): {r.note}" for r in table if r.note],
            "files": [str(out / n) for n in ("bdrate.csv", "bdrate_summary.csv", "report.md", "report.html")]
            + ([str(out / "bdrate_groups.csv")] if by_group else []) + [str(p) for p in pngs]}


def compare(base: str | Path, test: str | Path, out_dir: str | Path, *, method: str = "pchip",
            latest: bool = False, min_overlap: float = MIN_OVERLAP) -> dict:
    """BD-rate of each curve of `test` against the same curve of `base` (two stores, or two runs
    of one store: STORE@RUN), per texture and geometry both hold; compare.csv and
    compare_summary.csv under out_dir; returns the summary."""
    from hostd.extras import need

    need("bjontegaard", "corpus", "BD-rate (hostd corpus compare)")
    a_rows, a_notes = load(base, latest)
    b_rows, b_notes = load(test, latest)
    table = []
    for metric in METRICS:
        ca, cb = curves(a_rows, metric), curves(b_rows, metric)
        for key in sorted(set(ca) & set(cb)):
            for label in sorted(set(ca[key]) & set(cb[key])):
                val, note, ov = bd_rate(ca[key][label], cb[key][label], method, with_overlap=True)
                table.append(BDRow(metric, *key, f"{label} in {base}", label, val, note, ov))
    if not table:
        raise HostdError(f"{base} and {test} have no curve on a texture and geometry in common: nothing to "
                         "compare")
    summ = summarise(table, min_overlap)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    _write_csv(out / "compare.csv", [{**r.__dict__, "transform": METRICS[r.metric], "interpolation": method}
                                     for r in table])
    _write_csv(out / "compare_summary.csv", [{**s, "interpolation": method} for s in summ])
    return {"base": str(base), "test": str(test), "interpolation": method, "summary": summ,
            "min_overlap": min_overlap,
            "left_out": [f"{base}: {n}" for n in a_notes] + [f"{test}: {n}" for n in b_notes],
            "warnings": [f"{r.texture} {r.curve} ({r.metric}): {r.note}" for r in table if r.note],
            "files": [str(out / "compare.csv"), str(out / "compare_summary.csv")]}
