"""`hostd bench soak`: the real daemon playing one texture on the firmware's host port for
minutes, optionally with a CPU hog on the other core.

Every playback figure comes from the firmware's DAC log (what the device actually played,
tick by tick) and the device's own counters, never from the host's bookkeeping: played
fraction, underrun episodes, silences (their count is the recoveries the device saw), the
longest silence. The host side adds what only it can know: the stalls it measured on itself
(pauses longer than the buffer), the pump process's CPU share, and the CPU time of one pump
cycle (p50/p99/p99.9, thread CPU time).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from hostd.device import hostport
from hostd.errors import HostdError

HOG = "import os, sys\nos.sched_setaffinity(0, {int(sys.argv[1])})\nwhile True:\n    pass\n"


def _proc_cpu_s(pid: int) -> float:
    """utime + stime of a process, in seconds (from /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def child_pids(pid: int) -> list[int]:
    """The process's children, from /proc (every thread's list)."""
    out = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            out += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            pass
    return out


def _pump_pid(daemon_pid: int) -> int | None:
    """The daemon's pump process (a multiprocessing 'spawn' child)."""
    for c in child_pids(daemon_pid):
        try:
            if "spawn_main" in Path(f"/proc/{c}/cmdline").read_text():
                return c
        except OSError:
            pass
    return None


def run(minutes: float = 10.0, load: bool = False, texture: str = "wood", progress: bool = True,
        host_cycle_ms: int = 1) -> dict:
    from hostd.codec import stream as vtx
    from hostd.codec import transform
    from hostd.perception import thresholds
    from hostd.service.client import ClientError, request, send_file
    from hostd.texture import synth

    seconds = minutes * 60.0
    hogs: list[subprocess.Popen] = []
    with tempfile.TemporaryDirectory(prefix="hostd-soak-") as tmp:
        d = Path(tmp)
        log = d / "dac.bin"
        hp = hostport.HostPort(["--motion", "metronome", "--duration", str(seconds + 120)], log=log)
        cfg = d / "hostd.toml"
        cfg.write_text(f'[device]\ntransport = "serial:{hp.pty}"\nhost_cycle_ms = {int(host_cycle_ms)}\n'
                       '[library]\ndir = "lib"\nspool = "spool"\n'
                       '[control]\nsocket = "hostd.sock"\ngroup = ""\n[quality]\ndb = "q.sqlite"\n')
        sock = str(d / "hostd.sock")
        daemon = subprocess.Popen([sys.executable, "-m", "hostd", "run", "--config", str(cfg)], cwd=d,
                                  stderr=open(d / "hostd.log", "w"), stdout=subprocess.DEVNULL)
        try:
            t_end = time.monotonic() + 60
            while True:
                try:
                    if request(sock, {"cmd": "status"}, timeout_s=2)["connected"]:
                        break
                except ClientError:
                    pass
                if time.monotonic() > t_end or daemon.poll() is not None:
                    raise HostdError(f"the daemon did not connect to the host port: "
                                     f"{(d / 'hostd.log').read_text()[-500:]}")
                time.sleep(0.1)
            prof = synth.make(texture, seed=1)
            f = d / "texture.vtx"
            f.write_bytes(vtx.encode_profile(prof.heights_um, transform.Geometry(prof.n, prof.length_mm),
                                             thresholds.default_curve(), method="quant", levels=14))
            send_file(sock, str(f), "soak")
            request(sock, {"cmd": "select", "name": "soak"})
            if load:
                cpu = max(os.sched_getaffinity(0))
                hogs.append(subprocess.Popen([sys.executable, "-c", HOG, str(cpu)]))
            pump = _pump_pid(daemon.pid)
            cpu0 = _proc_cpu_s(pump) if pump else 0.0
            dcpu0 = _proc_cpu_s(daemon.pid)
            cycles0 = request(sock, {"cmd": "status"})["cycles"]
            t0 = time.monotonic()
            bar = None
            if progress:
                from tqdm import tqdm

                bar = tqdm(total=int(seconds), unit="s", desc="soak", leave=False)
            while (el := time.monotonic() - t0) < seconds:
                time.sleep(min(1.0, seconds - el))
                if bar is not None:
                    bar.n = int(time.monotonic() - t0)
                    bar.refresh()
            wall = time.monotonic() - t0
            cpu1 = _proc_cpu_s(pump) if pump else 0.0
            dcpu1 = _proc_cpu_s(daemon.pid)
            st = request(sock, {"cmd": "status"})
            if bar is not None:
                bar.close()
        finally:
            hp.close()  # the DAC log ends while the texture still plays
            for h in hogs:
                h.send_signal(signal.SIGKILL)
                h.wait()
            if daemon.poll() is None:
                daemon.terminate()
                daemon.wait(20)
        fig = hostport.playback_figures(hostport.read_log(log))
    return {
        "minutes": minutes, "load": load,
        "played_fraction": round(fig["played_fraction"], 6),
        "underrun_episodes": fig["underrun_episodes"],
        "silences": len(fig["silences"]),
        # silences followed by playback again: the recoveries the device saw
        "recoveries": fig["recovered_silences"],
        "longest_silence_ms": round(fig["longest_silence_ms"], 1),
        "device_underruns": st["device_underruns"],  # the daemon's health figure, to compare
        "stalls": st["stalls"], "longest_stall_ms": round(st["longest_stall_ms"], 1),
        "host_recoveries": st["recoveries"],  # episodes the host saw (a burst of silences counts once)
        "host_cycle_ms": int(host_cycle_ms),
        "pump_cpu_share": round((cpu1 - cpu0) / wall, 4) if pump else None,
        "daemon_cpu_share": round((dcpu1 - dcpu0) / wall, 4),  # the daemon process, its pump excluded
        # the pump process's CPU per cycle (a loaded machine skips cycles: the share alone hides it)
        "pump_cpu_us_per_cycle": round((cpu1 - cpu0) / max(1, st["cycles"] - cycles0) * 1e6, 1) if pump
        else None,
        "cycles_per_s": round((st["cycles"] - cycles0) / wall, 1),
        "batch_p50_us": round(st["batch_p50_us"], 1), "batch_p99_us": round(st["batch_p99_us"], 1),
        "batch_p999_us": round(st["batch_p999_us"], 1),
    }
