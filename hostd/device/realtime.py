"""The pump's scheduling policy: real-time while it streams, an ordinary process while it supervises.

A pump that streams samples (host rendering, a stimulus) must write every millisecond, and the
display's buffer covers only a few: a SCHED_OTHER pump waited 4-6 ms behind a busier neighbour
on a quiet machine, and the display ran dry (DEVELOPMENT.md, "Link latency"). SCHED_FIFO
removes those waits. A pump that supervises a display rendering itself (device mode) sleeps
between reports 300 ms apart and needs none of it; at SCHED_FIFO it woke while the kernel still
handed the display's report over, and its read (TIOCINQ takes the line discipline's lock) waited
again: 1.8 sleeps per run of its loop instead of 1.0 (`hostd bench soak --render device --check
ci`, 2026-11-27). So the pump asks for SCHED_FIFO when it begins to stream and gives it back when
it stops (`Pump(realtime=...)`).

SCHED_RESET_ON_FORK: nothing the pump starts (its equalizer's design, for one) is real-time.
Not permitted (no LimitRTPRIO, not root): one line says what to do, once, and the pump streams
SCHED_OTHER as before; it does not ask again.
"""

from __future__ import annotations

import os


class SchedPolicy:
    """SCHED_FIFO at `priority` while streaming(True), SCHED_OTHER otherwise; priority 0: never
    real-time. `policy` says what the calling thread runs now (and why not real-time)."""

    def __init__(self, priority: int, log=None) -> None:
        self.priority = priority
        self.log = log
        self.policy = "SCHED_OTHER"
        self._denied = priority <= 0
        self._fifo = False
        self._said = False

    def streaming(self, on: bool) -> None:
        if on == self._fifo or (on and self._denied):
            return
        flags = getattr(os, "SCHED_RESET_ON_FORK", 0)
        try:
            if on:
                os.sched_setscheduler(0, os.SCHED_FIFO | flags, os.sched_param(self.priority))
            else:  # (always permitted; an unprivileged thread keeps RESET_ON_FORK once set)
                os.sched_setscheduler(0, os.SCHED_OTHER | flags, os.sched_param(0))
        except (OSError, AttributeError) as e:
            if on:
                self._denied = True
                why = getattr(e, "strerror", None) or str(e)
                self.policy = f"SCHED_OTHER (SCHED_FIFO {self.priority} not permitted: {why})"
                self._say(f"pump: SCHED_FIFO {self.priority} not permitted ({why}); it streams SCHED_OTHER: "
                          "grant LimitRTPRIO/CAP_SYS_NICE (systemd/hostd.service does), or set [realtime] "
                          "sched_fifo_priority = 0 not to ask")
            return
        self._fifo = on
        self.policy = f"SCHED_FIFO {self.priority}" if on else "SCHED_OTHER"
        if on and not self._said:
            self._said = True
            self._say(f"pump streams SCHED_FIFO priority {self.priority} (supervises SCHED_OTHER)")

    def _say(self, msg: str) -> None:
        if self.log is not None:
            self.log(msg)


# The kernel's preemption model decides whether a real-time pump gets its CPU back from kernel code
# at once ("full", "lazy", "rt") or only where that code yields ("none", "voluntary"); a display
# PC runs one of the first three. `hostd doctor` says which model runs. On this project's VM
# (6.18, preempt=none by its build default) the model was not what held the pump: in 60 traced
# latency runs no real-time task waited runnable over 1.5 ms, while the hypervisor left one or
# both virtual CPUs unrun for 2.3-4.4 ms, unaccounted as steal, and the 4 ms buffer ran dry
# (DEVELOPMENT.md, "Link latency"). `hypervisor()` lets doctor say so.
PREEMPT_MODELS = ("none", "voluntary", "full", "lazy", "rt")
_CONFIG_MODELS = (("CONFIG_PREEMPT_RT", "rt"), ("CONFIG_PREEMPT_LAZY", "lazy"), ("CONFIG_PREEMPT", "full"),
                  ("CONFIG_PREEMPT_VOLUNTARY", "voluntary"), ("CONFIG_PREEMPT_NONE", "none"))


def _read(path: str) -> str | None:
    try:
        if path.endswith(".gz"):
            import gzip

            with gzip.open(path, "rt") as fh:
                return fh.read()
        with open(path) as fh:
            return fh.read()
    except (OSError, EOFError, UnicodeDecodeError):  # absent, not permitted (debugfs), damaged
        return None


# A guest's virtual CPU runs when its hypervisor runs it; time it is not run while it halts, or
# while a busy host runs something else, need not show as steal in /proc/stat. DMI vendors that
# only ever name a virtual machine (not "Google", a Chromebook's too, nor "Amazon EC2", its bare
# metal instances' too; on x86 their guests have the CPU flag).
_DMI_VIRTUAL = ("QEMU", "KVM", "VMware", "innotek", "Xen", "Parallels", "Bochs", "BHYVE")


def hypervisor(read=_read) -> str | None:
    """Where this kernel says it runs under a hypervisor (the CPU's `hypervisor` flag in
    /proc/cpuinfo, /sys/hypervisor/type, a virtual machine's DMI vendor), or None on bare metal
    or when nothing says."""
    for line in (read("/proc/cpuinfo") or "").splitlines():
        key, _, value = line.partition(":")
        if key.strip() == "flags" and "hypervisor" in value.split():
            return "the CPU's hypervisor flag, /proc/cpuinfo"
    kind = (read("/sys/hypervisor/type") or "").strip()
    if kind:
        return f"/sys/hypervisor/type: {kind}"
    vendor = (read("/sys/class/dmi/id/sys_vendor") or "").strip()
    product = (read("/sys/class/dmi/id/product_name") or "").strip()
    if any(vendor.startswith(v) for v in _DMI_VIRTUAL) or (
            vendor.startswith("Microsoft") and product == "Virtual Machine"):
        return f"DMI vendor {vendor!r}"
    return None


def preemption_model(read=_read, uname_version: str | None = None,
                     release: str | None = None) -> tuple[str, str]:
    """(model, where it was read): the running model from debugfs where it can be read (the one
    in parentheses), else a PREEMPT_RT kernel from uname, else `preempt=` on the kernel's command
    line, else the kernel's build default (/proc/config.gz, /boot/config-RELEASE); ("unknown", why)
    when none says."""
    un = os.uname()
    version = un.version if uname_version is None else uname_version
    release = un.release if release is None else release
    text = read("/sys/kernel/debug/sched/preempt")
    if text:
        for word in text.split():
            if word.startswith("(") and word.endswith(")") and word[1:-1] in PREEMPT_MODELS:
                return word[1:-1], "/sys/kernel/debug/sched/preempt"
    if "PREEMPT_RT" in version.split():
        return "rt", "uname -v"
    cmdline = read("/proc/cmdline") or ""
    for arg in cmdline.split():
        if arg.startswith("preempt=") and arg[len("preempt="):] in PREEMPT_MODELS:
            return arg[len("preempt="):], "preempt= on the kernel's command line"
    for path in ("/proc/config.gz", f"/boot/config-{release}"):
        config = read(path)
        if not config:
            continue
        on = {line.split("=", 1)[0] for line in config.splitlines() if line.endswith("=y")}
        for key, model in _CONFIG_MODELS:
            if key in on:
                return model, f"the kernel's build default, {path}"
    return "unknown", "no debugfs, no preempt= and no kernel config to read"
