"""Hotplug from udev events: the monitor's events (a fake monitor, and a real pyudev monitor on the
kernel's own uevents where this machine lets us make one), the poll fallback and why, and the
pump process reacting to an arrival and a removal at once (a fake monitor fed through a pipe;
the real USB gadget unplugged and replugged under udev is tests/hil)."""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import select
import sys
import time
from collections import deque
from pathlib import Path

import pytest

from hostd.device import hotplug
from hostd.device import protocol as pr

DISPLAY_HID = f"0003:{pr.USB_VID:08X}:{pr.USB_PID:08X}"


class FakeDevice:
    def __init__(self, action, subsystem, node=None, devtype=None, props=None, parents=()):
        self.action, self.subsystem, self.device_node, self.device_type = action, subsystem, node, devtype
        self.properties = props or {}
        self._parents = parents

    @property
    def ancestors(self):
        if self.action == "remove":
            raise OSError("no sysfs for a removed device")
        return iter(self._parents)


class FakeMonitor:
    """pyudev.Monitor's surface: fileno() and poll(timeout=0); events come from a pipe (JSON lines)
    so another process can feed them."""

    def __init__(self):
        self.r, self.w = os.pipe()
        os.set_blocking(self.r, False)
        self.queue: deque = deque()
        self.buf = b""

    def fileno(self):
        return self.r

    def push(self, **ev):
        os.write(self.w, json.dumps(ev).encode() + b"\n")

    def poll(self, timeout=None):
        if not self.queue:
            try:
                self.buf += os.read(self.r, 65536)
            except BlockingIOError:
                pass
            *lines, self.buf = self.buf.split(b"\n")
            for line in lines:
                e = json.loads(line)
                parents = [FakeDevice("add", "hid", props={"HID_ID": e.pop("parent_hid")})] \
                    if "parent_hid" in e else []
                self.queue.append(FakeDevice(parents=parents, **e))
        return self.queue.popleft() if self.queue else None


def test_events_match_the_display_by_its_ids_and_skip_the_rest():
    mon = FakeMonitor()
    h = hotplug.Hotplug(mon, ("hidraw", "usb", "tty"))
    assert h.mode == "udev" and h.fileno() == mon.fileno()
    now = time.monotonic()
    mon.push(action="add", subsystem="hidraw", node="/dev/hidraw2", parent_hid=DISPLAY_HID,
             props={"USEC_INITIALIZED": str(int((now - 0.25) * 1e6))})
    mon.push(action="add", subsystem="hidraw", node="/dev/hidraw1", parent_hid="0003:0000046D:0000C077")
    mon.push(action="add", subsystem="usb", devtype="usb_interface", props={"PRODUCT": "1209/7470/100"})
    mon.push(action="add", subsystem="usb", node="/dev/bus/usb/001/004", devtype="usb_device",
             props={"PRODUCT": "1209/7470/100"})
    mon.push(action="change", subsystem="tty", node="/dev/ttyACM0")
    mon.push(action="remove", subsystem="hidraw", node="/dev/hidraw2")
    evs = h.events()
    assert [(e.action, e.node, e.display) for e in evs] == [
        ("add", "/dev/hidraw2", True), ("add", "/dev/hidraw1", False),
        ("add", "/dev/bus/usb/001/004", True), ("remove", "/dev/hidraw2", False)]
    assert abs(evs[0].t - (now - 0.25)) < 1e-3  # udev's own stamp of the arrival
    assert h.events() == []


def test_poll_fallback_says_why(tmp_path, monkeypatch):
    h = hotplug.watch("hid", control=str(tmp_path / "no-udev-control"))
    assert h.mode == "poll" and "udev is not running" in h.describe() and h.fileno() is None
    assert hotplug.watch("serial:/dev/pts/3").mode == "poll"
    assert hotplug.watch("sim").mode == "none"
    ctl = tmp_path / "control"
    ctl.touch()
    monkeypatch.setitem(sys.modules, "pyudev", None)  # not installed
    h = hotplug.watch("usb", control=str(ctl))
    assert h.mode == "poll" and "pip install '" in h.describe() and "[device]'" in h.describe()


def _kernel_monitor(spec):
    pytest.importorskip("pyudev")
    h = hotplug.watch(spec, source="kernel")
    if h.mode != "udev":
        pytest.skip(f"no netlink uevent socket here: {h.describe()}")
    return h


def test_a_real_pyudev_monitor_gets_a_kernel_uevent_filtered_by_subsystem():
    trigger = Path("/sys/class/tty/ttyS0/uevent")
    if not os.access(trigger, os.W_OK):
        pytest.skip("cannot make the kernel send a uevent here (no writable /sys/class/tty/ttyS0/uevent)")
    tty = _kernel_monitor("serial")
    hid = _kernel_monitor("hid")
    trigger.write_text("add")  # a synthetic uevent: the kernel sends it, nothing changes
    got = []
    t_end = time.monotonic() + 2.0
    while not got and time.monotonic() < t_end:
        select.select([tty.fileno()], [], [], 0.1)
        got = [e for e in tty.events() if e.node == "/dev/ttyS0"]
    if not got:
        pytest.skip("the kernel's uevents do not reach this network namespace")
    assert got[0].action == "add" and got[0].subsystem == "tty" and not got[0].display
    assert [e for e in hid.events() if e.node == "/dev/ttyS0"] == []  # filtered in the kernel


# ------------------------------------------------------------------ the pump process
def _pump_child(cfg, conn, stats, mon, flag, listed=None):
    """The daemon's pump, with the fake monitor as udev and a display that exists while `flag`
    does (a simulated device behind a hidraw-looking name)."""
    from hostd.device import transport as tr
    from hostd.device.simdev import SimTransport
    from hostd.errors import DeviceNotFound
    from hostd.service import pumpproc

    class Plugged(SimTransport):
        node = "/dev/hidraw9"

        def describe(self):
            return "hid:/dev/hidraw9"

    class Silent(Plugged):  # opens, never answers (a display without our firmware)
        def recv(self, timeout_s=0.0):
            time.sleep(timeout_s)

        def close(self):
            Path(flag + ".closed").touch()

    def open_transport(spec):
        if os.path.exists(flag + ".silent"):
            return Silent()
        if not os.path.exists(flag):
            raise DeviceNotFound("no HID display 1209:7470 (hidraw devices seen: none)")
        return Plugged()

    hotplug.watch = lambda spec: hotplug.Hotplug(mon, ("hidraw",))
    tr.open_transport = open_transport
    # what sysfs lists (nothing is opened): the display while `listed` exists
    tr.present = lambda spec: [{"spec": "hid:/dev/hidraw9"}] if listed and os.path.exists(listed) else []
    pumpproc.pump_main(cfg, conn, stats)


class PumpChild:
    """The pump process on a config with `transport`, the fake monitor as udev; collects its log
    lines and info messages."""

    def __init__(self, tmp_path, transport):
        from hostd.service.config import load
        from hostd.service.pumpproc import STAT_FIELDS

        p = tmp_path / "c.toml"
        p.write_text(f'[device]\ntransport = "{transport}"\nreconnect_s = 1.0\n')
        ctx = mp.get_context("fork")
        self.stats = ctx.Array("d", len(STAT_FIELDS), lock=False)
        self.parent, child = ctx.Pipe()
        self.mon = FakeMonitor()
        self.flag = tmp_path / "plugged"
        self.listed = tmp_path / "listed"
        self.proc = ctx.Process(target=_pump_child, args=(load(p), child, self.stats, self.mon,
                                                          str(self.flag), str(self.listed)), daemon=True)
        self.proc.start()
        self.lines: list = []
        self.info: dict = {}

    def says(self, pred, timeout_s):
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            if self.parent.poll(0.02):
                kind, msg = self.parent.recv()
                if kind == "info":
                    self.info.update(msg)
                else:
                    self.lines.append(msg)
            if pred():
                return True
        return False

    def close(self):
        self.parent.send(("quit",))
        self.proc.join(5)
        if self.proc.is_alive():
            self.proc.kill()


def test_pump_reconnects_on_the_udev_event_at_once_and_drops_on_removal(tmp_path):
    from hostd.service.pumpproc import STAT_INDEX

    pc = PumpChild(tmp_path, "hid")
    parent, stats, mon, flag, lines, info, pump_says = (pc.parent, pc.stats, pc.mon, pc.flag, pc.lines,
                                                        pc.info, pc.says)
    try:
        assert pump_says(lambda: any("no HID display" in m for m in lines), 60), lines
        assert info["hotplug"] == "udev"
        from hostd.bench.accuracy import texture_coeffs
        from hostd.texture import synth

        c, n, length = texture_coeffs(synth.make("wood", seed=1))
        parent.send(("select", ("wood", list(c), n, length)))  # kept until a display is there
        # absent: no retry by the clock (the 1 s poll is only the fallback), only wake-ups
        attempts = stats[STAT_INDEX["reconnects"]]
        time.sleep(2.5)
        assert stats[STAT_INDEX["reconnects"]] == attempts
        assert stats[STAT_INDEX["wait_ticks"]] >= 2  # the watchdog still sees the pump alive
        # plugged: the udev add event, and the pump is connected within a fraction of a second
        flag.touch()
        mon.push(action="add", subsystem="hidraw", node="/dev/hidraw9", parent_hid=DISPLAY_HID)
        # what the design guarantees, in order and by cause (how fast is a speed goal: the VM rig
        # measures udev add -> playing, DEVELOPMENT.md; a loaded machine stretches it here):
        # the event, not a retry by the clock (there was none while absent), brought it back
        assert pump_says(lambda: info.get("transport") == "hid:/dev/hidraw9", 60), lines
        assert pump_says(lambda: info.get("last_reconnect_s") is not None, 60), lines
        assert info["last_reconnect_s"] > 0 and info["reconnected"] == 1
        assert any("playing again" in m and "after its udev add event" in m for m in lines), lines
        # and it plays: the device's own counter advances (samples played from its buffer when
        # the host renders, ticks rendered at full gain when the display renders: auto's choice)
        assert pump_says(lambda: stats[STAT_INDEX["device_samples_played"]] > 0
                         or stats[STAT_INDEX["device_rendered_s"]] > 0, 3)
        # unplugged: the udev remove event of our node ends the link at once (the simulated
        # device would have gone on answering: only the event can have done it)
        flag.unlink()
        mon.push(action="remove", subsystem="hidraw", node="/dev/hidraw9")
        assert pump_says(lambda: any("removed (udev event)" in m for m in lines), 5), lines
        assert pump_says(lambda: info.get("transport") is None, 5)
        assert stats[STAT_INDEX["connected"]] == 0
    finally:
        pc.close()


def test_auto_waits_for_the_hidraw_node_after_the_usb_event(tmp_path):
    # with "auto", the USB device's event comes before usbhid made the hidraw node; opening at
    # once would take the display as raw USB (detaching usbhid) or fail
    pc = PumpChild(tmp_path, "auto")
    try:
        def tries():
            return sum("no HID display" in m for m in pc.lines)

        assert pc.says(lambda: tries() == 1, 60), pc.lines
        pc.mon.push(action="add", subsystem="usb", devtype="usb_device", node="/dev/bus/usb/001/009",
                    props={"PRODUCT": f"{pr.USB_VID:x}/{pr.USB_PID:x}/100"})
        pc.says(lambda: False, 0.3)
        assert tries() == 1  # not yet: usbhid has had no time to bind
        pc.flag.touch()
        t0 = time.monotonic()
        pc.mon.push(action="add", subsystem="hidraw", node="/dev/hidraw9", parent_hid=DISPLAY_HID)
        assert pc.says(lambda: pc.info.get("transport") == "hid:/dev/hidraw9", 5), pc.lines
        assert time.monotonic() - t0 < 1.0
    finally:
        pc.close()


def test_a_missed_udev_event_costs_one_reconnect_interval_not_forever(tmp_path):
    # the unit's PrivateNetwork=yes (a private network namespace) hides udev's events: the
    # display's sysfs entry, looked at once per device.reconnect_s, still brings it back
    pc = PumpChild(tmp_path, "hid")
    try:
        assert pc.says(lambda: any("no HID display" in m for m in pc.lines), 60), pc.lines
        pc.flag.touch()
        pc.listed.touch()  # plugged, and no event comes
        assert pc.says(lambda: pc.info.get("transport") == "hid:/dev/hidraw9", 3), pc.lines
        assert any("no udev event said so" in m and "PrivateNetwork" in m for m in pc.lines)
        assert pc.info["hotplug_missed"] == 1 and pc.info["last_reconnect_s"] is None  # no event to time
    finally:
        pc.close()


def test_a_display_that_opens_but_does_not_answer_is_closed_before_the_retry(tmp_path):
    # the fd (hidraw) or the interface claim with usbhid detached (raw USB) must not leak per retry
    pc = PumpChild(tmp_path, "hid")
    try:
        Path(str(pc.flag) + ".silent").touch()
        assert pc.says(lambda: any("no answer to IDENTIFY" in m for m in pc.lines), 60), pc.lines
        assert Path(str(pc.flag) + ".closed").exists()
    finally:
        pc.close()


def test_a_hidraw_node_unplugged_while_listed_is_skipped_not_a_crash(tmp_path, monkeypatch):
    """The VM rig's replug (2026-11-27, under load): /sys/class/hidraw/hidraw0 went away between
    the listing and its resolve(); the FileNotFoundError ended the pump. A node gone meanwhile is
    not there; the others are listed."""
    from pathlib import Path

    from hostd.device import hidlink
    from hostd.device import protocol as pr

    for name in ("hidraw0", "hidraw1"):
        dev = tmp_path / "devices" / name
        (dev / "device").mkdir(parents=True)
        (dev / "device" / "uevent").write_text(f"HID_ID=0003:{pr.USB_VID:08X}:{pr.USB_PID:08X}\nHID_NAME=x\n")
        (dev / "uevent").write_text(f"DEVNAME={name}\n")
        (tmp_path / "class" / "hidraw").mkdir(parents=True, exist_ok=True)
        (tmp_path / "class" / "hidraw" / name).symlink_to(dev)
    real = Path.resolve

    def resolve(self, strict=False):
        if self.name == "hidraw0":
            raise FileNotFoundError(2, "No such file or directory", str(self))
        return real(self, strict=strict)

    monkeypatch.setattr(Path, "resolve", resolve)
    found = hidlink.enumerate_hidraw(str(tmp_path))
    assert [d["node"] for d in found] == ["/dev/hidraw1"]
