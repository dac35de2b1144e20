"""Issue 11 item 6: the encoder writes the same bytes on every CPU.

Every golden vector is regenerated in fresh interpreters under different OpenBLAS kernels
(OPENBLAS_CORETYPE) and with numpy's run-time SIMD dispatch switched off
(NPY_DISABLE_CPU_FEATURES); every run must reproduce the committed files byte for byte. A
probe dot product shows that the kernels really differ (so the test can fail: numpy's dot
gave different last bits under Sandybridge, Haswell and the generic kernel here).
Cores the machine cannot run (AVX-512 kernels on an AVX2 CPU die with SIGILL) are skipped.
"""

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from hostd.perception import indices
from tests.conftest import ROOT, VECTORS

SCRIPT = r"""
import hashlib, json, sys
import numpy as np
from tests.vectors.make_stream_vectors import build
rng = np.random.default_rng(7)
a, b = rng.normal(size=161), rng.normal(size=161)
out = {"probe_dot": repr(float(a @ b)),
       "vectors": {k: hashlib.sha256(v).hexdigest() for k, v in build().items()}}
print(json.dumps(out))
"""

VARIANTS = [
    {"OPENBLAS_CORETYPE": "Prescott"},
    {"OPENBLAS_CORETYPE": "Sandybridge"},
    {"OPENBLAS_CORETYPE": "Haswell"},
    {"OPENBLAS_CORETYPE": "Zen"},
    {"OPENBLAS_CORETYPE": "SkylakeX"},
    {"NPY_DISABLE_CPU_FEATURES": "X86_V3 X86_V4 AVX512_ICL AVX512_SPR"},
]


def _run(extra: dict, script: str = SCRIPT) -> dict | None:
    env = {k: v for k, v in os.environ.items()
           if k not in ("OPENBLAS_CORETYPE", "NPY_DISABLE_CPU_FEATURES")}
    env.update(extra, OPENBLAS_VERBOSE="2", PYTHONPATH=str(ROOT), OPENBLAS_NUM_THREADS="1")
    p = subprocess.run([sys.executable, "-c", script], env=env, cwd=ROOT, capture_output=True,
                       text=True, timeout=120)
    if p.returncode < 0:  # SIGILL: this CPU cannot run the forced kernel
        return None
    assert p.returncode == 0, p.stderr[-2000:]
    res = json.loads(p.stdout.strip().splitlines()[-1])
    res["core"] = " ".join(ln for ln in p.stderr.splitlines() if ln.startswith("Core"))
    return res


def test_vectors_are_byte_identical_under_every_blas_kernel_and_simd_level():
    committed = {p.stem: hashlib.sha256(p.read_bytes()).hexdigest()
                 for p in VECTORS.glob("*.vtx")}
    runs = {json.dumps(v): r for v in VARIANTS if (r := _run(v)) is not None}
    assert len(runs) >= 3, "fewer than three kernel variants could run here"
    for variant, r in runs.items():
        for name, digest in r["vectors"].items():
            assert committed.get(name) == digest, f"{name} differs under {variant} ({r['core']})"
    # The variants are not all the same kernel: numpy's own dot differs between them.
    assert len({r["probe_dot"] for r in runs.values()}) >= 2, {
        k: (r["core"], r["probe_dot"]) for k, r in runs.items()}


DEVICE_SCRIPT = r"""
import hashlib, json, math
from dataclasses import replace
import numpy as np
from hostd.device import devrender
from hostd.render.equalizer import ActuatorModel, EqualizerConfig, design, load_actuator
from hostd.render.pipeline import RenderConfig

def digest(params):
    return hashlib.sha256(repr(sorted((k, np.asarray(v).tobytes()) for k, v in params.items()))
                          .encode()).hexdigest()

cfg = RenderConfig()
out = {"default": digest(devrender.device_params(cfg)),
       "measured": digest(devrender.device_params(replace(cfg, actuator=load_actuator("example-measured"))))}
for corner, damping in ((150.0, 0.3), (270.0, 1.0), (400.0, 2.5), (600.0, 1.0000001)):
    for order in range(2, 9):
        sos = design(ActuatorModel(corner_hz=corner, damping=damping), EqualizerConfig(reg_order=order))
        out[f"{corner:g} Hz, damping {damping:g}, order {order}"] = hashlib.sha256(sos.tobytes()).hexdigest()
rng = np.random.default_rng(3)
h = hashlib.sha256()
for _ in range(300):  # libm's FMA and plain builds round 1 argument in ~1500 differently: many designs
    model = ActuatorModel(corner_hz=float(rng.uniform(80, 700)), damping=float(rng.uniform(0.2, 3.0)))
    h.update(design(model, EqualizerConfig(reg_order=int(rng.integers(2, 9)),
                                           reg_hz=float(rng.uniform(800, 1450)))).tobytes())
out["300 random designs"] = h.hexdigest()
rng = np.random.default_rng(7)
a, b = rng.normal(size=161), rng.normal(size=161)
out["probe_dot"] = repr(float(a @ b))
xs = rng.uniform(-4, 4, 20000).tolist()
out["probe_libm"] = hashlib.sha256(repr([math.exp(x) + math.sin(x) for x in xs]).encode()).hexdigest()
print(json.dumps(out))
"""
# glibc's libm as on a CPU without FMA (its exp, sin, cos, ... then take the plain builds)
NO_FMA = {"GLIBC_TUNABLES": "glibc.cpu.hwcaps=-AVX2,-FMA"}


def test_device_parameters_are_byte_identical_under_every_blas_kernel_and_simd_level():
    """What a display is told to render with (the equalizer's sections, designed from the model
    or fitted to a measured table; the band, scale and delay) is the same bytes on every CPU:
    two displays driven from an Intel and an AMD host render the same samples. Also with glibc's
    libm as on a CPU without FMA, whose exp/sin/cos differ in the last bit for some arguments."""
    runs = {json.dumps(v): r for v in [*VARIANTS, NO_FMA] if (r := _run(v, DEVICE_SCRIPT)) is not None}
    assert len(runs) >= 3, "fewer than three kernel variants could run here"
    assert len({r["probe_dot"] for r in runs.values()}) >= 2, {
        k: (r["core"], r["probe_dot"]) for k, r in runs.items()}
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.exists() and "fma" in cpuinfo.read_text().split():  # then libm differs between them too
        assert len({r["probe_libm"] for r in runs.values()}) >= 2
    first_variant, first = next(iter(runs.items()))
    for variant, r in runs.items():
        for name, digest in r.items():
            if not name.startswith("probe") and name != "core":
                assert digest == first[name], (f"{name}: differs under {variant} ({r['core']}) "
                                               f"from {first_variant} ({first['core']})")


def test_weighted_sums_are_correctly_rounded_and_order_independent(rng):
    from fractions import Fraction

    b = rng.uniform(0.05, 5.0, 160)
    c = rng.normal(0, 1, 160) * 10.0 ** rng.uniform(-6, 3, 160)
    P, A = indices.weighted_sums(c, b)
    w2, w1 = indices.weights(b)
    exact_P = sum(Fraction(float(x)) for x in (c * c) * w2)
    exact_A = sum(Fraction(float(x)) for x in np.abs(c) * w1)
    assert float(P) == float(exact_P) and float(A) == float(exact_A)
    perm = rng.permutation(160)
    assert indices.weighted_sums(c[perm], b[perm]) == (P, A)
