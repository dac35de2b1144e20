"""Start one MPEG-I Haptics reference tool in a sandbox, then exec it (standard library only: it is
run as a script, `python -I hjif_sandbox.py MEM_BYTES CPU_S FSIZE_BYTES INPUT TOOL ARGS...`, by
hostd.texture.hjif.run_rm, in the private temporary folder that holds a read-only copy of the
tool's input and nothing else).

What it takes away before the exec, each where the platform allows it (the parent has checked the
opt-in, copied the input and chosen the folder):
- the network: a network namespace of its own (unshare(CLONE_NEWNET), in a user namespace when not
  root), so the tool sees only a loopback interface that is down;
- writing its input: INPUT (a copy the parent made) is bind-mounted read-only onto itself in a
  mount namespace of its own, so even a tool running as root gets EROFS;
- resources: address space, CPU seconds, the size of any file it writes, open files, core dumps;
- system calls a file parser has no use for, by a seccomp filter (libseccomp through ctypes; they
  fail with EPERM): sockets, ptrace, mounts, namespaces, kernel modules, keyrings, BPF, perf.
It prints `sandbox: ...` lines on stderr for what it could not apply (the parent reports them when
the tool fails) and never runs the tool without its rlimits.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import os
import resource
import sys

CLONE_NEWNS, CLONE_NEWUSER, CLONE_NEWNET = 0x00020000, 0x10000000, 0x40000000
MS_RDONLY, MS_REMOUNT, MS_BIND, MS_REC, MS_PRIVATE = 1, 32, 4096, 16384, 1 << 18
SCMP_ACT_ALLOW = 0x7FFF0000
DENIED = ("socket", "socketpair", "connect", "bind", "listen", "accept", "accept4", "ptrace",
          "process_vm_readv", "process_vm_writev", "mount", "umount2", "pivot_root", "chroot", "unshare",
          "setns", "init_module", "finit_module", "delete_module", "kexec_load", "keyctl", "add_key",
          "request_key", "bpf", "perf_event_open", "userfaultfd", "personality")


def namespaces(read_only: str) -> list[str]:
    """A network and a mount namespace of its own (in a user namespace when not root); `read_only`
    bind-mounted read-only onto itself. What could not be done, as reasons."""
    libc = ctypes.CDLL(None, use_errno=True)
    libc.mount.argtypes = [ctypes.c_char_p, ctypes.c_char_p, ctypes.c_char_p, ctypes.c_ulong, ctypes.c_void_p]
    uid, gid = os.getuid(), os.getgid()
    if libc.unshare(CLONE_NEWNET | CLONE_NEWNS) != 0:
        if libc.unshare(CLONE_NEWUSER | CLONE_NEWNET | CLONE_NEWNS) != 0:
            return [f"no network namespace ({os.strerror(ctypes.get_errno())})"]
        try:  # stay the same user inside the new user namespace
            with open("/proc/self/setgroups", "w") as f:
                f.write("deny")
            with open("/proc/self/uid_map", "w") as f:
                f.write(f"{uid} {uid} 1")
            with open("/proc/self/gid_map", "w") as f:
                f.write(f"{gid} {gid} 1")
        except OSError as e:
            return [f"user namespace without an id map ({e.strerror})"]
    if read_only == "-":
        return []
    src = read_only.encode()
    if (libc.mount(None, b"/", None, MS_REC | MS_PRIVATE, None) != 0
            or libc.mount(src, src, None, MS_BIND, None) != 0
            or libc.mount(None, src, None, MS_BIND | MS_REMOUNT | MS_RDONLY, None) != 0):
        return [f"input not mounted read-only ({os.strerror(ctypes.get_errno())}; it is a copy)"]
    return []


def seccomp() -> str:
    name = ctypes.util.find_library("seccomp") or "libseccomp.so.2"
    try:
        lib = ctypes.CDLL(name)
    except OSError:
        return "no seccomp filter (libseccomp not installed: apt-get install libseccomp2)"
    lib.seccomp_init.restype = ctypes.c_void_p
    lib.seccomp_init.argtypes = [ctypes.c_uint32]
    lib.seccomp_syscall_resolve_name.argtypes = [ctypes.c_char_p]
    lib.seccomp_rule_add.argtypes = [ctypes.c_void_p, ctypes.c_uint32, ctypes.c_int, ctypes.c_uint]
    lib.seccomp_load.argtypes = [ctypes.c_void_p]
    ctx = lib.seccomp_init(SCMP_ACT_ALLOW)
    if not ctx:
        return "no seccomp filter (seccomp_init failed)"
    eperm = 0x00050000 | errno.EPERM
    for call in DENIED:
        nr = lib.seccomp_syscall_resolve_name(call.encode())
        if nr >= 0 and lib.seccomp_rule_add(ctx, eperm, nr, 0) != 0:
            return f"no seccomp filter (rule for {call} refused)"
    if lib.seccomp_load(ctx) != 0:
        return "no seccomp filter (seccomp_load failed)"
    return ""


def main(argv: list[str]) -> None:
    mem, cpu, fsize = (int(x) for x in argv[1:4])
    read_only, tool = argv[4], argv[5:]
    for what, limit in ((resource.RLIMIT_AS, mem), (resource.RLIMIT_CPU, cpu), (resource.RLIMIT_FSIZE, fsize),
                        (resource.RLIMIT_NOFILE, 64), (resource.RLIMIT_CORE, 0)):
        resource.setrlimit(what, (limit, limit))
    for why in [*namespaces(read_only), seccomp()]:
        if why:
            print(f"sandbox: {why}", file=sys.stderr)
    os.execv(tool[0], tool)


if __name__ == "__main__":
    main(sys.argv)
