"""The board firmware's USB descriptors (firmware/src/usb/usbd.c) against the host
transports' constants (protocol.toml via hostd.device.protocol, as hidlink.py and usblink.py
use them): VID/PID, endpoints, 64-byte reports without report IDs, 1 ms interval.

The descriptors come from the built code: the host build of usbd.c (`test_usbd --dump`), and,
when the ARM toolchain is installed, the board image itself (read from the ELF's flash)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from hostd.device import protocol as pr

FIRMWARE = Path(__file__).resolve().parent.parent / "firmware"
ELF = FIRMWARE / "build" / "stm32g4" / "hostd-fw-stm32g4.elf"
FLASH_BASE = 0x0800_0000


@pytest.fixture(scope="module")
def dumped() -> dict[str, bytes]:
    if shutil.which("make") is None or shutil.which("cc") is None:
        pytest.skip("make and a C compiler are needed to build the USB descriptors")
    r = subprocess.run(["make", "-s", "-C", str(FIRMWARE), "build/test_usbd"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    out = subprocess.run([str(FIRMWARE / "build" / "test_usbd"), "--dump"], capture_output=True, text=True,
                         check=True).stdout
    return {k: bytes.fromhex(v) for k, v in (line.split() for line in out.splitlines())}


def split_descriptors(blob: bytes) -> list[bytes]:
    out, i = [], 0
    while i < len(blob):
        n = blob[i]
        assert n >= 2 and i + n <= len(blob), f"bad descriptor length {n} at {i}"
        out.append(blob[i:i + n])
        i += n
    return out


def hid_report_sizes(desc: bytes) -> dict[str, int]:
    """Walk the HID report descriptor's short items (HID 1.11, 6.2.2.2): bytes per Input and
    Output report, and whether any Report ID item appears."""
    size = count = 0
    bits = {"input": 0, "output": 0, "feature": 0}
    report_id = False
    i = 0
    while i < len(desc):
        prefix = desc[i]
        assert prefix != 0xFE, "long items are not expected"
        n = (0, 1, 2, 4)[prefix & 3]
        val = int.from_bytes(desc[i + 1:i + 1 + n], "little")
        tag = prefix & 0xFC
        if tag == 0x74:
            size = val
        elif tag == 0x94:
            count = val
        elif tag == 0x84:
            report_id = True
        elif tag == 0x80:
            bits["input"] += size * count
        elif tag == 0x90:
            bits["output"] += size * count
        elif tag == 0xB0:
            bits["feature"] += size * count
        i += 1 + n
    assert all(b % 8 == 0 for b in bits.values())
    return {k: b // 8 for k, b in bits.items()} | {"report_id": report_id}


def test_device_descriptor_has_the_hosts_vid_pid(dumped):
    d = dumped["device"]
    assert len(d) == 18 and d[0] == 18 and d[1] == 1
    assert int.from_bytes(d[2:4], "little") == 0x0200
    assert d[7] == 64  # EP0 max packet
    assert int.from_bytes(d[8:10], "little") == pr.USB_VID
    assert int.from_bytes(d[10:12], "little") == pr.USB_PID
    major, minor, patch = pr.P["fw_version"]
    assert int.from_bytes(d[12:14], "little") == (major << 8) | (minor << 4) | patch
    assert d[16] == 3 and d[17] == 1  # a serial number string, one configuration


def test_configuration_has_the_hosts_endpoints_and_report_size(dumped):
    cfg = dumped["config"]
    descs = split_descriptors(cfg)
    assert descs[0][1] == 2 and int.from_bytes(descs[0][2:4], "little") == len(cfg)
    by_type: dict[int, list[bytes]] = {}
    for d in descs:
        by_type.setdefault(d[1], []).append(d)
    (iface,) = by_type[4]
    assert iface[4] == 2 and iface[5] == 3  # two endpoints, HID class
    (hid,) = by_type[0x21]
    assert hid[6] == 0x22 and int.from_bytes(hid[7:9], "little") == len(dumped["report"])
    eps = {d[2]: d for d in by_type[5]}
    assert set(eps) == {pr.P["usb_ep_in"], pr.P["usb_ep_out"]}
    for ep in eps.values():
        assert ep[3] & 3 == 3  # interrupt
        assert int.from_bytes(ep[4:6], "little") == pr.REPORT_SIZE
        assert ep[6] == 1  # 1 ms


def test_hid_reports_are_what_hidlink_reads_and_writes(dumped):
    sizes = hid_report_sizes(dumped["report"])
    # hidlink.py writes 0x00 + a 64-byte report (report ID 0: the device uses none) and reads
    # REPORT_SIZE bytes; usblink.py moves REPORT_SIZE-byte packets on the same endpoints
    assert sizes == {"input": pr.REPORT_SIZE, "output": pr.REPORT_SIZE, "feature": 0, "report_id": False}
    assert dumped["report"][:3] == bytes([0x06, 0x00, 0xFF])  # vendor page: no driver but hid-generic


def test_serial_number_is_the_unique_id_in_hex(dumped):
    s = dumped["serial"]
    assert s[0] == len(s) and s[1] == 3
    text = s[2:].decode("utf-16-le")
    # test_usbd's UID words 0x00390021 0x4D4B5011 0x20343634
    assert text == "003900214D4B501120343634"


def test_board_image_carries_the_same_descriptors(dumped, tmp_path):
    """The bytes in the board ELF's flash are the ones checked above."""
    nm, objcopy = shutil.which("arm-none-eabi-nm"), shutil.which("arm-none-eabi-objcopy")
    if nm is None or objcopy is None:
        pytest.skip("ARM toolchain not installed (./run test installs it as root): board image not built")
    r = subprocess.run(["make", "-s", "-C", str(FIRMWARE), "build/stm32g4/hostd-fw-stm32g4.elf"],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    syms = {}
    listing = subprocess.run([nm, "-S", str(ELF)], capture_output=True, text=True, check=True).stdout
    for line in listing.splitlines():
        parts = line.split()
        if len(parts) == 4:
            syms[parts[3]] = (int(parts[0], 16), int(parts[1], 16))
    subprocess.run([objcopy, "-O", "binary", str(ELF), str(tmp_path / "fw.bin")], check=True)
    image = (tmp_path / "fw.bin").read_bytes()
    for name, key in (("usbd_device_desc", "device"), ("usbd_config_desc", "config"),
                      ("usbd_hid_report_desc", "report")):
        addr, size = syms[name]
        assert addr >= FLASH_BASE, f"{name} is not in flash"
        assert image[addr - FLASH_BASE:addr - FLASH_BASE + size] == dumped[key], name
