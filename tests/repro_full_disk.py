"""Issue 29's full-disk reproduction (not a test: run by hand, as root, for the figures in
docs/daemon.md): the quality database alone on a 1 MiB tmpfs filled to 0 bytes free, N
acknowledged uploads, FREE_KB freed, WAIT_S, a restart, WAIT_S; prints the rows, the -wal's size
and the free bytes at each step.

    PYTHONPATH=. .venv/bin/python tests/repro_full_disk.py 60 256 40
"""

import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from hostd.cli import main as hostd_main
from hostd.service import qualitylog
from hostd.service.client import ClientError, request


def run(n: int, free_kb: int, wait_s: float) -> None:
    d = Path(tempfile.mkdtemp(prefix="hostd-fulldisk-"))
    q = d / "qfs"
    q.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(q)], check=True)
    cfg = d / "hostd.toml"
    cfg.write_text('[device]\ntransport = "sim"\n[library]\ndir = "lib"\nspool = "spool"\n'
                   'max_stream_bytes = 4096\n[control]\nsocket = "hostd.sock"\ngroup = ""\n'
                   '[quality]\ndb = "qfs/q.sqlite"\n')
    sock = str(d / "hostd.sock")

    def start(tag: int) -> subprocess.Popen:
        p = subprocess.Popen([sys.executable, "-m", "hostd", "run", "--config", str(cfg)],
                             stderr=open(d / f"log{tag}.txt", "w"), cwd=d)
        for _ in range(1200):
            try:
                request(sock, {"cmd": "status"}, timeout_s=5)
                return p
            except ClientError:
                time.sleep(0.1)
        raise SystemExit("the daemon did not start")

    def rows() -> int:
        con = qualitylog.connect_readonly(q / "q.sqlite")
        try:
            return con.execute("SELECT count(*) FROM streams").fetchone()[0]
        finally:
            con.close()

    def fs() -> str:
        st = os.statvfs(q)
        wal = q / "q.sqlite-wal"
        return f"free={st.f_bavail * st.f_frsize} wal={wal.stat().st_size if wal.exists() else 0}"

    try:
        src = d / "s.vtx"
        assert hostd_main(["encode", "synthetic:wood:4", "-o", str(src), "--method", "quant", "--levels", "4",
                           "--length-mm", "2"]) == 0
        body = src.read_bytes()
        p = start(1)
        fill = []
        while True:
            f = q / f"fill{len(fill)}"
            try:
                f.write_bytes(b"\0" * 4096)
                fill.append(f)
            except OSError:
                f.unlink(missing_ok=True)
                break
        try:
            with open(q / "tail", "wb") as fh:
                while True:
                    fh.write(b"\0" * 512)
                    fh.flush()
        except OSError:
            pass
        print("filled:", fs())
        for k in range(n):
            assert request(sock, {"cmd": "send", "name": f"u{k}", "size": len(body)}, body)["ok"]
        print(f"{n} uploads acknowledged; rows={rows()}", fs())
        time.sleep(2)
        for f in fill[len(fill) - free_kb // 4:]:
            f.unlink()
        print(f"freed {free_kb} kB:", fs())
        t0 = time.monotonic()
        while time.monotonic() - t0 < wait_s and rows() < n:
            time.sleep(0.5)
        print(f"after {time.monotonic() - t0:.1f} s: rows={rows()}/{n}", fs())
        p.send_signal(signal.SIGTERM)
        p.wait(30)
        print("at exit:", fs(), [ln for ln in (d / "log1.txt").read_text().splitlines() if "at exit" in ln])
        p = start(2)
        t0 = time.monotonic()
        while time.monotonic() - t0 < wait_s and rows() < n:
            time.sleep(0.5)
        print(f"restarted, after {time.monotonic() - t0:.1f} s: rows={rows()}/{n}", fs())
        p.send_signal(signal.SIGTERM)
        p.wait(30)
    finally:
        subprocess.run(["umount", "-l", str(q)])
        shutil.rmtree(d, ignore_errors=True)


if __name__ == "__main__":
    run(int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3]))
