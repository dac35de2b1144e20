"""Rate-quality report: both methods swept, real stream bytes against Ip, Ia, Iobj (+ peers)."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
from tqdm import tqdm

from hostd.codec import stream as vtx
from hostd.codec import transform
from hostd.perception import indices, peer
from hostd.perception.thresholds import ThresholdCurve
from hostd.plotting import place_labels

TABLE_I_LEVELS = (14, 12, 10, 8, 6, 5, 4)
TABLE_I_B0 = (-12, -8, -4, 0, 4, 8, 12)
LEVELS = (*range(2, 17), 20, 24, 32, 48, 64)
B0_DB = tuple(float(b) for b in range(-16, 17))
SERIES = {  # label -> encoder settings besides the swept parameter
    "quant": {"method": "quant"},
    "cut (exact survivors)": {"method": "cut", "value_bits": 0},
    "cut (16-bit survivors)": {"method": "cut", "value_bits": 16},
}
# Stream v2 (issue 14): the threshold-shaped quantizer swept over its knob g.
V2_SERIES = {"v2 shaped": {"method": "shaped"}}
G_DB = tuple(float(g) for g in np.arange(-30.0, 15.0 + 1e-9, 1.5))
G_TABLE = (-24.0, -18.0, -12.0, -6.0, 0.0, 6.0, 12.0)
COLUMNS = ("series", "version", "method", "levels", "b0_db", "g_db", "value_bits", "bytes",
           "ratio_coeffs", "ratio_profile", "kept", "Ip", "Ia", "Iobj", "wsnr_db", "ssnr_db", "st_sim",
           "spqi", "table_I")


def sweep(y_um: np.ndarray, geometry: transform.Geometry, curve: ThresholdCurve,
          ab: tuple[float, float] = indices.DEFAULT_AB, with_peers: bool = True,
          progress: bool = True) -> list[dict]:
    c = transform.analyze(y_um, geometry.n_keep)
    b_k = curve(geometry.frequencies_hz())
    P, A = indices.weighted_sums(c, b_k)
    jobs = []
    for label, base in SERIES.items():
        params = LEVELS if base["method"] == "quant" else B0_DB
        for v in params:
            key = "levels" if base["method"] == "quant" else "b0_db"
            jobs.append((label, {**base, key: v}))
    jobs += v2_jobs()
    peers_on = with_peers and peer.available()
    rows = []
    for label, kw in tqdm(jobs, desc="rate-quality", unit="stream", disable=not progress,
                          leave=False):
        data = _encode(label, kw, c, geometry, curve)
        s = vtx.decode(data)
        Pp, Ap = indices.weighted_sums(s.coefficients, b_k)
        sc = indices.scores_from_sums(P, A, Pp, Ap, *ab)
        row = {
            "series": label, "version": s.version, "method": s.method, "levels": s.levels,
            "b0_db": s.b0_db, "g_db": s.g_db,
            "value_bits": s.value_bits, "bytes": s.nbytes, "ratio_coeffs": s.ratio_coeffs,
            "ratio_profile": s.ratio_profile, "kept": int(np.count_nonzero(s.coefficients)),
            "Ip": float(sc.Ip), "Ia": float(sc.Ia), "Iobj": float(sc.Iobj),
            "wsnr_db": guard_column(c, s.coefficients, b_k),
            "ssnr_db": ssnr_column(c, s.coefficients, s.frequencies_hz),
            "st_sim": None, "spqi": None,
            "table_I": _in_table(s),
        }
        if peers_on:
            row.update(peer.peer_scores(c, s.coefficients, geometry.n, geometry.length_mm,
                                        geometry.speed_mm_s) or {})
        rows.append(row)
    return rows


def v2_jobs() -> list[tuple[str, dict]]:
    """The v2 series: the shaped quantizer at every g of G_DB."""
    return [(label, {**base, "g_db": g}) for label, base in V2_SERIES.items() for g in G_DB]


def _encode(label: str, kw: dict, c: np.ndarray, geometry: transform.Geometry,
            curve: ThresholdCurve) -> bytes:
    if label in V2_SERIES:
        from hostd.codec import stream2

        ig = stream2.int_geometry(geometry)
        if ig.n_keep != c.size:
            raise ValueError("this geometry is not representable exactly in stream v2")
        return stream2.encode_coefficients(c, ig, curve, **kw)
    return vtx.encode_coefficients(c, geometry, curve, **kw)


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
            "Ip", "Ia", "Iobj", "wsnr_db", "ssnr_db", "st_sim", "spqi")
    lines = [f"# Rate-quality: {title}", ""] + [f"- {n}" for n in notes] + [""]
    lines.append("| " + " | ".join(cols) + " |")
    lines.append("|" + "---|" * len(cols))
    for r in rows:
        if r["table_I"]:
            lines.append("| " + " | ".join(_fmt(r[c]) for c in cols) + " |")
    lines += ["", "(Table I levels of the paper shown; the CSV holds the full sweep.)", ""]
    path.write_text("\n".join(lines), encoding="utf-8")


def plot(rows: list[dict], path: Path, title: str, raw_coeff_bytes: int,
         ab: tuple[float, float] | None = None) -> None:
    """Three panels sharing the byte axis: Iobj = a Ip + b Ia (with a, b), Ip and Ia. Table I
    settings of the paper are labelled (L = levels for quant, b0 in dB for cut) where there
    is room; the cut series with 16-bit survivors shares the b0 labels of the exact one."""
    from hostd.extras import need

    matplotlib = need("matplotlib", "plot", "the rate-quality PNG")

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 5), dpi=110, sharex=True)
    markers = {"quant": "o-", "cut (exact survivors)": "s-", "cut (16-bit survivors)": "^-",
               "v2 shaped": "d-"}
    a_, b_ = ab if ab is not None else (None, None)
    panels = (("Iobj", "Iobj = a·Ip + b·Ia" + (f"  (a = {a_:g}, b = {b_:g})" if ab else "")),
              ("Ip", "Ip: relative error of the threshold-weighted power"),
              ("Ia", "Ia: relative error of the threshold-weighted amplitude"))
    all_labels = []
    for ax, (key, label) in zip(axes, panels, strict=True):
        labels = []
        for series_label in (*SERIES, *V2_SERIES):
            pts = sorted(((r["bytes"], r[key], r) for r in rows if r["series"] == series_label),
                         key=lambda t: (t[0], t[1]))
            if not pts:
                continue
            ax.plot([p[0] for p in pts], [p[1] for p in pts], markers.get(series_label, "o-"), ms=3.5,
                    lw=1.1, label=series_label)
            if series_label == "cut (16-bit survivors)":
                continue  # same b0 settings as the exact series: one set of labels is enough
            for bx, iy, r in pts:
                if r["table_I"]:
                    tag = (f"L={r['levels']}" if r["method"] == "quant"
                           else f"g={r['g_db']:+.0f} dB" if r["method"] == "shaped"
                           else f"{r['b0_db']:+.0f} dB")
                    labels.append((bx, iy, tag))
        ax.axvline(raw_coeff_bytes, color="grey", ls=":", lw=1)
        ax.text(raw_coeff_bytes, 0.98, " 16-bit raw\n coefficients", transform=ax.get_xaxis_transform(),
                fontsize=7, color="grey", va="top")
        ax.set_xscale("log")  # quant's steep small-stream end gets room next to cut's long tail
        ax.set_xlabel("encoded stream size [bytes, log scale] (header, payload, CRC)")
        ax.set_ylabel(f"{key} [dimensionless]")
        ax.set_title(label, fontsize=9)
        ax.grid(True, alpha=0.3)
        ax.set_ylim(bottom=0)
        all_labels.append(labels)
    axes[0].legend(title="method", fontsize=8)
    fig.suptitle(f"Rate-quality: {title}", fontsize=11)
    fig.tight_layout()
    for ax, labels in zip(axes, all_labels, strict=True):
        # after the layout the pixel scale is final once the (lazy) autoscaled limits are set:
        # no full draw is needed before savefig's
        ax.get_xlim(), ax.get_ylim()
        place_labels(ax, labels, draw=False)
    fig.savefig(path)
    plt.close(fig)


def rate_quality(y_um: np.ndarray, geometry: transform.Geometry, curve: ThresholdCurve,
                 out_dir: str | Path, title: str,
                 ab: tuple[float, float] = indices.DEFAULT_AB, progress: bool = True) -> dict:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows = sweep(y_um, geometry, curve, ab, progress=progress)
    notes = [
        f"N = {geometry.n}, L = {geometry.length_mm:.6g} mm, v_ref = {geometry.speed_mm_s:g} mm/s,"
        f" fmax = {geometry.fmax_hz:g} Hz, N' = {geometry.n_keep}",
        f"threshold curve {curve.name} ({curve.curve_id}), (a, b) = {ab}",
        f"16-bit raw coefficients: {2 * geometry.n_keep} bytes; raw 16-bit profile: "
        f"{2 * geometry.n} bytes",
    ]
    if not peer.available():
        notes.append(peer.NOTE_MISSING)
    write_csv(rows, out / "rate_quality.csv")
    write_markdown(rows, out / "rate_quality.md", title, notes)
    plot(rows, out / "rate_quality.png", title, 2 * geometry.n_keep, ab=ab)
    return {"rows": rows, "notes": notes, "dir": str(out)}
