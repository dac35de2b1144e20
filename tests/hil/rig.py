"""The HIL rig's host side: builds (once, cached) and boots the Debian guest of tests/hil.

The guest image (tests/hil/build_image.sh: bookworm, systemd, udev, the Debian kernel, a venv in
/opt/hostd holding hostd's dependencies) is cached outside the repository, in
$HOSTD_HIL_CACHE (default /var/cache/hostd-hil), under a key hashed from its recipe; the guest
boots it with -kernel/-initrd and snapshot=on (nothing it writes survives), and gets one host
directory over 9p (tag "hil"): what to run, the hostd wheel and the gadget binary built from the
tree under test, and where it writes its results.

Accelerator: KVM when /dev/kvm opens and is a hypervisor that boots a stock kernel; these
machines' /dev/kvm is PVM (/sys/module/kvm_pvm), which does not (the kernel hangs in the
decompressor or qemu aborts on MSR 0x10a), so TCG there. HOSTD_HIL_ACCEL=kvm|tcg overrides.

    python -m tests.hil.rig build            build the image (if not cached) and print its dir
    python -m tests.hil.rig serve DIR        boot with DIR shared, running DIR/queue/*.sh as they
                                             appear (interactive work; touch DIR/queue/poweroff)
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import time
import tomllib
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
RECIPE = [HERE / "build_image.sh", HERE / "guest" / "hil-boot", HERE / "guest" / "hil-run.service"]
QEMU = "qemu-system-x86_64"
TOOLS = {"qemu-system-x86_64": "qemu-system-x86", "mmdebstrap": "mmdebstrap", "mkfs.ext4": "e2fsprogs"}


def cache_root() -> Path:
    return Path(os.environ.get("HOSTD_HIL_CACHE", "/var/cache/hostd-hil"))


def requirements() -> str:
    """What the image's /opt/hostd venv holds: hostd's runtime dependencies and its [device] extra
    (pyudev included), one per line. Part of the image's key: a new dependency rebuilds it, an
    unrelated edit of pyproject.toml does not."""
    p = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    deps = list(p["dependencies"]) + list(p["optional-dependencies"].get("device", []))
    if not any(d.startswith("pyudev") for d in deps):
        deps.append("pyudev>=0.24")
    return "\n".join(deps) + "\n"


def recipe_key() -> str:
    h = hashlib.sha256()
    for p in RECIPE:
        h.update(p.name.encode() + b"\0" + p.read_bytes() + b"\0")
    h.update(requirements().encode())
    return h.hexdigest()[:16]


def image_dir() -> Path:
    return cache_root() / f"bookworm-{recipe_key()}"


def missing_tools() -> list[str]:
    """Debian packages whose commands the rig needs and this machine lacks."""
    return sorted({pkg for cmd, pkg in TOOLS.items() if shutil.which(cmd) is None
                   and not Path("/usr/sbin", cmd).exists()})


def why_not() -> str | None:
    """None when the rig can run here, else the reason (for a SKIP)."""
    if sys.platform != "linux" or os.uname().machine != "x86_64":
        return "the HIL rig needs an x86_64 Linux host"
    missing = missing_tools()
    if missing:
        pkgs = " ".join(missing)
        return f"the HIL rig needs {pkgs} (as root: apt-get install {pkgs}; ./run test does)"
    d = image_dir()
    if not (d / "rootfs.img").exists() and os.geteuid() != 0:
        return f"the HIL image is not built ({d}) and building it needs root (mmdebstrap)"
    return None


def ensure_image(log=sys.stderr) -> Path:
    d = image_dir()
    if (d / "rootfs.img").exists():
        return d
    d.parent.mkdir(parents=True, exist_ok=True)
    tmp = d.with_name(d.name + f".tmp{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    t = time.monotonic()
    req = d.parent / f"requirements-{os.getpid()}.txt"
    req.write_text(requirements())
    r = subprocess.run(["bash", str(HERE / "build_image.sh"), str(tmp), str(req)], stdout=subprocess.PIPE,
                       stderr=subprocess.STDOUT, text=True)
    req.unlink()
    if r.returncode != 0:
        shutil.rmtree(tmp, ignore_errors=True)
        raise RuntimeError(f"building the HIL image failed:\n{r.stdout[-4000:]}")
    os.replace(tmp, d)
    print(f"HIL image built in {time.monotonic() - t:.0f} s: {d}", file=log)
    return d


def accel() -> str:
    forced = os.environ.get("HOSTD_HIL_ACCEL")
    if forced in ("kvm", "tcg"):
        return forced
    if Path("/sys/module/kvm_pvm").exists():
        return "tcg"  # PVM: stock kernels do not boot on it (see the module docstring)
    try:
        fd = os.open("/dev/kvm", os.O_RDWR)
    except OSError:
        return "tcg"
    os.close(fd)
    return "kvm"


def qemu_cmd(img: Path, share: Path, accel_name: str) -> list[str]:
    cpu = ["-cpu", "host"] if accel_name == "kvm" else ["-cpu", "max"]
    return [QEMU, "-accel", accel_name, *cpu, "-smp", "2", "-m", "1024", "-nographic", "-monitor", "none",
            "-no-reboot", "-nic", "none",
            "-kernel", str(img / "vmlinuz"), "-initrd", str(img / "initrd.img"),
            "-append", "console=ttyS0 root=/dev/vda rw quiet loglevel=5 systemd.show_status=false "
                       "mitigations=off",
            "-drive", f"file={img / 'rootfs.img'},format=raw,if=virtio,snapshot=on",
            "-virtfs", f"local,path={share},mount_tag=hil,security_model=none,id=hil",
            "-serial", f"file:{share / 'console.log'}"]


KVM_PROBE_S = 60  # a kernel that boots under KVM prints its banner (loglevel 5) within seconds
NOMINAL_BOOT_S = 20.0  # host start to the share mounted: TCG on a quiet 2-core host


def boot(share: Path, timeout_s: float, mode: str = "cmd") -> dict:
    """Boots the guest with `share` as its 9p share and waits for it to power off.
    mode "cmd": the guest runs share/cmd; "serve": it runs share/queue/*.sh until queue/poweroff.
    KVM is tried when accel() offers it; a guest that aborts or prints no kernel message within
    KVM_PROBE_S is restarted under TCG (a hypervisor that cannot boot a stock kernel).
    Returns timings: boot_s (host start to the guest's share mounted), total_s."""
    img = ensure_image()
    share = share.resolve()
    if mode == "serve":
        (share / "serve").touch()
        (share / "queue").mkdir(exist_ok=True)
    else:
        (share / "serve").unlink(missing_ok=True)
    a = accel()
    while True:
        for f in ("booted", "cmd.rc", "cmd.out", "console.log"):
            (share / f).unlink(missing_ok=True)
        t0 = time.monotonic()
        proc = subprocess.Popen(qemu_cmd(img, share, a), stdin=subprocess.DEVNULL,
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        boot_s = None
        fallback = False
        try:
            while proc.poll() is None:
                el = time.monotonic() - t0
                if boot_s is None and (share / "booted").exists():
                    boot_s = el
                if a == "kvm" and el > KVM_PROBE_S and b"Linux" not in _console(share) \
                        and b"HIL-BOOTED" not in _console(share):
                    fallback = True
                    break
                # the guest scales its own deadlines by its boot (hil_suite.Pace); so does this one
                scale = max(1.0, boot_s / NOMINAL_BOOT_S) if boot_s is not None else 1.0
                if el > timeout_s * scale:
                    said = (f"it booted in {boot_s:.0f} s against {NOMINAL_BOOT_S:.0f} s nominal"
                            if boot_s is not None else "it did not boot")
                    raise TimeoutError(f"the HIL guest did not finish within {timeout_s * scale:.0f} s "
                                       f"({timeout_s:.0f} s nominal; {said}; console: "
                                       f"{share / 'console.log'})")
                time.sleep(0.2)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        out = proc.stdout.read().decode(errors="replace") if proc.stdout else ""
        if a == "kvm" and boot_s is None and (fallback or proc.returncode != 0):
            a = "tcg"  # detected, not assumed: this KVM does not boot the guest
            continue
        break
    if boot_s is None and (share / "booted").exists():
        boot_s = time.monotonic() - t0
    return {"accel": a, "boot_s": boot_s, "total_s": time.monotonic() - t0, "qemu_rc": proc.returncode,
            "qemu_out": out[-2000:]}


def _console(share: Path) -> bytes:
    try:
        return (share / "console.log").read_bytes()
    except OSError:
        return b""


def main(argv: list[str]) -> int:
    if argv[:1] == ["build"]:
        print(ensure_image())
        return 0
    if argv[:1] == ["serve"] and len(argv) == 2:
        share = Path(argv[1])
        share.mkdir(parents=True, exist_ok=True)
        print(boot(share, timeout_s=3600, mode="serve"))
        return 0
    print(__doc__, file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
