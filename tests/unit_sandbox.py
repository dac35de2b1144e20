"""Run a command under the seccomp filters that systemd/hostd.service asks systemd for.

Reproduces what systemd (252) installs for the unit's SystemCallFilter= lines (allow-list mode:
@default is implicit, `~` lines remove, later lines add back; other calls kill the process
with SIGSYS), MemoryDenyWriteExecute=yes (EPERM for W+X mappings) and
RestrictAddressFamilies= (EAFNOSUPPORT for other socket families). The syscall groups are
expanded with `systemd-analyze syscall-filter` when it is installed, else from the checked-in
expansion tests/data/syscall-filter-systemd252.txt (made with that command, systemd 252).
The filters are applied with libseccomp (libseccomp.so.2, through ctypes), then the command is
exec'd: `python tests/unit_sandbox.py UNIT -- CMD ARGS...`.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import os
import shutil
import subprocess
import sys
from pathlib import Path

CHECKED_IN = Path(__file__).resolve().parent / "data" / "syscall-filter-systemd252.txt"

SCMP_ACT_KILL_PROCESS = 0x80000000
SCMP_ACT_ALLOW = 0x7FFF0000
SCMP_CMP_EQ, SCMP_CMP_GT, SCMP_CMP_MASKED_EQ = 4, 6, 7
PROT_WRITE, PROT_EXEC, SHM_EXEC = 0x2, 0x4, 0o100000
AF = {"AF_UNIX": 1, "AF_INET": 2, "AF_INET6": 10, "AF_NETLINK": 16, "AF_PACKET": 17}


def SCMP_ACT_ERRNO(e: int) -> int:
    return 0x00050000 | (e & 0xFFFF)


class ArgCmp(ctypes.Structure):
    _fields_ = [("arg", ctypes.c_uint), ("op", ctypes.c_int), ("datum_a", ctypes.c_uint64),
                ("datum_b", ctypes.c_uint64)]


def libseccomp():
    """The libseccomp library, or None with the reason."""
    name = ctypes.util.find_library("seccomp") or "libseccomp.so.2"
    try:
        lib = ctypes.CDLL(name, use_errno=True)
    except OSError as e:
        return None, f"libseccomp is not installed ({e}): apt-get install libseccomp2"
    lib.seccomp_init.restype = ctypes.c_void_p
    lib.seccomp_init.argtypes = [ctypes.c_uint32]
    lib.seccomp_syscall_resolve_name.argtypes = [ctypes.c_char_p]
    lib.seccomp_rule_add_array.argtypes = [ctypes.c_void_p, ctypes.c_uint32, ctypes.c_int, ctypes.c_uint,
                                           ctypes.POINTER(ArgCmp)]
    lib.seccomp_load.argtypes = [ctypes.c_void_p]
    lib.seccomp_release.argtypes = [ctypes.c_void_p]
    return lib, ""


def groups_text() -> tuple[str, str]:
    """`systemd-analyze syscall-filter` output and where it came from."""
    exe = shutil.which("systemd-analyze")
    if exe:
        r = subprocess.run([exe, "syscall-filter", "--no-pager"], capture_output=True, text=True)
        if r.returncode == 0 and "@system-service" in r.stdout:
            return r.stdout, f"{exe} syscall-filter"
    return CHECKED_IN.read_text(), str(CHECKED_IN)


def parse_groups(text: str) -> dict[str, list[str]]:
    groups: dict[str, list[str]] = {}
    cur = None
    for line in text.splitlines():
        if line.startswith("@"):
            cur = groups.setdefault(line.strip(), [])
        elif line.startswith("    ") and cur is not None and not line.strip().startswith("#"):
            cur.append(line.strip())
        elif not line.strip():
            cur = None
    return groups


def expand(item: str, groups: dict[str, list[str]]) -> set[str]:
    if not item.startswith("@"):
        return {item}
    if item not in groups:
        raise ValueError(f"unknown syscall group {item}")
    out: set[str] = set()
    for x in groups[item]:
        out |= expand(x, groups)
    return out


def unit_settings(unit: Path) -> dict[str, list[str]]:
    """Every `Key=value` of the unit's [Service] section, values in order."""
    out: dict[str, list[str]] = {}
    section = ""
    for raw in unit.read_text().splitlines():
        line = raw.strip()
        if line.startswith("["):
            section = line
        elif section == "[Service]" and "=" in line and not line.startswith("#"):
            k, v = line.split("=", 1)
            out.setdefault(k.strip(), []).append(v.strip())
    return out


def allowed_syscalls(unit: Path, groups: dict[str, list[str]]) -> set[str]:
    """systemd's reading of SystemCallFilter= (allow-list mode when the first line is not ~)."""
    lines = unit_settings(unit).get("SystemCallFilter", [])
    if not lines or lines[0].startswith("~"):
        raise ValueError("this reproduction handles allow-list filters only")
    allowed = expand("@default", groups)
    for line in lines:
        deny = line.startswith("~")
        items = line.lstrip("~").split()
        names = set().union(*(expand(i, groups) for i in items)) if items else set()
        allowed = allowed - names if deny else allowed | names
    # systemd always lets the service exec its binary and exit
    return allowed | {"execve", "exit", "exit_group", "rt_sigreturn"}


def load_filters(unit: Path, debug_errno: bool = False) -> list[str]:
    """Install the unit's filters on this process; returns the syscalls the kernel does not know."""
    lib, why = libseccomp()
    if lib is None:
        raise RuntimeError(why)
    settings = unit_settings(unit)
    text, _source = groups_text()
    groups = parse_groups(text)

    def rule(ctx, action: int, nr: int, *cmps: tuple[int, int, int, int]) -> None:
        arr = (ArgCmp * max(len(cmps), 1))(*[ArgCmp(*c) for c in cmps])
        if lib.seccomp_rule_add_array(ctx, action, nr, len(cmps), arr) != 0:
            raise OSError(f"seccomp_rule_add for syscall {nr} failed")

    # 1. MemoryDenyWriteExecute and RestrictAddressFamilies: default allow, errno for the rest
    ctx = lib.seccomp_init(SCMP_ACT_ALLOW)
    if settings.get("MemoryDenyWriteExecute", ["no"])[-1] == "yes":
        eperm = SCMP_ACT_ERRNO(errno.EPERM)
        wx = PROT_WRITE | PROT_EXEC
        rule(ctx, eperm, lib.seccomp_syscall_resolve_name(b"mmap"), (2, SCMP_CMP_MASKED_EQ, wx, wx))
        for name in (b"mprotect", b"pkey_mprotect"):
            rule(ctx, eperm, lib.seccomp_syscall_resolve_name(name),
                 (2, SCMP_CMP_MASKED_EQ, PROT_EXEC, PROT_EXEC))
        rule(ctx, eperm, lib.seccomp_syscall_resolve_name(b"shmat"),
             (2, SCMP_CMP_MASKED_EQ, SHM_EXEC, SHM_EXEC))
    fams = settings.get("RestrictAddressFamilies")
    if fams:
        allowed_fams = {AF[f] for f in fams[-1].split()}
        sock = lib.seccomp_syscall_resolve_name(b"socket")
        for fam in range(0, 64):
            if fam not in allowed_fams:
                rule(ctx, SCMP_ACT_ERRNO(errno.EAFNOSUPPORT), sock, (0, SCMP_CMP_EQ, fam, 0))
        rule(ctx, SCMP_ACT_ERRNO(errno.EAFNOSUPPORT), sock, (0, SCMP_CMP_GT, 63, 0))
    if lib.seccomp_load(ctx) != 0:
        raise OSError("seccomp_load failed")
    lib.seccomp_release(ctx)
    # 2. SystemCallFilter (an allow list: anything else kills the process with SIGSYS)
    action = SCMP_ACT_ERRNO(errno.ENOSYS) if debug_errno else SCMP_ACT_KILL_PROCESS
    ctx = lib.seccomp_init(action)
    unknown = []
    for name in sorted(allowed_syscalls(unit, groups)):
        nr = lib.seccomp_syscall_resolve_name(name.encode())
        if nr < 0:
            unknown.append(name)  # not a syscall of this architecture (systemd skips these too)
            continue
        rule(ctx, SCMP_ACT_ALLOW, nr)
    if lib.seccomp_load(ctx) != 0:
        raise OSError("seccomp_load failed")
    lib.seccomp_release(ctx)
    return unknown


def main() -> None:
    unit = Path(sys.argv[1])
    cmd = sys.argv[sys.argv.index("--") + 1:]
    load_filters(unit, debug_errno=os.environ.get("UNIT_SANDBOX_DEBUG") == "1")
    os.execv(cmd[0], cmd)


if __name__ == "__main__":
    main()
