"""`hostd encode --target-iobj`: the output leads with the constraint that set the stream's size
(often SPQI >= --spqi-min, not the Iobj target), in the text, the JSON and the help."""

import json

from hostd.cli import main


def test_the_binding_constraint_leads_the_output(tmp_path, capsys):
    out = str(tmp_path / "w.vtx")
    assert main(["encode", "synthetic:wood:1", "--target-iobj", "0.05", "-o", out, "--json"]) == 0
    cap = capsys.readouterr()
    enc = json.loads(cap.out)
    assert list(enc)[:2] == ["binding", "size_set_by"], list(enc)[:4]
    assert enc["size_set_by"] == "waveform" and enc["binding"] == "SPQI >= 0.9"  # wood 1: SPQI binds
    assert enc["Iobj"] < 0.05 and enc["spqi"] >= 0.9 and "set the size" not in cap.err
    assert main(["encode", "synthetic:wood:1", "--target-iobj", "0.05", "-o", out]) == 0
    first = capsys.readouterr().err.splitlines()[0]
    assert first.startswith(f"{out}: {enc['bytes']} bytes, the smallest stream with SPQI >= 0.9: the "
                            "constraint that set its size (Iobj "), first
    # Iobj alone (--no-guard): the target binds, and says so first
    assert main(["encode", "synthetic:wood:1", "--target-iobj", "0.05", "-o", out, "--no-guard"]) == 0
    first = capsys.readouterr().err.splitlines()[0]
    assert "the smallest stream with Iobj <= 0.05: the constraint that set its size" in first, first


def test_help_says_what_the_target_promises(capsys):
    try:
        main(["encode", "--help"])
    except SystemExit:
        pass
    text = " ".join(capsys.readouterr().out.split())
    assert "leads with the one that set the size" in text and "binding, size_set_by" in text
