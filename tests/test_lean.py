"""A lean service and a cheap command line (issue 28): what each process loads and runs.

Counts and structure, not time: the BLAS pool has one thread in `hostd run` and in the pump
it starts whatever OPENBLAS_NUM_THREADS the user's environment says; `hostd encode` does not
load what it never uses; the control pool holds one handler at rest; and the replacements that
keep scipy.signal out (the chirp-z transform, the equalizer designed in Python arithmetic) give
the same numbers. The footprint of a running daemon in device mode is asserted in test_device_mode.py;
its figures (PSS, threads, CPU, wake-ups) are `hostd bench soak --check` (DEVELOPMENT.md).
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("threadpoolctl")

ROOT = Path(__file__).resolve().parents[1]


def _env(**extra) -> dict:
    # the thread counts go (each test sets its own); the machine's BLAS kernel choice stays
    # (OPENBLAS_CORETYPE, OPENBLAS_L2_SIZE: set on some CPUs, and a child given another kernel
    # computes other last bits than its parent)
    env = {k: v for k, v in os.environ.items()
           if not (k.startswith(("OPENBLAS", "OMP", "MKL")) and k.endswith("_THREADS"))}
    env.update(PYTHONPATH=str(ROOT), **extra)
    return env


def test_hostd_run_loads_numpy_with_one_blas_thread(tmp_path):
    """`hostd run` sets the thread count before numpy loads, over a user's OPENBLAS_NUM_THREADS
    (here 8, as on an 8-core PC): the config is bad, so it stops after loading numpy."""
    (tmp_path / "bad.toml").write_text("[bogus]\n")
    code = ("import json, sys\nfrom hostd.cli import main\nrc = main(['run', '--config', sys.argv[1]])\n"
            "from threadpoolctl import threadpool_info\n"
            "print(json.dumps({'rc': rc, 'numpy': 'numpy' in sys.modules, "
            "'blas': [i['num_threads'] for i in threadpool_info() if i['user_api'] == 'blas']}))")
    out = subprocess.run([sys.executable, "-c", code, str(tmp_path / "bad.toml")], capture_output=True,
                         text=True, env=_env(OPENBLAS_NUM_THREADS="8", OMP_NUM_THREADS="8"), timeout=120)
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert r["rc"] == 2 and r["numpy"], (r, out.stderr[-500:])
    assert r["blas"] and set(r["blas"]) == {1}, r


def _probe(conn) -> None:
    import numpy  # noqa: F401  (loads OpenBLAS as the pump does)
    from threadpoolctl import threadpool_info

    conn.send([i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"])


def test_the_daemon_starts_its_pump_with_one_blas_thread(tmp_path, monkeypatch):
    """Daemon.start_pump (the pump's start, also when the daemon runs inside another process) gives
    the spawned process one BLAS thread and leaves this process's environment as it was."""
    from hostd.service.config import load
    from hostd.service.daemon import Daemon

    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "8")
    monkeypatch.setenv("OMP_NUM_THREADS", "8")
    cfg = tmp_path / "hostd.toml"
    cfg.write_text('[device]\ntransport = "sim"\n[library]\ndir = "lib"\nspool = "spool"\n'
                   '[control]\nsocket = "hostd.sock"\ngroup = ""\n[quality]\ndb = "q.sqlite"\n')
    d = Daemon(load(cfg))
    d.proc = mp.get_context("spawn").Process(target=_probe, args=(d.child_conn,), daemon=True)
    d.start_pump()
    try:
        assert d.conn.poll(60), "the probe did not answer"
        blas = d.conn.recv()
    finally:
        d.proc.join(10)
    assert blas and set(blas) == {1}, blas
    assert os.environ["OPENBLAS_NUM_THREADS"] == "8"  # (restored)


def test_hostd_encode_loads_only_what_it_uses():
    code = ("import sys\nfrom hostd.cli import main\n"
            "assert main(['encode', 'synthetic:wood:3', '-o', '/dev/null', '--target-iobj', '0.05']) == 0\n"
            "print(sorted(m for m in sys.modules if m in ('scipy.signal', 'scipy.optimize', 'scipy.linalg', "
            "'scipy.stats', 'scipy.fft', 'scipy.special', 'matplotlib', 'tqdm', 'hostd.render.pipeline', "
            "'hostd.sim.scene', "
            "'hostd.sim.chain', 'finufft')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=_env(),
                         timeout=120)
    assert out.returncode == 0, out.stderr[-800:]
    assert out.stdout.strip().splitlines()[-1] == "[]", out.stdout


def test_the_command_line_parser_does_not_load_numpy():
    code = "import sys\nimport hostd.cli\nhostd.cli.build_parser()\nprint('numpy' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=_env(),
                         timeout=60)
    assert out.stdout.strip() == "False", out.stderr[-500:]


@pytest.mark.parametrize(("n", "m", "dtheta"), [(160, 4800, 0.013), (7, 3, 1.1), (33, 1, 0.5),
                                                (1000, 2000, 0.0021)])
def test_chirp_z_is_scipy_signal_czt_bit_for_bit(n, m, dtheta):
    import scipy.signal

    from hostd.render import series

    rng = np.random.default_rng(n)
    x = rng.normal(size=n) + 1j * rng.normal(size=n)
    want = scipy.signal.CZT(n, m=m, w=np.exp(1j * dtheta), a=1.0)(x)
    assert np.array_equal(series._czt(n, m, dtheta)(x), want)


def test_device_params_designed_in_the_pump_are_the_same_numbers():
    from hostd.device import devrender
    from hostd.render.pipeline import RenderConfig

    cfg = RenderConfig()
    here = devrender.device_params(cfg)
    # in a fresh process that loads no scipy.signal, as the pump
    code = ("import pickle, sys\nfrom hostd.device import devrender\nfrom hostd.render.pipeline import "
            "RenderConfig\np = devrender.device_params(RenderConfig())\n"
            "assert 'scipy.signal' not in sys.modules\nsys.stdout.buffer.write(pickle.dumps(p))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, env=_env(), timeout=120)
    assert out.returncode == 0, out.stderr[-800:]
    import pickle

    apart = pickle.loads(out.stdout)
    assert apart.keys() == here.keys()
    for k, v in here.items():
        assert np.array_equal(np.asarray(apart[k]), np.asarray(v)), k


def test_the_control_pool_holds_one_handler_at_rest_and_grows_on_demand(tmp_path):
    import socket
    import threading

    from hostd.service.control import ControlServer

    started = threading.Event()
    release = threading.Event()

    def handle(client) -> None:
        started.set()
        release.wait(10)
        client.reply(b"{}\n")

    srv = ControlServer(tmp_path / "c.sock", "", 4, handle)
    srv.start_pool()
    acc = threading.Thread(target=srv.accept_loop, daemon=True)
    acc.start()
    try:
        assert srv.handlers == 1
        socks = []
        for _ in range(3):
            s = socket.socket(socket.AF_UNIX)
            s.connect(str(tmp_path / "c.sock"))
            s.sendall(b"{}\n")
            socks.append(s)
        assert started.wait(10)
        for _ in range(200):
            if srv.handlers >= 3:
                break
            threading.Event().wait(0.02)
        assert 3 <= srv.handlers <= 4  # one handler per client being served, within max_clients
        release.set()
        for s in socks:
            s.settimeout(10)
            assert s.recv(16)
            s.close()
    finally:
        release.set()
        srv.close()


def test_pocketfft_is_scipy_fft_bit_for_bit_and_scipy_fft_still_loads_after_it():
    """hostd.pocketfft calls scipy.fft's own routine without scipy.fft's import; in a fresh
    process: loaded first, then scipy.fft imported (it takes the same module), every transform
    the codec, SPQI, synth and the chirp-z use equals scipy.fft's."""
    code = """
import sys
import numpy as np
from hostd import pocketfft as p
assert p.IMPLEMENTATION == "pypocketfft" and "scipy.fft" not in sys.modules
import scipy.fft as f
rng = np.random.default_rng(3)
for n in (2, 7, 160, 1000, 20000, 20001):
    x = rng.normal(size=n)
    assert np.array_equal(p.dct(x, type=2), f.dct(x, type=2)), n
    y = x.copy(); z = x.copy()
    assert np.array_equal(p.dct(y, type=3, overwrite_x=True), f.dct(z, type=3, overwrite_x=True)), n
    c = x + 1j * rng.normal(size=n)
    for m in (None, n, n + 5, 2 * n + 3, max(1, n // 2)):
        assert np.array_equal(p.fft(c, m), f.fft(c, m)), (n, m)
        assert np.array_equal(p.ifft(c, m), f.ifft(c, m)), (n, m)
    for m in (2 * n - 2, 2 * n - 1, n, 4 * n):
        if m >= 1:
            assert np.array_equal(p.irfft(c, m), f.irfft(c, m)), (n, m)
    assert p.next_fast_len(n) == f.next_fast_len(n)
b = rng.normal(size=(9, 1024))
assert np.array_equal(p.dct(b, type=2, norm="ortho", axis=1), f.dct(b, type=2, norm="ortho", axis=1))
print("ok")
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=_env(),
                         timeout=120)
    assert out.stdout.strip() == "ok", out.stderr[-1500:]


def _imports(path: Path) -> set[str]:
    import ast

    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            out.add(node.module)
    return out


def test_the_service_and_the_codec_never_import_the_fleet_room():
    """The daemon never sees the central store's credentials nor loads its driver: no module of the
    service (nor codec, perception, render) imports hostd.fleet or psycopg, at any depth of the
    function bodies; and a process that loads the daemon, status and doctor has neither loaded."""
    bad = []
    for room in ("service", "codec", "perception", "render"):
        for f in sorted((ROOT / "hostd" / room).rglob("*.py")):
            bad += [f"{f.relative_to(ROOT)}: {m}" for m in _imports(f)
                    if m == "hostd.fleet" or m.startswith(("hostd.fleet.", "psycopg"))]
    assert not bad, bad
    code = ("import sys\nimport hostd.service.daemon, hostd.service.doctor, hostd.service.cli\n"
            "import hostd.service.outbox\n"
            "print(sorted(m for m in sys.modules if m.startswith(('hostd.fleet', 'psycopg'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=_env(),
                         timeout=120)
    assert out.returncode == 0, out.stderr[-500:]
    assert out.stdout.strip() == "[]", out.stdout
