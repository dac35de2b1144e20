"""A throwaway PostgreSQL server in a temporary directory, for the tests and `hostd bench soak`:
initdb as an unprivileged user (as root: user nobody, through runuser), a random free TCP port on
127.0.0.1 and the unix socket in the directory, trust for the owner on the socket only and
scram-sha-256 for every TCP login (the PCs' roles). Stopped and started again at will (the
central server away and back)."""

from __future__ import annotations

import glob
import os
import shutil
import socket
import subprocess
import tempfile
import time
from pathlib import Path

from hostd.errors import HostdError

OWNER = "hostd_admin"


def bindir() -> Path | None:
    """Debian's server binaries (the newest major installed), else initdb on PATH."""
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"), key=lambda p: int(p.split("/")[4]))
    if found:
        return Path(found[-1]).parent
    which = shutil.which("initdb")
    return Path(which).parent if which else None


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class LocalPG:
    def __init__(self, ssl: tuple[str, str] | None = None, client_ca: str | None = None,
                 cert_roles: tuple[str, ...] = ()):
        """ssl: the server's certificate and key (TLS on, TCP logins only over TLS); client_ca: the
        CA that signs the PCs' client certificates; cert_roles: roles that log in with one (CN =
        the role), the others with their password."""
        b = bindir()
        if b is None:
            raise HostdError("PostgreSQL's server is not installed: apt-get install postgresql")
        self.bin = b
        self.dir = Path(tempfile.mkdtemp(prefix="hostd-pg-"))
        self.data = self.dir / "data"
        self.port = _free_port()
        self.as_user: list[str] = []
        if os.geteuid() == 0:  # the server refuses to run as root
            self.as_user = ["runuser", "-u", "nobody", "--"]
            os.chmod(self.dir, 0o755)
            shutil.chown(self.dir, "nobody")
        self._run([str(b / "initdb"), "-D", str(self.data), "-U", OWNER, "--auth-local=trust",
                   "--auth-host=scram-sha-256", "-E", "UTF8", "--locale=C.UTF-8", "--no-sync"])
        conf = [f"port = {self.port}", "listen_addresses = '127.0.0.1'",
                f"unix_socket_directories = '{self.dir}'", "fsync = off", "full_page_writes = off",
                "shared_buffers = 16MB", "max_connections = 40", "log_min_messages = warning",
                "TimeZone = 'UTC'"]
        if ssl:  # copied into the server's directory: its own, mode 0600
            for src, name in zip(ssl, ("server.pem", "server.key"), strict=True):
                shutil.copyfile(src, self.dir / name)
                os.chmod(self.dir / name, 0o600)
                if self.as_user:
                    shutil.chown(self.dir / name, "nobody")
            conf += ["ssl = on", f"ssl_cert_file = '{self.dir / 'server.pem'}'",
                     f"ssl_key_file = '{self.dir / 'server.key'}'"]
            if client_ca:
                shutil.copyfile(client_ca, self.dir / "client-ca.pem")
                conf.append(f"ssl_ca_file = '{self.dir / 'client-ca.pem'}'")
        with open(self.data / "postgresql.conf", "a") as f:
            f.write("\n".join(conf) + "\n")
        if ssl:  # TCP only with TLS
            hba = self.data / "pg_hba.conf"
            hba.write_text("local all all trust\n"
                           + "".join(f"hostssl all {r} 127.0.0.1/32 cert\n" for r in cert_roles)
                           + "hostssl all all 127.0.0.1/32 scram-sha-256\n")
        self.start()

    def _run(self, cmd: list[str], timeout: float = 60) -> None:
        r = subprocess.run(self.as_user + cmd, capture_output=True, text=True, timeout=timeout)
        if r.returncode:
            logf = self.dir / "server.log"
            tail = logf.read_text()[-300:] if logf.exists() else ""
            raise HostdError(f"{Path(cmd[0]).name} failed: {(r.stderr or r.stdout).strip()[-300:]} {tail}")

    def start(self) -> None:
        self._run([str(self.bin / "pg_ctl"), "-D", str(self.data), "-l", str(self.dir / "server.log"),
                   "-w", "-t", "60", "start"])

    def stop(self, mode: str = "fast") -> None:
        self._run([str(self.bin / "pg_ctl"), "-D", str(self.data), "-m", mode, "-w", "-t", "60", "stop"])

    def pid(self) -> int:
        return int((self.data / "postmaster.pid").read_text().split()[0])

    @property
    def admin_url(self) -> str:  # as the owner, on the unix socket (trust)
        return f"postgresql://{OWNER}@/postgres?host={self.dir}&port={self.port}"

    def url(self, db: str = "postgres", **params) -> str:  # TCP, as a PC connects
        extra = "".join(f"&{k}={v}" for k, v in params.items())
        return f"postgresql://127.0.0.1:{self.port}/{db}?connect_timeout=5{extra}"

    def close(self) -> None:
        try:
            self.stop("immediate")
        except (HostdError, subprocess.TimeoutExpired):
            pass
        shutil.rmtree(self.dir, ignore_errors=True)


def wait_gone(port: int, timeout_s: float = 10.0) -> None:
    """Until nothing listens on 127.0.0.1:port."""
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)):
                return
        time.sleep(0.05)
