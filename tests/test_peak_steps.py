"""The peak search on the visited angle steps alone (:mod:`mems_stereo.pipeline.step_windows`,
``background_rate_at_steps``) gives the bits of the whole-row forms: window sums over
all S steps, the expected background per step, the background rate from the acceptance
counts; compiled (numba loaded) and NumPy forms alike."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from mems_stereo.physics import background as bg
from mems_stereo.pipeline import step_windows as sw
from mems_stereo.pipeline.histograms import moving_average, moving_average_argmax
from mems_stereo.pipeline.peak_table import window_rows
from mems_stereo.pipeline.peaks import excess_band

SAMPLES = Path(__file__).resolve().parents[1] / "samples"


def _bits(a):
    return np.asarray(a, np.float64).view(np.int64)


def _visited(rng, S, U, P, scale):
    """A row set over S steps of which U are visited: counts (integers) and a
    non-integer background there, zero elsewhere; rows dense and at the steps."""
    steps = np.sort(rng.choice(S, U, replace=False)).astype(np.int64)
    counts = rng.poisson(scale, (P, U)).astype(np.float64)
    counts[: P // 3, U // 2:U // 2 + 5] += 9.0  # a cluster
    back = rng.random((P, U)) * scale * (rng.random((P, U)) < 0.8)
    dense_c, dense_b = np.zeros((P, S)), np.zeros((P, S))
    dense_c[:, steps], dense_b[:, steps] = counts, back
    return steps, counts, back, dense_c, dense_b


@pytest.mark.parametrize("numba_loaded", [True, False])
@pytest.mark.parametrize(("S", "U", "width"), [(700, 90, 21), (300, 280, 11), (50, 3, 51),
                                                (400, 0, 5), (9, 9, 3)])
def test_strongest_windows_on_visited_steps_equal_whole_rows(monkeypatch, numba_loaded, S, U,
                                                             width):
    """The strongest window from the visited steps' events equals argmax over all S
    positions of rint(moving_sum) − moving_sum (first of ties), and its sums, bit for bit;
    and independently the window count at j is the plain sum of the counts inside."""
    if numba_loaded:
        pytest.importorskip("numba")
    else:
        monkeypatch.delitem(sys.modules, "numba", raising=False)
    rng = np.random.default_rng(S + U)
    steps, counts, back, dc, db = _visited(rng, S, U, 12, 0.7)
    got = sw.strongest_windows(counts, back, steps, S, width)
    sw_ = np.rint(bg.moving_sum(dc, width))
    bw_ = bg.moving_sum(db, width)
    j = np.argmax(sw_ - bw_, axis=1)
    rows = np.arange(12)
    assert np.array_equal(got.j, j)
    assert np.array_equal(_bits(got.cnt), _bits(sw_[rows, j]))
    assert np.array_equal(_bits(got.mu), _bits(bw_[rows, j]))
    assert np.array_equal(got.n_positive, np.count_nonzero(db > 0, axis=1))
    h = width // 2
    for r in range(12):
        assert got.cnt[r] == dc[r, max(0, j[r] - h):j[r] + h + 1].sum()


@pytest.mark.parametrize("numba_loaded", [True, False])
def test_visited_excess_band_equals_the_dense_band(monkeypatch, numba_loaded):
    """visited_excess_band (compiled: walking out from j) equals excess_band of the rows
    laid out over all steps, for peaks at visited steps, between them and at the ends."""
    if numba_loaded:
        pytest.importorskip("numba")
    else:
        monkeypatch.delitem(sys.modules, "numba", raising=False)
    rng = np.random.default_rng(31)
    S, width = 600, 15
    steps, counts, back, dc, db = _visited(rng, S, 150, 20, 0.5)
    rows = np.array([0, 3, 5, 19, 7, 2])
    j = np.array([steps[75], 0, S - 1, steps[3] + 1, 300, steps[-1]])
    got = sw.visited_excess_band(counts, back, steps, S, width, rows, j)
    if got is None:
        assert not numba_loaded
        got = excess_band(sw.dense_rows(counts, steps, S, rows),
                          sw.dense_rows(back, steps, S, rows), width, j)
    want = excess_band(dc[rows], db[rows], width, j)
    assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
    # independently: the band holds j and, where the excess at j is positive, stays at
    # or above half of it, and just outside it falls below
    E = moving_average(dc[rows], width) - moving_average(db[rows], width)
    assert np.count_nonzero(E[np.arange(rows.size), j] > 0) >= 3
    for k in range(rows.size):
        lo, hi = got[0][k], got[1][k]
        assert lo <= j[k] <= hi
        thr = 0.5 * E[k, j[k]]
        if thr <= 0:
            continue
        assert np.all(E[k, lo:hi + 1] >= thr)
        assert lo == 0 or E[k, lo - 1] < thr
        assert hi == S - 1 or E[k, hi + 1] < thr


def test_visited_window_rows_equal_the_dense_rows():
    """The background rows stored at the visited steps alone are window_rows' matrix."""
    rng = np.random.default_rng(7)
    S = 80
    steps, _, back, _, db = _visited(rng, S, 30, 6, 1.0)
    q, lo, hi = np.array([3, 0, 5, 5]), np.array([10, 0, 79, 4]), np.array([40, 79, 79, 3])
    a, b = sw.visited_window_rows(back, steps, S, q, lo, hi), window_rows(db, q, lo, hi)
    assert a.shape == b.shape and np.array_equal(_bits(a.toarray()), _bits(b.toarray()))
    # stored: the visited steps of each row's columns (independently counted)
    want = [np.count_nonzero((steps >= lo[i]) & (steps <= hi[i])) for i in range(q.size)]
    assert np.array_equal(np.diff(a.indptr), want)
    assert set(a.indices.tolist()) <= set(steps.tolist())


@pytest.mark.parametrize("numba_loaded", [True, False])
def test_background_at_steps_equals_the_numpy_form(monkeypatch, numba_loaded):
    """The expected background from each pixel's distinct powers equals
    expected_background_at_steps (exp of every entry) bit for bit, including empty
    intervals, rates 0, NaN and inf; and independently a first-photon probability."""
    if numba_loaded:
        pytest.importorskip("numba")
    else:
        monkeypatch.delitem(sys.modules, "numba", raising=False)
    rng = np.random.default_rng(11)
    U, P, n_bins = 200, 9, 4096
    lo = np.repeat(rng.integers(1, 300, (U // 20, P)), 20, axis=0).astype(np.uint16)
    hi = (lo.astype(np.int64) + rng.integers(-5, 3000, (U, P))).clip(0, n_bins)
    hi = hi.astype(np.uint16)
    shots = rng.integers(1, 9, U)
    rate = np.array([1e5, 6e6, 0.0, np.nan, np.inf, 3e3, 1e8, 2e5, 7e5])
    bw = 65e-12
    got = sw.background_at_steps(lo, hi, shots, rate, bw)
    want = bg.expected_background_at_steps(lo, hi, shots, rate, bw)
    assert got.shape == (P, U) and np.array_equal(_bits(got), _bits(want))
    q = -np.expm1(-rate[1] * bw)
    u = int(np.argmax(lo[:, 1] <= hi[:, 1]))
    a, b = int(lo[u, 1]), int(hi[u, 1])
    assert got[1, u] == pytest.approx(shots[u] * ((1 - q) ** (a - 1) - (1 - q) ** b),
                                      rel=1e-9)


def test_background_rate_at_steps_equals_the_acceptance_route(monkeypatch):
    """background_rate_at_steps (acceptance counts and trial sums in one compiled pass)
    equals background_rate_from_noise with the acceptance counts A, bit for bit; input
    the reference refuses gives None (the caller then takes that route)."""
    pytest.importorskip("numba")
    rng = np.random.default_rng(12)
    U, P, n_bins = 120, 8, 700
    lo = rng.integers(1, 200, (U, P)).astype(np.uint16)
    hi = (lo + rng.integers(-3, 500, (U, P))).clip(0, n_bins).astype(np.uint16)
    shots = rng.integers(1, 6, U).astype(np.int64)
    n_valid = int(shots.sum())
    raw = rng.poisson(0.2, (P, n_bins))
    sig = rng.binomial(raw, 0.3)
    noise = (raw - sig).astype(np.int64)
    sig = sig.astype(np.int64)
    A = np.zeros((P, n_bins), np.int64)  # independent: code by code
    codes = np.arange(1, n_bins + 1)
    for p in range(P):
        inside = (codes[:, None] >= lo[:, p]) & (codes[:, None] <= hi[:, p])
        A[p] = inside @ shots
    bw = 65e-12
    monkeypatch.setattr(bg, "COMPILED_SUM_ENTRIES", 1)
    got = bg.background_rate_at_steps(noise, sig, lo, hi, shots, n_valid, bw)
    want = bg.background_rate_from_noise(noise, sig + noise, A, n_valid, bw)
    assert got is not None and np.array_equal(_bits(got), _bits(want))
    assert bg.background_rate_at_steps(noise, sig + n_valid, lo, hi, shots, n_valid,
                                       bw) is None  # more detections than shots


@pytest.mark.parametrize("numba_loaded", [True, False])
def test_moving_average_argmax_equals_numpy(monkeypatch, numba_loaded):
    if numba_loaded:
        pytest.importorskip("numba")
    else:
        monkeypatch.delitem(sys.modules, "numba", raising=False)
    rng = np.random.default_rng(13)
    h = rng.poisson(0.05, (40, 500)).astype(np.int64)
    h[5] = 0  # all equal: the first bin
    h[6, :3] = 4  # at the start, where the average divides by fewer bins
    for width in (1, 5, 9, 999):
        got = moving_average_argmax(h, width)
        assert np.array_equal(got, np.argmax(moving_average(h, width), axis=1))


def test_peak_search_compiled_equals_numpy_on_a_recording(monkeypatch):
    """find_peaks with numba loaded (the kernels on the visited steps) and without it
    (the NumPy forms): the same peaks, candidates (with their background rows) and rates."""
    pytest.importorskip("numba")
    from mems_stereo.io.recording import read_header
    from mems_stereo.pipeline.angles import shot_angles
    from mems_stereo.pipeline.intervals import IntervalTable
    from mems_stereo.pipeline.pass1 import accumulate_range
    from mems_stereo.pipeline.peak_table import PEAK_ARRAYS
    from mems_stereo.pipeline.peaks import find_peaks
    from mems_stereo.pipeline.settings import Settings
    from mems_stereo.pipeline.shot_range import ShotRange

    h = read_header(SAMPLES / "room.h5")
    s, st = h.system, Settings()
    th, va = shot_angles(h, s)
    t = IntervalTable.for_settings(s, st)
    acc = accumulate_range(SAMPLES / "room.h5", s, ShotRange(th, va), st, table=t)
    nb, H, W = s.tdc.n_bins, s.receiver.height, s.receiver.width
    sig = acc.hist_signal[:, 1:].astype(np.int64)
    noise = acc.hist_raw[:, 1:].astype(np.int64) - sig
    args = (s, sig.reshape(H, W, nb), noise.reshape(H, W, nb), th, va, st)
    kw = {"signal_angle": acc.hist_angle, "table": t, "n_per_step": acc.n_per_step}
    fast, rate_f = find_peaks(*args, **kw)
    with monkeypatch.context() as m:
        m.delitem(sys.modules, "numba")
        ref, rate_r = find_peaks(*args, **kw)
    assert len(ref) > 10 and np.array_equal(_bits(rate_f), _bits(rate_r))
    for a, b in ((ref, fast), (ref.candidates, fast.candidates)):
        for k in PEAK_ARRAYS:
            assert np.array_equal(getattr(a, k), getattr(b, k), equal_nan=True), k
        for f in ("indptr", "indices", "data"):
            assert np.array_equal(getattr(a.background_by_step, f),
                                  getattr(b.background_by_step, f)), f
    # the rows hold the expected background over the peak's steps, zero elsewhere
    dense = fast.background_by_step.toarray()
    for i in range(len(fast)):
        out = np.ones(dense.shape[1], bool)
        out[fast.step_lo[i]:fast.step_hi[i] + 1] = False
        assert not dense[i, out].any() and dense[i, ~out].sum() > 0


def test_range_mode_band_compiled_equals_numpy(monkeypatch):
    """RangeMode.finish with its band from the compiled pass equals the NumPy form bit
    for bit (coverage of random intervals, a row without detections, a NaN row); and
    independently the centre of one interval is the middle of its grid cells."""
    pytest.importorskip("numba")
    from mems_stereo.pipeline.sums import RangeMode

    rng = np.random.default_rng(17)
    rm = RangeMode(33)
    n = 400
    peak = rng.integers(0, 28, n)
    r = rng.uniform(0.5, 20.0, n)
    rm.add(peak, r, 0.02 * r, rng.uniform(-0.3, 2.0, n))
    rm.add(np.array([28]), np.array([3.0]), np.array([0.1]), np.array([1.0]))
    rm.cover[29, 100] = np.nan
    # (the compiled pass reads a row between its first and last nonzero entries:) a
    # row of negative weights only, one from the grid's first point, one to its end
    rm.add(np.array([30, 30]), np.array([2.0, 5.0]), np.array([0.1, 0.2]),
           np.array([-1.0, -0.5]))
    rm.add(np.array([31, 31]), np.array([0.0101, 0.5]), np.array([0.0001, 0.1]),
           np.array([1.0, 2.0]))
    rm.add(np.array([32]), np.array([900.0]), np.array([200.0]), np.array([1.0]))
    fast = rm.finish()
    with monkeypatch.context() as m:
        m.delitem(sys.modules, "numba")
        ref = rm.finish()
    for a, b in zip(fast, ref):
        assert np.array_equal(_bits(a), _bits(b))
    lo, hi = (np.floor((np.log(x) - rm.log_min) / rm.dlog) for x in (2.9, 3.1))
    r_lo, r_hi = (np.exp(rm.log_min + x * rm.dlog) for x in (lo, hi + 1))
    assert fast[0][28] == pytest.approx(0.5 * (r_lo + r_hi), rel=1e-12)
    assert np.isnan(fast[0][29]) and fast[1][29] == 0.0
