"""Stimuli through the daemon on the firmware's host port (device mode, as on a v2 display):
N stimuli of 0.5 s at 250 Hz, every other one at amplitude 0 (a silent interval), one at a
time; prints how many were played and how many answered "retry", and the time from the request
to the answer. docs/experiments.md quotes it.

    PYTHONPATH=. python docs/examples/stimulus_timing.py /tmp/stim-timing 40
"""

import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

from hostd.device import hostport
from hostd.service.client import ClientError, request


def main(d: Path, n: int) -> None:
    d.mkdir(parents=True, exist_ok=True)
    hp = hostport.HostPort(["--motion", "none", "--duration", "600"])
    cfg = d / "hostd.toml"
    cfg.write_text(f'[device]\ntransport = "serial:{hp.pty}"\n[library]\ndir = "lib"\nspool = "spool"\n'
                   '[control]\nsocket = "hostd.sock"\ngroup = ""\n[quality]\ndb = "q.sqlite"\n'
                   '[experiment]\nstimuli = true\n')
    sock = str(d / "hostd.sock")
    daemon = subprocess.Popen([sys.executable, "-m", "hostd", "run", "--config", str(cfg)], cwd=d,
                              stderr=subprocess.DEVNULL)
    played, retry, took = 0, 0, []
    try:
        while True:
            try:
                if request(sock, {"cmd": "status"}, timeout_s=2)["connected"]:
                    break
            except ClientError:
                pass
            time.sleep(0.05)
        time.sleep(2)  # past the daemon's start-up work
        for i in range(n):
            t = time.monotonic()
            try:
                amp_um = 1.0 if i % 2 else 0.0
                request(sock, {"cmd": "stimulus", "frequency_hz": 250.0, "amplitude_um": amp_um,
                               "duration_s": 0.5}, timeout_s=20)
                played += 1
                took.append(time.monotonic() - t)
            except ClientError as e:
                retry += int(bool(e.reply and e.reply.get("retry")))
    finally:
        daemon.terminate()
        daemon.wait(20)
        hp.close()
    print(f"{played} played, {retry} answered retry; request to answer for a 0.5 s stimulus: median "
          f"{statistics.median(took) * 1e3:.0f} ms, max {max(took) * 1e3:.0f} ms; "
          f"load average {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main(Path(sys.argv[1]), int(sys.argv[2]))
