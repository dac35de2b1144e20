"""Latency from a change of encoder position to the first DAC sample that reflects it,
measured through the real firmware (host port) on a pseudo-terminal.

The host port's hand jumps between 0 and `step_mm` every `period_s`. Its log holds, per 3 kHz
tick, the encoder count it decoded and the DAC code it wrote, both on the device's clock; the
latency of one step is the first tick whose code differs from the resting code minus the
tick at which the count changed.
"""

from __future__ import annotations

import subprocess
import tempfile
from pathlib import Path

import numpy as np

from hostd.device import hostport


def run(duration_s: float = 8.0, target_fill: int = 12, period_s: float = 0.4, step_mm: float = 0.05) -> dict:
    from hostd.bench.accuracy import texture_coeffs
    from hostd.device.link import DeviceLink
    from hostd.device.pump import Pump
    from hostd.device.seriallink import SerialTransport
    from hostd.render import RenderConfig, Renderer
    from hostd.texture import synth

    exe = hostport.build()
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "dac.bin"
        proc = subprocess.Popen([str(exe), "--motion", f"steps:{period_s}:{step_mm}", "--log", str(log),
                                 "--duration", str(duration_s + 2)], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        try:
            port = proc.stdout.readline().split()[1]
            t = SerialTransport(port)
            link = DeviceLink(t, target_fill=target_fill)
            link.handshake(timeout_s=2.0)
            c, n, length = texture_coeffs(synth.make("sandpaper", seed=1))
            r = Renderer(c, n, length, RenderConfig())
            r.start()
            pump = Pump(link, None)
            link.poll(0.01)
            pump.begin(r)
            pump.run(duration_s)
            link.poll(0.01)
            underruns = pump.health.underruns
            link.stop()
            t.close()
        finally:
            proc.terminate()
            proc.communicate(timeout=10)
        rec = hostport.read_log(log)
    enc = rec["enc"].astype(np.int64)
    code = rec["code"].astype(np.int64)
    changes = np.flatnonzero(np.diff(enc) != 0) + 1
    lat_ticks = []
    for i in changes:
        if i < 3000:  # let start-up and the soft start pass
            continue
        rest = code[i - 1]
        after = np.flatnonzero(code[i : i + 900] != rest)
        if after.size:
            lat_ticks.append(int(after[0]))
    lat_ms = np.array(lat_ticks) / 3.0
    return {"bench": "latency", "link": "pty (firmware host port)", "target_fill": target_fill,
            "events": int(lat_ms.size), "underruns": underruns,
            "p50_ms": float(np.median(lat_ms)) if lat_ms.size else float("nan"),
            "min_ms": float(lat_ms.min()) if lat_ms.size else float("nan"),
            "max_ms": float(lat_ms.max()) if lat_ms.size else float("nan")}
