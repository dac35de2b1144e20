"""Issue 32: the toolkit and the service as users meet them (completion, man page, hints, API)."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from hostd import docgen
from hostd.cli import main
from hostd.parser import build_parser

ROOT = Path(__file__).resolve().parent.parent


# ---------------------------------------------------------------- man page and completion


@pytest.mark.skipif(shutil.which("groff") is None, reason="no groff (apt-get install groff-base)")
def test_man_page_is_clean_for_groff():
    man = docgen.man_page(build_parser())
    r = subprocess.run(["groff", "-ww", "-man", "-Tutf8"], input=man, capture_output=True, text=True)
    assert r.returncode == 0 and r.stderr == "", r.stderr
    lines = man.splitlines()
    assert not [i for i, ln in enumerate(lines) if ln.strip() in (".SH", ".SS")], "an empty .SH"
    for sec in ("EXIT STATUS", "ENVIRONMENT", "FILES", "SEE ALSO", "EXAMPLES"):
        assert f".SH {sec}" in lines, sec
    import re

    text = re.sub(r".\x08", "", r.stdout)
    text = re.sub("\u2010\n\\s+", "", text).replace("\u2212", "-").replace("\u2010", "-")  # hyphenation
    assert "stream .vtx stream" in text  # hostd render's '.vtx stream' line is text, not a macro
    for needle in ("HOSTD_CONFIG", "/etc/hostd/hostd.toml", "quality.sqlite", "systemd.unit(5)", "udev(7)",
                   "/dev/hostd/by-serial"):
        assert needle in text, needle


def test_roff_escaping_keeps_requests_and_escapes_text():
    out = docgen.fix_roff(".SH\nOPTIONS\n.TP\n.vtx stream\n'quoted\n.B bold")
    assert out.splitlines() == [".SH OPTIONS", ".TP", "\\&.vtx stream", "\\&'quoted", ".B bold"]


@pytest.fixture
def files_here(tmp_path, monkeypatch):
    (tmp_path / "prof.csv").write_text("1\n")
    (tmp_path / "pq.vtx").write_bytes(b"")
    (tmp_path / "pdir").mkdir()
    monkeypatch.chdir(tmp_path)
    return tmp_path


@pytest.mark.skipif(shutil.which("bash") is None, reason="no bash")
def test_bash_completion_completes_files(files_here, capsys):
    assert main(["completion", "bash"]) == 0
    script = capsys.readouterr().out
    (files_here / "c.bash").write_text(script)
    assert "complete -o bashdefault -o default -F _shtab_hostd hostd" in script  # other args: files too

    def complete(*words):
        cw = " ".join(f"'{w}'" for w in words)
        prev = ("hostd", *words)[-2]
        r = subprocess.run(["bash", "-c", f"source c.bash; COMP_WORDS=(hostd {cw}); "
                            f"COMP_CWORD={len(words)}; _shtab_hostd hostd '{words[-1]}' '{prev}'; "
                            "printf '%s\\n' \"${COMPREPLY[@]}\""], capture_output=True, text=True,
                           cwd=files_here)
        assert r.returncode == 0, r.stderr
        return set(r.stdout.split())

    assert {"prof.csv", "pq.vtx"} <= complete("encode", "p")  # the profile
    assert {"prof.csv", "pq.vtx"} <= complete("encode", "-o", "p")  # the output
    assert "pq.vtx" in complete("iobj", "p") and "pq.vtx" in complete("send", "p")
    assert "prof.csv" in complete("corpus", "run", "-o", "p")  # -o FILE.sqlite: files, not directories only
    assert complete("encode", "--method", "") == {"shaped", "quant", "cut"}  # choices stay choices
    assert "encode" in complete("enc")


def _bash_tab(cwd: Path, script: Path, line: str) -> str:
    """What an interactive bash (readline on a pseudo-terminal, the completion script sourced)
    shows when `line` is typed and then TAB: the candidates it lists, or the completed line.
    The echo typed after the TAB ends the reading: readline handles keys in order."""
    import pty
    import select
    import signal

    pid, fd = pty.fork()
    if pid == 0:  # the child: bash on the terminal
        os.chdir(cwd)
        os.execvpe("bash", ["bash", "--norc", "--noprofile", "-i"],
                   {"PATH": os.environ["PATH"], "TERM": "dumb", "PS1": "$ ", "HOME": str(cwd),
                    "HISTFILE": "/dev/null", "INPUTRC": "/dev/null"})

    def read_until(marker: bytes) -> bytes:
        out = b""
        deadline = time.monotonic() + 60
        while marker not in out and time.monotonic() < deadline:
            if select.select([fd], [], [], 1.0)[0]:
                try:
                    chunk = os.read(fd, 4096)
                except OSError:
                    break
                out += chunk
        assert marker in out, out
        return out

    import time

    try:
        os.write(fd, b"bind 'set show-all-if-ambiguous on'; bind 'set completion-query-items 0'; "
                 b"bind 'set page-completions off'; source " + str(script).encode() + b"; echo RE''ADY\n")
        read_until(b"READY\r\n$ ")  # the prompt: readline has the terminal (keys typed before are not its)
        os.write(fd, line.encode() + b"\t\x15echo DO''NE\n")  # TAB, then erase the line and mark the end
        return read_until(b"DONE\r\n").decode(errors="replace")
    finally:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        os.close(fd)


@pytest.mark.skipif(shutil.which("bash") is None, reason="no bash")
def test_bash_completion_in_an_interactive_bash(files_here, capsys):
    """A real bash's readline: files where a command takes one, choices, commands; and -o default:
    an argument without completion of its own (--codec takes file.py:attr) still gets file names."""
    assert main(["completion", "bash"]) == 0
    script = files_here / "c.bash"
    script.write_text(capsys.readouterr().out)
    (files_here / "my_codec.py").write_text("")
    got = _bash_tab(files_here, script, "hostd encode p")
    assert "prof.csv" in got and "pq.vtx" in got and "pdir/" in got, got
    got = _bash_tab(files_here, script, "hostd corpus run --codec my")
    assert "hostd corpus run --codec my_codec.py" in got, got
    got = _bash_tab(files_here, script, "hostd encode --method ")
    assert "quant" in got and "shaped" in got and "prof.csv" not in got, got
    assert "hostd encode " in _bash_tab(files_here, script, "hostd enc")


@pytest.mark.skipif(shutil.which("fish") is None, reason="fish is not installed (apt-get install fish)")
def test_fish_completion_completes_files_and_commands(files_here, capsys):
    assert main(["completion", "fish"]) == 0
    (files_here / "hostd.fish").write_text(capsys.readouterr().out)

    def complete(line):
        r = subprocess.run(["fish", "--no-config", "-c", f"source hostd.fish; complete -C '{line}'"],
                           capture_output=True, text=True, cwd=files_here, timeout=60)
        assert r.returncode == 0, r.stderr
        return {ln.split("\t")[0] for ln in r.stdout.splitlines()}

    assert {"prof.csv", "pq.vtx", "pdir/"} <= complete("hostd encode p")
    assert {"prof.csv", "pq.vtx"} <= complete("hostd encode -o p")
    assert complete("hostd encode --method ") == {"shaped", "quant", "cut"}
    assert complete("hostd enc") == {"encode"}
    assert complete("hostd report ") == {"rate-quality"}
    assert "--target-iobj" in complete("hostd encode --tar")
    assert complete("hostd stop --da") == {"--daemon"}
    assert {"prof.csv", "pq.vtx"} <= complete("hostd corpus run -o p")  # -o FILE.sqlite: a file
    assert {"prof.csv", "pdir/"} <= complete("hostd corpus report p")  # the store
    assert "pdir/" in complete("hostd demo --out p")
    # a command of the same name deeper down (hostd bench sim) takes its own options, not hostd sim's
    assert "--plot" in complete("hostd sim --") and "--plot" not in complete("hostd bench sim --")
    assert "prof.csv" not in complete("hostd list ")  # no file where none is taken


@pytest.mark.skipif(shutil.which("zsh") is None, reason="zsh is not installed (apt-get install zsh)")
def test_zsh_completion_parses_and_offers_files(tmp_path, capsys):
    """The script parses; a real zsh (its line editor on a pseudo-terminal, tests/zsh_capture.zsh)
    completes file names where a command takes a file, commands, options and choices."""
    assert main(["completion", "zsh"]) == 0
    script = capsys.readouterr().out
    (tmp_path / "_hostd").write_text(script)
    r = subprocess.run(["zsh", "-n", str(tmp_path / "_hostd")], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    (tmp_path / "fp").mkdir()
    (tmp_path / "fp" / "_hostd").write_text(script)
    (tmp_path / "w").mkdir()
    for f in ("prof.csv", "pq.vtx"):
        (tmp_path / "w" / f).write_text("")

    def complete(line):  # a real zsh on a pseudo-terminal, completion system loaded, then TAB
        r = subprocess.run(["zsh", "-f", str(ROOT / "tests" / "zsh_capture.zsh"), line], cwd=tmp_path / "w",
                           capture_output=True, text=True, timeout=60,
                           env={**os.environ, "FPATH_EXTRA": str(tmp_path / "fp"), "TMPDIR_Z": str(tmp_path)})
        assert r.returncode == 0, r.stderr
        return {ln.strip() for ln in r.stdout.splitlines() if ln.strip()}

    assert {"prof.csv", "pq.vtx"} <= complete("hostd encode p")
    assert {"prof.csv", "pq.vtx"} <= complete("hostd encode -o p")
    assert complete("hostd enc") == {"encode"}
    assert complete("hostd completion ") == {"bash", "zsh", "fish"}
    assert complete("hostd encode --method ") == {"shaped", "quant", "cut"}
    assert "--target-iobj" in complete("hostd encode --tar")
    assert "prof.csv" not in complete("hostd list ")  # no file where none is taken
    enc = script.split("_shtab_hostd_encode_options=(", 1)[1].split("\n)", 1)[0]
    assert enc.count(":_files") >= 3 and '":profile file' in enc  # the profile, -o, --thresholds
    pos = [ln for ln in enc.splitlines() if ln.startswith('  ":profile file')]
    assert pos and pos[0].endswith(':_files"')


def test_every_path_argument_is_marked_for_completion():
    """Arguments that name files: the positional profile/stream/scores/scene/file and -o, --config,
    --thresholds, --db ...; nothing that takes a number."""
    kinds = {(" ".join(path), a.dest): docgen.path_kind(a) for path, p in docgen.walk(build_parser())
             for a in p._actions if docgen.path_kind(a)}
    marked = set(kinds)
    for want in (("encode", "profile"), ("encode", "output"), ("decode", "stream"), ("iobj", "first"),
                 ("render", "output"), ("fit", "scores"), ("send", "file"), ("run", "config"),
                 ("quality", "db"), ("sim", "scene"), ("report rate-quality", "out"),
                 ("encode", "thresholds"), ("export", "source"), ("corpus run", "sweep"),
                 ("corpus run", "parquet"), ("corpus report", "store"), ("corpus export", "store"),
                 ("experiment similarity", "design"), ("experiment calibration", "fit")):
        assert want in marked, want
    assert not [m for m in marked if m[1] in ("speed", "levels", "seconds", "length_mm")]
    # a file named by its metavar is a file, whatever its dest says (out is a directory elsewhere)
    for want in (("corpus run", "out"), ("corpus export", "out"), ("bench accuracy", "plot")):
        assert kinds[want] == "file", want
    assert kinds[("corpus report", "out")] == kinds[("demo", "out")] == "dir"


# ---------------------------------------------------------------- --help examples


def test_each_command_help_shows_the_readme_examples():
    from hostd import helptext

    readme = (ROOT / "README.md").read_text()
    assert helptext.EXAMPLES in readme  # the README's block, verbatim
    ap = build_parser()
    with_examples = {p for p, _ in helptext.examples()}
    assert {("encode",), ("render",), ("send",), ("bench", "latency"), ("demo",), ("completion",)} <= {
        p[:2] if p[0] == "bench" else p[:1] for p in with_examples}
    for path, p in docgen.walk(ap):
        if not path:
            continue
        mine = [t for q, t in helptext.examples() if q[:len(path)] == path]
        help_text = p.format_help()
        for t in mine:
            assert t in help_text, (path, t)
    enc = next(p for path, p in docgen.walk(ap) if path == ("encode",)).format_help()
    assert "examples:\n  hostd encode PROFILE -o OUT.vtx --target-iobj 0.05" in enc
    # every command and group, and hostd itself, ends its --help with examples
    missing = [" ".join(path) or "hostd" for path, p in docgen.walk(ap)
               if "\nexamples:\n" not in p.format_help()]
    assert not missing, missing
    calib = next(p for path, p in docgen.walk(ap) if path == ("experiment", "calibration")).format_help()
    assert "hostd experiment calibration -o lab.toml" in calib


def test_a_mistyped_command_gets_the_closest_one(capsys):
    with pytest.raises(SystemExit) as e:
        main(["encod"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "did you mean 'encode'?" in err and "'inspect'" not in err
    with pytest.raises(SystemExit):
        main(["encode", "x", "-o", "y", "--method", "quantt"])
    assert "did you mean 'quant'?" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["xyzzy"])
    assert "choose from 'encode'" in capsys.readouterr().err  # nothing close: the list
    # a mistyped option: the command's own error, with its closest option
    with pytest.raises(SystemExit) as e:
        main(["encode", "x", "-o", "y", "--metod", "quant"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and err == ("hostd encode: error: unrecognized arguments: --metod quant, "
                                         "did you mean '--method'? (see 'hostd encode --help')\n"), err
    with pytest.raises(SystemExit):
        main(["bench", "latency", "--jsn"])
    assert "hostd bench latency: error: unrecognized arguments: --jsn, did you mean '--json'?" in (
        capsys.readouterr().err)


# ---------------------------------------------------------------- hints that lead the right way


def test_install_refusal_names_a_command_that_works_from_the_checkout(tmp_path):
    from hostd.errors import HostdError
    from hostd.service import install

    with pytest.raises(HostdError) as e:
        install.install(build_parser(), prefix=str(tmp_path), exec_path="/home/u/venv/bin/hostd")
    msg = str(e.value)
    assert f"/opt/hostd/bin/pip install '{ROOT}[device]'" in msg, msg  # this checkout, with the extra
    assert "'hostd[device]'" not in msg


def test_pip_hint_names_the_wheel_hostd_was_installed_from(monkeypatch):
    import importlib.metadata
    import json

    from hostd import extras

    class Dist:
        def read_text(self, name):
            assert name == "direct_url.json"
            return json.dumps({"url": "file:///srv/dl/hostd-0.1.0-cp311-cp311-linux_x86_64.whl",
                               "archive_info": {}})

    monkeypatch.setattr(extras, "_is_checkout", lambda root: False)
    monkeypatch.setattr(importlib.metadata, "distribution", lambda name: Dist())
    want = "pip install '/srv/dl/hostd-0.1.0-cp311-cp311-linux_x86_64.whl[plot]'"
    assert extras.pip_install("plot") == want
    with pytest.raises(extras.MissingExtra, match=r"pip install '/srv/dl/hostd-0\.1\.0.*\.whl\[nope\]'"):
        extras.need("no_such_module_hostd", "nope", "this")

    def none(name):
        raise importlib.metadata.PackageNotFoundError(name)

    monkeypatch.setattr(importlib.metadata, "distribution", none)  # unknown: says which wheel
    assert "the wheel you installed hostd from" in extras.pip_install("device")


def test_messages_name_no_file_of_the_source_tree():
    """An installed user has no docs/ or config/: messages and --help point at the man page,
    --help, or files the package ships (its paths are computed where they are named)."""
    import ast
    import re

    # and no 'hostd[EXTRA]', a package no index has (extras.pip_install gives the command that works)
    pat = re.compile(r"\b(docs/\w|config/(hostd\.toml|thresholds|scenes|actuators))|hostd\[\w+\]")
    allowed = {"hostd/device/gen_header.py"}  # a developer's tool that says when there is no source tree
    found = []
    for f in sorted((ROOT / "hostd").rglob("*.py")):
        rel = str(f.relative_to(ROOT))
        if rel in allowed:
            continue
        tree = ast.parse(f.read_text())
        docs = {id(n.body[0].value) for n in ast.walk(tree)
                if isinstance(n, ast.Module | ast.FunctionDef | ast.ClassDef | ast.AsyncFunctionDef)
                and n.body and isinstance(n.body[0], ast.Expr) and isinstance(n.body[0].value, ast.Constant)}
        found += [f"{rel}:{n.lineno}: {n.value[:80]}" for n in ast.walk(tree)
                  if isinstance(n, ast.Constant) and isinstance(n.value, str) and id(n) not in docs
                  and pat.search(n.value)]
    assert not found, "\n".join(found)
    # the files the package ships and install-service copies (/etc/hostd/hostd.toml, the unit, the
    # udev rule ...): their comments are read by a user who has no source tree either
    wide = re.compile(r"\b(docs/\w|config/\w|tests/\w|README)|'hostd\[")
    for d in ("hostd/data", "hostd/systemd"):
        for f in sorted((ROOT / d).rglob("*")):
            if f.is_file() and f.suffix in (".toml", ".rules", ".service", ".conf"):
                found += [f"{d}/{f.relative_to(ROOT / d)}:{i}: {ln.strip()[:80]}"
                          for i, ln in enumerate(f.read_text().splitlines(), 1) if wide.search(ln)
                          and "tests/test_service_unit.py runs hostd under" not in ln]  # where it was checked
    assert not found, "\n".join(found)


def test_fit_points_at_its_help_for_the_columns(tmp_path):
    (tmp_path / "s.csv").write_text("texture,score\nwood,1\n")
    r = subprocess.run([sys.executable, "-m", "hostd", "fit", str(tmp_path / "s.csv")], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 2 and "see hostd fit --help" in r.stderr and "docs/" not in r.stderr, r.stderr


# ---------------------------------------------------------------- MATLAB .mat profiles


@pytest.fixture
def mats(tmp_path):
    import numpy as np
    import scipy.io

    x_um = np.arange(20000) * 0.5
    h_um = np.sin(x_um / 7.0) + 0.3 * np.cos(x_um / 3.1)
    scipy.io.savemat(tmp_path / "one.mat", {"h": h_um})
    scipy.io.savemat(tmp_path / "two.mat", {"x": x_um, "z": h_um, "meta": np.array([1.0, 2.0])})
    scipy.io.savemat(tmp_path / "cols.mat", {"p": np.column_stack([x_um, h_um])})
    hdr = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, HDF5 schema 1.00 .".ljust(116, b" ") + b"\0" * 8
    (tmp_path / "v73.mat").write_bytes(hdr + b"\x00\x02IM" + b"\x89HDF\r\n\x1a\n" + b"\0" * 400)
    np.savetxt(tmp_path / "ref.csv", np.column_stack([x_um, h_um]), delimiter=",")
    return tmp_path


@pytest.mark.filterwarnings("ignore:.*read its one numeric variable")  # said, tested below
def test_mat_profiles_read_like_the_same_numbers_in_csv(mats):
    import numpy as np

    from hostd import api
    from hostd.texture import formats

    assert formats.format_for("a.MAT").name == "matlab"
    ref = api.load_profile(mats / "ref.csv").heights_um
    for f, kw in (("one.mat", {"spacing": 0.5}), ("two.mat", {"var": "x,z"}), ("cols.mat", {}),
                  ("two.mat", {"var": "z", "spacing": 0.5})):
        got = api.load_profile(mats / f, **kw).heights_um
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12, err_msg=f)


def test_mat_note_says_which_variable_once_in_the_cli_and_the_api(mats, capsys):
    """The one variable taken without --var is said (once, the file named once); the API returns
    it in the profile's note and raises it as a HostdWarning. --var asked: nothing to say."""
    from hostd import api
    from hostd.errors import HostdWarning

    out = ["-o", str(mats / "o.vtx"), "--method", "quant", "--levels", "14"]
    assert main(["encode", str(mats / "one.mat"), "--spacing", "0.5", *out]) == 0
    err = capsys.readouterr().err
    assert f"{mats / 'one.mat'}: read its one numeric variable, 'h'" in err and err.count("one.mat") == 1, err
    assert main(["encode", str(mats / "two.mat"), "--var", "x,z", *out]) == 0
    assert "warning" not in capsys.readouterr().err
    with pytest.warns(HostdWarning, match=r"one\.mat: read its one numeric variable, 'h'"):
        prof = api.load_profile(mats / "one.mat", spacing=0.5)
    assert prof.note == "read its one numeric variable, 'h'"


def test_mat_errors_say_what_to_do(mats):
    from hostd import api
    from hostd.errors import ProfileError

    with pytest.raises(ProfileError, match=r"several arrays \(x 1x20000, z 1x20000, meta 1x2\): choose one "
                       r"with --var NAME"):
        api.load_profile(mats / "two.mat")
    with pytest.raises(ProfileError, match=r"no variable 'q' \(its numeric arrays: x 1x20000"):
        api.load_profile(mats / "two.mat", var="q")
    with pytest.raises(ProfileError, match=r"v7\.3 \(HDF5\) file.*save it as v7 .*'-v7'"):
        api.load_profile(mats / "v73.mat")


def test_mat_through_the_cli_and_scipy_io_only_for_mat(mats, capsys):
    def run(*a):
        return main(["encode", *(str(mats / x) if x.endswith((".mat", ".vtx")) else x for x in a)])

    assert run("two.mat", "--var", "x,z", "-o", "t.vtx", "--method", "quant", "--levels", "14") == 0
    capsys.readouterr()
    assert run("v73.mat", "-o", "t.vtx", "--method", "quant", "--levels", "14") == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "-v7" in err, err
    code = ("import sys; from hostd.cli import main; "
            "main(['encode', 'ref.csv', '-o', 'u.vtx', '--method', 'quant', '--levels', '14']); "
            "print('scipy.io.matlab' in sys.modules)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=mats, timeout=120)
    assert r.stdout.strip() == "False", r.stderr


def test_render_refuses_an_extension_it_cannot_write(tmp_path, capfdbinary):
    vtx = tmp_path / "w.vtx"
    assert main(["encode", "synthetic:wood:1", "-o", str(vtx), "--method", "quant", "--levels", "14"]) == 0
    capfdbinary.readouterr()

    def run(out):
        return main(["render", str(vtx), "-o", out, "--seconds", "0.05"])

    assert run(str(tmp_path / "out.mp3")) == 2
    err = capfdbinary.readouterr().err.decode()
    assert "writes WAV files only" in err and "out.wav" in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "out.mp3").exists()
    assert run(str(tmp_path / "out.WAV")) == 0 and (tmp_path / "out.WAV").read_bytes()[:4] == b"RIFF"
    capfdbinary.readouterr()
    assert run("-") == 0 and capfdbinary.readouterr().out[:4] == b"RIFF"


def test_decode_writes_what_the_extension_says(tmp_path, capsys):
    """hostd decode -o: heights one per line for a text name, a .npy array for .npy (both read
    back by hostd as the same profile), and a name for another format (out.wav) refused."""
    import numpy as np

    from hostd import api

    vtx = tmp_path / "w.vtx"
    assert main(["encode", "synthetic:wood:1", "-o", str(vtx), "--method", "quant", "--levels", "14"]) == 0
    want = api.decode(vtx).reconstruct()
    assert main(["decode", str(vtx), "-o", str(tmp_path / "h.npy")]) == 0
    assert main(["decode", str(vtx), "-o", str(tmp_path / "h.csv")]) == 0
    capsys.readouterr()
    np.testing.assert_array_equal(np.load(tmp_path / "h.npy"), want)
    np.testing.assert_array_equal(np.loadtxt(tmp_path / "h.csv"), want)
    assert main(["decode", str(vtx), "-o", str(tmp_path / "h.wav")]) == 2
    err = capsys.readouterr().err
    assert "not .wav: name it h.csv" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "h.wav").exists()


# ---------------------------------------------------------------- progress only on a terminal


def test_progress_bars_only_on_a_terminal():
    """The same bar: drawn (with '\\r') on a pseudo-terminal, nothing in a pipe (a log)."""
    import os
    import pty

    code = ("from hostd.tty import progress_bar\n"
            "for _ in progress_bar(True, iterable=range(5), desc='working', mininterval=0): pass\n"
            "import sys; sys.stderr.write('done\\n')")
    piped = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert piped.returncode == 0 and piped.stderr == "done\n", piped.stderr
    main_fd, sub_fd = pty.openpty()
    import fcntl
    import struct
    import termios

    fcntl.ioctl(sub_fd, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 80, 0, 0))  # a terminal 80 wide
    try:
        p = subprocess.Popen([sys.executable, "-c", code], stderr=sub_fd, stdout=subprocess.DEVNULL)
        os.close(sub_fd)
        out = b""
        while True:
            try:
                chunk = os.read(main_fd, 4096)
            except OSError:  # EIO: the child closed the terminal
                break
            if not chunk:
                break
            out += chunk
        assert p.wait(timeout=60) == 0
    finally:
        os.close(main_fd)
    assert b"working" in out and b"\r" in out, out


def test_progress_goes_through_one_helper():
    """Every bar of the package is hostd.tty.progress_bar (which checks for a terminal)."""
    users = [str(f.relative_to(ROOT)) for f in (ROOT / "hostd").rglob("*.py")
             if "tqdm(" in f.read_text() and f.name != "tty.py"]
    assert not users, users
    # a status line redrawn with '\r' is printed only where the file asks whether it is on a terminal
    import ast

    redraw = set()
    for f in (ROOT / "hostd").rglob("*.py"):
        for n in ast.walk(ast.parse(f.read_text())):
            text = n.value if isinstance(n, ast.Constant) and isinstance(n.value, str) else ""
            if "\r" in text.replace("\r\n", ""):
                redraw.add(f)
    assert (ROOT / "hostd" / "demo.py") in redraw  # the demo's status line: the scan sees it
    unguarded = [str(f.relative_to(ROOT)) for f in redraw if "on_terminal(" not in f.read_text()]
    assert not unguarded, unguarded


# ---------------------------------------------------------------- the API: exceptions, notes, warnings


def test_api_errors_are_the_builtin_exceptions_callers_catch(tmp_path):
    import numpy as np

    from hostd import api
    from hostd.errors import HostdError, ProfileError

    with pytest.raises(FileNotFoundError) as e:
        api.load_profile("/nonexistent")
    assert isinstance(e.value, ProfileError) and isinstance(e.value, HostdError)
    assert str(e.value) == "no such profile file: /nonexistent"
    with pytest.raises(FileNotFoundError):
        api.load_profile(tmp_path / "missing.npy")
    with pytest.raises(ValueError, match=r"unknown method .bogus."):
        api.encode(np.sin(np.arange(2000) / 5.0), length_mm=1.0, method="bogus")
    with pytest.raises(ValueError):
        api.decode(b"not a stream")
    np.savetxt(tmp_path / "p.csv", np.sin(np.arange(2000) / 5.0))
    with pytest.raises(ValueError, match="unknown y unit 'furlong'"):
        api.load_profile(tmp_path / "p.csv", y_unit="furlong", spacing=0.5)
    with pytest.raises(FileNotFoundError):
        api.encode(np.sin(np.arange(2000) / 5.0), length_mm=1.0, method="quant", levels=8,
                   thresholds=str(tmp_path / "none.csv"))
    # every function that takes a file: a missing one is FileNotFoundError with hostd's one line
    from hostd.errors import ConfigError, FitError, StreamError

    no_vtx = tmp_path / "none.vtx"
    for call, cls, text in ((lambda: api.decode(no_vtx), StreamError, "no such stream file"),
                            (lambda: api.score(str(no_vtx)), StreamError, "no such stream file"),
                            (lambda: api.run_scene(tmp_path / "none.toml"), ConfigError, "no such scene"),
                            (lambda: api.run_scene("no-such-scene"), ConfigError, "no such scene"),
                            (lambda: api.fit(tmp_path / "none.csv"), FitError, "no such scores file")):
        with pytest.raises(FileNotFoundError, match=text) as e:
            call()
        assert isinstance(e.value, cls) and isinstance(e.value, ValueError) and "\n" not in str(e.value)
    # a scores CSV by its path, as hostd fit reads it (Ip, Ia columns)
    ips, ias = np.linspace(0.1, 1.0, 10).tolist(), (np.linspace(0.9, 0.05, 10) ** 2).tolist()
    rows = [(p, a, 0.5 * p + 0.2 * a) for p, a in zip(ips, ias, strict=True)]
    (tmp_path / "s.csv").write_text("texture,method,level,score,Ip,Ia\n" + "".join(
        f"w,quant,{i},{sc!r},{p!r},{a!r}\n" for i, (p, a, sc) in enumerate(rows)))
    res = api.fit(tmp_path / "s.csv", n_boot=0)
    assert res["a"] == pytest.approx(0.5, abs=1e-9) and res["b"] == pytest.approx(0.2, abs=1e-9)


def test_cli_keeps_its_one_line_message_and_exit_code(tmp_path):
    r = subprocess.run([sys.executable, "-m", "hostd", "encode", str(tmp_path / "no.csv"), "-o", "x.vtx",
                        "--method", "quant"], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert r.returncode == 2 and r.stderr == f"hostd encode: error: no such profile file: {tmp_path}/no.csv\n"


def test_api_returns_and_warns_what_the_cli_notes():
    import warnings

    from hostd import api
    from hostd.errors import HostdWarning
    from hostd.texture import synth

    p = synth.wood(seed=4)  # the waveform criterion, not Iobj, sets the size (test_ratecontrol_report)
    with pytest.warns(HostdWarning, match=r"the waveform criterion \(SPQI >= 0\.9\), not Iobj, set the size"):
        res = api.encode(p.heights_um, length_mm=p.length_mm, target_iobj=0.05)
    assert res["size_set_by"] == "waveform"
    assert res["size_note"] in res["notes"]
    assert "target_iobj=" in res["size_note"] and "--target-iobj" not in res["size_note"]  # API words
    assert issubclass(HostdWarning, UserWarning)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warnings.simplefilter("ignore", HostdWarning)  # filterable on its own
        api.encode(p.heights_um, length_mm=p.length_mm, method="quant", levels=14, b0_db=-3)
    with pytest.warns(HostdWarning, match="b0_db= is ignored with method= quant"):
        res = api.encode(p.heights_um, length_mm=p.length_mm, method="quant", levels=14, b0_db=-3)
    assert any("b0_db=" in n for n in res["notes"])


# ---------------------------------------------------------------- the rate-quality PNG


def test_rate_quality_png_has_no_overlapping_texts(tmp_path, monkeypatch):
    """At its default size, every text the PNG draws (titles, tick labels, axis labels, the
    settings' labels, the legend) has a box of its own: recorded as Agg draws them (texts
    outside the view are not drawn), measured with get_window_extent. synthetic:wood:5 had
    L=6 on L=14 and L=4 on L=8 before."""
    import itertools

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.backends.backend_agg import RendererAgg

    from hostd import report
    from hostd.codec import transform
    from hostd.perception import thresholds
    from hostd.texture import synth
    from hostd.texture.load import LoadOptions, cut_patch

    drawn = []
    draw_text = RendererAgg.draw_text

    def record(self, gc, x, y, s, prop, angle, ismath=False, mtext=None):
        if mtext is not None and s.strip():
            drawn.append(mtext)
        return draw_text(self, gc, x, y, s, prop, angle, ismath, mtext)

    monkeypatch.setattr(RendererAgg, "draw_text", record)
    prof = synth.make("wood", seed=5)
    p = cut_patch(prof.heights_um, prof.spacing_um, LoadOptions(), "wood:5")
    geom = transform.Geometry(p.n, p.length_mm)
    rows = report.sweep(p.heights_um, geom, thresholds.default_curve(), with_peers=True, progress=False,
                        repeats=1)
    fig = report.figure(rows, "synthetic:wood:5", 2 * geom.n_keep, ab=(0.581, 0.464))  # what plot() saves
    fig.savefig(tmp_path / "rq.png")
    renderer = fig.canvas.get_renderer()
    boxes = [(t.get_text(), t.get_window_extent(renderer)) for t in drawn]
    assert len(boxes) > 80 and sum(t.startswith(("L=", "g=")) for t, _ in boxes) >= 8  # labels remain
    overlaps = [(a, b) for (a, ba), (b, bb) in itertools.combinations(boxes, 2) if ba.overlaps(bb)]
    assert not overlaps, overlaps
    assert all(fig.bbox.contains(b.x0, b.y0) and fig.bbox.contains(b.x1, b.y1) for _, b in boxes)
    plt.close("all")


def test_a_figure_named_for_a_format_no_backend_writes_is_refused_before_the_work(tmp_path, capsys,
                                                                                  monkeypatch):
    """bench accuracy --plot runs minutes before it saves: an extension matplotlib cannot write
    is refused first (one line, exit 2); the ones accepted are all matplotlib's own."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from hostd.plotting import IMAGE_SUFFIXES

    supported = plt.figure().canvas.get_supported_filetypes()
    plt.close("all")
    assert {s[1:] for s in IMAGE_SUFFIXES} <= set(supported), set(supported)
    from hostd.bench import accuracy

    def ran(*a, **k):
        raise AssertionError("the benchmark ran before the --plot name was checked")

    monkeypatch.setattr(accuracy, "run", ran)
    assert main(["bench", "accuracy", "--plot", str(tmp_path / "out.mp3")]) == 2
    err = capsys.readouterr().err
    assert "--plot" in err and ".mp3 is none of" in err and "out.png" in err and len(err.splitlines()) == 1
