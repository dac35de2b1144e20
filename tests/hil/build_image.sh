#!/usr/bin/env bash
# The HIL guest image: Debian bookworm with systemd as PID 1, udev, python3 + venv, the Debian
# kernel (dummy_hcd, libcomposite, usb_f_hid, usbhid, 9p), and /opt/hostd: a venv holding every
# runtime dependency of hostd from wheels fetched here (the guest has no network). hostd itself
# is NOT in the image: the test builds its wheel from the tree under test and the guest installs
# it into /opt/hostd, as a user would (so the image stays valid across code changes).
#
# usage: build_image.sh OUTDIR REQUIREMENTS   (writes OUTDIR/{rootfs.img,vmlinuz,initrd.img}; run as root)
# The caller (tests/hil/rig.py) keys OUTDIR by a hash of this recipe and REQUIREMENTS.
set -euo pipefail
out=$1
here=$(cd "$(dirname "$0")" && pwd)
repo=$(cd "$here/../.." && pwd)
work=$(mktemp -d "${TMPDIR:-/tmp}/hostd-hil-build.XXXXXX")
trap 'rm -rf "$work"' EXIT

# REQUIREMENTS: hostd's runtime dependencies and its [device] extra (rig.py writes it from
# pyproject.toml), as wheels for the guest's CPython 3.11 / x86_64
cp "$2" "$work/requirements.txt"
mkdir -p "$work/wheels"
# `pip wheel`: binary wheels as published, pure-Python sdists (sdnotify) built here into wheels
python3 -m pip wheel --quiet --prefer-binary --wheel-dir "$work/wheels" -r "$work/requirements.txt" pip setuptools

mmdebstrap --quiet --variant=apt --components=main \
  --include=systemd,systemd-sysv,udev,dbus,python3,python3-venv,linux-image-amd64,kmod,libusb-1.0-0,procps,usbutils,util-linux,iproute2 \
  --customize-hook='echo hostd-hil > "$1/etc/hostname"' \
  --customize-hook='passwd --root "$1" -d root' \
  --customize-hook="mkdir -p \"\$1/opt/hostd-wheels\" && cp $work/wheels/* \"\$1/opt/hostd-wheels/\"" \
  --customize-hook="cp $work/requirements.txt \"\$1/opt/hostd-wheels/requirements.txt\"" \
  --customize-hook='chroot "$1" python3 -m venv /opt/hostd' \
  --customize-hook='chroot "$1" /opt/hostd/bin/pip install --quiet --no-index --find-links /opt/hostd-wheels -r /opt/hostd-wheels/requirements.txt' \
  --customize-hook='chroot "$1" /opt/hostd/bin/pip install --quiet --no-index --find-links /opt/hostd-wheels -U pip setuptools' \
  --customize-hook="cp $here/guest/hil-run.service \"\$1/etc/systemd/system/\" && mkdir -p \"\$1/etc/systemd/system/multi-user.target.wants\" && ln -s /etc/systemd/system/hil-run.service \"\$1/etc/systemd/system/multi-user.target.wants/hil-run.service\"" \
  --customize-hook="cp $here/guest/hil-boot \"\$1/usr/local/sbin/hil-boot\" && chmod 755 \"\$1/usr/local/sbin/hil-boot\"" \
  --customize-hook='printf "9p\n9pnet_virtio\n" > "$1/etc/modules-load.d/hil.conf"' \
  --customize-hook='printf "/dev/vda / ext4 rw,noatime 0 1\n" > "$1/etc/fstab"' \
  --customize-hook='chroot "$1" systemctl mask apt-daily.timer apt-daily-upgrade.timer e2scrub_all.timer fstrim.timer systemd-timesyncd.service 2>/dev/null || true' \
  --customize-hook='chroot "$1" useradd -m -s /bin/bash alice' \
  --customize-hook="cp \"\$1\"/boot/vmlinuz-* $work/vmlinuz && cp \"\$1\"/boot/initrd.img-* $work/initrd.img" \
  --customize-hook='rm -rf "$1/var/cache/apt/archives/"*.deb "$1/var/lib/apt/lists/"*' \
  bookworm "$work/rootfs.tar" http://deb.debian.org/debian

mkdir -p "$work/root"
tar -C "$work/root" -xf "$work/rootfs.tar"
rm -f "$work/rootfs.tar"
truncate -s 3G "$work/rootfs.img"
mkfs.ext4 -q -F -L hostd-hil -d "$work/root" "$work/rootfs.img"
mkdir -p "$out"
mv "$work/rootfs.img" "$work/vmlinuz" "$work/initrd.img" "$out/"
echo "image: $out"
