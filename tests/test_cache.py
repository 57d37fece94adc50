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
    fp.first_photon_table.cache_clear()
    try:
        fresh = fp.first_photon_table()
        assert len(list(tmp_path.glob("first-photon-*.npz"))) == 1
        fp.first_photon_table.cache_clear()
        again = fp.first_photon_table()
        for name in ("a_grid", "logmu_grid", "mean", "var"):
            assert np.array_equal(getattr(fresh, name), getattr(again, name))
        m, v = fp.first_photon_moments(fresh.a_grid[7], np.exp(fresh.logmu_grid[11]))
        assert abs(m - again.mean[7, 11]) < 1e-12 and abs(v - again.var[7, 11]) < 1e-12
    finally:
        fp.first_photon_table.cache_clear()


def test_interval_table_read_from_the_cache_counts_as_used(tmp_path, monkeypatch):
    """The cache keeps the most recently used tables: reading one marks it used, so a
    table read at every run is not the first evicted when other tables are written."""
    import os

    from mems_stereo.model.system import burkard2022
    from mems_stereo.pipeline.intervals import IntervalTable
    from mems_stereo.pipeline.settings import Settings

    monkeypatch.setenv("MEMS_STEREO_CACHE", str(tmp_path))
    t = IntervalTable.for_settings(burkard2022(), Settings())
    t.ensure(np.array([0, 5, 17]))
    assert t.save_cache()
    (path,) = tmp_path.glob("intervals-*.npz")
    os.utime(path, (1_000_000, 1_000_000))  # written long ago
    u = IntervalTable.for_settings(burkard2022(), Settings())
    assert u.load_cache() == 3
    assert np.array_equal(u.lo[[0, 5, 17]], t.lo[[0, 5, 17]])
    assert path.stat().st_mtime > 1_000_000 + 86400  # marked used now
