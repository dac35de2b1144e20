"""Time from `hostd run` to READY=1 with N stored streams that have no quality row (as after a
crash), measured on a notify socket of its own (not a test: run by hand for docs/daemon.md).

    PYTHONPATH=. .venv/bin/python tests/repro_ready.py 5644
"""

import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from hostd.cli import main as hostd_main


def run(n: int) -> float:
    d = Path(tempfile.mkdtemp(prefix="hostd-ready-"))
    try:
        lib = d / "lib"
        lib.mkdir()
        src = d / "s.vtx"
        assert hostd_main(["encode", "synthetic:wood:3", "-o", str(src), "--method", "quant", "--levels", "6",
                           "--length-mm", "2"]) == 0
        for i in range(n):
            shutil.copy(src, lib / f"t{i}.vtx")
        (d / "h.toml").write_text('[device]\ntransport = "sim"\n[render]\nwhere = "host"\n'
                                  '[library]\ndir = "lib"\nspool = "spool"\n'
                                  '[control]\nsocket = "hostd.sock"\ngroup = ""\n'
                                  '[quality]\ndb = "q.sqlite"\n')
        ns = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        ns.bind(str(d / "notify"))
        ns.settimeout(600)
        t0 = time.monotonic()
        env = dict(os.environ, NOTIFY_SOCKET=str(d / "notify"))
        p = subprocess.Popen([sys.executable, "-m", "hostd", "run", "--config", str(d / "h.toml")], cwd=d,
                             stderr=open(d / "log.txt", "w"), env=env)
        got = b""
        while b"READY=1" not in got:
            got = ns.recv(4096)
        t_ready = time.monotonic() - t0
        p.send_signal(signal.SIGTERM)
        p.wait(120)
        return t_ready
    finally:
        shutil.rmtree(d, ignore_errors=True)


if __name__ == "__main__":
    n = int(sys.argv[1])
    print(f"{n} unscored streams: READY=1 after {run(n):.1f} s (wall, load {os.getloadavg()[0]:.1f})")
