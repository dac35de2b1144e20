"""`hostd bench soak`: the real daemon playing one texture on the firmware's host port for
minutes, optionally with a CPU hog on the other core, rendering on the host, on the device or
where `[render] where = "auto"` puts it; `--runs N` repeats it and reports the medians.

Every playback figure comes from the firmware's DAC log (what the device actually played,
tick by tick) and the device's own counters, never from the host's bookkeeping: played
fraction (host rendering: ticks played from the buffer; device rendering: ticks rendered at
full gain, the log's FULL_GAIN flag), underrun episodes (device rendering: its host-lost
episodes and the silences), the longest silence. The host side adds what only it can know: the
stalls it measured on itself, the daemon's and the pump process's CPU share (every thread's time
on a CPU, /proc/PID/task/*/schedstat, over the run), their wake-ups per second (voluntary
context switches of every thread, /proc/PID/task/*/status), their footprint (PSS from
/proc/PID/smaps_rollup and threads, the peak over the run), and the CPU time of one
host-rendering cycle (p50/p99/p99.9).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from hostd.device import hostport
from hostd.errors import HostdError
from hostd.procstat import CpuClock, child_pids, pss_kb, threads

HOG = "import os, sys\nos.sched_setaffinity(0, {int(sys.argv[1])})\nwhile True:\n    pass\n"


def mapped_libs(pid: int, packages: tuple[str, ...] = ("scipy", "matplotlib", "PIL", "finufft")) -> list[str]:
    """What the process imported beyond numpy, from the shared libraries it maps
    (/proc/PID/maps): each of `packages` with a library mapped, scipy by subpackage (scipy.fft is
    the codec's pocketfft, hostd.pocketfft; scipy.libs its own BLAS, loaded by scipy.linalg)."""
    found = set()
    try:
        for line in Path(f"/proc/{pid}/maps").read_text().splitlines():
            path = line.split(None, 5)[-1] if line.count(" ") >= 5 else ""
            for pkg in packages:
                i = path.find(f"/site-packages/{pkg}")
                if i < 0:
                    continue
                rest = path[i + len("/site-packages/"):]
                top, _, sub = rest.partition("/")
                if top == pkg and pkg == "scipy" and "/" in sub:
                    found.add(f"scipy.{sub.split('/')[0]}")
                elif top == pkg or top.startswith(pkg + "."):
                    found.add(top)
    except OSError:
        pass
    return sorted(found)


def _pump_pid(daemon_pid: int) -> int | None:
    """The daemon's pump process (a multiprocessing 'spawn' child)."""
    for c in child_pids(daemon_pid):
        try:
            if "spawn_main" in Path(f"/proc/{c}/cmdline").read_text():
                return c
        except OSError:
            pass
    return None


def _start_fleet(fleet: bool | None, seconds: float, db: Path, sock: str, out: dict):
    """The fleet shipper beside the daemon (hostd.fleet.bench: a live PostgreSQL, one row a second
    into the daemon's log), in a thread filling `out`; None when not asked (fleet=None: when
    psycopg and a PostgreSQL server are installed; under CI=true their absence is an error). A run
    shorter than 20 s (two of the shipper's default looks) has it look every 2 s: its PSS and its
    CPU per central commit, not its CPU share, which only the default look gives."""
    import threading

    if fleet is None:
        from importlib.util import find_spec

        from hostd.fleet.localpg import bindir

        fleet = find_spec("psycopg") is not None and bindir() is not None
        if not fleet and os.environ.get("CI") == "true":
            raise HostdError("the soak measures the fleet shipper in CI: install psycopg (./run does) and "
                             "PostgreSQL's server (apt-get install postgresql)")
    if not fleet:
        return None
    from hostd.fleet import bench as fleet_bench

    def measure():
        try:
            out.update(fleet_bench.measure(seconds, db=db, socket=sock,
                                           interval_s=2.0 if seconds < 20 else None))
        except Exception as e:  # reported with the row, not lost in the thread
            out["error"] = str(e)

    t = threading.Thread(target=measure, daemon=True)
    t.start()
    return t


def run(minutes: float = 10.0, load: bool = False, texture: str = "wood", progress: bool = True,
        render: str = "host", host_cycle_ms: int = 1, seconds: float | None = None,
        fleet: bool | None = None) -> dict:
    """One run. render: host | device | auto ([render] where); host_cycle_ms: [device] host_cycle_ms.
    Footprint: the peak PSS and thread count of the daemon and of its pump over the run (sampled
    once a second), and the packages beyond numpy whose libraries each has mapped."""
    from hostd.codec import stream as vtx
    from hostd.codec import transform
    from hostd.perception import thresholds
    from hostd.service.client import ClientError, request, send_file
    from hostd.texture import synth

    seconds = minutes * 60.0 if seconds is None else float(seconds)
    minutes = seconds / 60.0
    hogs: list[subprocess.Popen] = []
    with tempfile.TemporaryDirectory(prefix="hostd-soak-") as tmp:
        d = Path(tmp)
        log = d / "dac.bin"
        hp = hostport.HostPort(["--motion", "metronome", "--duration", str(seconds + 120)], log=log)
        cfg = d / "hostd.toml"
        cfg.write_text(f'[device]\ntransport = "serial:{hp.pty}"\nhost_cycle_ms = {int(host_cycle_ms)}\n'
                       f'[render]\nwhere = "{render}"\n'
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
            f.write_bytes(vtx.v1.encode_profile(prof.heights_um, transform.Geometry(prof.n, prof.length_mm),
                                             thresholds.default_curve(), method="quant", levels=14))
            send_file(sock, str(f), "soak")
            request(sock, {"cmd": "select", "name": "soak"})
            if load:
                cpu = max(os.sched_getaffinity(0))
                hogs.append(subprocess.Popen([sys.executable, "-c", HOG, str(cpu)]))
            t_ready = time.monotonic() + 30  # playing, and where it was asked to render (the upload's
            while time.monotonic() < t_ready:  # acknowledgements can take seconds on a busy machine)
                st = request(sock, {"cmd": "status"})
                if st["state"] == "playing" and (render != "device" or st["render_at"] == "device"):
                    break
                time.sleep(0.1)
            time.sleep(1.0)  # the upload or the priming is not the steady state
            fleet_out: dict = {}
            fleet_thread = _start_fleet(fleet, seconds, d / "q.sqlite", sock, fleet_out)
            pump = _pump_pid(daemon.pid)
            pids = {"pump": pump, "daemon": daemon.pid}
            clocks = {k: CpuClock(v) for k, v in pids.items() if v}
            cpu0 = dict.fromkeys(clocks, 0.0)
            wake0 = dict.fromkeys(clocks, 0)
            st0 = request(sock, {"cmd": "status"})
            t0 = time.monotonic()
            from hostd.tty import progress_bar

            bar = progress_bar(progress, total=int(seconds), unit="s", desc=f"soak ({render})", leave=False)
            peak_pss = dict.fromkeys(cpu0, 0)
            peak_threads = dict.fromkeys(cpu0, 0)
            while (el := time.monotonic() - t0) < seconds:
                time.sleep(min(1.0, seconds - el))
                for k in cpu0:  # the footprint's peak over the run, sampled once a second
                    clocks[k].sample()
                    peak_pss[k] = max(peak_pss[k], pss_kb(pids[k]))
                    peak_threads[k] = max(peak_threads[k], threads(pids[k]))
                bar.n = int(time.monotonic() - t0)
                bar.refresh()
            wall = time.monotonic() - t0
            cpu1 = {k: c.elapsed_s() for k, c in clocks.items()}
            wake1 = {k: c.wakeups() for k, c in clocks.items()}  # (after cpu1: sampled there)
            libs = {k: mapped_libs(pids[k]) for k in cpu0}
            st = request(sock, {"cmd": "status"})
            bar.close()
            if fleet_thread is not None:
                fleet_thread.join(seconds + 120)
        finally:
            hp.close()  # the DAC log ends while the texture still plays
            for h in hogs:
                h.send_signal(signal.SIGKILL)
                h.wait()
            if daemon.poll() is None:
                daemon.terminate()
                daemon.wait(20)
        rec = hostport.read_log(log)
        fig = hostport.playback_figures(rec)
    share = {k: round((cpu1[k] - cpu0[k]) / wall, 5) for k in cpu1}
    wakes = {k: round((wake1[k] - wake0[k]) / wall, 1) for k in wake1}
    cycles = st["cycles"] - st0["cycles"]
    loop_runs = (st["wakeups"] - st0["wakeups"]) if st["render_at"] == "device" else cycles
    row = {
        "render": render, "render_at": st["render_at"], "minutes": minutes, "load": load,
        "host_cycle_ms": int(host_cycle_ms),
        "daemon_cpu_share": share.get("daemon"), "pump_cpu_share": share.get("pump"),
        "cpu_share": round(sum(share.values()), 5),
        "daemon_wakeups_s": wakes.get("daemon"), "pump_wakeups_s": wakes.get("pump"),
        # the pump's loop runs (device mode: runs of its sleeping loop, DeviceMode.wakeups; host
        # rendering: its cycles), to set against its wake-ups (the kernel's count)
        "pump_loop_runs_s": round(loop_runs / wall, 1),
        # the pump's own count of its sleeps (getrusage) against its loop's runs, both published at
        # the same instant (the /proc figure above and the status are read some ms apart, and the
        # status is up to 0.25 s old: a few % of a short run)
        "pump_wakeups_per_run": round((st["voluntary_switches"] - st0["voluntary_switches"])
                                      / max(1, loop_runs), 3) if st["render_at"] == "device"
        else round((wake1["pump"] - wake0["pump"]) / max(1, loop_runs), 3) if "pump" in wake1 else None,
        "daemon_pss_mb": round(peak_pss.get("daemon", 0) / 1024, 1),
        "pump_pss_mb": round(peak_pss.get("pump", 0) / 1024, 1),
        "pss_mb": round(sum(peak_pss.values()) / 1024, 1),
        "daemon_threads": peak_threads.get("daemon"), "pump_threads": peak_threads.get("pump"),
        "threads": sum(peak_threads.values()),
        "daemon_libs": ",".join(libs.get("daemon", [])), "pump_libs": ",".join(libs.get("pump", [])),
        # the pump process's CPU per cycle (a loaded machine skips cycles: the share alone hides it)
        "pump_cpu_us_per_cycle": round((cpu1["pump"] - cpu0["pump"]) / max(1, cycles) * 1e6, 1)
        if "pump" in cpu1 else None,
        "cycles_per_s": round(cycles / wall, 1),
        "stalls": st["stalls"] - st0["stalls"], "longest_stall_ms": round(st["longest_stall_ms"], 1),
        "played_fraction_status": round(st["played_fraction"], 6),  # the daemon's figure, to compare
    }
    if "error" in fleet_out:
        raise HostdError(f"the fleet shipper's measurement: {fleet_out['error']}")
    row.update(fleet_out)  # the shipper beside it (fleet_cpu_share, fleet_pss_mb), when it ran
    if st["render_at"] == "device":
        # the display renders: its DAC log's full-gain flag from the first full-gain tick
        full = (rec["flags"] & hostport.FULL_GAIN) != 0
        first = int(np.argmax(full)) if full.any() else full.size
        quiet = hostport.runs(~full[first:])
        row.update({
            "played_fraction": round(float(full[first:].mean()) if full[first:].size else 0.0, 6),
            "underrun_episodes": len(quiet),  # stretches below full gain (fades, idle)
            "longest_silence_ms": round(max((b - a for a, b in quiet), default=0) / 3.0, 1),
            "device_host_lost": st["device_host_lost"] - st0["device_host_lost"],
            "device_reuploads": st["device_reuploads"] - st0["device_reuploads"],
        })
    else:
        row.update({
            "played_fraction": round(fig["played_fraction"], 6),
            "underrun_episodes": fig["underrun_episodes"],
            "silences": len(fig["silences"]),
            # silences followed by playback again: the recoveries the device saw
            "recoveries": fig["recovered_silences"],
            "longest_silence_ms": round(fig["longest_silence_ms"], 1),
            "device_underruns": st["device_underruns"],  # the daemon's health figure, to compare
            "host_recoveries": st["recoveries"],  # episodes the host saw (a burst of silences counts once)
            "batch_p50_us": round(st["batch_p50_us"], 1), "batch_p99_us": round(st["batch_p99_us"], 1),
            "batch_p999_us": round(st["batch_p999_us"], 1),
        })
    return row


def run_many(runs: int = 1, **kw) -> dict:
    """`runs` runs; the median of every numeric figure (the runs themselves under "runs")."""
    rows = [run(**kw) for _ in range(runs)]
    if runs == 1:
        return rows[0]
    med: dict = {}
    for k, v in rows[0].items():
        vals = [r.get(k) for r in rows]
        if isinstance(v, bool) or not isinstance(v, int | float) or any(x is None for x in vals):
            med[k] = v
        else:
            med[k] = float(np.median(vals))
    med["runs"] = rows
    med["median_of"] = runs
    return med
