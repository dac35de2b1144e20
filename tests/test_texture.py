"""Profile loading (formats, units, resampling, patches) and the synthetic generators."""

import numpy as np
import pytest

from hostd.codec import transform
from hostd.errors import ProfileError
from hostd.texture import synth
from hostd.texture.load import LoadOptions, load_profile
from tests.conftest import real_profile_path


def test_one_column_needs_and_uses_the_spacing(tmp_path):
    p = tmp_path / "h.txt"
    np.savetxt(p, np.arange(100.0))
    with pytest.raises(ProfileError, match="--spacing"):
        load_profile(p)
    prof = load_profile(p, LoadOptions(spacing=0.5, x_unit="um", y_unit="nm", length_mm=None))
    assert prof.n == 100 and prof.spacing_um == 0.5
    assert prof.heights_um[10] == pytest.approx(10 * 1e-3)


def test_npy_two_columns_and_units(tmp_path):
    x_m = np.arange(2000) * 1e-6
    y_m = np.sin(x_m * 1e4) * 1e-6
    np.save(tmp_path / "p.npy", np.column_stack([x_m, y_m]))
    prof = load_profile(tmp_path / "p.npy", LoadOptions(x_unit="m", y_unit="m"))
    assert prof.spacing_um == pytest.approx(1.0) and prof.n == 2000
    assert np.max(np.abs(prof.heights_um - y_m * 1e6)) < 1e-12


def test_non_uniform_x_is_resampled_onto_a_uniform_grid(tmp_path):
    rng = np.random.default_rng(3)
    x = np.sort(rng.uniform(0, 1000, 400))
    y = 2.0 * x
    p = tmp_path / "nu.txt"
    np.savetxt(p, np.column_stack([x, y]))
    prof = load_profile(p, LoadOptions(spacing=2.0, length_mm=None))
    grid = x[0] + 2.0 * np.arange(prof.n)
    assert np.max(np.abs(prof.heights_um - 2.0 * grid)) < 1e-9
    assert grid[-1] <= x[-1]


def test_patch_length_and_offset(tmp_path):
    p = tmp_path / "long.csv"
    np.savetxt(p, np.column_stack([np.arange(50000) * 0.5, np.arange(50000.0)]), delimiter=",")
    prof = load_profile(p, LoadOptions(length_mm=10.0, offset_mm=1.0))
    assert prof.n == 20000 and prof.length_mm == pytest.approx(10.0)
    assert prof.heights_um[0] == 2000.0


def test_dektak_export_header_is_skipped():
    prof = load_profile(real_profile_path("dektak-1.csv"), LoadOptions(length_mm=None))
    assert prof.n == 9600 and prof.spacing_um == pytest.approx(0.15625, rel=1e-3)
    assert abs(prof.heights_um[0] - (-0.00933)) < 1e-12


def test_opdx_metres_become_micrometres():
    prof = load_profile(real_profile_path("opdx-3.txt"), LoadOptions(x_unit="m", y_unit="m"))
    assert prof.spacing_um == pytest.approx(0.016655563, rel=1e-6)
    assert 1e-4 < np.std(prof.heights_um) < 1e-1  # nm-scale heights, in µm


def test_bad_unit_and_empty_file(tmp_path):
    p = tmp_path / "e.txt"
    p.write_text("# nothing\nheader only\n")
    with pytest.raises(ProfileError, match="no numeric rows"):
        load_profile(p)
    with pytest.raises(ProfileError, match="unit"):
        load_profile(p, LoadOptions(x_unit="furlong"))


def test_synthetic_textures_are_seeded():
    for kind in ("wood", "sandpaper"):
        a, b, c = synth.make(kind, 1), synth.make(kind, 1), synth.make(kind, 2)
        assert np.array_equal(a.heights_um, b.heights_um)
        assert not np.array_equal(a.heights_um, c.heights_um)
        assert np.all(np.isfinite(a.heights_um)) and a.n == 20000 and a.spacing_um == 0.5


def _low_band_fraction(y):
    c = transform.amplitudes(y)[1:]
    e = c * c
    return e[: e.size // 100].sum() / e.sum()  # energy below 1 % of the spatial band


def test_wood_concentrates_energy_at_low_spatial_frequency_and_sandpaper_is_broadband():
    wood = np.mean([_low_band_fraction(synth.wood(seed=s).heights_um) for s in range(4)])
    sand = np.mean([_low_band_fraction(synth.sandpaper(seed=s).heights_um) for s in range(4)])
    assert wood > 0.8
    assert sand < 0.5


def test_finer_grit_has_smaller_grains():
    coarse = synth.sandpaper(seed=0, grit=240).heights_um
    fine = synth.sandpaper(seed=0, grit=1500).heights_um
    assert np.std(fine) < np.std(coarse)


# ----------------------------------------------------------------- inputs that cannot be misread

from tests.fuzz import profile_inputs as pin  # noqa: E402


def _wav(path, data, **kw):
    path.write_bytes(pin.wav(data, **kw))
    return path


def test_wav_samples_become_a_profile_with_the_spacing_given(tmp_path):
    import scipy.io.wavfile

    y = np.sin(np.arange(3000) / 40.0)
    scipy.io.wavfile.write(tmp_path / "m.wav", 48000, np.round(y * 16000).astype(np.int16))
    prof = load_profile(tmp_path / "m.wav", LoadOptions(spacing=2.0, length_mm=None))
    assert prof.n == 3000 and prof.spacing_um == 2.0
    np.testing.assert_allclose(prof.heights_um, np.round(y * 16000) / 32768.0, atol=0, rtol=0)
    assert "48000 Hz" in prof.note
    # stereo float: a channel chosen with --columns; unsigned 8-bit: (x - 128) / 128
    scipy.io.wavfile.write(tmp_path / "s.wav", 8000, np.column_stack([y, -y]).astype(np.float32))
    prof = load_profile(tmp_path / "s.wav", LoadOptions(spacing=1.0, x_unit="mm", length_mm=None,
                                                        columns=(1,)))
    np.testing.assert_allclose(prof.heights_um, -y.astype(np.float32), rtol=0, atol=0)
    assert prof.spacing_um == 1000.0
    _wav(tmp_path / "u8.wav", bytes([0, 128, 255, 64]), bits=8)
    prof = load_profile(tmp_path / "u8.wav", LoadOptions(spacing=1.0, length_mm=None))
    assert list(prof.heights_um) == [-1.0, 0.0, 127 / 128, -0.5]
    # 24-bit PCM (3-byte samples): full scale 2^23
    _wav(tmp_path / "i24.wav", (4194304).to_bytes(3, "little", signed=True) + (-8388608).to_bytes(
        3, "little", signed=True), bits=24)
    prof = load_profile(tmp_path / "i24.wav", LoadOptions(spacing=1.0, length_mm=None))
    assert list(prof.heights_um) == [0.5, -1.0]


def test_a_wav_without_spacing_or_channel_is_refused_saying_what_to_give(tmp_path):
    import scipy.io.wavfile

    scipy.io.wavfile.write(tmp_path / "s.wav", 48000, np.zeros((100, 2), np.int16))
    with pytest.raises(ProfileError, match=r"2 channels: choose one with --columns CHANNEL"):
        load_profile(tmp_path / "s.wav", LoadOptions(spacing=1.0))
    with pytest.raises(ProfileError, match=r"recording at 48000 Hz: give the distance .* --spacing"):
        load_profile(tmp_path / "s.wav", LoadOptions(columns=(0,)))
    (tmp_path / "adpcm.wav").write_bytes(pin.wav(b"\0" * 64, fmt_tag=2, bits=4, align=1))
    with pytest.raises(ProfileError, match=r"ffmpeg -i IN -c:a pcm_f32le OUT.wav"):
        load_profile(tmp_path / "adpcm.wav", LoadOptions(spacing=1.0))


def test_bytes_are_sniffed_before_text_is_parsed(tmp_path):
    """A WAV named .csv (whose bytes once gave 21 'heights'), an image named .txt, random bytes
    named .npy: each refused saying what it holds and what was expected."""
    import scipy.io.wavfile

    scipy.io.wavfile.write(tmp_path / "corduroy.csv", 48000, (np.arange(2000) % 300).astype(np.int16))
    with pytest.raises(ProfileError, match=r"holds a WAV recording, not text .* name it \*\.wav"):
        load_profile(tmp_path / "corduroy.csv", LoadOptions(spacing=1.0))
    (tmp_path / "photo.txt").write_bytes(b"\x89PNG\r\n\x1a\n" + b"12 34\n" * 50)
    with pytest.raises(ProfileError, match="holds a PNG image, not text"):
        load_profile(tmp_path / "photo.txt", LoadOptions(spacing=1.0))
    (tmp_path / "nul.dat").write_bytes(b"1 2\n\0\0\0\x013 4\n" * 50)
    with pytest.raises(ProfileError, match="holds binary data, not text"):
        load_profile(tmp_path / "nul.dat", LoadOptions(spacing=1.0))
    (tmp_path / "r.npy").write_bytes(np.random.default_rng(1).bytes(3000))
    with pytest.raises(ProfileError, match=r"not a NumPy \.npy file .* numpy\.save") as e:
        load_profile(tmp_path / "r.npy")
    assert "allow_pickle" not in str(e.value) and "pickle" not in str(e.value)
    np.save(tmp_path / "o.npy", np.array([1.0, "a"], dtype=object), allow_pickle=True)
    with pytest.raises(ProfileError, match=r"Python objects .* never loads") as e:
        load_profile(tmp_path / "o.npy")
    assert "allow_pickle" not in str(e.value)


def test_a_manifest_without_a_file_column_is_refused_as_a_manifest(tmp_path):
    from hostd.texture import manifest

    m = tmp_path / "textures.csv"
    m.write_text("name,units,length_mm\nwood,um,5\n")
    assert manifest.is_manifest(m)
    with pytest.raises(ProfileError, match=r"a manifest needs a `file` column .* name, units, length_mm"):
        manifest.read(m)
    with pytest.raises(ProfileError, match=r"is a texture manifest .* not a profile"):
        load_profile(m, LoadOptions(spacing=1.0))
    # `file` need not come first
    (tmp_path / "p.csv").write_text("".join(f"{i},{i % 7}\n" for i in range(50)))
    m.write_text("name,file\nwood,p.csv\n")
    assert [e.name for e in manifest.read(m)] == ["wood"]


def _cli(*args, cwd, timeout=60):
    import subprocess
    import sys

    return subprocess.run([sys.executable, "-m", "hostd", *args], cwd=cwd, capture_output=True, text=True,
                          timeout=timeout)


def test_a_fifo_is_refused_not_waited_on(tmp_path):
    import os

    os.mkfifo(tmp_path / "pipe.csv")
    r = _cli("encode", "pipe.csv", "--spacing", "1", "-o", "x.vtx", cwd=tmp_path, timeout=30)
    assert r.returncode == 2 and "is a FIFO (named pipe): only regular files are read" in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    (tmp_path / "m.csv").write_text("file,name\npipe.csv,p\n")
    from hostd.texture import manifest

    with pytest.raises(ProfileError, match=r"m.csv row 2: pipe.csv is a FIFO"):
        manifest.read(tmp_path / "m.csv")
    from hostd.corpus import jobs

    assert jobs.input_sha256(str(tmp_path / "pipe.csv")).startswith("unreadable:")  # not waited on


_PEAK = """
import json, resource, sys
from hostd.texture.load import load_profile, LoadOptions
from hostd.errors import HostdError
import scipy.io, scipy.io.wavfile
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
errs = []
for path in sys.argv[1:]:
    try:
        load_profile(path, LoadOptions(spacing=1.0, length_mm=None))
        errs.append("")
    except HostdError as e:
        errs.append(str(e))
    except MemoryError:
        errs.append("MemoryError")
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(json.dumps({"errs": errs, "grew_mb": (peak - base) / 1024}))
"""


def _peak(*paths):
    """Loads in a child process (address space capped at 3 GiB, so a blow-up fails there, not on
    the machine): (their errors, how much the peak RSS grew in MB over the interpreter with its
    imports, over all the loads)."""
    import json
    import os
    import resource
    import subprocess
    import sys

    def cap():
        resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))

    r = subprocess.run([sys.executable, "-c", _PEAK, *map(str, paths)], capture_output=True, text=True,
                       timeout=120, preexec_fn=cap,
                       env=dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1"))
    assert r.returncode == 0, r.stderr[-2000:]
    out = json.loads(r.stdout)
    return out["errs"], out["grew_mb"]


def test_a_mat_zlib_bomb_is_refused_as_it_inflates(tmp_path):
    """128 MiB of zeros in 125 kB: scipy alone inflates it whole (and more) before any shape check."""
    (tmp_path / "bomb.mat").write_bytes(pin.mat_bomb(16 << 20))
    (err,), grew = _peak(tmp_path / "bomb.mat")
    assert "inflates to more than" in err and "-v6" in err, err
    assert grew < 40, grew  # the limit: 64 x 125 kB, inflated in a stream that stops there
    # a real profile still reads: a vector with its compressed copy
    import scipy.io

    y = np.random.default_rng(2).normal(size=20000)
    scipy.io.savemat(tmp_path / "ok.mat", {"h": y}, do_compression=True)
    prof = load_profile(tmp_path / "ok.mat", LoadOptions(spacing=1.0, length_mm=None))
    np.testing.assert_array_equal(prof.heights_um, y)


def test_declared_sizes_are_checked_before_anything_is_allocated(tmp_path):
    """A few bytes declaring gigabytes (a cell array of a million cells, a 2^31-element vector, a
    .npy of 10^9 doubles) and two rows spanning 10^12 µm at 1 µm spacing: refused, memory flat."""
    paths = []
    for name in ("mat-cell-million.mat", "mat-declared-huge.mat", "npy-declared-huge.npy"):
        data = (pin.Path(pin.__file__).parent / "corpus" / "profiles" / name).read_bytes()
        paths.append(tmp_path / (name.split(".")[0] + pin.options(data[0])[0]))
        paths[-1].write_bytes(data[1:])
    (tmp_path / "wide.csv").write_text("0,0\n1e12,1\n")
    errs, grew = _peak(*paths, tmp_path / "wide.csv")
    assert all(errs) and "more than 4,194,304" in errs[-1], errs
    assert grew < 20, (errs, grew)


def _reader_that_breaks(path, opts):
    return {}["a reader's own bug on bytes it did not expect"]


def test_every_reader_exception_becomes_its_one_line_error(tmp_path):
    from hostd.texture import formats

    formats.register(formats.Format("broken", (".brk",), "tests.test_texture:_reader_that_breaks"))
    try:
        (tmp_path / "p.brk").write_bytes(b"1 2\n")
        with pytest.raises(ProfileError) as e:
            load_profile(tmp_path / "p.brk")
        msg = str(e.value)
        assert msg.startswith(f"cannot read {tmp_path / 'p.brk'} as broken: KeyError"), msg
        assert "\n" not in msg
    finally:
        formats._registry.pop(".brk")


@pytest.mark.parametrize("reader", ["sniff", "npy", "mat", "wav"])
def test_every_binary_reader_opens_a_profile_the_same_way(tmp_path, reader):
    """Each reader that opens a profile itself (the kind sniffer, .npy, .mat, .wav) says the
    same one line for a missing file, a FIFO and a directory: one opener, not four copies."""
    import os

    from hostd.errors import ProfileNotFound
    from hostd.texture import formats, load, matfile, wav

    call = {"sniff": formats._head, "npy": load._npy_header, "mat": matfile._load,
            "wav": wav.read_samples}[reader]
    with pytest.raises(ProfileNotFound, match=r"^no such profile file: .*absent$"):
        call(tmp_path / "absent")
    os.mkfifo(tmp_path / "pipe")
    with pytest.raises(ProfileError, match=r"pipe is a FIFO \(named pipe\): only regular files are read"):
        call(tmp_path / "pipe")
    (tmp_path / "dir").mkdir()
    with pytest.raises(ProfileError, match=r"dir is a directory: only regular files are read"):
        call(tmp_path / "dir")
