"""The pump's scheduling policy (hostd.device.realtime.SchedPolicy, `[realtime]
sched_fifo_priority`, 10 by default): SCHED_FIFO while it streams, SCHED_OTHER while it
supervises, nothing it starts inherits real time; where real time is not permitted one line says
what to do, once, and the pump streams as before."""

from __future__ import annotations

import os
import resource
import subprocess
import sys

import pytest

from hostd.device.pump import Pump
from hostd.device.simdev import SimTransport

PROBE = r"""
import os, resource, sys
from hostd.device.realtime import SchedPolicy
from hostd.service.config import RealtimeCfg
if sys.argv[1] == "drop":  # a user without the right: no RLIMIT_RTPRIO, not root
    resource.setrlimit(resource.RLIMIT_RTPRIO, (0, 0))
    os.setresgid(65534, 65534, 65534)
    os.setresuid(65534, 65534, 65534)
lines = []
sp = SchedPolicy(RealtimeCfg().sched_fifo_priority, lines.append)
seen = [os.sched_getscheduler(0)]
sp.streaming(True)
seen += [os.sched_getscheduler(0), os.sched_getparam(0).sched_priority]
pid = os.fork()
if pid == 0:
    os._exit(0 if os.sched_getscheduler(0) & ~os.SCHED_RESET_ON_FORK == os.SCHED_OTHER else 3)
_, status = os.waitpid(pid, 0)
seen.append(os.waitstatus_to_exitcode(status))
sp.streaming(False)
seen.append(os.sched_getscheduler(0))
sp.streaming(True)  # a second stream: said once
seen.append(os.sched_getscheduler(0))
sp.streaming(False)
print(*seen)
print("\n".join(lines))
"""


def _probe(mode: str) -> tuple[list[int], list[str]]:
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH")) if p))
    out = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True, env=env,
                         timeout=60, cwd=root)
    assert out.returncode == 0, out.stderr
    first, *lines = out.stdout.splitlines()
    return [int(x) for x in first.split()], lines


FIFO = os.SCHED_FIFO | os.SCHED_RESET_ON_FORK
OTHER = os.SCHED_OTHER | os.SCHED_RESET_ON_FORK


@pytest.mark.skipif(os.geteuid() != 0 and resource.getrlimit(resource.RLIMIT_RTPRIO)[0] < 10,
                    reason="SCHED_FIFO 10 is not permitted to this user (the refused case runs as root)")
def test_the_pump_streams_sched_fifo_10_supervises_sched_other_and_what_it_starts_is_not_real_time():
    (before, streaming, prio, child, after, again), lines = _probe("keep")
    assert before == os.SCHED_OTHER and streaming == FIFO and prio == 10
    assert child == 0  # the forked child runs SCHED_OTHER
    assert after == OTHER and again == FIFO
    assert lines == ["pump streams SCHED_FIFO priority 10 (supervises SCHED_OTHER)"]


@pytest.mark.skipif(os.geteuid() != 0, reason="dropping to an unprivileged user needs root")
def test_a_pump_not_permitted_sched_fifo_says_what_to_do_once_and_streams_as_before():
    (before, streaming, prio, child, after, again), lines = _probe("drop")
    assert before == streaming == after == again == os.SCHED_OTHER and prio == 0 and child == 0
    assert len(lines) == 1 and lines[0].startswith("pump: SCHED_FIFO 10 not permitted (")
    assert "LimitRTPRIO" in lines[0] and "sched_fifo_priority = 0" in lines[0]


class _Policy:
    def __init__(self) -> None:
        self.calls: list[bool] = []

    def streaming(self, on: bool) -> None:
        self.calls.append(on)


def test_the_pump_is_real_time_from_before_its_prime_until_it_stops():
    from hostd.bench.accuracy import texture_coeffs
    from hostd.device.link import DeviceLink
    from hostd.render import RenderConfig, Renderer
    from hostd.texture import synth

    t = SimTransport(realtime=False)
    link = DeviceLink(t, target_fill=12)
    link.handshake(timeout_s=2.0)
    policy = _Policy()
    sent: list[tuple[bool, bytes]] = []  # each message to the display, and whether it streamed then
    real_send = t.send

    def send(msg: bytes) -> None:
        sent.append((bool(policy.calls and policy.calls[-1]), msg))
        real_send(msg)

    pump = Pump(link, None, realtime=policy)
    assert policy.calls == [False]  # a pump with nothing to stream supervises
    c, n, length = texture_coeffs(synth.make("wood", seed=1))
    r = Renderer(c, n, length, RenderConfig())
    r.start()
    t.send = send
    pump.begin(r)
    # the prime and START went out, and all of it real-time
    assert policy.calls == [False, True] and sent and all(on for on, _ in sent), sent[:3]
    pump.end()
    assert policy.calls == [False, True, False]


@pytest.mark.parametrize("files, version, want", [
    # debugfs names the running model in parentheses: it wins over everything else
    ({"/sys/kernel/debug/sched/preempt": "none voluntary (full) lazy\n",
      "/proc/cmdline": "quiet preempt=none", "/proc/config.gz": "CONFIG_PREEMPT_NONE=y\n"}, "#1 SMP", "full"),
    ({"/proc/cmdline": "quiet preempt=full"}, "#1 SMP PREEMPT_RT", "rt"),
    ({"/proc/cmdline": "ro quiet preempt=voluntary splash", "/proc/config.gz": "CONFIG_PREEMPT=y\n"},
     "#1 SMP PREEMPT_DYNAMIC", "voluntary"),
    # the build default: CONFIG_PREEMPT_DYNAMIC=y beside CONFIG_PREEMPT_NONE=y is "none"
    ({"/proc/cmdline": "quiet", "/proc/config.gz": "CONFIG_PREEMPT_BUILD=y\nCONFIG_PREEMPT_NONE=y\n"
      "CONFIG_PREEMPT_DYNAMIC=y\nCONFIG_PREEMPTION=y\n"}, "#1 SMP PREEMPT_DYNAMIC", "none"),
    ({"/boot/config-6.1.0-test": "# CONFIG_PREEMPT_NONE is not set\nCONFIG_PREEMPT_VOLUNTARY=y\n"},
     "#1 SMP", "voluntary"),
    ({"/boot/config-6.1.0-test": "CONFIG_PREEMPT=y\nCONFIG_PREEMPT_COUNT=y\n"}, "#1 SMP", "full"),
    ({"/sys/kernel/debug/sched/preempt": "garbage", "/proc/cmdline": "preempt=bogus"}, "#1 SMP", "unknown"),
    ({}, "#1 SMP", "unknown"),
])
def test_the_kernel_preemption_model_is_read_from_where_the_kernel_says_it(files, version, want):
    from hostd.device.realtime import preemption_model

    model, source = preemption_model(read=files.get, uname_version=version, release="6.1.0-test")
    assert model == want, (model, source)
    assert source


def test_doctor_says_the_kernels_preemption_model_and_what_to_do_when_it_holds_a_real_time_pump(capsys):
    from hostd.device.realtime import preemption_model
    from hostd.service.doctor import doctor

    doctor(None)
    out = capsys.readouterr().out
    model, _ = preemption_model()  # this machine's own
    line = next(ln for ln in out.splitlines() if "kernel preemption:" in ln)
    assert f"kernel preemption: {model}" in line
    if model in ("none", "voluntary", "unknown"):
        assert line.lstrip().startswith("note") and "preempt=full" in line, line
    else:
        assert line.lstrip().startswith("ok"), line


@pytest.mark.parametrize("files, says", [
    ({"/proc/cpuinfo": "processor\t: 0\nflags\t\t: fpu vme de pse tsc msr hypervisor lahf_lm\n"},
     "hypervisor flag"),
    ({"/proc/cpuinfo": "flags\t\t: fpu vme de pse tsc msr\n", "/sys/hypervisor/type": "xen\n"}, "xen"),
    ({"/sys/class/dmi/id/sys_vendor": "QEMU\n", "/sys/class/dmi/id/product_name": "Standard PC (Q35)\n"},
     "QEMU"),
    ({"/sys/class/dmi/id/sys_vendor": "Microsoft Corporation\n",
      "/sys/class/dmi/id/product_name": "Virtual Machine\n"}, "Microsoft"),
    # bare metal: a flag list without it, a maker's DMI, a Surface (Microsoft, but no virtual machine)
    ({"/proc/cpuinfo": "flags\t\t: fpu vme de pse tsc msr hypervisorish\n",
      "/sys/class/dmi/id/sys_vendor": "Dell Inc.\n"}, None),
    ({"/sys/class/dmi/id/sys_vendor": "Microsoft Corporation\n",
      "/sys/class/dmi/id/product_name": "Surface Pro\n"}, None),
    # a Chromebook, a bare-metal EC2 instance: vendors that virtual machines share with real ones
    ({"/sys/class/dmi/id/sys_vendor": "Google\n", "/sys/class/dmi/id/product_name": "Eve\n"}, None),
    ({"/sys/class/dmi/id/sys_vendor": "Amazon EC2\n", "/sys/class/dmi/id/product_name": "c7g.metal\n"}, None),
    ({}, None),
])
def test_a_virtual_machine_is_told_from_what_the_kernel_says(files, says):
    from hostd.device.realtime import hypervisor

    where = hypervisor(read=files.get)
    if says is None:
        assert where is None, where
    else:
        assert where is not None and says in where, where


def test_doctor_says_a_virtual_machine_and_what_its_hypervisor_costs_a_real_time_pump(capsys):
    from hostd.device.realtime import hypervisor
    from hostd.service.doctor import doctor

    doctor(None)
    out = capsys.readouterr().out
    lines = [ln for ln in out.splitlines() if "virtual machine (" in ln]
    if hypervisor() is None:  # bare metal: nothing to say
        assert not lines, lines
    else:
        assert len(lines) == 1 and lines[0].lstrip().startswith("note") and "bare metal" in lines[0], lines
