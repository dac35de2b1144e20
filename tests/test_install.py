"""Installation as a user gets it: the wheel built from a copy of the tree, installed in a fresh
venv, run from a directory outside the tree; the package data; `hostd install-service`."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SKIP_DIRS = {".venv", ".git", "build", "__pycache__", ".pytest_cache", ".ruff_cache", ".hypothesis", "out"}


def _copy_tree(dst: Path) -> Path:
    """The source tree as a fresh clone has it (no venv, no build products; symlinks kept)."""

    def ignore(_d, names):
        return {n for n in names if n in SKIP_DIRS or n.endswith((".egg-info", ".so", ".pyd"))}

    shutil.copytree(ROOT, dst, symlinks=True, ignore=ignore)
    return dst


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    pytest.importorskip("setuptools", minversion="77")
    src = _copy_tree(tmp_path_factory.mktemp("clone") / "hostd")
    out = tmp_path_factory.mktemp("dist")
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "-v", "--no-deps", "--no-build-isolation",
                        "--no-index", "-w", str(out), str(src)], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    # no build warnings (setuptools' deprecations, missing data, ...); pip's own note that it
    # does not byte-compile is not a warning about this project
    warnings = [ln for ln in (r.stdout + r.stderr).splitlines()
                if "warn" in ln.lower() and "byte-compil" not in ln and "Location" not in ln]
    assert not warnings, "\n".join(warnings)
    (whl,) = out.glob("hostd-*.whl")
    return whl


def test_wheel_carries_the_data_the_code_needs(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    for f in ("hostd/data/hostd.toml", "hostd/data/thresholds/default.csv",
              "hostd/data/actuators/paper-parametric.toml", "hostd/data/scenes/ideal.toml",
              "hostd/device/protocol.toml", "hostd/systemd/hostd.service", "hostd/systemd/70-hostd.rules",
              "hostd/systemd/hostd-sysusers.conf", "hostd/systemd/hostd-tmpfiles.conf"):
        assert f in names, f
    assert not [n for n in names if n.startswith("firmware/")]
    meta = zipfile.ZipFile(wheel).read(next(n for n in names if n.endswith("/METADATA"))).decode()
    import hostd

    assert f"Version: {hostd.__version__}\n" in meta  # one version number
    assert "License-Expression: MIT" in meta
    assert any(n.endswith("licenses/LICENSE") for n in names)
    # the compiled index coder (setup.py, optional): built wherever a C compiler is
    cc = (sysconfig.get_config_var("CC") or "cc").split()[0]
    if shutil.which(cc):
        assert [n for n in names if n.startswith("hostd/codec/_rangecoder.") and n.endswith(".so")], names


@pytest.fixture(scope="module")
def venv(wheel, tmp_path_factory) -> Path:
    """A fresh venv holding only the wheel; numpy & co. come from the project's environment
    (a .pth line, so no download), never hostd itself."""
    v = tmp_path_factory.mktemp("venv") / "v"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(v)], check=True)
    site = next((v / "lib").glob("python3*/site-packages"))
    import numpy

    deps = Path(numpy.__file__).resolve().parent.parent
    (site / "project-deps.pth").write_text(f"{deps}\n")
    r = subprocess.run([sys.executable, "-m", "pip", "--python", str(v / "bin" / "python"), "install",
                        "--no-deps", "--no-index", str(wheel)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    return v


def _run(venv: Path, cwd: Path, *args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "HOSTD_"))}
    env["HOSTD_CONFIG_DIR"] = str(cwd / "no-etc")  # no site override: the package's own data
    return subprocess.run([str(venv / "bin" / "hostd"), *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=timeout)


def test_wheel_works_outside_the_tree(venv, tmp_path):
    r = subprocess.run([str(venv / "bin" / "python"), "-c", "import hostd; print(hostd.__file__)"],
                       cwd=tmp_path, capture_output=True, text=True)
    assert str(venv) in r.stdout and str(ROOT) not in r.stdout, r.stdout + r.stderr
    r = subprocess.run([str(venv / "bin" / "python"), "-c", "from hostd.codec import rangecoder as r; "
                        "print(r.IMPLEMENTATION, r._C.__file__ if r._C else '')"],
                       cwd=tmp_path, capture_output=True, text=True)
    impl, *where = r.stdout.split()
    if shutil.which((sysconfig.get_config_var("CC") or "cc").split()[0]):
        assert impl == "c" and str(venv) in where[0], r.stdout + r.stderr
    r = _run(venv, tmp_path, "encode", "synthetic:wood:1", "-o", "x.vtx", "--method", "quant",
             "--levels", "14")
    assert r.returncode == 0, r.stderr
    r = _run(venv, tmp_path, "iobj", "x.vtx", "--json")
    assert r.returncode == 0 and '"Iobj"' in r.stdout, r.stderr
    r = _run(venv, tmp_path, "sim", "ideal", "--json", "--quiet")
    assert r.returncode == 0, r.stderr
    r = _run(venv, tmp_path, "demo", "--sim", "--seconds", "0.3", "--out", str(tmp_path / "demo"))
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    assert "quality log" in r.stdout and "6 rows" in r.stdout


def test_gen_header_never_writes_into_site_packages(venv, tmp_path):
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTHON")}
    r = subprocess.run([str(venv / "bin" / "python"), "-m", "hostd.device.gen_header"], cwd=tmp_path,
                       env=env, capture_output=True, text=True)
    assert r.returncode == 2 and "give the output file" in r.stderr
    assert not list(venv.rglob("hostd_proto.h"))
    r = subprocess.run([str(venv / "bin" / "python"), "-m", "hostd.device.gen_header", "h.h"], cwd=tmp_path,
                       env=env, capture_output=True, text=True)
    assert r.returncode == 0 and (tmp_path / "h.h").read_text().startswith("/* GENERATED")


def test_etc_overrides_the_shipped_data(tmp_path, monkeypatch):
    from hostd import paths
    from hostd.perception import thresholds

    monkeypatch.setenv("HOSTD_CONFIG_DIR", str(tmp_path))
    shipped = thresholds.default_curve()
    assert paths.find("thresholds", "default.csv") == paths.shipped_dir() / "thresholds" / "default.csv"
    (tmp_path / "thresholds").mkdir()
    (tmp_path / "thresholds" / "default.csv").write_text("frequency_hz,threshold_um\n10,1\n100,0.5\n1000,2\n")
    assert paths.find("thresholds", "default.csv") == tmp_path / "thresholds" / "default.csv"
    site = thresholds.default_curve()
    assert len(site.freq_hz) == 3 and len(shipped.freq_hz) != 3


def test_install_service_from_the_wheel(venv, tmp_path):
    stage = tmp_path / "root"
    # this venv is under /tmp, which the unit hides (PrivateTmp=yes): refused with the reason and the fix
    r = _run(venv, tmp_path, "install-service", "--prefix", str(stage), "--dry-run")
    assert r.returncode == 2 and "PrivateTmp=yes" in r.stderr and "203/EXEC" in r.stderr, r.stderr
    assert "/opt/hostd" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    exe = "/opt/hostd/bin/hostd"  # a package build stages the files for where hostd will be
    r = _run(venv, tmp_path, "install-service", "--prefix", str(stage), "--exec", exe, "--dry-run")
    assert r.returncode == 0 and "would install" in r.stdout, r.stderr
    assert not stage.exists()  # a dry run writes nothing
    r = _run(venv, tmp_path, "install-service", "--prefix", str(stage), "--exec", exe)
    assert r.returncode == 0, r.stderr
    unit = stage / "etc/systemd/system/hostd.service"
    for f in (unit, stage / "etc/udev/rules.d/70-hostd.rules", stage / "etc/sysusers.d/hostd.conf",
              stage / "etc/tmpfiles.d/hostd.conf", stage / "etc/hostd/hostd.toml"):
        assert f.is_file() and (f.stat().st_mode & 0o777) == 0o644, f
    assert f"ExecStart={exe} run --config /etc/hostd/hostd.toml" in unit.read_text()
    assert "systemctl daemon-reload" in r.stdout  # another prefix: the commands are printed, not run
    # an edited config is never overwritten
    (stage / "etc/hostd/hostd.toml").write_text("# mine\n")
    r = _run(venv, tmp_path, "install-service", "--prefix", str(stage), "--exec", exe)
    assert r.returncode == 0 and "kept" in r.stdout
    assert (stage / "etc/hostd/hostd.toml").read_text() == "# mine\n"
    if shutil.which("systemd-analyze"):
        # verify wants ExecStart to exist: the same unit pointed at this venv's hostd (the man page
        # of Documentation= is installed by the live install-service, not in this staging tree)
        here = tmp_path / "hostd.service"
        here.write_text(unit.read_text().replace(exe, str(venv / "bin" / "hostd")))
        v = subprocess.run(["systemd-analyze", "verify", "--man=no", str(here)], capture_output=True,
                           text=True)
        assert v.returncode == 0, v.stderr


@pytest.mark.parametrize("where, why", [
    ("/home/ann/.venv/bin/hostd", "ProtectHome=yes"), ("/root/v/bin/hostd", "ProtectHome=yes"),
    ("/run/user/1000/v/bin/hostd", "ProtectHome=yes"), ("/tmp/v/bin/hostd", "PrivateTmp=yes"),
    ("/var/tmp/v/bin/hostd", "PrivateTmp=yes"), ("/opt/pipx/venvs/hostd/bin/hostd", "pipx"),
    ("/home/ann/.local/share/pipx/venvs/hostd/bin/hostd", "pipx"),
])
def test_install_service_refuses_an_exec_the_unit_cannot_reach(where, why, tmp_path, capsys):
    from hostd.cli import main

    assert main(["install-service", "--prefix", str(tmp_path / "r"), "--exec", where]) == 2
    err = capsys.readouterr().err
    assert why in err and "/opt/hostd" in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "r").exists()
    from hostd.service.install import exec_problem

    assert exec_problem(Path("/opt/hostd/bin/hostd"), Path("/usr/bin/python3.11")) is None
    assert "its Python" in exec_problem(Path("/opt/hostd/bin/hostd"), Path("/home/a/.pyenv/bin/python3"))


def test_dry_run_says_exactly_what_the_real_run_does(tmp_path, monkeypatch, capsys):
    """--dry-run lists the commands the same call runs (and --enable adds systemctl enable --now)."""
    from hostd.service import install as inst

    monkeypatch.setattr(inst, "hostd_executable", lambda: Path("/opt/hostd/bin/hostd"))
    monkeypatch.setattr(inst.sys, "executable", "/usr/bin/python3")
    sysfs = tmp_path / "sys"  # a plugged-in display and another USB device
    for name, vid, pid in (("1-2", "1209", "7470"), ("1-3", "046d", "c52b")):
        (sysfs / name).mkdir(parents=True)
        (sysfs / name / "idVendor").write_text(vid + "\n")
        (sysfs / name / "idProduct").write_text(pid + "\n")
    monkeypatch.setattr(inst, "SYS_USB", sysfs)
    monkeypatch.setattr(inst.shutil, "which", lambda c: f"/usr/bin/{c}")
    ran: list[str] = []
    monkeypatch.setattr(inst.subprocess, "run", lambda c, **kw: ran.append(" ".join(c)) or
                        subprocess.CompletedProcess(c, 0, "", ""))
    for enable in (False, True):
        root = tmp_path / f"root{enable}"
        assert inst.install(str(root), dry_run=True, run_commands=True, enable=enable) == 0
        said = [ln.removeprefix("would run ") for ln in capsys.readouterr().out.splitlines()
                if ln.startswith("would run ")]
        assert not root.exists() and not ran
        assert inst.install(str(root), dry_run=False, run_commands=True, enable=enable) == 0
        capsys.readouterr()
        assert said == ran, (said, ran)
        assert ("systemctl enable --now hostd" in ran) == enable
        assert f"udevadm trigger --action=add --parent-match={(sysfs / '1-2').resolve()}" in ran
        assert not [c for c in ran if "1-3" in c or "--subsystem-match" in c]  # only the display
        ran.clear()
