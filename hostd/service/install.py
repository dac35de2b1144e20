"""`hostd install-service`: put the package's unit, udev rule, sysusers and tmpfiles files and a
default config in place, pointing the unit at this installation's `hostd`.

The files come from the package itself (hostd/systemd, hostd/data/hostd.toml), so a wheel
installed into a venv (/opt/hostd on the display PC) carries everything it needs. An existing
/etc/hostd/hostd.toml is never overwritten. With the default prefix (/) the system is then told
(systemd-sysusers, systemd-tmpfiles --create, udevadm, systemctl daemon-reload); with another
prefix (a staging tree, a package build) those commands are printed, not run.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

from hostd import paths
from hostd.errors import HostdError
from hostd.fileio import write_output

# (file in hostd/systemd, destination under the prefix, mode)
FILES = (
    ("hostd.service", "etc/systemd/system/hostd.service", 0o644),
    ("70-hostd.rules", "etc/udev/rules.d/70-hostd.rules", 0o644),
    ("hostd-sysusers.conf", "etc/sysusers.d/hostd.conf", 0o644),
    ("hostd-tmpfiles.conf", "etc/tmpfiles.d/hostd.conf", 0o644),
)
CONFIG_DEST = "etc/hostd/hostd.toml"
SHIPPED_EXEC = "/opt/hostd/bin/hostd"


def hostd_executable() -> Path:
    """The `hostd` script of this installation (the venv's bin/, next to its python)."""
    here = Path(sys.executable).parent / "hostd"
    if here.is_file() and os.access(here, os.X_OK):
        return here.absolute()
    found = shutil.which("hostd")
    if found:
        return Path(found).absolute()
    raise HostdError("cannot find this installation's `hostd` script: install hostd into a venv "
                     "(python3 -m venv /opt/hostd && /opt/hostd/bin/pip install hostd-*.whl) and run "
                     "/opt/hostd/bin/hostd install-service")


def unit_text(exe: Path) -> str:
    text = (paths.systemd_dir() / "hostd.service").read_text()
    if SHIPPED_EXEC not in text:
        raise HostdError(f"the shipped unit does not run {SHIPPED_EXEC}; cannot point it at {exe}")
    return text.replace(SHIPPED_EXEC, str(exe))


def plan(prefix: Path, exe: Path) -> list[tuple[Path, bytes, int, bool]]:
    """(destination, content, mode, overwrite) for every file."""
    out = []
    for src, dest, mode in FILES:
        data = unit_text(exe).encode() if src == "hostd.service" else (paths.systemd_dir() / src).read_bytes()
        out.append((prefix / dest, data, mode, True))
    out.append((prefix / CONFIG_DEST, (paths.shipped_dir() / "hostd.toml").read_bytes(), 0o644, False))
    return out


COMMANDS = (
    ["systemd-sysusers"],
    ["systemd-tmpfiles", "--create"],
    ["udevadm", "control", "--reload"],
    ["udevadm", "trigger", "--subsystem-match=hidraw", "--subsystem-match=usb", "--subsystem-match=tty"],
    ["systemctl", "daemon-reload"],
)


def install(prefix: str = "/", dry_run: bool = False, run_commands: bool | None = None) -> int:
    root = Path(prefix)
    exe = hostd_executable()
    steps = plan(root, exe)
    live = root.resolve() == Path("/") if run_commands is None else run_commands
    say = "would install" if dry_run else "installed"
    for dest, data, mode, overwrite in steps:
        if dest.exists() and not overwrite:
            print(f"kept      {dest} (exists; compare with {paths.shipped_dir() / 'hostd.toml'})")
            continue
        if not dry_run:
            try:
                dest.parent.mkdir(parents=True, exist_ok=True)
            except PermissionError:
                raise HostdError(f"cannot create {dest.parent}: permission denied (run as root: "
                                 f"sudo {exe} install-service)") from None
            write_output(dest, data, mode=mode)
        print(f"{say:<9} {dest}")
    print(f"the unit runs {exe} run --config /etc/hostd/hostd.toml")
    if dry_run or not live:
        print("then run:" if not dry_run else "would then run:")
        for c in COMMANDS:
            print("  " + " ".join(c))
        print("  systemctl enable --now hostd")
        return 0
    for c in COMMANDS:
        if shutil.which(c[0]) is None:
            print(f"skipped   {' '.join(c)} ({c[0]} is not installed)")
            continue
        r = subprocess.run(c, capture_output=True, text=True)
        if r.returncode != 0:
            raise HostdError(f"`{' '.join(c)}` failed: {(r.stderr or r.stdout).strip()[:300]}")
        print(f"ran       {' '.join(c)}")
    print("now: edit /etc/hostd/hostd.toml (device, paths), then systemctl enable --now hostd; "
          "hostd doctor --config /etc/hostd/hostd.toml checks it")
    return 0
