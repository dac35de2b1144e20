"""One name per concept on the command line, read from the parser itself.

Every leaf command of `hostd` is walked: outputs are `-o/--output`; options carry their unit in
their name (`--ref-speed-mm-s`, `--rate-hz`, `--seconds`, `--fmax-hz`, `--g-db`, `--b0-db`); the
old spellings still work for one release, hidden, with a note on stderr; every command that
prints results takes `--json`. A new command or option that breaks a rule fails here.
"""

from __future__ import annotations

import argparse

import pytest

from hostd.parser import build_parser

# spellings retired for the unit-bearing or the one shared name; they may only be hidden aliases
RETIRED = {"--out": "--output", "--speed": None, "--rate": "--rate-hz", "--duration": "--seconds",
           "--minutes": "--seconds", "--fmax": "--fmax-hz", "--g": "--g-db", "--b0": "--b0-db"}
# commands that print no result a script would parse, each with its reason
NO_JSON = {
    "completion": "prints a shell script",
    "manpage": "prints roff",
    "run": "the daemon: logs, no result",
    "demo": "the interactive tour (its files go to -o DIR)",
    "decode": "its output is the data itself (heights, one per line, or .npy)",
    "install-service": "prints the commands it ran or would run",
    "corpus export": "writes the store to -o FILE and prints nothing",
    "fleet ship": "the shipper service: it logs what it ships (as hostd run)",
    "fleet simulate": "its results are JSON lines always",
    "experiment threshold": "a live session: the participant's URL, then its files",
    "experiment similarity": "a live session: the participant's URL, then its files",
}


def leaves(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()):
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield " ".join(path), parser
        return
    for sp in subs:
        seen = set()
        for name, child in sp.choices.items():
            if id(child) not in seen:  # an alias names the same parser
                seen.add(id(child))
                yield from leaves(child, (*path, name))


@pytest.fixture(scope="module")
def commands():
    return dict(leaves(build_parser()))


def _visible(parser):
    return [a for a in parser._actions if a.option_strings and a.help != argparse.SUPPRESS]


def test_retired_spellings_are_nowhere_visible(commands):
    bad = [f"hostd {cmd} {o}" for cmd, p in commands.items() for a in _visible(p)
           for o in a.option_strings if o in RETIRED]
    assert not bad, "retired spellings still shown: " + ", ".join(bad)


def test_every_output_option_is_dash_o_dash_dash_output(commands):
    bad = [f"hostd {cmd} {'/'.join(a.option_strings)}" for cmd, p in commands.items() for a in _visible(p)
           if ("-o" in a.option_strings or a.dest in ("out", "output"))
           and a.option_strings != ["-o", "--output"]]
    assert not bad, "outputs not spelled -o/--output: " + ", ".join(bad)


def test_every_command_that_prints_results_takes_json(commands):
    missing = [cmd for cmd, p in commands.items() if cmd not in NO_JSON
               and not any("--json" in a.option_strings for a in p._actions)]
    assert not missing, "commands without --json: " + ", ".join(missing)
    assert set(NO_JSON) <= set(commands), "NO_JSON names a command that is gone"


@pytest.mark.parametrize("old, new", [
    (["encode", "synthetic:wood", "-o", "x.vtx", "--speed", "60", "--fmax", "300", "--g", "-6"],
     ["encode", "synthetic:wood", "-o", "x.vtx", "--ref-speed-mm-s", "60", "--fmax-hz", "300",
      "--g-db", "-6"]),
    (["encode", "synthetic:wood", "-o", "x.vtx", "--method", "cut", "--b0", "-4"],
     ["encode", "synthetic:wood", "-o", "x.vtx", "--method", "cut", "--b0-db", "-4"]),
    (["render", "s.vtx", "-o", "r.wav", "--speed", "20", "--rate", "3000"],
     ["render", "s.vtx", "-o", "r.wav", "--speed-mm-s", "20", "--rate-hz", "3000"]),
    (["report", "rate-quality", "synthetic:wood", "--out", "d"],
     ["report", "rate-quality", "synthetic:wood", "--output", "d"]),
    (["corpus", "run", "synthetic:wood", "--out", "c.sqlite", "--speed", "40,60", "--g=-6,0"],
     ["corpus", "run", "synthetic:wood", "--output", "c.sqlite", "--ref-speed-mm-s", "40,60", "--g-db=-6,0"]),
    (["bench", "latency", "--duration", "3"], ["bench", "latency", "--seconds", "3"]),
    (["corpus", "export", "c.sqlite", "--out", "c.csv"], ["corpus", "export", "c.sqlite", "-o", "c.csv"]),
    (["bench", "soak", "--minutes", "2"], ["bench", "soak", "--seconds", "120"]),
])
def test_old_spellings_still_work_with_a_note(old, new, capsys, monkeypatch):
    from hostd import cliopts

    monkeypatch.setattr(cliopts, "_NOTED", set())  # the note is once per process
    parser = build_parser()
    got_new = vars(parser.parse_args(new))
    assert "deprecated" not in capsys.readouterr().err
    got_old = vars(build_parser().parse_args(old))
    err = capsys.readouterr().err
    for o in old:
        if o.split("=")[0] in RETIRED:
            assert f"{o.split('=')[0]} is deprecated: use " in err
    strip = ("func", "root_parser")
    assert {k: v for k, v in got_old.items() if k not in strip} == \
        {k: v for k, v in got_new.items() if k not in strip}


def test_a_required_output_is_still_required(capsys):
    with pytest.raises(SystemExit) as e:
        build_parser().parse_args(["corpus", "export", "c.sqlite"])
    assert e.value.code == 2
    assert "the following arguments are required: -o/--output" in capsys.readouterr().err
