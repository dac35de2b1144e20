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
