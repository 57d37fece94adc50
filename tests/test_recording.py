"""HDF5 recordings: write/read round trip, validation errors, chunked reading."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mems_stereo.errors import FormatError
from mems_stereo.io.labels import write_labels
from mems_stereo.io.recording import (
    iter_shot_chunks,
    read_header,
    read_recording,
    write_recording,
)
from mems_stereo.model.system import burkard2022, system_to_json


def _tiny(rng, k=50):
    s = burkard2022()
    t = np.arange(k) / 20000.0 + 1e-4
    bins = rng.integers(0, 4097, size=(k, 1, 192)).astype(np.uint16)
    zc = np.arange(-2, 40) / (2 * 1570.0)
    rising = (np.arange(zc.size) % 2).astype(np.uint8)
    return s, t, bins, zc, rising


def test_round_trip_and_chunks(tmp_path, rng):
    s, t, bins, zc, r = _tiny(rng)
    p = write_recording(tmp_path / "r.h5", s, t, bins, zc, r, truth={"theta": t * 0})
    rec = read_recording(p)
    np.testing.assert_array_equal(rec.bins, bins)
    np.testing.assert_array_equal(rec.shot_time, t)
    assert rec.truth["theta"].shape == (50,)
    chunks = list(iter_shot_chunks(p, chunk_shots=16))
    assert [c[0] for c in chunks] == [0, 16, 32, 48]
    np.testing.assert_array_equal(np.concatenate([c[2] for c in chunks]), bins)
    h = read_header(p)
    assert h.shape == (50, 1, 192)
    assert sorted(x.name for x in tmp_path.iterdir()) == ["r.h5"]


def test_labels_file(tmp_path):
    p = write_labels(tmp_path / "l.h5", np.zeros((3, 1, 4)), np.array([0.1, 0.2, np.nan]))
    with h5py.File(p) as f:
        assert f["label"].dtype == np.uint8 and f["theta"].shape == (3,)


def _write_raw(path, s, t, bins, zc, r, fmt="mems-stereo/recording", system=None):
    with h5py.File(path, "w") as f:
        f.attrs["format"] = fmt
        f.attrs["version"] = 1
        f["system"] = system if system is not None else system_to_json(s)
        f["shots/time"] = t
        f["shots/bins"] = bins
        f["scanner/zero_crossings"] = zc
        f["scanner/rising"] = r


CASES = {
    "format": (lambda a: {**a, "fmt": "other"}, "attrs/format"),
    "bins dtype": (lambda a: {**a, "bins": a["bins"].astype(np.int32)}, "/shots/bins: expected dtype uint16"),
    "bins shape": (lambda a: {**a, "bins": a["bins"][:, :, :100]}, "/shots/bins: expected shape"),
    "codes": (lambda a: {**a, "bins": np.where(a["bins"] > 4000, 5000, a["bins"]).astype(np.uint16)},
              "expected codes 0..4096"),
    "time order": (lambda a: {**a, "t": a["t"][::-1].copy()}, "/shots/time: expected strictly increasing"),
    "few crossings": (lambda a: {**a, "zc": a["zc"][:1], "r": a["r"][:1]}, "at least 2"),
    "crossing order": (lambda a: {**a, "zc": a["zc"][::-1].copy()}, "zero_crossings: expected strictly"),
    "system": (lambda a: {**a, "system": '{"format": "mems-stereo/system", "version": 1}'},
               "/system: receiver: required field"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_recordings_name_the_dataset(tmp_path, rng, case):
    s, t, bins, zc, r = _tiny(rng)
    bins[3, 0, 5] = 4096
    args = {"t": t, "bins": bins, "zc": zc, "r": r, "fmt": "mems-stereo/recording", "system": None}
    change, expect = CASES[case]
    a = change(args)
    p = tmp_path / "bad.h5"
    _write_raw(p, s, a["t"], a["bins"], a["zc"], a["r"], a["fmt"], a["system"])
    with pytest.raises(FormatError) as e:
        read_recording(p)
    assert expect in str(e.value) and str(p) in str(e.value)


def test_not_hdf5(tmp_path):
    p = tmp_path / "x.h5"
    p.write_text("hello")
    with pytest.raises(FormatError, match="cannot open as HDF5"):
        read_recording(p)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.sampled_from(["uint8", "int16", "float32"]), st.integers(0, 3))
def test_writer_refuses_bad_arrays_and_leaves_nothing(tmp_path, dtype, drop):
    s = burkard2022()
    k = 5
    bins = np.zeros((k, 1, 192 - drop), dtype=dtype)
    with pytest.raises(FormatError):
        write_recording(tmp_path / "w.h5", s, np.arange(k) * 1e-4, bins, [0.0, 1.0], [0, 1])
    assert not list(tmp_path.glob("*w*"))


def test_chunked_writer_matches_one_shot_writer(tmp_path, rng):
    from mems_stereo.io.recording import RecordingWriter

    s, t, bins, zc, r = _tiny(rng)
    with RecordingWriter(tmp_path / "c.h5", s, 50, zc, r, chunk_shots=16) as w:
        for a in range(0, 50, 16):
            w.append(t[a:a + 16], bins[a:a + 16])
    rec = read_recording(tmp_path / "c.h5")
    np.testing.assert_array_equal(rec.bins, bins)
    np.testing.assert_array_equal(rec.shot_time, t)


def test_chunked_writer_leaves_nothing_when_incomplete(tmp_path, rng):
    from mems_stereo.io.recording import RecordingWriter

    s, t, bins, zc, r = _tiny(rng)
    with pytest.raises(FormatError, match="10 shots written, 50 declared"):
        with RecordingWriter(tmp_path / "c.h5", s, 50, zc, r) as w:
            w.append(t[:10], bins[:10])
    with pytest.raises(FormatError, match="increasing"):
        with RecordingWriter(tmp_path / "c.h5", s, 50, zc, r) as w:
            w.append(t[:10], bins[:10])
            w.append(t[:10], bins[:10])
    assert list(tmp_path.iterdir()) == []
