"""The transports' error paths against fakes; the real kernel is tests/hil (a VM with a USB gadget).

Which fake stands in for what:
- hidraw (Linux): a SOCK_SEQPACKET socketpair in place of /dev/hidrawN (one record per report,
  zero-length records like the zero-length packets a 64-byte report is followed by, hang-up
  when the peer closes like an unplugged node); a fake sysfs tree for enumeration by VID:PID.
- hidapi (macOS, Windows): a fake `hid` module.
- raw USB: a fake pyusb device + `usb.util` recorder, a fake sysfs and /proc for "who holds it".
"""

from __future__ import annotations

import errno
import os
import socket
import sys
import threading
import time
from pathlib import Path

import pytest

from hostd.device import backend, hidlink, hotplug, usblink
from hostd.device import protocol as pr
from hostd.device.hidlink import HidapiTransport, HidrawTransport
from hostd.device.link import DeviceLink
from hostd.device.transport import open_transport
from hostd.device.usblink import UsbTransport
from hostd.errors import DeviceBusy, DeviceGone, DeviceNotFound, DevicePermission, DeviceVersion

VECTORS = Path(__file__).resolve().parent / "vectors" / "protocol.txt"


def vec(name: str) -> bytes:
    return next(bytes.fromhex(line.split()[2]) for line in VECTORS.read_text().splitlines()
                if line.startswith("msg ") and line.split()[1] == name)


# ------------------------------------------------------------------ hidraw, through a socketpair
@pytest.fixture
def hidraw():
    """(transport, device end): the device end reads what the host wrote, record by record."""
    host, device = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    t = HidrawTransport("/dev/hidraw7", fd=os.dup(host.fileno()))
    host.close()
    device.settimeout(1.0)
    yield t, device
    t.close()
    device.close()


def test_hidraw_writes_report_id_zero_then_the_64_byte_report(hidraw):
    t, dev = hidraw
    t.send(pr.encode("IDENTIFY"))
    got = dev.recv(256)
    assert got == b"\x00" + pr.pad_report(vec("identify")) and len(got) == 65
    assert t.describe() == "hid:/dev/hidraw7" and t.fileno() >= 0


def test_hidraw_zero_length_packets_are_not_reports_20_of_20_exchanges_match(hidraw):
    # the 6.1 gadget sends a zero-length packet after every 64-byte report; the old transport
    # returned it as "no report", and 19 of 20 request/reply exchanges were mismatched
    t, dev = hidraw
    for i in range(20):
        t.send(pr.encode("IDENTIFY"))
        assert dev.recv(256)[1] == pr.IDS["IDENTIFY"]
        reply = pr.pad_report(pr.encode("IDENT", protocol_version=pr.VERSION, fw_patch=i))
        dev.send(reply)
        dev.send(b"")  # the zero-length packet after a full-size report
        assert t.recv(0.5) == reply
    assert t.empty_reads >= 19
    assert t.recv(0.0) is None  # the last one's trailing empty packet is skipped, nothing left


def test_hidraw_short_reports_are_passed_on_and_the_link_counts_truncated_ones(hidraw):
    t, dev = hidraw
    link = DeviceLink(t)
    status = vec("status")
    dev.send(status[:10])  # truncated: malformed, counted, not fatal
    dev.send(status)  # complete but unpadded: a message
    assert link.poll(0.2) == 1
    assert link.stats.bad_messages_received == 1
    assert link.stats.last_status["encoder_count"] == pr.decode(status)[1]["encoder_count"]


def test_hidraw_handshake_and_blocking_wait(hidraw):
    t, dev = hidraw
    assert t.wait(0.01) is False
    r, w = os.pipe()
    os.write(w, b"x")  # a command for the pump: the wait ends at once, False (nothing from the device)
    t0 = time.monotonic()
    assert t.wait(5.0, fds=[r]) is False and time.monotonic() - t0 < 1.0
    os.close(r)
    os.close(w)
    threading.Timer(0.05, lambda: dev.send(pr.pad_report(vec("ident")))).start()
    t0 = time.monotonic()
    assert t.wait(2.0) is True
    assert time.monotonic() - t0 < 1.5
    assert DeviceLink(t).handshake(timeout_s=0.5)["limit_code"] == 16383


def test_hidraw_removed_mid_read_is_device_gone_at_once(hidraw):
    t, dev = hidraw
    threading.Timer(0.05, dev.close).start()  # the node hangs up while recv waits
    t0 = time.monotonic()
    with pytest.raises(DeviceGone, match=r"/dev/hidraw7.*re-plug"):
        t.recv(5.0)
    assert time.monotonic() - t0 < 2.0


def test_hidraw_read_and_write_errors_map_to_what_to_do(hidraw, monkeypatch):
    t, _dev = hidraw

    def fail(code):
        def f(*_a):
            raise OSError(code, os.strerror(code))
        return f

    monkeypatch.setattr(hidlink.os, "read", fail(errno.EIO))
    with pytest.raises(DeviceGone, match="hostd reconnects"):
        t.recv(0.01)
    monkeypatch.setattr(hidlink.os, "write", fail(errno.ENODEV))
    with pytest.raises(DeviceGone):
        t.send(pr.encode("START"))
    monkeypatch.setattr(hidlink.os, "write", fail(errno.ETIMEDOUT))
    with pytest.raises(DeviceBusy, match="transient"):  # the link retries it within the cycle
        t.send(pr.encode("START"))


def _sysfs(tmp: Path, nodes: dict[str, str]) -> str:
    """A fake /sys/class/hidraw: name -> HID_ID."""
    for name, hid_id in nodes.items():
        d = tmp / "class" / "hidraw" / name
        (d / "device").mkdir(parents=True)
        (d / "uevent").write_text(f"MAJOR=241\nMINOR=0\nDEVNAME={name}\n")
        (d / "device" / "uevent").write_text(f"DRIVER=hid-generic\nHID_ID={hid_id}\nHID_NAME=x\n")
    return str(tmp)


MINE, MOUSE = "0003:00001209:00007470", "0003:0000046D:0000C077"


def test_hidraw_found_by_vid_pid_in_sysfs_and_a_named_node_is_used(tmp_path, monkeypatch):
    sysfs = _sysfs(tmp_path, {"hidraw0": MOUSE, "hidraw3": MINE})
    assert [d["spec"] for d in hidlink.enumerate_displays(sysfs)] == ["hid:/dev/hidraw3"]
    opened = []
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)

    def fake_open(path, flags, *_):
        opened.append((path, flags))
        return os.dup(a.fileno())

    monkeypatch.setattr(hidlink.os, "open", fake_open)
    t = hidlink.open_hid(None, sysfs=sysfs)  # [device] transport = "hid": found by VID:PID
    assert opened[-1][0] == "/dev/hidraw3" and opened[-1][1] & os.O_NONBLOCK
    t.close()
    t = hidlink.open_hid("/dev/hidraw9", sysfs=sysfs)  # transport = "hid:/dev/hidraw9": that node
    assert opened[-1][0] == "/dev/hidraw9" and t.describe() == "hid:/dev/hidraw9"
    t.close()
    a.close()
    b.close()
    with pytest.raises(DeviceNotFound, match=r"/dev/hidraw0 is 046d:c077, not the display"):
        hidlink.open_hid("/dev/hidraw0", sysfs=sysfs)  # a mouse: nothing is written to it
    assert len(opened) == 2
    if sys.platform == "linux":  # before the HID modules load there is no /sys/class/hidraw: still hidraw
        with pytest.raises(DeviceNotFound, match=r"hidraw devices seen: none"):
            hidlink.open_hid(None, sysfs=str(tmp_path / "no-sysfs"))
    with pytest.raises(DeviceNotFound, match=r"hidraw devices seen: 046d:c077"):
        hidlink.open_hid(None, sysfs=_sysfs(tmp_path / "other", {"hidraw0": MOUSE}))


def test_hidraw_permission_denied_names_the_node_the_rule_and_the_group(tmp_path, monkeypatch):
    node = tmp_path / "hidraw4"
    node.write_text("")
    node.chmod(0o600)

    def denied(path, flags, *_):
        raise PermissionError(errno.EACCES, "Permission denied", path)

    monkeypatch.setattr(hidlink.os, "open", denied)
    with pytest.raises(DevicePermission) as e:
        HidrawTransport(str(node))
    msg = str(e.value)
    assert str(node) in msg and "0600" in msg and "70-hostd.rules" in msg and "'hostd' group" in msg
    assert "must exist before the display appears" in msg and "\n" not in msg
    # the rule worked (group hostd) but this user is not in the group: say that instead
    monkeypatch.setattr(backend, "node_owner", lambda n: {"node": n, "owner": "root", "group": "hostd",
                                                          "mode": "0660", "access": False})
    with pytest.raises(DevicePermission, match=r"\(root:hostd 0660\): the udev rule \(systemd/70-hostd"
                       r"\.rules\) gave it to group 'hostd': add your user to it \(sudo usermod -aG hostd"):
        HidrawTransport(str(node))
    monkeypatch.undo()
    with pytest.raises(DeviceNotFound, match="does not exist"):
        HidrawTransport(str(tmp_path / "hidraw5"), sysfs=str(tmp_path))


# ------------------------------------------------------------------ hidapi (no hidraw), fake module
class FakeHidDevice:
    def __init__(self, replies):
        self.writes: list[bytes] = []
        self.replies = list(replies)
        self.opened = None
        self.fail_read = None

    def open_path(self, path):
        self.opened = path

    def set_nonblocking(self, flag):
        pass

    def write(self, data):
        self.writes.append(bytes(data))
        return len(data)

    def read(self, size, timeout_ms=0):
        if self.fail_read:
            raise self.fail_read
        return list(self.replies.pop(0)) if self.replies else []

    def close(self):
        pass


class FakeHid:
    def __init__(self, present=True, replies=()):
        self.present = present
        self.dev = FakeHidDevice(replies)

    def enumerate(self, vid=0, pid=0):
        mine = {"path": b"DevSrvsID:4294971234", "vendor_id": pr.USB_VID, "product_id": pr.USB_PID}
        other = {"path": b"DevSrvsID:4294970000", "vendor_id": 0x046D, "product_id": 0xC077}
        devs = [mine, other] if self.present else [other]
        return [d for d in devs if (vid, pid) in ((0, 0), (d["vendor_id"], d["product_id"]))]

    def device(self):
        return self.dev


def test_hidapi_writes_exact_reports_and_reads_recorded_ones():
    fake = FakeHid(replies=[pr.pad_report(vec("ident")), pr.pad_report(vec("status"))])
    t = HidapiTransport(hid_module=fake)
    assert fake.dev.opened == b"DevSrvsID:4294971234"
    link = DeviceLink(t)
    ident = link.handshake(timeout_s=0.2)
    assert fake.dev.writes[0] == b"\x00" + pr.pad_report(vec("identify"))
    assert len(fake.dev.writes[0]) == 65  # report ID 0 + 64 bytes
    assert ident["limit_code"] == 16383
    link.send_samples([100, -200, 16383])
    assert fake.dev.writes[-1][1:6] == bytes([0x01, 0x00, 0x01, 0x00, 0x03])
    assert fake.dev.writes[-1][6:12] == bytes.fromhex("640038ffff3f")
    assert link.poll() == 1 and link.stats.last_status["encoder_count"] == 0xFFFFFFF0


def test_hidapi_zero_length_packet_between_reports_is_skipped():
    reply = pr.pad_report(vec("ident"))
    fake = FakeHid(replies=[b"", reply, b"", reply])
    t = HidapiTransport(hid_module=fake)
    assert t.recv(0.2) == reply and t.recv(0.2) == reply and t.empty_reads == 2


def test_hidapi_not_found_lists_what_was_seen_and_unplug_is_device_gone():
    with pytest.raises(DeviceNotFound, match="046d:c077"):
        HidapiTransport(hid_module=FakeHid(present=False))
    fake = FakeHid()
    t = HidapiTransport(hid_module=fake)
    fake.dev.fail_read = OSError(errno.EIO, "Input/output error")
    with pytest.raises(DeviceGone, match="re-plug"):
        t.recv(0.01)


def test_version_mismatch_is_refused_with_what_to_do():
    bad = pr.encode("IDENT", protocol_version=9, sample_rate_hz=3000, dac_bits=16, max_samples=29)
    t = HidapiTransport(hid_module=FakeHid(replies=[pr.pad_report(bad)]))
    with pytest.raises(DeviceVersion, match="update the firmware"):
        DeviceLink(t).handshake(timeout_s=0.2)


# ------------------------------------------------------------------ raw USB, fake pyusb
class USBError(Exception):
    def __init__(self, code, text):
        super().__init__(text)
        self.errno = code


class FakeUsbDev:
    idVendor, idProduct, bus, address = pr.USB_VID, pr.USB_PID, 1, 7

    def __init__(self, replies=(), fail=None, driver=False, configured=True):
        self.writes: list[tuple[int, bytes]] = []
        self.replies = list(replies)
        self.fail = fail
        self.driver = driver
        self.configured = configured
        self.calls: list[str] = []

    def is_kernel_driver_active(self, i):
        return self.driver

    def detach_kernel_driver(self, i):
        self.calls.append("detach")
        self.driver = False

    def attach_kernel_driver(self, i):
        self.calls.append("attach")
        self.driver = True

    def get_active_configuration(self):
        if not self.configured:
            raise USBError(None, "Configuration not set")
        return self.config

    config = None  # {(interface, alt): [endpoints]} when a test gives one

    def set_configuration(self):
        self.calls.append("set_configuration")
        self.configured = True

    def write(self, ep, data, timeout):
        self.writes.append((ep, bytes(data)))
        return len(data)

    def read(self, ep, size, timeout):
        if self.fail:
            raise self.fail
        if not self.replies:
            raise USBError(errno.ETIMEDOUT, "Operation timed out")
        return self.replies.pop(0)


class FakeUtil:
    def __init__(self, dev, claim_error=None):
        self.dev, self.claim_error = dev, claim_error

    def claim_interface(self, dev, i):
        if self.claim_error:
            raise self.claim_error
        dev.calls.append("claim")

    def release_interface(self, dev, i):
        dev.calls.append("release")

    def dispose_resources(self, dev):
        dev.calls.append("dispose")


def fake_find(dev):
    def find(find_all=False, idVendor=None, idProduct=None, bus=None, address=None):
        if find_all:
            return [dev] if dev else []
        if dev and bus is not None and (bus, address) != (dev.bus, dev.address):
            return None
        return dev if dev and (idVendor, idProduct) == (dev.idVendor, dev.idProduct) else None
    return find


def usb(dev, tmp_path=None, claim_error=None, where=None):
    root = tmp_path or Path("/nonexistent")
    return UsbTransport(where, find=fake_find(dev), sysfs=str(root / "sys"), proc=str(root / "proc"),
                        util=FakeUtil(dev, claim_error))


def test_usb_writes_exact_packets_to_the_out_endpoint():
    dev = FakeUsbDev(replies=[pr.pad_report(vec("ident")), b""])
    t = usb(dev)
    link = DeviceLink(t)
    link.handshake(timeout_s=0.2)
    assert dev.writes[0] == (0x01, pr.pad_report(vec("identify")))
    link.start()
    assert dev.writes[-1] == (0x01, pr.pad_report(vec("start")))
    assert t.recv(0.001) is None  # a zero-length packet, then a timeout: "nothing yet", not an error
    assert t.recv(0.001) is None
    assert t.describe() == "usb:001/007"


def test_usb_endpoints_come_from_the_interface_descriptor():
    # the Linux gadget numbered its endpoints itself (0x81 IN, 0x02 OUT): 0x01 was "Invalid
    # endpoint address" on the real kernel
    from types import SimpleNamespace as Ep

    dev = FakeUsbDev()
    dev.config = {(0, 0): [Ep(bEndpointAddress=0x81, bmAttributes=3),
                           Ep(bEndpointAddress=0x02, bmAttributes=3)]}
    t = usb(dev)
    t.send(pr.encode("START"))
    assert dev.writes == [(0x02, pr.pad_report(vec("start")))] and t.ep_in == 0x81


def test_usb_claims_politely_and_gives_the_interface_back_to_usbhid():
    dev = FakeUsbDev(driver=True)
    t = usb(dev)
    assert dev.calls == ["detach", "claim"]  # configured already: not reset by set_configuration
    t.close()
    assert dev.calls == ["detach", "claim", "release", "attach", "dispose"]
    dev = FakeUsbDev(configured=False)
    usb(dev).close()
    assert dev.calls == ["set_configuration", "claim", "release", "dispose"]  # nothing to re-attach


def _usb_tree(tmp_path: Path, holder_of: str | None) -> None:
    """sysfs: device 1-1 (bus 1, address 7) with hidraw3 under its interface; /proc: pid 4242
    (hostd) holding `holder_of`."""
    d = tmp_path / "sys" / "devices" / "pci0" / "usb1" / "1-1"
    hid = d / "1-1:1.0" / "0003:1209:7470.0001" / "hidraw" / "hidraw3"
    hid.mkdir(parents=True)
    for name, value in (("idVendor", "1209"), ("idProduct", "7470"), ("busnum", "1"), ("devnum", "7")):
        (d / name).write_text(value + "\n")
    (tmp_path / "sys" / "bus" / "usb" / "devices").mkdir(parents=True)
    (tmp_path / "sys" / "bus" / "usb" / "devices" / "1-1").symlink_to(d)
    (tmp_path / "sys" / "class" / "hidraw").mkdir(parents=True)
    (tmp_path / "sys" / "class" / "hidraw" / "hidraw3").symlink_to(hid)
    if holder_of:
        p = tmp_path / "proc" / "4242"
        (p / "fd").mkdir(parents=True)
        (p / "comm").write_text("hostd\n")
        (p / "fd" / "5").symlink_to(holder_of)


def test_usb_refuses_to_detach_usbhid_under_a_process_using_the_hidraw_node(tmp_path):
    _usb_tree(tmp_path, holder_of="/dev/hidraw3")
    assert usblink.hidraw_nodes_of(1, 7, str(tmp_path / "sys")) == ["/dev/hidraw3"]
    dev = FakeUsbDev(driver=True)
    with pytest.raises(DeviceBusy) as e:
        usb(dev, tmp_path)
    msg = str(e.value)
    assert "usb:001/007 is busy" in msg and "pid 4242 (hostd) /dev/hidraw3" in msg and "\n" not in msg
    assert "detach" not in dev.calls  # the daemon's node was not pulled away


def test_usb_claimed_by_another_program_is_busy_naming_it(tmp_path):
    _usb_tree(tmp_path, holder_of="/dev/bus/usb/001/007")
    dev = FakeUsbDev()
    with pytest.raises(DeviceBusy, match=r"usb:001/007 is busy: pid 4242 \(hostd\) /dev/bus/usb/001/007 "
                       r"holds it"):
        usb(dev, tmp_path, claim_error=USBError(errno.EBUSY, "Resource busy"))
    assert "dispose" in dev.calls


def test_usb_permission_denied_names_the_node_and_the_udev_rule():
    err = USBError(errno.EACCES, "Access denied (insufficient permissions)")
    with pytest.raises(DevicePermission, match=r"/dev/bus/usb/001/007.*70-hostd\.rules"):
        usb(FakeUsbDev(), claim_error=err)
    with pytest.raises(DeviceNotFound, match="USB devices seen: none"):
        usb(None)
    with pytest.raises(DeviceNotFound, match="at usb:002/003"):
        usb(FakeUsbDev(), where="002/003")


def test_usb_wait_reads_ahead_and_watches_other_descriptors():
    dev = FakeUsbDev(replies=[pr.pad_report(vec("status"))])
    t = usb(dev)
    assert t.wait(0.01) is True and t.pending()  # the packet read while waiting is kept for recv
    assert t.recv(0.0) == pr.pad_report(vec("status")) and not t.pending()
    r, w = os.pipe()
    os.write(w, b"x")
    assert t.wait(5.0, fds=[r]) is False  # libusb has no descriptor: it reads in slices meanwhile
    os.close(r)
    os.close(w)


def test_usb_removed_mid_read_is_device_gone():
    dev = FakeUsbDev(fail=USBError(errno.ENODEV, "No such device (it may have been disconnected)"))
    t = usb(dev)
    with pytest.raises(DeviceGone, match="usb:001/007 went away"):
        t.wait(0.01)


def test_usb_enumeration_from_sysfs(tmp_path):
    _usb_tree(tmp_path, holder_of=None)
    found = usblink.enumerate_displays(sysfs=str(tmp_path / "sys"))
    assert [(d["spec"], d["node"]) for d in found] == [("usb:001/007", "/dev/bus/usb/001/007")]


# ------------------------------------------------------------------ the registry
def test_the_backends_do_not_import_the_factory():
    # the factory maps names to backends lazily; a backend importing it back would be a circle
    import ast

    root = Path(__file__).resolve().parent.parent / "hostd" / "device"
    for name in ("hidlink", "usblink", "seriallink", "simdev", "backend"):
        imported = set()
        for node in ast.walk(ast.parse((root / f"{name}.py").read_text())):
            if isinstance(node, ast.ImportFrom):
                imported.add(node.module)
                imported.update(f"{node.module}.{a.name}" for a in node.names)
            elif isinstance(node, ast.Import):
                imported.update(a.name for a in node.names)
        assert "hostd.device.transport" not in imported, name
        assert "hostd.device.backend" in imported or name == "backend", name


def test_unknown_spec_and_sim_through_the_registry():
    from hostd.errors import DeviceError

    with pytest.raises(DeviceError, match=r"use auto, hid\[:PATH\]"):
        open_transport("bogus")
    t = open_transport("sim")
    assert t.describe() == "sim"
    t.close()


def test_doctor_lists_each_display_with_its_spec_and_its_nodes_owner_group_mode(tmp_path, monkeypatch,
                                                                              capsys):
    import json

    from hostd.cli import main
    from hostd.device import transport as tr

    node = tmp_path / "hidraw3"
    node.write_text("")
    node.chmod(0o640)
    monkeypatch.setattr(tr, "find_displays", lambda: [
        {"spec": f"hid:{node}", "node": str(node), "serial": "0001"},
        {"spec": "usb:001/007", "node": str(tmp_path / "gone"), "serial": "0001"}])
    cfg = tmp_path / "c.toml"
    cfg.write_text('[device]\ntransport = "hid"\n')
    main(["doctor", "--json", "--config", str(cfg)])
    out = json.loads(capsys.readouterr().out)
    first, second = out["displays"]
    assert first["spec"] == f"hid:{node}" and first["node"] == str(node)
    import grp
    import pwd

    assert first["mode"] == "0640" and first["owner"] == pwd.getpwuid(os.getuid()).pw_name
    assert first["group"] == grp.getgrgid(os.getgid()).gr_name
    assert first["access"] is True
    assert second["spec"] == "usb:001/007" and "error" in second  # vanished between listing and stat
    assert out["hotplug"] in ("udev", "poll")
    msgs = [c["message"] for c in out["checks"] if c["section"] == "device"]
    hot = [m for m in msgs if m.startswith("hotplug: ")]
    assert hot == [f"hotplug: {hotplug.watch('hid').describe()}"] and not hot[0].endswith(": ")
    assert any(m.startswith("device.transport = 'hid': found hid:") for m in msgs), msgs


# ------------------------------------------------------------------ serial, on a real pty
def test_serial_hangup_mid_read_is_device_gone_at_once():
    from hostd.device.seriallink import SerialTransport

    master, slave = os.openpty()
    t = SerialTransport(os.ttyname(slave))
    os.close(slave)
    os.write(master, pr.frame(pr.encode("START")))
    assert t.wait(1.0) and t.recv(0.5) == pr.encode("START")
    assert t.describe().startswith("serial:/dev/pts/") and t.fileno() >= 0
    threading.Timer(0.05, os.close, [master]).start()  # the display is unplugged while we wait
    t0 = time.monotonic()
    with pytest.raises(DeviceGone, match="hostd reconnects"):
        t.recv(5.0)
    assert time.monotonic() - t0 < 2.0
    t.close()


@pytest.mark.parametrize("gather", ["compiled", "python"])
def test_serial_never_reads_an_empty_port_and_a_hung_up_one_is_gone(gather, monkeypatch):
    """drain(), recv() and gather() read only what the line discipline holds (TIOCINQ): a read()
    of a tty that holds nothing waits for the kernel's buffer work (n_tty_read ->
    tty_buffer_flush_work), which held the pump's 1 ms cycle 9-14 ms on a busy machine. The
    kernel counts the thread's read() calls (tests/readcount.py)."""
    from hostd.device import fastlink
    from hostd.device.seriallink import SerialTransport
    from tests.readcount import ReadCounter

    if gather == "python":
        monkeypatch.setattr(fastlink, "GATHER", None)
    elif fastlink.GATHER is None:
        pytest.skip("the compiled link module is not built")
    reads = ReadCounter()
    if reads() is None:
        pytest.skip("this kernel does not count a thread's read() calls (/proc/thread-self/io)")
    master, slave = os.openpty()
    t = SerialTransport(os.ttyname(slave))
    try:
        n0 = reads()
        assert t.drain() == [] and t.recv(0.0) is None and t.recv(0.02) is None  # (waits in select)
        assert t.gather((), 20, 2) == (set(), 1)
        assert reads() == n0  # nothing there: not one read
        start = pr.encode("START")
        os.write(master, pr.frame(start) * 3)
        assert t.recv(2.0) == start  # (select until the bytes are in, then one read of them)
        assert t.drain() == [start, start]  # (read already)
        assert t.drain() == [] and t.recv(0.0) is None
        assert reads() == n0 + 1
        os.write(master, pr.frame(start) * 2)
        others, runs = t.gather((), 2000, 2)  # (a wake-up per arrival, each with one read)
        assert others == set() and runs >= 1 and t.take() == [start, start]
        assert t.drain() == []
        assert reads() == n0 + 1 + runs
        os.close(master)  # unplugged: TIOCINQ answers EIO
        master = None
        with pytest.raises(DeviceGone, match="hostd reconnects"):
            t.drain()
        with pytest.raises(DeviceGone, match="hostd reconnects"):
            t.recv(0.0)
    finally:
        t.close()
        os.close(slave)
        if master is not None:
            os.close(master)
        reads.close()


def test_serial_permission_denied_names_the_port_and_the_rule(monkeypatch, tmp_path):
    import serial

    from hostd.device.seriallink import SerialTransport

    port = tmp_path / "ttyACM0"
    port.write_text("")

    def denied(*_a, **_k):
        try:
            raise PermissionError(errno.EACCES, "Permission denied")
        except PermissionError as e:
            raise serial.SerialException(errno.EACCES, f"could not open port {port}: {e}") from e

    monkeypatch.setattr(serial, "Serial", denied)
    with pytest.raises(DevicePermission, match=rf"{port} \(.*\).*70-hostd\.rules.*'hostd' group"):
        SerialTransport(str(port))


def test_a_new_transport_is_its_module_plus_one_backend_entry(monkeypatch, tmp_path):
    """One descriptor per transport: the config's grammar, hotplug's udev subsystems, auto's
    order and the opener all follow an entry added to BACKENDS, and nothing else."""
    import types

    from hostd.device import transport
    from hostd.device.transport import Backend
    from hostd.errors import ConfigError
    from hostd.service import config

    mod = types.ModuleType("hostd_test_ble")
    mod.open_ble = lambda arg: f"opened {arg}"
    mod.enumerate_displays = lambda: [{"spec": "ble:AA-BB", "node": None, "serial": "S9"}]
    monkeypatch.setitem(sys.modules, "hostd_test_ble", mod)
    entry = Backend("ble", "hostd_test_ble", "open_ble", "enumerate_displays", ("bluetooth",),
                    arg="ADDR", arg_re=r"[0-9A-F]{2}-[0-9A-F]{2}")
    backends = {**transport.BACKENDS, "ble": entry}
    monkeypatch.setattr(transport, "BACKENDS", backends)
    monkeypatch.setattr(transport, "AUTO_ORDER", (*transport.AUTO_ORDER, "ble"))
    assert transport.parse_spec("ble:AA-BB") == ("ble", "AA-BB")
    with pytest.raises(ValueError, match="must be"):
        transport.parse_spec("ble:nonsense")
    assert transport.subsystems("ble") == ("bluetooth",)
    assert "bluetooth" in transport.subsystems("auto")
    assert transport.open_transport("ble:AA-BB") == "opened AA-BB"
    assert transport.open_transport("ble", serial="S9") == "opened AA-BB"
    p = tmp_path / "h.toml"
    p.write_text('[device]\ntransport = "ble:AA-BB"\n')
    assert config.load(p).device.transport == "ble:AA-BB"
    p.write_text('[device]\ntransport = "ble:zz"\n')
    with pytest.raises(ConfigError, match=r"device.transport must be auto, hid\[:PATH\].*not 'ble:zz'"):
        config.load(p)
