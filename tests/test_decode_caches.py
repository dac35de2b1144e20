"""What decoding caches (issue 14, decoder speed) and that the caches never serve stale data:
the shipped threshold curves (per directory and file modification times) and b(f_k) per
curve and geometry."""

import os

import numpy as np
import pytest

from hostd.codec import stream as vtx
from hostd.codec import transform
from hostd.codec.stream import v2 as stream2
from hostd.errors import StreamError
from hostd.perception import thresholds

CURVE_CSV = "frequency_hz,threshold_um\n10,1\n100,0.5\n1000,2\n"


def test_shipped_curves_see_a_curve_added_edited_and_removed(tmp_path, monkeypatch):
    monkeypatch.setenv("HOSTD_CONFIG_DIR", str(tmp_path))
    base = dict(thresholds.shipped_curves())
    assert thresholds.shipped_curves() is thresholds.shipped_curves()  # cached while nothing changes
    d = tmp_path / "thresholds"
    d.mkdir()
    f = d / "site.csv"
    f.write_text(CURVE_CSV)
    added = thresholds.shipped_curves()
    new = thresholds.load_csv(f)
    assert set(added) == set(base) | {new.id_bytes}
    # edited in place (the directory's time may not change): seen through the file's time
    st = f.stat()
    with open(f, "w") as fh:
        fh.write(CURVE_CSV.replace("100,0.5", "100,0.25"))
    os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))
    edited = thresholds.shipped_curves()
    assert new.id_bytes not in edited and thresholds.load_csv(f).id_bytes in edited
    f.unlink()
    assert set(thresholds.shipped_curves()) == set(base)


def test_a_decoder_may_skip_the_disk_check_for_a_while(tmp_path, monkeypatch):
    monkeypatch.setenv("HOSTD_CONFIG_DIR", str(tmp_path))
    base = thresholds.shipped_curves()
    (tmp_path / "thresholds").mkdir()
    (tmp_path / "thresholds" / "site.csv").write_text(CURVE_CSV)
    assert thresholds.shipped_curves(max_age_s=3600) is base  # not looked at again yet
    assert len(thresholds.shipped_curves()) == len(base) + 1  # the default: always checked


def test_a_daemon_decodes_a_stream_of_a_curve_installed_after_start(tmp_path, monkeypatch):
    monkeypatch.setenv("HOSTD_CONFIG_DIR", str(tmp_path))
    (tmp_path / "src").mkdir()
    (tmp_path / "src" / "c.csv").write_text(CURVE_CSV)
    curve = thresholds.load_csv(tmp_path / "src" / "c.csv")
    geom = transform.Geometry(20000, 10.0)
    c = np.random.default_rng(3).normal(0, 1, geom.n_keep)
    data = stream2.encode_coefficients(c, geom, curve, method="shaped", g_db=-6.0, embed_curve=False)
    with pytest.raises(StreamError, match="not shipped"):
        vtx.decode(data)
    monkeypatch.setattr(stream2, "SHIPPED_MAX_AGE_S", 3600.0)  # no periodic re-check in this test
    thresholds.shipped_curves()
    (tmp_path / "thresholds").mkdir()
    (tmp_path / "thresholds" / "c.csv").write_text(CURVE_CSV)
    assert vtx.decode(data).threshold_id == curve.id_bytes  # a miss makes it look again
    quant = stream2.encode_coefficients(c, geom, curve, method="quant", levels=9, embed_curve=False)
    assert vtx.decode(quant).threshold_id == curve.id_bytes


def test_thresholds_at_is_b_of_f_k_and_read_only():
    curve = thresholds.default_curve()
    for ig in (stream2.PAPER_GEOMETRY, stream2.IntGeometry(3000, 1_000_000, 20_000, 250_000)):
        b = stream2.thresholds_at(curve, ig)
        assert np.array_equal(b, curve(ig.frequencies_hz())) and b.shape == (ig.n_keep,)
        assert stream2.thresholds_at(curve, ig) is b
        with pytest.raises(ValueError):
            b[0] = 1.0
    other = thresholds.ThresholdCurve(np.array([1.0, 500.0]), np.array([1.0, 3.0]))
    assert not np.array_equal(stream2.thresholds_at(other, stream2.PAPER_GEOMETRY),
                              stream2.thresholds_at(curve, stream2.PAPER_GEOMETRY))
