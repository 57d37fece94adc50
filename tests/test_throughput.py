"""Throughput machinery: the kernels' three forms agree, compact results add and travel
exactly, the interval table is built once per run and cached on disk bit for bit."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest

from mems_stereo.model.system import burkard2022
from mems_stereo.model.tdc import path_length_from_codes
from mems_stereo.pipeline.classify_kernel import (
    KernelOptions,
    _kernel_nolabels_py,
    _kernel_py,
    classify_and_accumulate,
)
from mems_stereo.pipeline.intervals import IntervalTable, interval_table
from mems_stereo.pipeline.pass1 import (
    RangeAccumulation,
    accumulate_range,
    sum_accumulations,
)
from mems_stereo.pipeline.pass2 import (
    PeakWindows,
    _window_keys_py,
    decode_peak_keys,
    encode_peak_keys,
    peak_window_keys,
)
from mems_stereo.pipeline.settings import Settings
from mems_stereo.pipeline.shot_range import ShotRange

SAMPLES = Path(__file__).resolve().parents[1] / "samples"


@pytest.fixture(scope="module")
def table():
    return interval_table(burkard2022())


def _block(rng, k, p_zero=0.3):
    s = burkard2022()
    sc = s.scanner
    theta = sc.theta0 + sc.theta_mech_max * np.cos(rng.uniform(0, 2 * np.pi, k))
    theta[rng.random(k) < 0.05] = np.nan
    bins = rng.integers(0, s.tdc.n_bins + 1, size=(k, 1, 192)).astype(np.uint16)
    bins[rng.random(bins.shape) < p_zero] = 0
    return bins, theta, rng.random(k) > 0.1


@pytest.mark.parametrize("seed", [1, 2, 3])
@pytest.mark.parametrize("want_labels", [True, False])
def test_pass1_numpy_compiled_and_python_kernels_agree(table, seed, want_labels, monkeypatch):
    import mems_stereo.pipeline.classify_kernel as classify_kernel

    rng = np.random.default_rng(seed)
    bins, theta, valid = _block(rng, 97)
    out = []
    # compiled with the raw histogram counted in uint16 first (seeds 1, 3) or straight
    # into the uint32 one (seed 2); the NumPy form
    monkeypatch.setattr(classify_kernel, "RAW16_SHOTS", 1 << 16 if seed != 2 else 0)
    for compiled in (True, False):
        lab, h = classify_and_accumulate(bins, theta, valid, table, 4096,
                                         want_labels=want_labels,
                                         options=KernelOptions(compiled=compiled))
        out.append((lab, h.raw, h.signal, h.angle))
    rows = table.rows(theta, valid)
    raw = np.zeros((192, 4097), np.int64)
    sig = np.zeros_like(raw)
    angle = np.zeros((192, table.n_steps), np.int64)
    lab = np.empty((97, 192), np.uint8)
    if want_labels:
        _kernel_py(bins.reshape(97, 192), rows, table.lo, table.hi, lab, raw, sig, angle)
    else:
        _kernel_nolabels_py(bins.reshape(97, 192), rows, table.lo, table.hi, raw, sig, angle)
    for a, b in zip(out[0], out[1]):
        if a is None:
            assert b is None
        else:
            np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(out[0][1], raw)
    np.testing.assert_array_equal(out[0][2], sig)
    np.testing.assert_array_equal(out[0][3], angle)
    assert sig.sum() > 0 and raw[:, 1:].sum() > sig.sum()  # both outcomes exercised
    if want_labels:
        np.testing.assert_array_equal(out[0][0].reshape(97, 192), lab)


@pytest.mark.parametrize("seed", [4, 5])
def test_pass2_numpy_compiled_and_python_kernels_agree(table, seed):
    rng = np.random.default_rng(seed)
    bins, theta, valid = _block(rng, 600, p_zero=0.1)
    pix = np.array([60, 95, 96, 130])
    lo, hi = np.array([1, 100, 1, 200]), np.array([4096, 3000, 800, 4096])
    s_lo = np.array([0, 1000, 0, 3000])
    s_hi = np.array([table.n_steps, 8000, 5000, 9000])
    w = PeakWindows(pix, lo, hi, s_lo, s_hi)
    a = peak_window_keys(bins, theta, valid, table, w, 4096, compiled=True)
    b = peak_window_keys(bins, theta, valid, table, w, 4096, compiled=False)
    out = np.empty(600 * 4, np.int64)
    n = _window_keys_py(bins.reshape(600, -1), table.rows(theta, valid), table.lo, table.hi,
                        pix, lo, hi, s_lo, s_hi, table.n_steps, 4097, out)
    assert a.size > 10
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(a, out[:n])


def test_peak_keys_round_trip():
    rng = np.random.default_rng(6)
    q, step, code = rng.integers(0, 192, 50), rng.integers(0, 9140, 50), rng.integers(0, 4097, 50)
    k = encode_peak_keys(q, step, code, 9140, 4097)
    for x, y in zip(decode_peak_keys(k, 9140, 4097), (q, step, code)):
        np.testing.assert_array_equal(x, y)


def _acc(rng, n_shots, density=0.01, shape=((4, 9), (4, 7))):
    def counts(sh):
        a = rng.integers(0, 1000, sh).astype(np.uint32)
        a[rng.random(sh) > density] = 0
        return a

    return RangeAccumulation(counts(shape[0]), counts(shape[0]), counts(shape[1]),
                             rng.integers(0, 9, shape[1][1]), n_shots, 1,
                             rng.integers(0, 5, (3, 3)), True)


@pytest.mark.parametrize("density", [0.01, 0.9])
def test_range_accumulation_travels_and_adds_exactly(density):
    rng = np.random.default_rng(7)
    parts = [_acc(rng, 10, density) for _ in range(5)]
    for p in parts:
        q = pickle.loads(pickle.dumps(p))
        for k in ("hist_raw", "hist_signal", "hist_angle", "n_per_step", "confusion"):
            x, y = getattr(p, k), getattr(q, k)
            assert x.dtype == y.dtype
            np.testing.assert_array_equal(x, y)
    total = sum_accumulations(parts)
    grouped = sum_accumulations([sum_accumulations(parts[:2]), sum_accumulations(parts[2:])])
    expect = np.sum([p.hist_raw.astype(np.int64) for p in parts], axis=0)
    np.testing.assert_array_equal(total.hist_raw, expect)
    np.testing.assert_array_equal(grouped.hist_raw, expect)
    assert total.hist_raw.dtype == np.uint32 and total.n_shots == 50


def test_counts_widen_before_uint32_could_overflow():
    rng = np.random.default_rng(8)
    a, b = _acc(rng, 2 ** 31), _acc(rng, 2 ** 31)
    a.hist_raw[0, 0] = b.hist_raw[0, 0] = 2 ** 31
    s = a + b
    assert s.hist_raw.dtype == np.int64 and s.hist_raw[0, 0] == 2 ** 32


class _NowClient:
    """Stands in for a Dask client: submit runs at once."""

    class _F:
        def __init__(self, v):
            self.v = v

        def result(self):
            return self.v

    def submit(self, fn, *args, pure=False):
        return self._F(fn(*[a.v for a in args]))


def test_tree_sum_equals_the_serial_sum():
    from mems_stereo.pipeline.dask_reduce import tree_sum

    rng = np.random.default_rng(9)
    parts = [_acc(rng, 10, 0.5) for _ in range(11)]
    c = _NowClient()
    t = tree_sum(c, [c._F(p) for p in parts], fan_in=3).result()
    np.testing.assert_array_equal(t.hist_angle, sum_accumulations(parts).hist_angle)
    assert t.n_shots == 110


def test_interval_tables_are_not_shared_between_calls():
    s = burkard2022()
    a, b = interval_table(s), interval_table(s)
    assert a is not b
    a.ensure([10, 11])
    assert not b.filled.any()


def test_rows_computed_in_blocks_equal_rows_filled_one_by_one():
    s = burkard2022()
    t1, t2 = IntervalTable(s), IntervalTable(s)
    rows = np.array([0, 5, 300, 301, 4570, 9000, 9139])
    t1.ensure(rows)
    for r in rows[::-1]:
        t2.ensure([r])
    np.testing.assert_array_equal(t1.lo[rows], t2.lo[rows])
    np.testing.assert_array_equal(t1.hi[rows], t2.hi[rows])
    lo, hi = t1.compute_rows(rows)
    np.testing.assert_array_equal(lo, t1.lo[rows])
    np.testing.assert_array_equal(hi, t1.hi[rows])


def test_disk_cache_gives_the_rows_back_bit_for_bit(tmp_path, monkeypatch):
    monkeypatch.setenv("MEMS_STEREO_CACHE", str(tmp_path))
    s = burkard2022()
    t = IntervalTable.for_settings(s, Settings())
    assert t.load_cache() == 0
    rows = np.arange(4000, 4300)
    t.ensure(rows)
    assert t.save_cache() and not t.save_cache()  # nothing new the second time
    u = IntervalTable.for_settings(s, Settings())
    assert u.load_cache() == rows.size
    np.testing.assert_array_equal(u.filled, t.filled)
    np.testing.assert_array_equal(u.lo, t.lo)
    np.testing.assert_array_equal(u.hi, t.hi)
    # other settings: another table, nothing from the cache
    assert IntervalTable.for_settings(s, Settings(confidence=0.99)).load_cache() == 0
    assert IntervalTable.for_settings(s, Settings(min_range=1.0)).load_cache() == 0
    # an unreadable file is ignored
    for f in tmp_path.glob("intervals-*.npz"):
        f.write_bytes(b"not a table")
    assert IntervalTable.for_settings(s, Settings()).load_cache() == 0


def test_disk_cache_can_be_switched_off(tmp_path, monkeypatch):
    monkeypatch.setenv("MEMS_STEREO_CACHE", "off")
    t = IntervalTable.for_settings(burkard2022(), Settings())
    t.ensure([100])
    assert not t.save_cache() and t.load_cache() == 0


def test_a_run_computes_each_table_row_once(tmp_path, monkeypatch):
    monkeypatch.setenv("MEMS_STEREO_CACHE", "off")
    from mems_stereo.pipeline.run import process_recording

    seen = []
    orig = IntervalTable.compute_rows

    def counting(self, rows):
        seen.extend(np.asarray(rows).tolist())
        return orig(self, rows)

    monkeypatch.setattr(IntervalTable, "compute_rows", counting)
    res = process_recording(SAMPLES / "room.h5")
    assert len(seen) == len(set(seen)) > 0
    assert res.counts["points"] > 0


def test_process_result_travels_compactly_and_exactly():
    from mems_stereo.pipeline.run import process_recording

    r = process_recording(SAMPLES / "room.h5")
    blob = pickle.dumps(r)
    q = pickle.loads(blob)
    assert list(q.histograms) == list(r.histograms)
    for k in r.histograms:
        assert q.histograms[k].dtype == r.histograms[k].dtype
        np.testing.assert_array_equal(q.histograms[k], r.histograms[k])
    assert len(blob) < sum(h.nbytes for h in r.histograms.values()) / 4


def test_chunked_range_with_angle_offset_equals_the_whole(tmp_path):
    from mems_stereo.io.recording import read_header
    from mems_stereo.pipeline.angles import shot_angles

    h = read_header(SAMPLES / "room.h5")
    th, va = shot_angles(h, h.system)
    st = Settings(chunk_shots=97)
    t = IntervalTable.for_settings(h.system, st)
    whole = accumulate_range(SAMPLES / "room.h5", h.system, ShotRange(th, va), st, table=t)
    parts = [accumulate_range(SAMPLES / "room.h5", h.system, ShotRange(th[a:b], va[a:b], a, b, a),
                              st, table=t) for a, b in ((0, 300), (300, 800))]
    s = sum_accumulations(parts)
    for k in ("hist_raw", "hist_signal", "hist_angle", "n_per_step"):
        np.testing.assert_array_equal(getattr(s, k), getattr(whole, k))
    np.testing.assert_array_equal(whole.n_per_step, t.shots_per_step(th, va))


@pytest.mark.parametrize("raw16_shots", [1 << 16, 250, 50])
def test_compiled_range_counts_raw_codes_in_uint16_between_flushes(monkeypatch, raw16_shots):
    """accumulate_range's compiled path counts raw codes into one uint16 table added to
    the range's counts every RAW16_SHOTS shots (250: flushed every 2-3 chunks of 97;
    50: chunks too large for it, counted straight into the range's table), with its
    signal keys through one reused buffer: the same counts as the NumPy path."""
    import mems_stereo.pipeline.classify_kernel as classify_kernel
    import mems_stereo.pipeline.pass1 as pass1
    from mems_stereo.io.recording import read_header
    from mems_stereo.pipeline.angles import shot_angles
    from mems_stereo.pipeline.signal_store import SignalStore

    path = SAMPLES / "floodlight.h5"
    h = read_header(path)
    th, va = shot_angles(h, h.system)
    st = Settings(chunk_shots=97)
    t = IntervalTable.for_settings(h.system, st)
    monkeypatch.setattr(pass1, "RAW16_SHOTS", raw16_shots)
    monkeypatch.setattr(classify_kernel, "RAW16_SHOTS", raw16_shots)
    out = []
    for slots in (0, 1 << 40):  # compiled, then NumPy
        monkeypatch.setattr(pass1, "COMPILE_SLOTS", slots)
        with SignalStore() as store:
            acc = accumulate_range(path, h.system, ShotRange(th, va), st, table=t,
                                   signal_store=store)
            keys = np.concatenate(list(store.blocks())) if store.complete else None
        out.append((acc, keys))
    (a, keys), (b, _) = out
    assert a.hist_raw.dtype == np.uint32 and a.hist_raw[:, 1:].sum() > 0
    for k in ("hist_raw", "hist_signal", "hist_angle", "n_per_step"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
    # the keys: one per signal count, each the (pixel, step, code) it was counted at
    assert keys.size == int(b.hist_signal[:, 1:].sum())
    p, j, c = classify_kernel.decode_signal_keys(keys, t.n_steps, h.system.tdc.n_bins + 1)
    assert j.max() < t.n_steps
    per_pixel_code = np.bincount(p * (h.system.tdc.n_bins + 1) + c,
                                 minlength=b.hist_signal.size).reshape(b.hist_signal.shape)
    np.testing.assert_array_equal(per_pixel_code, b.hist_signal)


def _random_detection_args(system, rng, n, n_steps):
    """detection_points' positional arguments for n random detections over n_steps
    scan-angle steps (steps, rows, columns, codes, step angles in rad)."""
    theta = rng.uniform(-0.35, 0.35, n_steps)
    return (rng.integers(0, n_steps, n), rng.integers(0, system.receiver.height, n),
            rng.integers(0, system.receiver.width, n), rng.uniform(0.5, system.tdc.n_bins, n),
            theta)


@pytest.mark.parametrize("seed", [0, 1])
def test_shared_evaluations_give_the_reference_detection_points_bit_for_bit(seed):
    """detection_points evaluates each geometry variant once; the reference propagates
    the three estimators one after the other: every field equal, NaN rows included."""
    from mems_stereo.pipeline.detections import _detection_points_reference, detection_points

    s = burkard2022()
    args = _random_detection_args(s, np.random.default_rng(seed), 3000, 200)
    a = detection_points(s, *args)
    b = _detection_points_reference(s, *args)
    assert 0.05 < a.ok.mean() < 0.95  # both finite and degenerate rows are compared
    for f in ("stereo", "cov_stereo", "tof", "cov_tof", "fused", "cov_fused", "weight_stereo",
              "ok", "dtof_dL"):
        assert np.array_equal(getattr(a, f), getattr(b, f), equal_nan=True), f


@pytest.mark.parametrize("seed", [2, 3])
def test_compiled_covariances_and_fused_only_points_are_the_same_bits(monkeypatch, seed):
    """_cov compiled (numba loaded, at least COMPILED_ROWS rows) equals its NumPy
    form; detection_points(fused_only=True) equals the full result's fused fields; the
    accumulator's fused ranges for the inlier margins equal those of its _points."""
    pytest.importorskip("numba")
    import mems_stereo.pipeline.detections as det
    from mems_stereo.pipeline.fusion_inputs import FusionPeaks
    from mems_stereo.pipeline.peak_accumulator import PeakAccumulator

    s = burkard2022()
    rng = np.random.default_rng(seed)
    n = 6000
    args = _random_detection_args(s, rng, n, 300)
    theta = args[4]
    args[3][::4] = rng.uniform(0.5, 3.0, n // 4)  # a quarter below 2|b| of path length
    # a second set in runs of equal (pixel, step), several codes each, as the fusion's
    # entries come: the kernel reads each run's stereo geometry by its run index
    first = rng.integers(0, n, n // 8)
    rep = np.sort(np.repeat(first, 8))
    runs = tuple(a[rep] for a in args[:3]) + (args[3][rng.permutation(n)], theta)
    fields = ("stereo", "cov_stereo", "tof", "cov_tof", "fused", "cov_fused",
              "weight_stereo", "ok", "dtof_dL")
    assert det._compiled_cov() is not None and det.compiled_entries() is not None
    assert n >= det.COMPILED_ROWS
    for args_ in (args, runs):
        a = det.detection_points(s, *args_)
        x, C, ok = det.detection_points(s, *args_, fused_only=True)
        monkeypatch.setattr(det, "COMPILED_ROWS", 10 ** 9)  # NumPy
        b = det.detection_points(s, *args_)
        x1, C1, ok1 = det.detection_points(s, *args_, fused_only=True)
        monkeypatch.setattr(det, "COMPILED_ROWS", 4096)
        assert 0.05 < a.ok.mean() < 0.95  # NaN rows too
        linear = (path_length_from_codes(args_[3], s.tdc, s.speed_of_light)
                  < 2 * np.linalg.norm(s.scanner.position))  # the ToF's linear part
        assert np.sum(linear & a.ok) > 200
        for f in fields:
            assert np.array_equal(getattr(a, f), getattr(b, f), equal_nan=True), f
        assert np.array_equal(x, a.fused, equal_nan=True)
        assert np.array_equal(C, a.cov_fused, equal_nan=True)
        assert np.array_equal(ok, a.ok)
        for u, v in ((x, x1), (C, C1), (ok, ok1)):
            assert np.array_equal(u, v, equal_nan=True)
    Q = 40
    acc = PeakAccumulator(s, FusionPeaks(rng.integers(0, s.receiver.height, Q),
                                         rng.integers(0, s.receiver.width, Q),
                                         rng.integers(1, 200, Q)))
    pk = rng.integers(0, Q, n)
    code = rng.uniform(0.5, s.tdc.n_bins, n)
    th = theta[rng.integers(0, 300, n)]
    e0 = acc.entry_points(np.arange(n), pk, code, th, None)
    e1 = acc.fused_ranges(pk, code, th)
    p0, r0, sr0, ok0 = e0.peak, e0.r, e0.sigma_r, e0.ok
    p1, r1, sr1, ok1 = e1.peak, e1.r, e1.sigma_r, e1.ok
    assert np.array_equal(p0, p1) and np.array_equal(ok0, ok1) and 0.05 < ok0.mean() < 1
    assert np.array_equal(r0, r1, equal_nan=True) and np.array_equal(sr0, sr1, equal_nan=True)


@pytest.mark.parametrize("name", ["room.h5", "floodlight.h5"])
def test_peak_detector_in_blocks_of_pixels_equals_the_whole(name):
    """The peak detector's per-pixel stage over random blocks of pixels, the neighbour
    support on the joined few numbers, each block's peaks joined: find_peaks' peaks,
    candidates (with their background rows) and rates, bit for bit."""
    from mems_stereo.io.recording import read_header
    from mems_stereo.pipeline.angles import shot_angles
    from mems_stereo.pipeline.peak_support import SupportInputs
    from mems_stereo.pipeline.peak_table import PEAK_ARRAYS
    from mems_stereo.pipeline.peaks import (
        concat_peaks,
        find_peaks,
        peak_scores,
        peaks_of_scores,
    )

    h = read_header(SAMPLES / name)
    s, st = h.system, Settings()
    th, va = shot_angles(h, s)
    t = IntervalTable.for_settings(s, st)
    acc = accumulate_range(SAMPLES / name, s, ShotRange(th, va), st, table=t)
    P, nb = s.receiver.width * s.receiver.height, s.tdc.n_bins
    sig = acc.hist_signal[:, 1:].astype(np.int64)
    noise = acc.hist_raw[:, 1:].astype(np.int64) - sig
    H, W = s.receiver.height, s.receiver.width
    whole, rate = find_peaks(s, sig.reshape(H, W, nb), noise.reshape(H, W, nb), th, va, st,
                             signal_angle=acc.hist_angle, table=t, n_per_step=acc.n_per_step)
    assert len(whole) > 10
    rng = np.random.default_rng(1417)
    for _ in range(2):
        edges = np.unique(np.concatenate([[0, P], rng.integers(1, P, 4)]))
        scores = [peak_scores(s, sig[a:b], noise[a:b], acc.hist_angle[a:b], acc.n_per_step, t,
                              st, np.arange(a, b)) for a, b in zip(edges[:-1], edges[1:])]
        keep = SupportInputs.concat(c.support_inputs() for c in scores).supported(W)
        got = concat_peaks([peaks_of_scores(s, c, keep[c.pixels], acc.n_per_step, t, st)
                            for c in scores])
        assert np.array_equal(np.concatenate([c.rate for c in scores]), rate.ravel(),
                              equal_nan=True)
        for a, b in ((whole, got), (whole.candidates, got.candidates)):
            for k in (*PEAK_ARRAYS, "background_by_step"):
                u, v = getattr(a, k), getattr(b, k)
                if k == "background_by_step":
                    assert u.shape == v.shape
                    for f in ("indptr", "indices", "data"):
                        assert np.array_equal(getattr(u, f), getattr(v, f)), f
                else:
                    assert u.dtype == v.dtype and np.array_equal(u, v, equal_nan=True), k
        for k in ("n_windows", "local_lo", "local_hi", "width"):
            assert np.array_equal(getattr(whole.candidates, k), getattr(got.candidates, k)), k


def test_stereo_cache_gives_the_same_detection_points():
    """detection_points with a StereoCache (runs met again gathered from it, new ones
    added) equals it without, every field, over calls with overlapping runs, fused-only
    calls, and runs it does not keep (non-integer pixel coordinates)."""
    from mems_stereo.pipeline.detections import StereoCache, detection_points

    s = burkard2022()
    rng = np.random.default_rng(1421)
    cache = StereoCache()
    theta = rng.uniform(-0.35, 0.35, 60)  # few angles: later calls meet cached runs
    for call in range(6):
        R = int(rng.integers(1, 300))
        length = rng.integers(1, 12, R)
        shot = np.repeat(rng.integers(0, 60, R), length)
        row = np.repeat(rng.integers(0, s.receiver.height, R), length)
        col = np.repeat(rng.integers(0, 20, R), length).astype(np.float64)
        if call == 4:
            col = col + 0.25  # not kept: computed, the same values
        code = rng.uniform(0.5, s.tdc.n_bins, shot.size)
        a = detection_points(s, shot, row, col, code, theta)
        if call % 2:
            x, C, ok = detection_points(s, shot, row, col, code, theta, fused_only=True,
                                        stereo_cache=cache)
            assert np.array_equal(x, a.fused, equal_nan=True)
            assert np.array_equal(C, a.cov_fused, equal_nan=True) and np.array_equal(ok, a.ok)
            continue
        b = detection_points(s, shot, row, col, code, theta, stereo_cache=cache)
        for f in ("stereo", "cov_stereo", "tof", "cov_tof", "fused", "cov_fused",
                  "weight_stereo", "ok", "dtof_dL"):
            assert np.array_equal(getattr(a, f), getattr(b, f), equal_nan=True), f
    assert 0 < cache.keys.size < 60 * 20 * s.receiver.height
    assert np.all(np.diff(cache.keys.real) >= 0)


def test_points_in_entry_blocks_equal_points_at_once(monkeypatch):
    """points_from_counts in blocks of 97 entries (sub-pass 1 from the fused ranges
    alone, sub-pass 2 for the inliers only) gives the cloud of one block, bit for bit."""
    import mems_stereo.pipeline.fusion as fusion
    from mems_stereo.pipeline.run import process_recording

    clouds = []
    for block in (1 << 17, 97):  # one block; blocks of 97
        monkeypatch.setattr(fusion, "ENTRY_BLOCK", block)
        clouds.append(process_recording(SAMPLES / "room.h5").cloud)
    a = clouds[0]
    assert len(a) > 10
    for b in clouds[1:]:
        assert np.array_equal(a.points, b.points)
        assert a.attributes.keys() == b.attributes.keys()
        for k in a.attributes:
            assert np.array_equal(a[k], b[k], equal_nan=True), k


def test_detection_points_in_runs_equal_reference():
    """detection_points on entries in runs of equal (u, v, θ) with different codes (the
    fusion's (peak, step) groups: the stereo geometry evaluated once per run) equals
    the reference, NaN rows included."""
    from mems_stereo.model.system import burkard2022
    from mems_stereo.pipeline.detections import (
        _detection_points_reference,
        _runs,
        detection_points,
    )

    s = burkard2022()
    rng = np.random.default_rng(1416)
    for _ in range(5):
        R = int(rng.integers(1, 400))
        length = rng.integers(1, 30, R)
        shot = np.repeat(rng.integers(0, 200, R), length)
        row = np.repeat(rng.integers(0, s.receiver.height, R), length)
        col = np.repeat(rng.integers(0, s.receiver.width, R), length)
        code = rng.uniform(0.5, s.tdc.n_bins, shot.size)
        theta = rng.uniform(-0.35, 0.35, 200)
        first, run = _runs(col.astype(float), row.astype(float), theta[shot])
        assert run is not None and first.size < shot.size
        a = detection_points(s, shot, row, col, code, theta)
        b = _detection_points_reference(s, shot, row, col, code, theta)
        for f in ("stereo", "cov_stereo", "tof", "cov_tof", "fused", "cov_fused",
                  "weight_stereo", "ok", "dtof_dL"):
            assert np.array_equal(getattr(a, f), getattr(b, f), equal_nan=True), f


def test_background_by_step_is_stored_over_the_counted_steps_only():
    """Peaks.background_by_step: the rows of the (P, S) expected background over each
    peak's steps step_lo..step_hi, sparse, zero elsewhere (checked densely)."""
    from mems_stereo.pipeline.peak_table import window_rows

    rng = np.random.default_rng(5)
    B = rng.random((12, 40))
    q, lo, hi = np.array([3, 7, 1, 0]), np.array([5, 0, 39, 10]), np.array([9, 39, 39, 9])
    got = window_rows(B, q, lo, hi)
    want = np.zeros((4, 40))
    for i in range(4):
        want[i, lo[i]:hi[i] + 1] = B[q[i], lo[i]:hi[i] + 1]
    assert got.nnz == 5 + 40 + 1
    assert np.array_equal(got.toarray(), want)


def test_dot3_equals_the_row_sum():
    """detections._dot3 (d·p added left to right) equals np.sum(d * p, axis=-1), bit for
    bit, on random rows and magnitudes (the time-of-flight geometry uses it)."""
    from mems_stereo.pipeline.detections import _dot3

    rng = np.random.default_rng(1420)
    for _ in range(5):
        d = rng.normal(size=(20000, 3)) * 10.0 ** rng.uniform(-8, 8, (20000, 3))
        p = rng.normal(size=3) * 10.0 ** rng.uniform(-3, 3, 3)
        assert np.array_equal(_dot3(d, p).view(np.int64), np.sum(d * p, axis=-1).view(np.int64))


def test_estimate_sums_compiled_equal_numpy(monkeypatch):
    """EstimateSums.add with its products added in one compiled pass equals the NumPy
    form (products, then add_rows), bit for bit, on random entries, repeated."""
    pytest.importorskip("numba")
    import mems_stereo.pipeline.sums as sums

    out = []
    for rows in (0, 10 ** 9):  # compiled; NumPy
        monkeypatch.setattr(sums, "COMPILED_ROWS", rows)
        r = np.random.default_rng(1422)
        e = sums.EstimateSums.zeros(30, timed=True)
        for _ in range(3):
            n = int(r.integers(1, 3000))
            q = r.integers(0, 30, n)
            m = r.normal(size=n) * 10.0 ** r.uniform(-3, 3, n)
            x = r.normal(size=(n, 3)) * 10.0 ** r.uniform(-6, 6, (n, 3))
            C = r.normal(size=(n, 3, 3)) * 10.0 ** r.uniform(-9, 3, (n, 3, 3))
            g = r.normal(size=(n, 3))
            e.add(q, x, C, m, g)
        out.append(e)
    assert sums._compiled("scaled") is not None
    for k in ("W", "X", "C", "D", "G"):
        assert np.array_equal(getattr(out[0], k), getattr(out[1], k)), k


def test_moving_sum_equals_the_padded_running_sum():
    """moving_sum (running sum written in place) against the running sum of the
    zero-padded array, bit for bit, over shapes, widths and magnitudes."""
    from mems_stereo.physics.background import moving_sum

    rng = np.random.default_rng(1418)
    for shape in ((192, 913), (7,), (3, 4), (2, 0), (2, 3, 50)):
        for width in (1, 3, 11, 101):
            h = rng.poisson(3.0, shape) * 10.0 ** rng.uniform(-6, 6, shape)
            half = width // 2
            pad = [(0, 0)] * (h.ndim - 1) + [(half + 1, half)]
            c = np.cumsum(np.pad(h, pad), axis=-1)
            ref = c[..., width:] - c[..., :-width]
            got = moving_sum(h, width)
            assert got.shape == ref.shape == h.shape
            assert np.array_equal(got.view(np.int64), ref.view(np.int64))


@pytest.mark.parametrize("form", ["numpy", "compiled"])
def test_add_rows_equals_add_at(monkeypatch, form):
    """sums.add_rows (one bincount per column, or the compiled loop where numba is
    loaded) against np.add.at, bit for bit, over random shapes, signs and magnitudes,
    onto non-zero sums, repeated."""
    import mems_stereo.pipeline.sums as sums
    from mems_stereo.pipeline.sums import add_rows, add_rows_gathered

    if form == "compiled":
        pytest.importorskip("numba")
        monkeypatch.setattr(sums, "COMPILED_ROWS", 0)
        assert sums._compiled("rows") is not None and sums._compiled("gathered") is not None
    else:
        monkeypatch.setattr(sums, "COMPILED_ROWS", 10 ** 9)

    rng = np.random.default_rng(1415)
    for _ in range(40):
        Q = int(rng.integers(1, 50))
        shape = [(), (3,), (3, 3), (5,)][int(rng.integers(0, 4))]
        A = np.zeros((Q,) + shape)
        B = A.copy()
        for _ in range(3):
            N = int(rng.integers(0, 2000))
            q = rng.integers(0, Q, N)
            V = rng.normal(size=(N,) + shape) * 10.0 ** rng.uniform(-12, 6, (N,) + shape)
            np.add.at(A, q, V)
            add_rows(B, q, V)
        assert np.array_equal(A, B)
        assert not np.any(np.signbit(B) & (B == 0))
    for _ in range(20):  # add_rows_gathered: rows of a table gathered per entry, scaled
        Q, R, J, N = (int(rng.integers(1, 40)), int(rng.integers(1, 300)), 41,
                      int(rng.integers(0, 3000)))
        A = rng.normal(size=(Q, J))
        B = A.copy()
        q, run, m = rng.integers(0, Q, N), rng.integers(0, R, N), rng.normal(size=N)
        rows = rng.normal(size=(R, J)) * 10.0 ** rng.uniform(-8, 4, (R, J))
        np.add.at(A, q, rows[run] * m[:, None])
        add_rows_gathered(B, q, rows, run, m)
        assert np.array_equal(A, B)


def test_is_in_equals_numpy_isin():
    """background_entries.is_in (binary search into sorted values) against np.isin: sorted and
    unsorted, empty, repeated and out-of-range values."""
    from mems_stereo.pipeline.background_entries import is_in

    rng = np.random.default_rng(16)
    for _ in range(200):
        b = rng.integers(-5, 60, int(rng.integers(0, 40)))
        if rng.random() < 0.7:
            b = np.sort(b)
        a = rng.integers(-10, 70, int(rng.integers(0, 50)))
        assert np.array_equal(is_in(a, b), np.isin(a, b))
