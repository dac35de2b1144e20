"""`hostd install-service`: put the package's unit, udev rule, sysusers and tmpfiles files and a
default config in place, pointing the unit at this installation's `hostd`.

The files come from the package itself (hostd/systemd, hostd/data/hostd.toml), so a wheel
installed into a venv (/opt/hostd on the display PC) carries everything it needs. An existing
/etc/hostd/hostd.toml is never overwritten. With the default prefix (/) the system is then told
(systemd-sysusers, systemd-tmpfiles --create, udevadm, systemctl daemon-reload); with another
prefix (a staging tree, a package build) those commands are printed, not run. `--enable` also
runs `systemctl enable --now hostd`; `--dry-run` prints exactly the files and commands the same
call without it would write and run.

The unit's ExecStart must be reachable inside the unit's sandbox: a venv under /home or
/run/user (ProtectHome=yes), /tmp or /var/tmp (PrivateTmp=yes), or a pipx venv (under a home)
gives a unit that fails with status 203/EXEC, so such a location is refused with the fix.
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
# --fleet: the fleet shipper's unit and user too (hostd fleet ship: docs/fleet.md)
FLEET_FILES = (
    ("hostd-fleet.service", "etc/systemd/system/hostd-fleet.service", 0o644),
    ("hostd-fleet-sysusers.conf", "etc/sysusers.d/hostd-fleet.conf", 0o644),
)
CONFIG_DEST = "etc/hostd/hostd.toml"
SHIPPED_EXEC = "/opt/hostd/bin/hostd"
# hidden from the service by the unit's sandbox (ProtectHome=yes, PrivateTmp=yes)
HIDDEN_DIRS = ("/home", "/root", "/run/user", "/tmp", "/var/tmp")


def fix() -> str:
    """What to run instead: a venv under /opt with this hostd installed from what the user has
    (the checkout or the wheel it came from: hostd.extras.pip_install)."""
    from hostd.extras import pip_install

    return ("install hostd into a venv under /opt: sudo python3 -m venv /opt/hostd && sudo "
            f"{pip_install('device', pip='/opt/hostd/bin/pip')} && sudo /opt/hostd/bin/hostd install-service")


def exec_problem(exe: Path, interpreter: Path | None = None) -> str | None:
    """Why the unit could not run `exe` (or the Python it runs on) under its sandbox, or None."""
    for what, p in (("hostd", exe), ("its Python", interpreter)):
        if p is None:
            continue
        text = str(p)
        if "/pipx/venvs/" in text or "/.local/pipx/" in text:
            return (f"{what} is a pipx install ({p}): pipx venvs live in a home directory, which the "
                    "unit hides")
        for d in HIDDEN_DIRS:
            if text == d or text.startswith(d + "/"):
                why = "PrivateTmp=yes" if d in ("/tmp", "/var/tmp") else "ProtectHome=yes"
                return (f"{what} is under {d} ({p}), which the unit hides from the service ({why}): "
                        "it would fail with status 203/EXEC")
    return None


def hostd_executable() -> Path:
    """The `hostd` script of this installation (the venv's bin/, next to its python)."""
    here = Path(sys.executable).parent / "hostd"
    if here.is_file() and os.access(here, os.X_OK):
        return here.absolute()
    found = shutil.which("hostd")
    if found:
        return Path(found).absolute()
    raise HostdError(f"cannot find this installation's `hostd` script: {fix()}")


def unit_text(exe: Path, unit: str = "hostd.service") -> str:
    text = (paths.systemd_dir() / unit).read_text()
    if SHIPPED_EXEC not in text:
        raise HostdError(f"the shipped unit does not run {SHIPPED_EXEC}; cannot point it at {exe}")
    return text.replace(SHIPPED_EXEC, str(exe))


def plan(prefix: Path, exe: Path, parser, fleet: bool = False) -> list[tuple[Path, bytes, int, bool]]:
    """(destination, content, mode, overwrite) for every file: the unit and its companions (fleet:
    the shipper's unit and user too), the man page the units' Documentation= names and the shell
    completions (generated from `parser`, hostd's whole command line: hostd.parser.build_parser())."""
    from hostd import docgen

    out = []
    for src, dest, mode in FILES + (FLEET_FILES if fleet else ()):
        data = unit_text(exe, src).encode() if src.endswith(".service") \
            else (paths.systemd_dir() / src).read_bytes()
        out.append((prefix / dest, data, mode, True))
    out.append((prefix / docgen.MAN_DEST, docgen.man_page(parser).encode(), 0o644, True))
    for shell, dest in docgen.COMPLETION_DEST.items():
        out.append((prefix / dest, docgen.completion(shell, parser).encode(), 0o644, True))
    out.append((prefix / CONFIG_DEST, (paths.shipped_dir() / "hostd.toml").read_bytes(), 0o644, False))
    return out


COMMANDS = (
    ["systemd-sysusers"],
    ["systemd-tmpfiles", "--create"],
    ["udevadm", "control", "--reload"],
    ["systemctl", "daemon-reload"],
)
ENABLE = ["systemctl", "enable", "--now", "hostd"]
SYS_USB = Path("/sys/bus/usb/devices")


def display_syspaths(sys_usb: Path | None = None) -> list[str]:
    """sysfs paths of the plugged-in displays (the VID:PID of the udev rule)."""
    from hostd.device import protocol as pr

    sys_usb = SYS_USB if sys_usb is None else sys_usb
    found = []
    for d in sorted(sys_usb.glob("*")) if sys_usb.is_dir() else []:
        try:
            vid, pid = ((d / a).read_text().strip().lower() for a in ("idVendor", "idProduct"))
        except OSError:
            continue
        if (vid, pid) == (f"{pr.USB_VID:04x}", f"{pr.USB_PID:04x}"):
            found.append(str(d.resolve()))
    return found


def commands(enable: bool, syspaths: list[str] | None = None) -> list[list[str]]:
    """What install-service runs. The udev rule is applied to a display already plugged in by
    re-triggering that device and its children (hidraw, tty) only (--parent-match), not every usb
    and tty device; the hidraw and tty nodes carry no idVendor of their own, so --attr-match on
    the vendor would miss them."""
    out = list(COMMANDS)
    trig = [["udevadm", "trigger", "--action=add", f"--parent-match={p}"] for p in syspaths or []]
    out[3:3] = trig
    return [*out, ENABLE] if enable else out


def install(parser, prefix: str = "/", dry_run: bool = False, run_commands: bool | None = None,
            enable: bool = False, exec_path: str | None = None, fleet: bool = False) -> int:
    """parser: hostd's whole command line (hostd.parser.build_parser()), for the man page and the
    completions. fleet: the shipper's unit (hostd-fleet.service) and its user too; it is not
    enabled here: it needs /etc/hostd/fleet.toml and the PC's password or certificate first."""
    root = Path(prefix)
    live = root.resolve() == Path("/") if run_commands is None else run_commands
    if exec_path is not None:  # a package build names where hostd will be (it need not exist yet)
        exe = Path(exec_path)
        if not exe.is_absolute():
            raise HostdError(f"--exec {exec_path}: give an absolute path (e.g. {SHIPPED_EXEC})")
        why = exec_problem(exe)
    else:
        exe = hostd_executable()
        why = exec_problem(exe, Path(sys.executable).resolve())
    if why:
        raise HostdError(f"refusing to install a unit that cannot start: {why}; {fix()}")
    steps = plan(root, exe, parser, fleet)
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
    if fleet:
        print(f"the fleet unit runs {exe} fleet ship --config /etc/hostd/fleet.toml: write that file "
              "([fleet] url, role) and /etc/hostd/fleet.password (0600), then systemctl enable --now "
              "hostd-fleet (hostd fleet ship --help)")
    if not live:  # a staging tree: the commands are for whoever installs it
        print(f"{'would print' if dry_run else 'printed'}, not run ({root} is not /); run them on the "
              "target:")
        for c in commands(True, ["/sys/bus/usb/devices/<the display>"]):
            print("  " + " ".join(c))
        return 0
    cmds = commands(enable, display_syspaths())
    if dry_run:
        for c in cmds:
            missing = shutil.which(c[0]) is None
            print(f"{'would skip' if missing else 'would run'} {' '.join(c)}"
                  + (f" ({c[0]} is not installed)" if missing else ""))
        if not enable:
            print("would not start the service (--enable: systemctl enable --now hostd)")
        return 0
    for c in cmds:
        if shutil.which(c[0]) is None:
            print(f"skipped   {' '.join(c)} ({c[0]} is not installed)")
            continue
        r = subprocess.run(c, capture_output=True, text=True)
        if r.returncode != 0:
            raise HostdError(f"`{' '.join(c)}` failed: {(r.stderr or r.stdout).strip()[:300]}")
        print(f"ran       {' '.join(c)}")
    if enable:
        print("hostd is enabled and started: systemctl status hostd; hostd doctor checks the set-up")
    else:
        print("now: edit /etc/hostd/hostd.toml (device, paths), then systemctl enable --now hostd "
              "(or run this again with --enable); hostd doctor checks the set-up")
    return 0
