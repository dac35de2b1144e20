"""MPEG-I Haptics .hjif in and out (hostd.texture.hjif) without the reference software: what hostd
writes reads back to the same samples, the loader options choose the perception and channel,
and bad files get one-line errors naming the file and the field. The reference software's own
verdict on these files is tests/test_hjif_rm.py."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest

from hostd import api
from hostd.cli import main
from hostd.codec import transform
from hostd.errors import ProfileError
from hostd.texture import hjif
from hostd.texture.load import LoadOptions, load_profile


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("hjif")
    stream = d / "wood.vtx"
    assert main(["encode", "synthetic:wood:3", "--length-mm", "5", "--method", "shaped", "--g-db", "0",
                 "-o", str(stream)]) == 0
    assert main(["export", str(stream), "-o", str(d / "wood.hjif"), "--speed-mm-s", "80"]) == 0
    assert main(["export", "synthetic:wood:3", "--length-mm", "5", "-o", str(d / "prof.hjif")]) == 0
    return d


def test_export_reads_back_to_the_same_samples(files):
    s = api.decode(files / "wood.vtx")
    tex = hjif.read_channel(files / "wood.hjif", "0")
    assert tex.spatial and tex.modality == "Vibrotactile Texture"
    assert tex.step_m * 1e6 == pytest.approx(s.spacing_um, rel=1e-12)
    # the spatial perception holds the stroke; the reader fits the series back: 1 pm
    np.testing.assert_allclose(tex.samples * tex.full_scale_um, s.reconstruct(), rtol=0, atol=1e-6)
    tim = hjif.read_channel(files / "wood.hjif", "id=1")
    assert not tim.spatial and tim.rate_hz == 8000 and tim.speed_mm_s == 80
    played = api.render_stroke(s, speed_mm_s=80, seconds=s.length_mm / 80, rate_hz=8000)["height_um"]
    np.testing.assert_allclose(tim.samples * tim.full_scale_um, played, rtol=0, atol=1e-12)
    doc = json.loads((files / "wood.hjif").read_bytes())
    prov = json.loads(doc["description"])["hostd"]
    assert prov["codec"] == "hostd vtx v2 shaped" and prov["setting"] == "g_db=0.0"
    assert prov["Iobj"] == pytest.approx(api.score(s)["Iobj"], rel=1e-5)
    assert doc["timescale"] == 48000 and doc["perceptions"][0]["unit_exponent"] == -6  # ticks of 1.67 µm
    # every description fits the 8-bit length of the binary format
    assert all(len(x.encode()) <= 255 for x in [doc["description"]]
               + [p["description"] for p in doc["perceptions"]])


def test_loader_reads_hjif_as_a_profile(files, capsys):
    prof = load_profile(files / "prof.hjif", LoadOptions(length_mm=None))
    ref = api.load_profile("synthetic:wood:3", length_mm=5)
    assert prof.spacing_um == pytest.approx(ref.spacing_um, rel=1e-12) and prof.n == ref.n
    # the profile as hostd models it: its components up to --fmax-hz at --ref-speed-mm-s (400 Hz, 50 mm/s)
    n_keep = transform.n_keep_for(5.0, 50.0, 400.0)
    modelled = transform.synthesize(transform.analyze(ref.heights_um, n_keep), ref.n)
    np.testing.assert_allclose(prof.heights_um, modelled, rtol=0, atol=1e-6)
    # `hostd iobj REF.hjif STREAM` scores as the profile it was exported from
    capsys.readouterr()
    assert main(["iobj", str(files / "prof.hjif"), str(files / "wood.vtx"), "--json"]) == 0
    via_hjif = json.loads(capsys.readouterr().out)
    assert main(["iobj", "synthetic:wood:3", str(files / "wood.vtx"), "--length-mm", "5", "--json"]) == 0
    direct = json.loads(capsys.readouterr().out)
    assert via_hjif["Iobj"] == pytest.approx(direct["Iobj"], rel=1e-9)
    # the time-domain perception: its spacing is the stated speed over the rate
    tprof = load_profile(files / "wood.hjif", LoadOptions(length_mm=None, member="1"))
    assert tprof.spacing_um == pytest.approx(80e3 / 8000)
    assert main(["encode", str(files / "wood.hjif"), "--member", "1", "--method", "shaped", "--g-db", "0",
                 "-o", str(files / "t.vtx"), "--length-mm", "5"]) == 0


def test_member_choice_and_its_messages(files, tmp_path):
    ch = hjif.read_channel(files / "wood.hjif")  # two perceptions: the one over space by default
    assert ch.perception == 0 and "--member" in ch.note
    with pytest.raises(ProfileError, match=r"wood.hjif: member: perception index 2 out of range .*"
                       r"0 \(id=0, 'Vibrotactile Texture'.*1 \(id=1, 'Vibrotactile'"):
        hjif.read_channel(files / "wood.hjif", "2")
    doc = json.loads((files / "wood.hjif").read_bytes())
    doc["perceptions"][0]["perception_modality"] = "Vibrotactile"
    (tmp_path / "two.hjif").write_text(json.dumps(doc))
    with pytest.raises(ProfileError, match=r"2 perceptions, choose one with --member"):
        hjif.read_channel(tmp_path / "two.hjif")
    doc = json.loads((files / "wood.hjif").read_bytes())
    ch2 = copy.deepcopy(doc["perceptions"][1]["channels"][0])
    ch2["id"] = 7
    doc["perceptions"][1]["channels"].append(ch2)
    (tmp_path / "chans.hjif").write_text(json.dumps(doc))
    with pytest.raises(ProfileError, match=r"perception 1 has 2 channels, .*--member 1/CHANNEL: 0 \(id=0\); "
                       r"1 \(id=7\)"):
        hjif.read_channel(tmp_path / "chans.hjif", "1")
    assert hjif.read_channel(tmp_path / "chans.hjif", "1/id=7").channel == 1


def _broken(files: Path, tmp_path: Path, change) -> Path:
    doc = json.loads((files / "wood.hjif").read_bytes())
    change(doc)
    p = tmp_path / "bad.hjif"
    p.write_text(json.dumps(doc))
    return p


def _kf(doc, p=0):
    return doc["perceptions"][p]["channels"][0]["bands"][0]["effects"][0]["keyframes"]


@pytest.mark.parametrize("change, member, field", [
    (lambda d: d["perceptions"][0].update(perception_modality="Temperature"), "0",
     r"perceptions\[0\]\.perception_modality: 'Temperature' is not a vibrotactile signal"),
    (lambda d: d["perceptions"][1].update(channels=[]), "1", r"perceptions\[1\]\.channels: empty"),
    (lambda d: _kf(d).__setitem__(5, {**_kf(d)[5], "relative_position": 1}), "0",
     r"perceptions\[0\]\.channels\[0\]\.bands\[0\]\.effects\[0\]\.keyframes\[5\]\.relative_position: "
     r"1 comes before 4: keyframes out of order"),
    (lambda d: d["perceptions"][0].update(unit_exponent=40), "0",
     r"perceptions\[0\]\.unit_exponent: 40: positions in 1e40 m are absurd"),
    (lambda d: d["perceptions"][0].update(unit_exponent=-12, description=""), "0",
     r"perceptions\[0\]\.unit_exponent: keyframes every 1 x 1e-12 m .* absurd spacing"),
    (lambda d: d["perceptions"][1]["channels"][0].update(sample_count=10**9), "1",
     r"perceptions\[1\]\.channels\[0\]\.sample_count: 1000000000 samples: absurd"),
    (lambda d: d.update(timescale=0), "1", r"timescale: 0 ticks per second is absurd"),
    (lambda d: _kf(d, 1)[3].update(amplitude_modulation="loud"), "1",
     r"keyframes\[3\]\.amplitude_modulation: must be a number"),
    (lambda d: d.pop("perceptions"), None, r"bad.hjif: perceptions: missing"),
    (lambda d: _kf(d)[2].update(relative_position=10**30), "0",
     r"keyframes\[2\]\.relative_position: 10{30} is outside the 32-bit range"),
])
def test_bad_files_name_the_file_and_the_field(files, tmp_path, change, member, field):
    p = _broken(files, tmp_path, change)
    with pytest.raises(ProfileError, match=field) as e:
        hjif.read_channel(p, member)
    assert "\n" not in str(e.value) and str(p) in str(e.value)


def test_bad_json_and_size_limit(files, tmp_path, monkeypatch, capsys):
    bad = tmp_path / "bad.hjif"
    bad.write_text('{"version": "2023", "perceptions": [')
    assert main(["encode", str(bad), "-o", str(tmp_path / "x.vtx"), "--method", "cut", "--b0-db", "0"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{bad}: not valid JSON" in err
    bad.write_text('{"timescale": NaN}')
    with pytest.raises(ProfileError, match="not valid JSON"):
        hjif.read_channel(bad)
    bad.write_text("[1, 2]")
    with pytest.raises(ProfileError, match="top level must be a JSON object"):
        hjif.read_channel(bad)
    # a file over the limit is refused from its size, before a byte is parsed
    monkeypatch.setattr(hjif, "MAX_HJIF_BYTES", 1000)
    monkeypatch.setattr(hjif.json, "loads", lambda *a, **k: pytest.fail("parsed a file over the limit"))
    with pytest.raises(ProfileError, match=r"wood.hjif: \d+ bytes, more than the 0 MiB"):
        hjif.read_channel(files / "wood.hjif")


def test_hmpg_without_the_reference_decoder_says_how(tmp_path, monkeypatch):
    monkeypatch.setenv(hjif.RM_ENV, str(tmp_path / "nothing"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setenv("PATH", str(tmp_path))
    (tmp_path / "x.hmpg").write_bytes(b"\0" * 16)
    with pytest.raises(ProfileError, match=r"x.hmpg: an .hmpg is read through the reference Decoder, which "
                       r"is not installed: build the MPEG-I Haptics reference software .*HOSTD_MPEG_RM"):
        load_profile(tmp_path / "x.hmpg", LoadOptions())


def test_export_refuses_what_it_cannot_write(files, tmp_path, capsys):
    assert main(["export", str(files / "wood.vtx"), "-o", str(tmp_path / "x.hmpg")]) == 2
    assert "reference Encoder" in capsys.readouterr().err
    assert main(["export", str(files / "wood.vtx"), "-o", str(tmp_path / "x.hjif"),
                 "--full-scale-um", "0.01"]) == 2
    assert "raise --full-scale-um" in capsys.readouterr().err
    assert main(["export", str(files / "wood.vtx"), "-o", str(tmp_path / "x.hjif"),
                 "--rate-hz", "96000"]) == 2
    assert "48000" in capsys.readouterr().err
    # a long source name is shortened to keep the description within 255 bytes
    long = {"tool": "hostd", "source": "x" * 400 + ".vtx", "codec": "none", "calibration": "c" * 300}
    text = hjif.provenance_text(long)
    assert len(text.encode()) <= 255 and json.loads(text)["hostd"]["source"].endswith("xxx.vtx")


def test_the_reader_s_notes_reach_the_user(files, tmp_path, capsys):
    capsys.readouterr()
    assert main(["encode", str(files / "wood.hjif"), "--method", "shaped", "--g-db", "0",
                 "-o", str(tmp_path / "x.vtx")]) == 0
    err = capsys.readouterr().err
    assert "wood.hjif: took perception 0 (id=0, 'Vibrotactile Texture'" in err and "--member" in err


def test_mutated_files_give_one_line_errors_or_samples(files, tmp_path):
    """Seeded mutations of a small valid file (values of every JSON type, removed keys): the reader
    either returns finite samples or raises ProfileError with one line, nothing else."""
    import random
    import warnings

    doc = json.loads((files / "wood.hjif").read_bytes())
    for p in doc["perceptions"]:
        p["channels"][0]["bands"][0]["effects"][0]["keyframes"] = _kf(doc, p["id"])[:30]
        p["channels"][0].pop("sample_count", None)
    paths: list[list] = []

    def walk(o, path):
        paths.append(path)
        items = o.items() if isinstance(o, dict) else enumerate(o[:3]) if isinstance(o, list) else ()
        for k, v in items:
            walk(v, [*path, k])

    walk(doc, [])
    values = [None, True, -1, 0, 2**40, 1e308, -1e-300, "x", [], {}, [1], {"a": 1}, 3.5, "Vibrotactile",
              "WaveletWave", "VectorialWave", "Transient", "Sine", "Square", 2**31 - 1, "full_scale_um=1-2",
              "full_scale_um=1e308 speed_mm_s=1e-300"]
    rng = random.Random(33)
    p = tmp_path / "m.hjif"
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # no overflow into inf or NaN either
        for _ in range(300):
            d = copy.deepcopy(doc)
            for _ in range(rng.randint(1, 3)):
                path = rng.choice(paths[1:])
                o = d
                try:
                    for k in path[:-1]:
                        o = o[k]
                    if rng.random() < 0.2 and isinstance(o, dict):
                        o.pop(path[-1], None)
                    else:
                        o[path[-1]] = rng.choice(values)
                except (KeyError, IndexError, TypeError):
                    pass
            p.write_text(json.dumps(d))
            for member in (None, "0", "1"):
                try:
                    ch = hjif.read_channel(p, member)
                except ProfileError as e:
                    assert "\n" not in str(e)
                else:
                    assert np.all(np.isfinite(ch.samples))


def test_wavelet_bands_decode_without_the_reference_software(tmp_path):
    """Garbage wavelet streams decode to finite samples (the decoder's work is bounded by the
    block); impossible blocks are one-line errors naming the field. The decoder's agreement with
    the reference Synthesizer is tests/test_hjif_rm.py's."""
    import random

    rng = random.Random(5)
    alphabet = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/"

    def doc(block_length=128, effects=8, stream=None):
        band = {"band_type": "WaveletWave", "block_length": block_length, "lower_frequency_limit": 0,
                "upper_frequency_limit": 8000,
                "effects": [{"effect_type": "Basis", "position": 0, "wavelet_stream":
                             stream if stream is not None
                             else "".join(rng.choice(alphabet) for _ in range(rng.randint(0, 400)))}
                            for _ in range(effects)]}
        ch = {"id": 0, "description": "", "gain": 1.0, "mixing_coefficient": 1.0, "body_part_mask": 0,
              "frequency_sampling": 8000, "sample_count": 8000, "bands": [band]}
        p = {"id": 0, "avatar_id": 0, "description": "", "perception_modality": "Other",
             "reference_devices": [], "effect_library": [], "channels": [ch]}
        return {"version": "2023", "profile": "Main", "level": 1, "date": "2026-11-26", "description": "",
                "timescale": 1000, "avatars": [], "perceptions": [p], "syncs": []}

    f = tmp_path / "w.hjif"
    for _ in range(5):
        f.write_text(json.dumps(doc()))
        ch = hjif.read_channel(f)
        assert ch.samples.size == 8000 and np.all(np.isfinite(ch.samples)) and ch.note == ""
    f.write_text(json.dumps(doc(stream="")))
    assert not np.any(hjif.read_channel(f).samples)  # an empty stream is silence
    f.write_text(json.dumps(doc(block_length=100)))  # 800 samples: not a power of two
    with pytest.raises(ProfileError, match=r"bands\[0\]\.block_length: 100 ms at 8000 Hz = 800 samples"):
        hjif.read_channel(f)
    f.write_text(json.dumps(doc(block_length=8192, effects=100, stream="")))
    with pytest.raises(ProfileError, match=r"bands\[0\]\.effects: 100 blocks of 65536 samples, more than"):
        hjif.read_channel(f)


def test_the_corpus_tool_reads_hjif(files, tmp_path, capsys):
    """`hostd corpus run` takes .hjif textures (a directory of them, --member to choose the
    perception): the same heights as the profile exported, so the same bytes and Iobj."""
    import shutil

    from hostd.corpus.store import Store

    d = tmp_path / "db"
    d.mkdir()
    shutil.copy(files / "prof.hjif", d / "prof.hjif")
    shutil.copy(files / "wood.hjif", d / "wood.hjif")
    common = ["--codec", "hostd-v2", "--methods", "shaped", "--g-db", "0", "--no-spqi", "--workers", "1",
              "--no-progress", "--length-mm", "5"]
    assert main(["corpus", "run", str(d), *common, "-o", str(tmp_path / "a.sqlite")]) == 0
    assert main(["corpus", "run", "synthetic:wood:3", *common, "-o", str(tmp_path / "b.sqlite")]) == 0
    assert main(["corpus", "run", str(d / "wood.hjif"), "--member", "1", *common,
                 "-o", str(tmp_path / "c.sqlite")]) == 0
    capsys.readouterr()

    def rows(db):
        st = Store(db)
        try:
            return {r["texture"]: r for r in st.rows()}
        finally:
            st.close()

    a, b, c = rows(tmp_path / "a.sqlite"), rows(tmp_path / "b.sqlite"), rows(tmp_path / "c.sqlite")
    assert sorted(a) == ["prof", "wood"] and all(r["error"] is None for r in a.values())
    ref = b["synthetic:wood:3"]
    for col in ("n", "bytes", "Iobj"):  # the profile exported, read back: the same job
        assert a["prof"][col] == pytest.approx(ref[col], rel=1e-9), col
    assert a["wood"]["spacing_um"] == pytest.approx(0.5)  # the texture over space by default
    (t,) = c.values()  # --member 1: the time-domain perception, 80 mm/s over 8 kHz
    assert t["error"] is None and t["spacing_um"] == pytest.approx(80e3 / 8000)


def test_iobj_scores_a_decoded_profile_against_its_reference(files, tmp_path, capsys):
    """`hostd iobj REFERENCE DECODED`: a decoded profile (another codec's output, an .hjif back from
    the reference software) scored as a stream is: the stream's decoded heights give its Iobj."""
    dec = tmp_path / "dec.txt"
    assert main(["decode", str(files / "wood.vtx"), "-o", str(dec)]) == 0
    capsys.readouterr()
    assert main(["iobj", str(files / "prof.hjif"), str(files / "wood.vtx"), "--json"]) == 0
    as_stream = json.loads(capsys.readouterr().out)
    assert main(["iobj", str(files / "prof.hjif"), str(dec), "--spacing", "0.5", "--json"]) == 0
    as_profile = json.loads(capsys.readouterr().out)
    assert as_profile["decoded"] == "profile" and as_profile["n_keep"] == 80
    for k in ("Ip", "Ia", "Iobj", "spqi"):
        assert as_profile[k] == pytest.approx(as_stream[k], rel=1e-6, abs=1e-12), k
    assert main(["iobj", str(files / "prof.hjif"), str(files / "prof.hjif"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["Iobj"] == 0
    # another grid is refused, naming both files
    assert main(["iobj", str(files / "prof.hjif"), str(dec), "--spacing", "0.25"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "dec.txt" in err and "prof.hjif" in err and "same options" in err


def test_provenance_names_the_calibration(files, tmp_path):
    """--calibration FILE: the description carries NAME@ID (as the quality log records it);
    without it, null (hostd's streams and profiles carry no display calibration)."""
    from hostd.perception import calibration, thresholds

    curve = thresholds.ThresholdCurve(np.array([40.0, 100.0, 250.0, 400.0]), np.array([2.0, 0.5, 0.2, 0.3]))
    cal = calibration.Calibration(curve, 0.9, 0.2, "lab-a", {"thresholds": "test", "weights": "test"})
    calibration.write(tmp_path / "lab-a.toml", cal)
    out = tmp_path / "c.hjif"
    assert main(["export", str(files / "wood.vtx"), "-o", str(out), "--calibration",
                 str(tmp_path / "lab-a.toml")]) == 0
    prov = json.loads(json.loads(out.read_bytes())["description"])["hostd"]
    assert prov["calibration"] == f"lab-a@{cal.cal_id}" and prov["source"] == "wood.vtx"
    base = json.loads(json.loads((files / "wood.hjif").read_bytes())["description"])["hostd"]
    assert base["calibration"] is None


def test_an_hmpg_over_the_limit_is_refused_before_decoding(tmp_path, monkeypatch):
    big = tmp_path / "big.hmpg"
    big.write_bytes(b"\0" * 2000)
    monkeypatch.setattr(hjif, "MAX_HMPG_BYTES", 1000)
    monkeypatch.setattr(hjif, "run_rm", lambda *a, **k: pytest.fail("ran the Decoder on a file over "
                                                                     "the limit"))
    with pytest.raises(ProfileError, match=r"big.hmpg: 2000 bytes, more than the 0 MiB an .hmpg may have .*"
                       r"refused before decoding"):
        load_profile(big, LoadOptions())


def _bomb(tmp_path: Path, sample_count: int, last: int, spatial: bool = False) -> Path:
    """A 3-kB .hjif whose declared sizes (eight Curve bands reaching `last`, a sample_count) ask
    for far more memory than its bytes."""
    kfs = [{"relative_position": 0, "amplitude_modulation": 0.5},
           {"relative_position": 1, "amplitude_modulation": 0.1},
           {"relative_position": last, "amplitude_modulation": 0.2}]
    band = {"band_type": "Curve", "curve_type": "Cubic", "lower_frequency_limit": 0,
            "upper_frequency_limit": 100,
            "effects": [{"effect_type": "Basis", "position": 0, "keyframes": kfs}]}
    ch = {"id": 0, "description": "", "gain": 1.0, "mixing_coefficient": 1.0, "body_part_mask": 0,
          "bands": [band] * 8}
    if not spatial:
        ch.update(frequency_sampling=8000, sample_count=sample_count)
    p = {"id": 0, "avatar_id": 0, "description": "", "unit_exponent": -6,
         "perception_modality": "Vibrotactile Texture" if spatial else "Vibrotactile",
         "reference_devices": [], "effect_library": [], "channels": [ch]}
    doc = {"version": "2023", "profile": "Main", "level": 1, "date": "2026-11-26", "description": "",
           "timescale": 8000, "avatars": [], "perceptions": [p], "syncs": []}
    f = tmp_path / f"bomb{sample_count}{'s' if spatial else ''}.hjif"
    f.write_text(json.dumps(doc))
    return f


_PEAK = """
import resource, sys
from pathlib import Path
from hostd.texture import hjif
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
try:
    n = hjif.read_channel(Path(sys.argv[1])).samples.nbytes
except Exception as e:
    n = -1
    print(type(e).__name__, str(e).replace(chr(10), ' '))
print((resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base) * 1024, n)
"""


@pytest.mark.parametrize("spatial", [False, True], ids=["time", "space"])
def test_declared_sizes_take_bounded_memory(tmp_path, spatial):
    """A crafted file of 3 kB takes at most a few times the samples it yields (peak RSS of a fresh
    process, over its RSS before reading), and declared sizes past the limit are refused in one
    line before anything is allocated (at 2de9ff1's limit of 2*10^7 samples the same file took
    2.8 GB)."""
    import subprocess
    import sys

    def peak(f: Path) -> tuple[int, int, str]:
        r = subprocess.run([sys.executable, "-c", _PEAK, str(f)], capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stderr
        *msg, last = r.stdout.strip().splitlines()
        grew, n = (int(x) for x in last.split())
        return grew, n, " ".join(msg)

    n = hjif.MAX_SAMPLES
    f = _bomb(tmp_path, n, n - 1, spatial)
    assert f.stat().st_size < 4000
    grew, nbytes, msg = peak(f)
    assert nbytes == 8 * n, msg
    print(f"{f.stat().st_size} B -> {nbytes >> 20} MiB of samples: peak grew {grew / 2**20:.0f} MiB")
    assert grew <= 4 * nbytes + (32 << 20)
    over = _bomb(tmp_path, 20_000_000, 19_999_999, spatial)
    grew, nbytes, msg = peak(over)
    assert nbytes == -1 and "ProfileError" in msg and "4194304" in msg and str(over) in msg
    assert grew < 16 << 20


def test_wavelet_bands_missing_fields_are_one_line(tmp_path):
    """What the reference software skips or cannot decode (no upper_frequency_limit, a block of
    fewer than 16 samples) is a one-line error naming the field, not a KeyError or IndexError."""
    band = {"band_type": "WaveletWave", "block_length": 1, "lower_frequency_limit": 0,
            "upper_frequency_limit": 8000,
            "effects": [{"effect_type": "Basis", "position": 0, "wavelet_stream": "QUJDRA"}]}
    ch = {"id": 0, "description": "", "gain": 1.0, "mixing_coefficient": 1.0, "body_part_mask": 0,
          "frequency_sampling": 8000, "sample_count": 800, "bands": [band]}
    p = {"id": 0, "avatar_id": 0, "description": "", "perception_modality": "Other",
         "reference_devices": [], "effect_library": [], "channels": [ch]}
    doc = {"version": "2023", "profile": "Main", "level": 1, "date": "2026-11-26", "description": "",
           "timescale": 1000, "avatars": [], "perceptions": [p], "syncs": []}
    f = tmp_path / "w.hjif"
    f.write_text(json.dumps(doc))
    with pytest.raises(ProfileError, match=r"w.hjif: .*bands\[0\]\.block_length: 1 ms at 8000 Hz = 8 "):
        hjif.read_channel(f)
    band["block_length"] = 16
    del band["upper_frequency_limit"]
    f.write_text(json.dumps(doc))
    with pytest.raises(ProfileError, match=r"w.hjif: .*bands\[0\]\.upper_frequency_limit: missing"):
        hjif.read_channel(f)


def _fake_rm(d: Path) -> Path:
    """Encoder, Decoder and Synthesizer that report what they may do (the sandbox's view)."""
    import sys

    probe = f"""#!{sys.executable}
import json, os, resource, socket, sys
lim = resource.getrlimit
out = {{"env": sorted(os.environ), "cwd": os.getcwd(), "as": lim(resource.RLIMIT_AS)[0],
       "cpu": lim(resource.RLIMIT_CPU)[0], "fsize": lim(resource.RLIMIT_FSIZE)[0],
       "ifaces": [l.split(":")[0].strip() for l in open("/proc/net/dev").read().splitlines()[2:]]}}
try:
    socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    out["socket"] = "allowed"
except OSError as e:
    out["socket"] = e.errno
try:
    open(sys.argv[2], "ab").write(b"x")
    out["write_input"] = "allowed"
except OSError as e:
    out["write_input"] = e.errno
print(json.dumps(out))
if "crash" in sys.argv:
    os.kill(os.getpid(), 11)
if "sleep" in sys.argv:
    import time
    time.sleep(30)
if "-o" in sys.argv:
    open(sys.argv[sys.argv.index("-o") + 1], "w").write("{{not json")
"""
    d.mkdir()
    for t in hjif.RM_TOOLS:
        (d / t).write_text(probe)
        (d / t).chmod(0o755)
    return d


def test_the_reference_tools_run_only_when_asked_and_sandboxed(tmp_path, monkeypatch):
    """No reference tool runs on a file's content without HOSTD_RUN_MPEG_RM=1; with it, the tool
    sees no network, no socket call, its limits, a private folder, a read-only copy of its input
    and an environment of four variables; its crash is one line naming the user's file."""
    import errno

    fake = _fake_rm(tmp_path / "rm")
    monkeypatch.setenv(hjif.RM_ENV, str(fake))
    monkeypatch.delenv(hjif.RM_OPT_IN_ENV, raising=False)
    user = tmp_path / "clip.hmpg"
    user.write_bytes(b"\x01" * 64)
    with pytest.raises(ProfileError, match=r"clip.hmpg: an .hmpg is a binary stream only the reference "
                       r"software evaluates, .* set HOSTD_RUN_MPEG_RM=1 to run it \(sandboxed") as e:
        load_profile(user, LoadOptions(spacing=6.25))
    assert "\n" not in str(e.value)
    # a band only the reference Synthesizer plays: refused in one line, the band's kind named
    doc = {"version": "2023", "profile": "Main", "level": 1, "date": "2026-11-26", "description": "",
           "timescale": 1000, "avatars": [], "syncs": [], "perceptions": [
               {"id": 0, "avatar_id": 0, "description": "", "perception_modality": "Vibrotactile",
                "reference_devices": [], "effect_library": [], "channels": [
                    {"id": 0, "description": "", "gain": 1.0, "mixing_coefficient": 1.0, "body_part_mask": 0,
                     "bands": [{"band_type": "Curve", "curve_type": "Akima", "lower_frequency_limit": 0,
                                "upper_frequency_limit": 1000, "effects": [
                                    {"effect_type": "Basis", "position": 0, "keyframes": [
                                        {"relative_position": 0, "amplitude_modulation": 0.1},
                                        {"relative_position": 5, "amplitude_modulation": 0.3},
                                        {"relative_position": 10, "amplitude_modulation": 0.5}]}]}]}]}]}
    (tmp_path / "t.hjif").write_text(json.dumps(doc))
    with pytest.raises(ProfileError, match=r"t.hjif: its Curve \(Akima\) band\(s\) are what only the "
                       r"reference software evaluates.*HOSTD_RUN_MPEG_RM=1"):
        hjif.read_channel(tmp_path / "t.hjif")

    monkeypatch.setenv(hjif.RM_OPT_IN_ENV, "1")
    import tempfile

    with tempfile.TemporaryDirectory() as t:
        copy = hjif._private_copy(user, Path(t), "input.hmpg", 1 << 20)
        seen = json.loads(hjif.run_rm("Decoder", "-f", copy.name, cwd=Path(t), read_only=copy))
        assert copy.read_bytes() == user.read_bytes()
    assert seen["cwd"] == t and seen["env"] == ["HOME", "LANG", "PATH", "TMPDIR"]
    limits = (hjif.RM_MEMORY_BYTES, hjif.RM_CPU_S, hjif.RM_FILE_BYTES)
    assert (seen["as"], seen["cpu"], seen["fsize"]) == limits
    assert seen["ifaces"] == ["lo"]  # a network namespace of its own
    assert seen["socket"] == errno.EPERM  # the seccomp filter
    assert seen["write_input"] in (errno.EROFS, errno.EACCES)  # read-only, even to root
    # a crash (SIGSEGV) is one line naming the user's file and the signal
    with tempfile.TemporaryDirectory() as t:
        copy = hjif._private_copy(user, Path(t), "input.hmpg", 1 << 20)
        with pytest.raises(ProfileError, match=r"clip.hmpg: the reference Decoder failed .killed by SIGSEGV"):
            hjif.run_rm("Decoder", "-f", copy.name, "crash", cwd=Path(t), source=user, read_only=copy)
        # a tool past its time is stopped; the message names the user's file
        monkeypatch.setattr(hjif, "RM_TIMEOUT_S", 1.0)
        with pytest.raises(ProfileError, match=r"clip.hmpg: the reference Decoder did not finish within 1 s"):
            hjif.run_rm("Decoder", "-f", copy.name, "sleep", cwd=Path(t), source=user, read_only=copy)
    # what the Decoder wrote is judged under the user's file's name, not the temporary one's
    with pytest.raises(ProfileError, match=r"clip.hmpg: not valid JSON") as e:
        hjif.read_channel(user)
    assert "decoded" not in str(e.value) and "hostd-rm-" not in str(e.value)


def test_errors_stay_short_on_a_file_of_50000_perceptions(tmp_path, capsys):
    """A message lists at most a few choices: 50,000 perceptions made a 2.2-MB 'one line'."""
    p = {"id": 0, "avatar_id": 0, "description": "x" * 200, "perception_modality": "Vibrotactile",
         "reference_devices": [], "effect_library": [], "channels": [{"id": 0}, {"id": 1}]}
    doc = {"version": "2023", "profile": "Main", "level": 1, "date": "2026-11-26", "description": "",
           "timescale": 1000, "avatars": [], "perceptions": [p] * 50_000, "syncs": []}
    f = tmp_path / "many.hjif"
    f.write_text(json.dumps(doc))
    assert main(["encode", str(f), "-o", str(tmp_path / "x.vtx"), "--method", "cut", "--b0-db", "0"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "50000 perceptions" in err and "and 49992 more" in err
    assert len(err) < 1000
    with pytest.raises(ProfileError, match=r"perception 7 has 2 channels") as e:
        hjif.read_channel(f, "7")
    assert len(str(e.value)) < 1000


def test_an_instrument_profile_round_trip_can_be_scored(tmp_path, capsys):
    """`hostd export dektak-1.csv -o d.hjif; hostd iobj dektak-1.csv d.hjif`: the spatial
    perception holds one stroke at 50 mm/s (ticks of 1.04 µm, not the profile's 0.156245 µm);
    the description states the profile's spacing, N and the series' terms, so hostd's reader
    fits the series back on the profile's grid and the round trip is scored: Iobj ~ 0."""
    dektak = Path(__file__).resolve().parent.parent / "config" / "profiles" / "dektak-1.csv"
    out = tmp_path / "d.hjif"
    assert main(["export", str(dektak), "-o", str(out)]) == 0
    doc = json.loads(out.read_bytes())
    assert doc["timescale"] == 48000 and doc["perceptions"][0]["unit_exponent"] == -6
    capsys.readouterr()
    assert main(["iobj", str(dektak), str(out), "--json"]) == 0
    iobj = json.loads(capsys.readouterr().out)["Iobj"]
    print(f"Iobj of dektak-1 against its round trip through .hjif: {iobj:.3g}")
    assert abs(iobj) <= 1e-9
    ref = load_profile(dektak, LoadOptions())
    back = load_profile(out, LoadOptions())
    assert back.spacing_um == pytest.approx(ref.spacing_um, rel=1e-12) and back.n == ref.n
    n_keep = transform.n_keep_for(ref.length_mm, 50.0, 400.0)
    modelled = transform.synthesize(transform.analyze(ref.heights_um, n_keep), ref.n)
    np.testing.assert_allclose(back.heights_um, modelled, rtol=0, atol=1e-6)


def test_a_file_written_by_the_previous_release_still_reads_back_exactly(capsys):
    """A file the previous exporter wrote (a keyframe per sample, positions in 0.1-µm units, the
    spacing stated in the description; tests/data/hjif-previous) is still hostd's own: read at
    its stated spacing, every sample as written, and scored against its source at Iobj 0."""
    here = Path(__file__).resolve().parent / "data" / "hjif-previous"
    ref = load_profile(here / "profile.csv", LoadOptions())
    back = load_profile(here / "profile.hjif", LoadOptions())
    assert back.n == ref.n == 400 and back.spacing_um == pytest.approx(0.156245, rel=1e-12)
    # written as height / full scale in float32-exact decimals: the samples, to the file's digits
    centred = [p.heights_um - p.heights_um.mean() for p in (back, ref)]
    np.testing.assert_allclose(*centred, rtol=0, atol=1e-4)
    capsys.readouterr()
    assert main(["iobj", str(here / "profile.csv"), str(here / "profile.hjif"), "--json"]) == 0
    assert abs(json.loads(capsys.readouterr().out)["Iobj"]) <= 1e-9


def test_an_opdx_in_the_wrong_unit_is_refused_in_one_line(tmp_path, capsys):
    """A profile whose patch holds no component below fmax (read in metres as µm) says what to
    check, not "N' must be in 1..N-1, got 0"."""
    f = tmp_path / "tiny.txt"
    np.savetxt(f, np.column_stack([np.arange(3001) * 1.6655563e-08, np.sin(np.arange(3001) / 50.0)]))
    assert main(["export", str(f), "-o", str(tmp_path / "t.hjif"), "--length-mm", "1"]) == 2
    err = capsys.readouterr().err
    assert "nothing to play" in err and "--x-unit" in err and "N'" not in err


def test_vectorial_bands_bound_their_work(tmp_path):
    """Effects that all span the whole signal would cost effects x samples: past
    hjif_vectorial.MAX_WORK samples, one line, before evaluating."""
    import time

    from hostd.texture import hjif_vectorial

    eff = {"effect_type": "Basis", "position": 0, "base_signal": "Sine", "keyframes": [
        {"relative_position": 0, "amplitude_modulation": 0.5, "frequency_modulation": 90},
        {"relative_position": 50_000, "amplitude_modulation": 0.5, "frequency_modulation": 250}]}
    band = {"band_type": "VectorialWave", "lower_frequency_limit": 0, "upper_frequency_limit": 1000,
            "effects": [eff] * 400}
    ch = {"id": 0, "description": "", "gain": 1.0, "mixing_coefficient": 1.0, "body_part_mask": 0,
          "bands": [band]}
    p = {"id": 0, "avatar_id": 0, "description": "", "perception_modality": "Vibrotactile",
         "reference_devices": [], "effect_library": [], "channels": [ch]}
    doc = {"version": "2023", "profile": "Main", "level": 1, "date": "2026-11-26", "description": "",
           "timescale": 1000, "avatars": [], "perceptions": [p], "syncs": []}
    f = tmp_path / "v.hjif"
    f.write_text(json.dumps(doc))
    t0 = time.process_time()
    with pytest.raises(ProfileError, match=r"v.hjif: .*bands\[0\]: its effects span \d+ samples in all, more "
                       r"than the \d+ hostd evaluates"):
        hjif.read_channel(f)
    assert time.process_time() - t0 < 5
    band["effects"] = [eff]  # one: 50 s at 8 kHz, evaluated
    f.write_text(json.dumps(doc))
    y = hjif.read_channel(f).samples
    assert y.size == 400_000 and np.max(np.abs(y)) == pytest.approx(0.5, abs=1e-3)
    assert hjif_vectorial.covers(band)


def test_mutated_vectorial_and_transient_bands_give_one_line_errors_or_samples(tmp_path):
    """hostd's port of the RM's Vectorial and Transient evaluation on seeded mutations of such a
    band (the shape the reference Encoder writes for AHAP): finite samples or one line."""
    import random
    import warnings

    vec = {"band_type": "VectorialWave", "lower_frequency_limit": 0, "upper_frequency_limit": 300,
           "effects": [{"effect_type": "Basis", "position": 100, "phase": 0.0, "base_signal": "Sine",
                        "keyframes": [{"relative_position": 0, "amplitude_modulation": 0.07,
                                       "frequency_modulation": 90},
                                      {"relative_position": 150, "amplitude_modulation": 0.37},
                                      {"relative_position": 300, "amplitude_modulation": 0.15,
                                       "frequency_modulation": 200}]}]}
    tra = {"band_type": "Transient", "lower_frequency_limit": 0, "upper_frequency_limit": 300,
           "effects": [{"effect_type": "Basis", "position": 0, "keyframes": [
               {"relative_position": 0, "amplitude_modulation": 0.13, "frequency_modulation": 120},
               {"relative_position": 10, "amplitude_modulation": -0.5}]}]}
    ch = {"id": 0, "description": "", "gain": 1.0, "mixing_coefficient": 1.0, "body_part_mask": 0,
          "bands": [tra, vec]}
    p = {"id": 0, "avatar_id": 0, "description": "", "perception_modality": "Other",
         "reference_devices": [], "effect_library": [], "channels": [ch]}
    doc = {"version": "2023", "profile": "Main", "level": 1, "date": "2026-11-26", "description": "",
           "timescale": 1000, "avatars": [], "perceptions": [p], "syncs": []}
    f = tmp_path / "v.hjif"
    f.write_text(json.dumps(doc))
    base = hjif.read_channel(f)
    assert base.samples.size == 3200 and base.note == "" and np.max(np.abs(base.samples)) > 0.1
    paths: list[list] = []

    def walk(o, path):
        paths.append(path)
        items = o.items() if isinstance(o, dict) else enumerate(o) if isinstance(o, list) else ()
        for k, v in items:
            walk(v, [*path, k])

    walk(doc["perceptions"][0]["channels"][0], ["perceptions", 0, "channels", 0])
    values = [None, True, -1, 0, 2**31 - 1, -(2**31), 1e308, -1e-300, "x", [], {}, 3.5, 1e6, "Square",
              "Triangle", "SawToothUp", "SawToothDown", "Reference", 2**40]
    rng = random.Random(7)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        for _ in range(200):
            d = copy.deepcopy(doc)
            for _ in range(rng.randint(1, 3)):
                path = rng.choice(paths[4:])
                o = d
                try:
                    for k in path[:-1]:
                        o = o[k]
                    o[path[-1]] = rng.choice(values)
                except (KeyError, IndexError, TypeError):
                    pass
            f.write_text(json.dumps(d))
            try:
                y = hjif.read_channel(f).samples
            except ProfileError as e:
                assert "\n" not in str(e)
            else:
                assert np.all(np.isfinite(y))
