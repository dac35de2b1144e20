"""Rate-quality report: every method swept, real stream bytes against Ip, Ia, Iobj, SPQI and
what each setting costs in time (encode and decode CPU).

The swept ranges follow the texture: the cut's b0 and the shaped quantizer's g cover the
paper's Table I levels and, beyond them, the span from "everything cut" down to ~45 dB below
the texture's strongest component relative to the threshold (a real profile of nm heights
sits tens of dB below the threshold, where a fixed grid would cut everything).
"""

from __future__ import annotations

import csv
import math
import os
from pathlib import Path

import numpy as np

from hostd.bench.common import cpu_median_s, one_blas_thread
from hostd.codec import stream as vtx
from hostd.codec import transform
from hostd.errors import HostdError
from hostd.perception import indices, peer
from hostd.perception.thresholds import ThresholdCurve
from hostd.plotting import log_byte_axis, place_labels
from hostd.tty import progress_bar

TABLE_I_LEVELS = (14, 12, 10, 8, 6, 5, 4)
TABLE_I_B0 = (-12, -8, -4, 0, 4, 8, 12)
LEVELS = (*range(2, 17), 20, 24, 32, 48, 64)
B0_DB = tuple(float(b) for b in range(-16, 17))  # the cut's sweep for a texture at threshold scale
SERIES = {  # label -> encoder settings besides the swept parameter
    "quant": {"method": "quant"},
    "cut (exact survivors)": {"method": "cut", "value_bits": 0},
    "cut (16-bit survivors)": {"method": "cut", "value_bits": 16},
}
# Stream v2 (issue 14): the threshold-shaped quantizer swept over its knob g.
V2_SERIES = {"v2 shaped": {"method": "shaped"}}
G_DB = tuple(float(g) for g in np.arange(-30.0, 15.0 + 1e-9, 1.5))
G_TABLE = (-24.0, -18.0, -12.0, -6.0, 0.0, 6.0, 12.0)
TIME_REPEATS = 5  # encode / decode CPU: median of this many runs (thread CPU time)
TARGET_IOBJ = 0.05  # marked on the Iobj panel (hostd encode --target-iobj's usual value)
SPQI_CRITERION = 0.9  # marked on the SPQI panel (the waveform criterion of rate control)
COLUMNS = ("series", "version", "method", "levels", "b0_db", "g_db", "value_bits", "bytes",
           "ratio_coeffs", "ratio_profile", "kept", "Ip", "Ia", "Iobj", "wsnr_db", "ssnr_db", "st_sim",
           "spqi", "encode_ms", "decode_ms", "table_I")


def peak_db(c: np.ndarray, b_k: np.ndarray) -> float:
    """20 log10 max_k |C_k| / b_k: the strongest component relative to its threshold (dB);
    computed on scaled weights, so finite for any finite input (0 for a silent texture)."""
    _, w1, t = indices.scaled_weights(b_k)
    r = np.abs(c) * w1  # |C| / b' with b' = b 2^t
    top = float(np.max(r)) if r.size else 0.0
    if top == 0.0 or not math.isfinite(top):
        return 0.0
    return 20.0 * (math.log10(top) + t * math.log10(2.0))


def _grid(table: tuple[float, ...], lo: float, hi: float, step: float) -> tuple[float, ...]:
    """The table's values plus lo..hi in steps of `step` (on the step's own lattice)."""
    k0, k1 = math.floor(lo / step), math.ceil(hi / step)
    if k1 - k0 > 64:  # a wide span: coarser, at most ~65 settings per series
        step *= math.ceil((k1 - k0) / 64)
        k0, k1 = math.floor(lo / step), math.ceil(hi / step)
    return tuple(sorted(set(table) | {float(k * step) for k in range(k0, k1 + 1)}))


def b0_grid(top_db: float) -> tuple[float, ...]:
    """The cut's b0: B0_DB, widened to cover top - 36 dB .. top + 1 dB (everything cut)."""
    return _grid(B0_DB, min(B0_DB[0], top_db - 36.0), max(B0_DB[-1], top_db + 1.0), 1.0)


def g_grid(top_db: float) -> tuple[float, ...]:
    """The shaped quantizer's g (0.25 dB multiples within G_MIN..G_MAX): G_DB, widened to cover
    top - 50 dB .. top + 7 dB (every index 0; at the low end SPQI reaches 0.9 on real profiles)."""
    from hostd.codec import methods

    lo = max(methods.G_MIN_DB, min(G_DB[0], top_db - 50.0))
    hi = min(methods.G_MAX_DB, max(G_DB[-1], top_db + 7.0))
    return tuple(g for g in _grid(G_DB, lo, hi, 1.5) if methods.G_MIN_DB <= g <= methods.G_MAX_DB)


def sweep(y_um: np.ndarray, geometry: transform.Geometry, curve: ThresholdCurve,
          ab: tuple[float, float] = indices.DEFAULT_AB, with_peers: bool = True,
          progress: bool = True, repeats: int = TIME_REPEATS) -> list[dict]:
    """One row per stream. encode_ms: CPU of the heights -> stream path (DCT analysis and
    encoding); decode_ms: stream -> coefficients (what a receiver does before it renders);
    each the median thread CPU time of `repeats` runs."""
    c = transform.analyze(y_um, geometry.n_keep)
    b_k = curve(geometry.frequencies_hz())
    ref = indices.scaled_sums(c, b_k)
    top = peak_db(c, b_k)
    jobs = []
    for label, base in SERIES.items():
        params = LEVELS if base["method"] == "quant" else b0_grid(top)
        for v in params:
            key = "levels" if base["method"] == "quant" else "b0_db"
            jobs.append((label, {**base, key: v}))
    jobs += v2_jobs(top)
    rows = []
    with one_blas_thread():  # once: the CPU figures are this thread's work alone
        for label, kw in progress_bar(progress, iterable=jobs, desc="rate-quality", unit="stream",
                                      leave=False):
            rows.append(_row(label, kw, y_um, c, geometry, curve, b_k, ref, ab, with_peers, repeats))
    return rows


def _row(label, kw, y_um, c, geometry, curve, b_k, ref, ab, with_peers, repeats) -> dict:
    """Encode one setting, score it, time its encode and decode."""
    data = _encode(label, kw, c, geometry, curve)
    s = vtx.decode(data)
    sc = indices.scores_from_weighted(ref, indices.scaled_sums(s.coefficients, b_k), *ab)
    enc_s = cpu_median_s(lambda: _encode(label, kw, transform.analyze(y_um, geometry.n_keep),
                                         geometry, curve), repeats, limit_blas=False)
    dec_s = cpu_median_s(lambda: vtx.decode(data), repeats, limit_blas=False)
    row = {
        "series": label, "version": s.version, "method": s.method, "levels": s.levels,
        "b0_db": s.b0_db, "g_db": s.g_db,
        "value_bits": s.value_bits, "bytes": s.nbytes, "ratio_coeffs": s.ratio_coeffs,
        "ratio_profile": s.ratio_profile, "kept": int(np.count_nonzero(s.coefficients)),
        "Ip": float(sc.Ip), "Ia": float(sc.Ia), "Iobj": float(sc.Iobj),
        "wsnr_db": guard_column(c, s.coefficients, b_k),
        "ssnr_db": ssnr_column(c, s.coefficients, s.frequencies_hz),
        "st_sim": None, "spqi": None,
        "encode_ms": enc_s * 1e3, "decode_ms": dec_s * 1e3,
        "table_I": _in_table(s),
    }
    if with_peers:
        got = peer.peer_scores(c, s.coefficients, geometry.n, geometry.length_mm,
                               geometry.speed_mm_s) or {}
        for k in ("st_sim", "spqi"):  # a metric that is not finite at this scale: left empty
            v = got.get(k)
            row[k] = float(v) if v is not None and math.isfinite(v) else None
    return row


def v2_jobs(top_db: float = 0.0) -> list[tuple[str, dict]]:
    """The v2 series: the shaped quantizer at every g of g_grid(top_db)."""
    return [(label, {**base, "g_db": g}) for label, base in V2_SERIES.items() for g in g_grid(top_db)]


def _encode(label: str, kw: dict, c: np.ndarray, geometry: transform.Geometry,
            curve: ThresholdCurve) -> bytes:
    if label in V2_SERIES:
        from hostd.codec.stream import v2 as stream2

        ig = stream2.int_geometry(geometry)
        if ig.n_keep != c.size:
            raise ValueError("this geometry is not representable exactly in stream v2")
        return stream2.encode_coefficients(c, ig, curve, **kw)
    return vtx.v1.encode_coefficients(c, geometry, curve, **kw)


def guard_column(c: np.ndarray, decoded: np.ndarray, b_k: np.ndarray) -> float:
    """The waveform guard (threshold-weighted SNR, dB) of a decoded stream."""
    from hostd.perception import guard

    return guard.weighted_snr_db(c, decoded, b_k)


def ssnr_column(c: np.ndarray, decoded: np.ndarray, freqs_hz: np.ndarray) -> float:
    """The guard's second SNR (weighted by the SPQI model's threshold curve, dB)."""
    from hostd.perception import guard

    return guard.spectral_snr_db(c, decoded, freqs_hz)


def _in_table(s) -> bool:
    if s.method == "quant":
        return s.levels in TABLE_I_LEVELS
    if s.method == "shaped":
        return s.g_db in G_TABLE
    return s.b0_db in TABLE_I_B0


def _fmt(v) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.6g}" if math.isfinite(v) else str(v)
    return str(v)


def write_csv(rows: list[dict], path: Path) -> None:
    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(COLUMNS)
        for r in rows:
            w.writerow([_fmt(r[c]) for c in COLUMNS])


def write_markdown(rows: list[dict], path: Path, title: str, notes: list[str]) -> None:
    cols = ("series", "levels", "b0_db", "g_db", "bytes", "ratio_coeffs", "ratio_profile", "kept",
            "Ip", "Ia", "Iobj", "wsnr_db", "ssnr_db", "st_sim", "spqi", "encode_ms", "decode_ms")
    lines = [f"# Rate-quality: {title}", ""] + [f"- {n}" for n in notes] + [""]
    lines.append("| " + " | ".join(cols) + " |")
    lines.append("|" + "---|" * len(cols))
    for r in rows:
        if r["table_I"]:
            lines.append("| " + " | ".join(_fmt(r[c]) for c in cols) + " |")
    lines += ["", "(Table I levels of the paper shown; the CSV holds the full sweep. encode_ms: heights "
              "to stream, decode_ms: stream to coefficients; median thread CPU time of "
              f"{TIME_REPEATS} runs.)", ""]
    path.write_text("\n".join(lines), encoding="utf-8")


MARKERS = {"quant": "o-", "cut (exact survivors)": "s-", "cut (16-bit survivors)": "^-",
           "v2 shaped": "d-"}
IOBJ_LINTHRESH = 1e-3  # the index panels are linear below this, logarithmic above


def _index_axis(ax, top: float) -> None:
    """0 .. top on a symmetric-log scale: linear up to IOBJ_LINTHRESH, logarithmic above, so
    the region around the target (0.01-0.1) gets as much room as the decade 0.1-1."""
    from matplotlib.ticker import FixedLocator, FuncFormatter, NullLocator

    ax.set_yscale("symlog", linthresh=IOBJ_LINTHRESH, linscale=0.4)
    ax.set_ylim(0.0, top)
    ticks = [t for t in (0.0, 1e-3, 1e-2, 0.05, 0.1, 0.5, 1.0, 2.0) if t <= top]
    ax.yaxis.set_major_locator(FixedLocator(ticks))
    ax.yaxis.set_minor_locator(NullLocator())
    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _pos: f"{v:g}"))


def plot(rows: list[dict], path: Path, title: str, raw_coeff_bytes: int,
         ab: tuple[float, float] | None = None, target_iobj: float = TARGET_IOBJ) -> None:
    """Write `figure(...)` as a PNG."""
    from hostd.extras import need

    matplotlib = need("matplotlib", "plot", "the rate-quality PNG")

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = figure(rows, title, raw_coeff_bytes, ab, target_iobj)
    try:
        fig.savefig(path)
    finally:
        plt.close(fig)


LABELLED_PANELS = ("Iobj", "spqi")  # the panels whose points carry their setting (L=, dB, g=)


def figure(rows: list[dict], title: str, raw_coeff_bytes: int,
           ab: tuple[float, float] | None = None, target_iobj: float = TARGET_IOBJ):
    """Six panels sharing the byte axis (log scale, plain-number ticks): Iobj = a Ip + b Ia
    (target marked, its region shaded), Ip, Ia (all three on one symmetric-log scale where
    the target's region is visible), SPQI (criterion marked), and the encode and decode CPU
    time of each stream. Table I settings of the paper are labelled (L = levels for quant, b0
    in dB for cut, g for shaped) on the Iobj and SPQI panels only, where there is room (Ip and
    Ia share Iobj's settings; the CSV holds every value); constrained layout keeps titles, tick
    labels and the legend below the panels apart, and no two texts overlap
    (tests/test_users.py)."""
    from hostd.extras import need

    matplotlib = need("matplotlib", "plot", "the rate-quality figure")

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, grid = plt.subplots(2, 3, figsize=(15, 9.2), dpi=110, sharex=True, layout="constrained")
    axes = list(grid.ravel())
    a_, b_ = ab if ab is not None else (None, None)
    idx_top = 2.0 * (abs(a_) + abs(b_)) * 1.05 if ab is not None else 2.2
    panels = (("Iobj", "Iobj = a·Ip + b·Ia" + (f"  (a = {a_:g}, b = {b_:g})" if ab else ""),
               "Iobj [dimensionless]"),
              ("Ip", "Ip: relative error of the threshold-weighted power", "Ip [dimensionless]"),
              ("Ia", "Ia: relative error of the threshold-weighted amplitude", "Ia [dimensionless]"),
              ("spqi", "SPQI of the played signal (1 = identical)", "SPQI"),
              ("encode_ms", "encode: heights → stream (thread CPU, median)", "CPU ms per stream"),
              ("decode_ms", "decode: stream → coefficients (thread CPU, median)", "CPU ms per stream"))
    all_labels = []
    xs_all = [r["bytes"] for r in rows] + [raw_coeff_bytes]
    for ax, (key, label, ylabel) in zip(axes, panels, strict=True):
        labels = []
        have = [r for r in rows if r.get(key) is not None]
        for series_label in (*SERIES, *V2_SERIES):
            pts = sorted(((r["bytes"], r[key], r) for r in have if r["series"] == series_label),
                         key=lambda t: (t[0], t[1]))
            if not pts:
                continue
            ax.plot([p[0] for p in pts], [p[1] for p in pts], MARKERS.get(series_label, "o-"), ms=3.2,
                    lw=1.0, label=series_label)
            if series_label == "cut (16-bit survivors)" or key not in LABELLED_PANELS:
                continue  # one set of setting labels per panel, on the Iobj and SPQI panels only
            for bx, iy, r in pts:
                if r["table_I"]:
                    tag = (f"L={r['levels']}" if r["method"] == "quant"
                           else f"g={r['g_db']:+.0f}" if r["method"] == "shaped"
                           else f"{r['b0_db']:+.0f} dB")
                    labels.append((bx, iy, tag))
        ax.axvline(raw_coeff_bytes, color="grey", ls=":", lw=1, label="16-bit raw coefficients")
        log_byte_axis(ax, min(xs_all), max(xs_all))
        ax.set_ylabel(ylabel)
        ax.set_title(label, fontsize=9)
        ax.grid(True, alpha=0.3)
        if key in ("Iobj", "Ip", "Ia"):
            _index_axis(ax, idx_top)
        if key == "Iobj":
            ax.axhspan(0.0, target_iobj, color="tab:green", alpha=0.08, lw=0)
            ax.axhline(target_iobj, color="tab:green", ls="--", lw=1.2,
                       label=f"target Iobj ≤ {target_iobj:g}")
        elif key == "spqi":
            if have:
                lo = min(r["spqi"] for r in have)
                ax.set_ylim(min(0.8, lo - 0.02), 1.005)
                ax.axhspan(SPQI_CRITERION, 1.005, color="tab:purple", alpha=0.06, lw=0)
                ax.axhline(SPQI_CRITERION, color="tab:purple", ls="--", lw=1.2,
                           label=f"SPQI ≥ {SPQI_CRITERION:g}")
            else:
                ax.text(0.5, 0.5, "SPQI not computed:\n" + peer.NOTE_MISSING.split(": ", 1)[-1],
                        transform=ax.transAxes, ha="center", va="center", fontsize=8, color="grey")
        elif key.endswith("_ms"):
            ax.set_ylim(bottom=0)
        if ax in axes[3:]:
            ax.set_xlabel("encoded stream size [bytes, log scale] (header, payload, CRC)")
        all_labels.append(labels)
    handles, names = [], []
    for ax in axes:  # one legend for the figure: every series and every marked line, once
        for h, n in zip(*ax.get_legend_handles_labels(), strict=True):
            if n not in names:
                handles.append(h)
                names.append(n)
    fig.legend(handles, names, loc="outside lower center", ncol=min(len(names), 7), fontsize=8,
               frameon=False)
    fig.suptitle(f"Rate-quality: {title}", fontsize=11)
    # the layout once, then frozen: the labels placed below must not move the panels
    fig.draw_without_rendering()
    fig.set_layout_engine("none")
    for ax, labels in zip(axes, all_labels, strict=True):
        place_labels(ax, labels, draw=False)
    return fig


def check_out_dir(out_dir: str | Path) -> Path:
    """The report's folder: created if missing; anything else that is not a writable
    directory (a file, /dev/null) is a one-line error, before any work is done."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise HostdError(f"-o {out} is not a directory: -o names the folder that receives "
                         "rate_quality.csv, .md and .png (use --json to print the rows as well)")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise HostdError(f"cannot create the report folder {out}: {exc.strerror or exc}") from None
    if not os.access(out, os.W_OK | os.X_OK):
        raise HostdError(f"cannot write into the report folder {out}: check its permissions")
    return out


def rate_quality(y_um: np.ndarray, geometry: transform.Geometry, curve: ThresholdCurve,
                 out_dir: str | Path, title: str,
                 ab: tuple[float, float] = indices.DEFAULT_AB, progress: bool = True) -> dict:
    out = check_out_dir(out_dir)
    rows = sweep(y_um, geometry, curve, ab, progress=progress)
    notes = [
        f"N = {geometry.n}, L = {geometry.length_mm:.6g} mm, v_ref = {geometry.speed_mm_s:g} mm/s,"
        f" fmax = {geometry.fmax_hz:g} Hz, N' = {geometry.n_keep}",
        f"threshold curve {curve.name} ({curve.curve_id}), (a, b) = {ab}",
        f"16-bit raw coefficients: {2 * geometry.n_keep} bytes; raw 16-bit profile: "
        f"{2 * geometry.n} bytes",
        f"encode_ms / decode_ms: median thread CPU time of {TIME_REPEATS} runs per stream",
    ]
    if all(r["spqi"] is None for r in rows):
        notes.append(peer.NOTE_MISSING)
    try:
        write_csv(rows, out / "rate_quality.csv")
        write_markdown(rows, out / "rate_quality.md", title, notes)
        plot(rows, out / "rate_quality.png", title, 2 * geometry.n_keep, ab=ab)
    except OSError as exc:
        raise HostdError(f"cannot write the report into {out}: {exc.strerror or exc}") from None
    return {"rows": rows, "notes": notes, "dir": str(out)}
