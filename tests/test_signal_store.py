"""Pass 2 from pass 1's stored signal detections: the same counts as reading the shots."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

import mems_stereo.pipeline.classify_kernel as classify_kernel
import mems_stereo.pipeline.pass1 as pass1
import mems_stereo.pipeline.run as run
from mems_stereo.io.recording import read_header
from mems_stereo.pipeline.angles import shot_angles
from mems_stereo.pipeline.classify_kernel import _kernel_keys_py, signal_keys
from mems_stereo.pipeline.intervals import IntervalTable
from mems_stereo.pipeline.pass1 import accumulate_range
from mems_stereo.pipeline.pass2 import peak_counts_range
from mems_stereo.pipeline.peak_table import Peaks
from mems_stereo.pipeline.peaks import find_peaks
from mems_stereo.pipeline.settings import Settings
from mems_stereo.pipeline.shot_range import ShotRange
from mems_stereo.pipeline.signal_store import SignalStore, peak_counts_from_store

SAMPLES = Path(__file__).resolve().parents[1] / "samples"
pytestmark = pytest.mark.skipif(not (SAMPLES / "floodlight.h5").exists(),
                                reason="samples not built")


def _peaks(path, st, table, acc):
    h = read_header(path)
    s = h.system
    K, H, W = h.shape
    theta, valid = shot_angles(h, s)
    sig = acc.hist_signal[:, 1:].astype(np.int64).reshape(H, W, -1)
    noise = acc.hist_raw[:, 1:].astype(np.int64).reshape(H, W, -1) - sig
    peaks, _ = find_peaks(s, sig, noise, theta, valid, st, signal_angle=acc.hist_angle,
                          table=table, n_per_step=acc.n_per_step)
    return s, theta, valid, peaks


@pytest.mark.parametrize("name", ["floodlight", "room"])
def test_store_counts_equal_reading_the_shots(monkeypatch, tmp_path, name):
    """In memory and spilled to a file, with and without labels, in chunks of 97 shots
    (the compiled kernels forced on a small recording)."""
    monkeypatch.setattr(pass1, "COMPILE_SLOTS", 0)
    path = SAMPLES / f"{name}.h5"
    h = read_header(path)
    s = h.system
    theta, valid = shot_angles(h, s)
    st = Settings(chunk_shots=97)
    table = IntervalTable.for_settings(s, st)
    ref = None
    for budget, labels in ((1 << 30, False), (1000, False), (1000, True)):
        with SignalStore(memory_bytes=budget, directory=tmp_path) as store:
            if labels:
                with h5py.File(tmp_path / "l.h5", "w") as f:
                    ds = f.create_dataset("label", shape=h.shape, dtype=np.uint8)
                    acc = accumulate_range(path, s, ShotRange(theta, valid), st, table=table,
                                           labels_out=ds, signal_store=store)
            else:
                acc = accumulate_range(path, s, ShotRange(theta, valid), st, table=table,
                                       signal_store=store)
            assert store.complete
            assert (store._file is not None) == (budget == 1000)
            assert store.n_keys == int(acc.hist_signal[:, 1:].sum())
            if ref is None:
                _, theta, valid, peaks = _peaks(path, st, table, acc)
                ref = peak_counts_range(path, s, ShotRange(theta, valid), st, peaks, table=table)
                assert ref.keys.size > 0
            got = peak_counts_from_store(store, s, peaks, table.n_steps)
        np.testing.assert_array_equal(got.keys, ref.keys)
        np.testing.assert_array_equal(got.counts, ref.counts)


def test_small_ranges_leave_the_store_incomplete(tmp_path):
    path = SAMPLES / "room.h5"
    h = read_header(path)
    theta, valid = shot_angles(h, h.system)
    st = Settings()
    with SignalStore(directory=tmp_path) as store:
        accumulate_range(path, h.system, ShotRange(theta, valid), st, signal_store=store)
        assert not store.complete and store.n_keys == 0
        with pytest.raises(ValueError):
            z = np.zeros(0, np.int64)
            peak_counts_from_store(store, h.system, Peaks(*[z] * 10), 1)


def test_signal_keys_kernel_and_labels_agree():
    """The keys kernel (pure-Python semantics) and the keys from labels: same keys."""
    rng = np.random.default_rng(1414)
    for _ in range(20):
        K, P, S, nb = int(rng.integers(1, 30)), int(rng.integers(1, 9)), 7, 33
        bins = rng.integers(0, nb, (K, P)).astype(np.uint16)
        rows = rng.integers(-1, S, K).astype(np.int64)
        lo = rng.integers(0, nb, (S, P)).astype(np.uint16)
        hi = np.minimum(lo + rng.integers(0, 20, (S, P)), nb - 1).astype(np.uint16)
        hr, hs, ha = (np.zeros((P, nb), np.int64), np.zeros((P, nb), np.int64),
                      np.zeros((P, S), np.int64))
        out = np.empty(K * P, np.int64)
        n = _kernel_keys_py(bins, rows, lo, hi, hr, hs, ha, *classify_kernel.signal_key_shifts(S, nb), out)
        lab = np.zeros((K, P), np.uint8)
        classify_kernel._kernel_py(bins, rows, lo, hi, lab, *(np.zeros_like(a) for a in (hr, hs, ha)))
        np.testing.assert_array_equal(out[:n], signal_keys(bins, rows, lab, S, nb))
        assert n == int(hs[:, 1:].sum())
        # each key holds its detection's pixel, step and code (bit fields)
        p, j, c = classify_kernel.decode_signal_keys(out[:n], S, nb)
        k_, p_ = np.nonzero(lab == 1)
        np.testing.assert_array_equal(p, p_)
        np.testing.assert_array_equal(j, rows[k_])
        np.testing.assert_array_equal(c, bins[k_, p_])


def test_process_recording_with_the_store_is_identical(monkeypatch):
    """The whole run with pass 2 from the store (forced) and from reading the shots."""
    path = SAMPLES / "floodlight.h5"
    a = run.process_recording(path)
    monkeypatch.setattr(pass1, "COMPILE_SLOTS", 0)
    monkeypatch.setattr(run, "COMPILE_SLOTS", 0)
    b = run.process_recording(path)
    assert a.cloud.points.shape == b.cloud.points.shape and len(a.cloud) > 0
    np.testing.assert_array_equal(a.cloud.points, b.cloud.points)
    for k, v in a.cloud.attributes.items():
        np.testing.assert_array_equal(v, b.cloud.attributes[k])


def test_store_only_where_reading_again_decompresses(tmp_path):
    """The store is kept for gzip'd bins only: an uncompressed file is read again
    faster than its signal keys are written and read back; a Recording in memory
    needs no reading."""
    from mems_stereo.io.recording import read_recording
    from mems_stereo.pipeline.signal_store import rereading_decompresses

    assert rereading_decompresses(SAMPLES / "floodlight.h5")
    assert not rereading_decompresses(read_recording(SAMPLES / "room.h5"))
    with h5py.File(tmp_path / "plain.h5", "w") as f:
        f.create_dataset("/shots/bins", data=np.zeros((4, 1, 3), np.uint16))
    assert not rereading_decompresses(tmp_path / "plain.h5")


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_window_keys_compiled_equal_vectorised(seed):
    """The compiled pass over the signal keys gives the vectorised form's keys (as a
    multiset: PeakCounts sums them whatever the order), pure-Python semantics too;
    pixels with no, one and several peaks, windows at the edges."""
    from mems_stereo.pipeline import signal_store as ss

    rng = np.random.default_rng(seed)
    P, S, nb = int(rng.integers(2, 30)), int(rng.integers(5, 400)), int(rng.integers(3, 70))
    Q = int(rng.integers(0, 3 * P))
    pix = np.sort(rng.integers(0, P, Q))
    order = np.argsort(pix, kind="stable").astype(np.int64)
    first = np.searchsorted(pix[order], np.arange(P + 1)).astype(np.int64)
    lo = rng.integers(0, nb, Q)
    hi = np.minimum(nb - 1, lo + rng.integers(0, nb, Q))
    s_lo = rng.integers(0, S, Q)
    s_hi = np.minimum(S, s_lo + rng.integers(0, S, Q))
    keys = classify_kernel.encode_signal_keys(rng.integers(0, P, 5000), rng.integers(0, S, 5000),
                                    rng.integers(0, nb, 5000), S, nb)
    want = np.sort(ss.window_keys_from_signal(keys, S, nb, first, order, lo, hi, s_lo, s_hi))
    for kernel in (None, ss._window_keys_py):
        got = ss.window_keys_compiled(keys, S, nb, first, order, lo, hi, s_lo, s_hi,
                                      kernel=kernel)
        assert np.array_equal(np.sort(got), want)
    print(f"seed {seed}: {keys.size} keys, {Q} peaks on {P} pixels -> {want.size} in windows")
