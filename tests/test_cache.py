"""The disk cache (mems_stereo.util.cache) and the first-photon table kept in it."""

from __future__ import annotations

import numpy as np

from mems_stereo.util.cache import cache_dir, cached_arrays, source_key


def test_cached_arrays_round_trip_and_recompute(tmp_path, monkeypatch):
    monkeypatch.setenv("MEMS_STEREO_CACHE", str(tmp_path))
    calls = []

    def compute():
        calls.append(1)
        return {"x": np.arange(5.0), "y": np.eye(2)}

    key = source_key("v1", (1, 2))
    a = cached_arrays("t", key, compute)
    b = cached_arrays("t", key, compute)
    assert len(calls) == 1 and np.array_equal(a["x"], b["x"]) and np.array_equal(a["y"], b["y"])
    (f,) = tmp_path.glob("t-*.npz")
    f.write_bytes(b"not a zip file")  # a corrupt file is recomputed, not trusted
    c = cached_arrays("t", key, compute)
    assert len(calls) == 2 and np.array_equal(c["x"], a["x"])
    assert source_key("v2", (1, 2)) != key  # another source, another file
    assert not list(tmp_path.glob("*.part*"))


def test_cache_off_writes_nothing(tmp_path, monkeypatch):
    monkeypatch.setenv("MEMS_STEREO_CACHE", "off")
    assert cache_dir() is None
    out = cached_arrays("t", "k", lambda: {"x": np.ones(3)})
    assert np.array_equal(out["x"], np.ones(3))


def test_first_photon_table_from_cache_equals_fresh(tmp_path, monkeypatch):
    from mems_stereo.physics import first_photon as fp

    monkeypatch.setenv("MEMS_STEREO_CACHE", str(tmp_path))
    fp._first_photon_table.cache_clear()
    try:
        fresh = fp._first_photon_table()
        assert len(list(tmp_path.glob("first-photon-*.npz"))) == 1
        fp._first_photon_table.cache_clear()
        again = fp._first_photon_table()
        for x, y in zip(fresh, again):
            assert np.array_equal(x, y)
        m, v = fp.first_photon_moments(fresh[0][7], np.exp(fresh[1][11]))
        assert abs(m - again[2][7, 11]) < 1e-12 and abs(v - again[3][7, 11]) < 1e-12
    finally:
        fp._first_photon_table.cache_clear()
