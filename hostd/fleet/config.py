"""The shipper's config (/etc/hostd/fleet.toml) and its credentials.

The password is never in argv nor in the config: it comes from a file only its owner (root, or
the shipper's own user) can read (mode 0600 or stricter; anything else is refused), or from a
systemd credential ($CREDENTIALS_DIRECTORY/CREDENTIAL, LoadCredential= in the unit), or there is
none and the PC logs in with a TLS client certificate (sslcert/sslkey in the URL).
"""

from __future__ import annotations

import os
import re
import stat
from dataclasses import dataclass, fields
from pathlib import Path

from hostd.errors import ConfigError, HostdError
from hostd.service.outbox import STATE_DEFAULT

CREDENTIAL = "hostd-fleet-password"  # the systemd credential's name (LoadCredential=NAME:FILE)
DEFAULT_BACKOFF_MAX_S = 60.0        # the largest wait between two tries while the centre is away


@dataclass
class FleetCfg:
    url: str = ""                   # postgresql://HOST:PORT/DB?sslmode=verify-full (no password)
    role: str = ""                  # this PC's database role; the central store's pc_id of its rows
    password_file: str = ""         # a root-only file (0600); else the systemd credential, else none
    quality_db: str = "/var/lib/hostd/quality.sqlite"   # the daemon's quality log (read only)
    state: str = STATE_DEFAULT      # the shipper's own file: what was shipped, health summaries
    socket: str = "/run/hostd/hostd.sock"   # the daemon's control socket (its status: device health)
    batch_rows: int = 500           # rows per central transaction
    interval_s: float = 10.0        # how often the log is looked at for new rows (a central commit each)
    health_interval_s: float = 300.0  # how often a device-health summary is taken
    backoff_min_s: float = 1.0      # the first wait after a failed try; doubles up to backoff_max_s
    backoff_max_s: float = DEFAULT_BACKOFF_MAX_S
    connect_timeout_s: float = 10.0
    path: str = ""


_LIMITS = {"batch_rows": (1, 100_000), "interval_s": (0.01, 3600.0), "health_interval_s": (0.1, 86400.0),
           "backoff_min_s": (0.01, 3600.0), "backoff_max_s": (0.01, 86400.0),
           "connect_timeout_s": (1.0, 600.0)}
_ROLE = re.compile(r"[a-z_][a-z0-9_]{0,62}")


def load(path: str | Path) -> FleetCfg:
    from hostd import tomlfile

    doc = tomlfile.read(path, "fleet config", "write one: a [fleet] section with url and role")
    unknown = set(doc) - {"fleet"}
    if unknown:
        raise ConfigError(f"{path}: unknown section [{sorted(unknown)[0]}]: only [fleet]")
    sec = doc.get("fleet", {})
    cfg = FleetCfg(path=str(path))
    names = {f.name: f for f in fields(FleetCfg) if f.name != "path"}
    for key, value in sec.items():
        if key not in names:
            raise ConfigError(f"{path}: unknown key fleet.{key} (the keys: {', '.join(names)})")
        want = type(getattr(cfg, key))
        if want is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not isinstance(value, want) or isinstance(value, bool):
            raise ConfigError(f"{path}: fleet.{key} must be a {want.__name__}, not {value!r:.40}")
        lo_hi = _LIMITS.get(key)
        if lo_hi and not lo_hi[0] <= value <= lo_hi[1]:
            raise ConfigError(f"{path}: fleet.{key} = {value} is outside {lo_hi[0]}..{lo_hi[1]}")
        setattr(cfg, key, value)
    if not cfg.url:
        raise ConfigError(f"{path}: fleet.url is missing: the central database, "
                          "postgresql://HOST:PORT/DB?sslmode=verify-full")
    if not cfg.url.startswith(("postgresql://", "postgres://")):
        raise ConfigError(f"{path}: fleet.url {cfg.url!r:.60} is not a postgresql:// URL "
                          "(postgresql://HOST:PORT/DB?sslmode=verify-full)")
    if re.match(r"postgres(?:ql)?://[^/@?]*:[^/@?]*@", cfg.url) or re.search(r"[?&]password=", cfg.url):
        raise ConfigError(f"{path}: fleet.url carries a password: remove it and put the password in "
                          "the file named by fleet.password_file (mode 0600) or a systemd credential")
    if not _ROLE.fullmatch(cfg.role):
        raise ConfigError(f"{path}: fleet.role {cfg.role!r:.40} is not a database role name (lower case "
                          "letters, digits, _; the role `hostd fleet add-pc` created for this PC)")
    if cfg.backoff_min_s > cfg.backoff_max_s:
        raise ConfigError(f"{path}: fleet.backoff_min_s exceeds fleet.backoff_max_s")
    return cfg


def read_secret(p: Path, what: str) -> str:
    """The first line of a file only its owner can read: mode 0600 or stricter, owned by root or
    by this process's user. Anything else is refused, with the fix."""
    try:
        fd = os.open(p, os.O_RDONLY | os.O_NOFOLLOW)
    except FileNotFoundError:
        raise HostdError(f"{what} {p} does not exist: write the PC role's password there "
                         "(install -m 600 -o root /dev/stdin FILE)") from None
    except OSError as e:
        raise HostdError(f"cannot open {what} {p} ({e.strerror}): run the shipper as root or "
                         "give it the password as a systemd credential (LoadCredential=)") from None
    with os.fdopen(fd) as f:
        st = os.fstat(f.fileno())
        if not stat.S_ISREG(st.st_mode):
            raise HostdError(f"{what} {p} is not a regular file")
        if st.st_mode & 0o077:
            raise HostdError(f"{what} {p} is readable by others (mode {stat.S_IMODE(st.st_mode):04o}): "
                             f"chmod 600 {p}")
        if st.st_uid not in (0, os.geteuid()):
            raise HostdError(f"{what} {p} belongs to uid {st.st_uid}, neither root nor this user: "
                             f"chown root {p}")
        text = f.read(4096).splitlines()
    if not text or not text[0]:
        raise HostdError(f"{what} {p} is empty: write the PC role's password on its first line")
    return text[0]


def password(cfg: FleetCfg) -> str | None:
    """The PC role's password: fleet.password_file, else the systemd credential, else None (a TLS
    client certificate, or a server that asks none)."""
    if cfg.password_file:
        return read_secret(Path(cfg.password_file), "fleet.password_file")
    creds = os.environ.get("CREDENTIALS_DIRECTORY")
    if creds and (Path(creds) / CREDENTIAL).exists():
        return read_secret(Path(creds) / CREDENTIAL, "the systemd credential")
    return None
