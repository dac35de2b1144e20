"""A calibration: one display's detection thresholds b(f) and Iobj's weights (a, b), with where
they came from, in one TOML file that every command (`--calibration FILE`) and the daemon's
quality log (`quality.calibration`) read.

    format = "hostd-calibration-1"
    name = "lab-a"
    a = 0.581
    b = 0.464
    [thresholds]
    frequency_hz = [40.0, 100.0, 250.0]
    threshold_um = [3.1, 0.55, 0.09]
    [provenance]                 # free text: who, when, how (hostd experiment writes it)
    thresholds = "hostd experiment threshold ..."

Its id is the first 8 bytes (hex) of SHA-256 over the curve's canonical table and (a, b) as
little-endian float64: the same numbers give the same id, whatever the name or provenance say.
Each quality-log row records `NAME@ID` of the calibration that scored it.
"""

from __future__ import annotations

import hashlib
import math
import os
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hostd.errors import ThresholdError
from hostd.perception.thresholds import ThresholdCurve, canonical_table, default_curve, load_csv

FORMAT = "hostd-calibration-1"
SUFFIX = ".toml"


@dataclass(frozen=True)
class Calibration:
    curve: ThresholdCurve
    a: float
    b: float
    name: str = "calibration"
    provenance: dict = field(default_factory=dict)

    @property
    def cal_id(self) -> str:
        blob = canonical_table(self.curve.freq_hz, self.curve.threshold_um)
        blob += struct.pack("<dd", self.a, self.b)
        return hashlib.sha256(blob).digest()[:8].hex()

    @property
    def label(self) -> str:
        """What a quality-log row records: NAME@ID."""
        return f"{self.name}@{self.cal_id}"


def is_calibration(path: str | Path) -> bool:
    return str(path).endswith(SUFFIX)


def load(path: str | Path) -> Calibration:
    from hostd.tomlfile import read

    p = Path(path)
    doc = read(p, "calibration file", "make one with hostd experiment calibration", exc=ThresholdError)
    if doc.get("format") != FORMAT:
        raise ThresholdError(f"{p}: not a hostd calibration (format = \"{FORMAT}\" expected)")
    for k in ("a", "b"):
        v = doc.get(k)
        if not isinstance(v, int | float) or isinstance(v, bool) or not math.isfinite(v):
            raise ThresholdError(f"{p}: {k} must be a finite number (Iobj = a Ip + b Ia)")
    t = doc.get("thresholds")
    if not isinstance(t, dict) or not isinstance(t.get("frequency_hz"), list) \
            or not isinstance(t.get("threshold_um"), list):
        raise ThresholdError(f"{p}: [thresholds] needs frequency_hz = [...] and threshold_um = [...]")
    try:
        f = np.array(t["frequency_hz"], dtype=np.float64)
        b = np.array(t["threshold_um"], dtype=np.float64)
    except (TypeError, ValueError):
        raise ThresholdError(f"{p}: [thresholds] frequency_hz and threshold_um must be numbers") from None
    prov = doc.get("provenance", {})
    if not isinstance(prov, dict):
        raise ThresholdError(f"{p}: [provenance] must be a table")
    name = doc.get("name", p.stem)
    if not isinstance(name, str) or not name or any(c.isspace() or c == "@" for c in name):
        raise ThresholdError(f"{p}: name must be one word without '@'")
    return Calibration(ThresholdCurve(f, b, name=name), float(doc["a"]), float(doc["b"]), name,
                       {str(k): str(v) for k, v in prov.items()})


def load_curve(path: str | Path) -> ThresholdCurve:
    """What a --thresholds option (or the quality.thresholds key) names: a threshold CSV, or a
    calibration file (.toml), whose curve it gives: every reader of that option takes one as-is."""
    return load(path).curve if is_calibration(path) else load_csv(path)


def resolve_curve(path: str | Path | None) -> ThresholdCurve:
    """load_curve(path), or the shipped default curve when no path is given."""
    return load_curve(path) if path else default_curve()


def _toml_str(s: str) -> str:
    return '"' + s.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n") + '"'


def dumps(cal: Calibration) -> str:
    lines = [f"# hostd calibration {cal.label}: detection thresholds b(f) in µm peak and Iobj's "
             "weights (a, b)",
             f"format = {_toml_str(FORMAT)}", f"name = {_toml_str(cal.name)}",
             f"a = {cal.a!r}", f"b = {cal.b!r}", "", "[thresholds]",
             "frequency_hz = [" + ", ".join(repr(float(v)) for v in cal.curve.freq_hz) + "]",
             "threshold_um = [" + ", ".join(repr(float(v)) for v in cal.curve.threshold_um) + "]",
             "", "[provenance]"]
    lines += [f"{k} = {_toml_str(v)}" for k, v in sorted(cal.provenance.items())]
    return "\n".join(lines) + "\n"


def write(path: str | Path, cal: Calibration) -> None:
    """Written whole or not at all (a temporary file renamed over the target)."""
    p = Path(path)
    tmp = p.with_name(f".{p.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(dumps(cal))
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, p)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        raise ThresholdError(f"cannot write the calibration {p}: {e.strerror or e}") from None
    if load(p).cal_id != cal.cal_id:  # the file says what was meant (float repr round-trips)
        raise ThresholdError(f"{p}: the calibration written does not read back the same")
