"""libdeflate's reading of gzip'd chunks gives h5py's bytes (io.deflate_chunks)."""

import h5py
import numpy as np
import pytest

from mems_stereo.io import deflate_chunks as dc

pytestmark = pytest.mark.skipif(dc.libdeflate() is None, reason="no libdeflate on this system")


def _write(path, data, **kw):
    with h5py.File(path, "w") as f:
        f.create_dataset("d", data=data, **kw)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_slices_equal_h5py(tmp_path, seed):
    rng = np.random.default_rng(seed)
    K, H, W = int(rng.integers(50, 3000)), int(rng.integers(1, 4)), int(rng.integers(1, 20))
    data = rng.integers(0, 1024, (K, H, W)).astype(np.uint16)
    data[rng.random(data.shape) < 0.5] = 0  # compressible, like the bins
    chunk = int(rng.integers(1, 700))
    p = tmp_path / "a.h5"
    _write(p, data, chunks=(chunk, H, W), compression="gzip",
           compression_opts=int(rng.integers(1, 10)))
    with h5py.File(p) as f:
        r = dc.chunk_reader(f["d"])
        assert r is not None
        for _ in range(40):
            a = int(rng.integers(0, K))
            b = int(min(K, a + rng.integers(1, 3 * chunk + 2)))
            got = r.read(a, b)
            assert got.dtype == data.dtype
            assert np.array_equal(got, data[a:b])
        assert np.array_equal(r.read(0, K), data)


def test_other_layouts_are_left_to_h5py(tmp_path):
    data = np.arange(6000, dtype=np.uint16).reshape(500, 3, 4)
    cases = {"plain": {"chunks": (64, 3, 4)},
             "shuffle": {"chunks": (64, 3, 4), "compression": "gzip", "shuffle": True},
             "partial chunks": {"chunks": (64, 1, 4), "compression": "gzip"},
             "contiguous": {}}
    for name, kw in cases.items():
        p = tmp_path / f"{name}.h5"
        _write(p, data, **kw)
        with h5py.File(p) as f:
            assert dc.chunk_reader(f["d"]) is None, name
    p = tmp_path / "float.h5"
    _write(p, data.astype(np.float32), chunks=(64, 3, 4), compression="gzip")
    with h5py.File(p) as f:
        assert dc.chunk_reader(f["d"]) is None


def test_unwritten_chunks_come_from_h5py(tmp_path):
    p = tmp_path / "sparse.h5"
    with h5py.File(p, "w") as f:
        d = f.create_dataset("d", shape=(300, 2, 3), dtype=np.uint16, chunks=(32, 2, 3),
                             compression="gzip", fillvalue=7)
        d[40:90] = 5  # chunks 1 and 2 written, the others never
    with h5py.File(p) as f:
        r = dc.chunk_reader(f["d"])
        want = f["d"][:]
        assert np.array_equal(r.read(0, 300), want)
        assert np.array_equal(r.read(33, 250), want[33:250])


def test_recording_chunks_same_with_and_without_libdeflate(tmp_path, monkeypatch):
    from pathlib import Path

    from mems_stereo.io.recording import iter_shot_chunks

    src = Path(__file__).resolve().parents[1] / "samples" / "room.h5"
    fast = [(s0, b.copy()) for s0, _t, b in iter_shot_chunks(src, 333)]
    monkeypatch.setattr(dc, "_LIB", [None])
    slow = [(s0, b) for s0, _t, b in iter_shot_chunks(src, 333)]
    assert len(fast) == len(slow)
    for (a, x), (b, y) in zip(fast, slow):
        assert a == b and np.array_equal(x, y)


def test_a_range_from_inside_a_chunk_inflates_each_stored_chunk_once(tmp_path, monkeypatch):
    """iter_shot_chunks from a shot inside a stored chunk (a Dask part's range): blocks
    end at whole multiples of the storage's chunks, so every stored chunk is inflated
    once (it was twice: once for each block straddling it); the shots are the file's."""
    from pathlib import Path

    from mems_stereo.io.recording import RecordingWriter, iter_shot_chunks, read_recording

    rec = read_recording(Path(__file__).resolve().parents[1] / "samples" / "room.h5")
    src = tmp_path / "r.h5"  # the sample (800 shots) gzip'd in stored chunks of 16 shots
    with RecordingWriter(src, rec.system, rec.n_shots, rec.zero_crossings, rec.rising,
                         compression="gzip", chunk_shots=16) as w:
        w.append(rec.shot_time, rec.bins)
    bins = rec.bins
    with h5py.File(src) as f:
        assert f["shots/bins"].chunks[0] == 16 and dc.chunk_reader(f["shots/bins"])
    calls = []
    real = dc.ChunkReader._inflate

    def counting(self, k0, out):
        calls.append(k0)
        return real(self, k0, out)

    monkeypatch.setattr(dc.ChunkReader, "_inflate", counting)
    start, stop = 101, bins.shape[0] - 3
    blocks = list(iter_shot_chunks(src, 70, start, stop))  # blocks of 64 shots (4 chunks)
    assert [b[0] for b in blocks[:3]] == [101, 128, 192]  # first block shorter, then aligned
    assert all(s0 % 64 == 0 for s0, _t, _b in blocks[1:])
    assert np.array_equal(np.concatenate([b for _s, _t, b in blocks]), bins[start:stop])
    assert sorted(calls) == sorted(set(calls))  # no stored chunk inflated twice
    assert len(calls) == -(-stop // 16) - start // 16
