"""The frame path's compiled forms (issue 31): the matched filter's search of a candidate
in one call (:mod:`mems_stereo.pipeline.matched_best_kernel`), its window sums over
steps a frame did not visit, and the first-photon likelihood's firing kernels
(:func:`mems_stereo.physics.first_photon_kernel.firing_kernels`), each against its
NumPy form."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import pdtrc
from test_matched_kernels import _candidate_grid

import mems_stereo.pipeline.matched_boxes as mb
from mems_stereo.physics import first_photon as fp

numba = pytest.importorskip("numba")


def _window(grid, box_s, box_c, min_counts):
    """``window_kernel_py`` (compiled) over the whole grid, one window, every box."""
    from mems_stereo.pipeline.matched_grid import EVERY, WINDOW_HELPERS, window_kernel_py
    from mems_stereo.util.lazy_numba import compiled_kernel

    q = np.array([0, grid.n_steps, 0, grid.n_cell, 1, 1, box_s, box_c, 1, 1, EVERY, 0,
                  grid.c_lo, grid.cell, grid.n_cell, 0], np.int64)
    kernel = compiled_kernel(window_kernel_py, WINDOW_HELPERS)
    return kernel(grid.ds, grid.dc, np.asarray(grid.cnt, np.float64), grid.lo, grid.hi,
                  grid.nps, grid.powers, q, float(min_counts))


def test_window_sums_over_unvisited_steps_equal_numpy(monkeypatch):
    """A grid whose steps are mostly unvisited (a short frame's): the kernel's box sums,
    whose rows without a visited step it writes as 0 without summing, equal NumPy's
    running-sum boxes bit for bit where a box is whole in the steps, and each box's
    count equals its counts summed by window (independent)."""
    from mems_stereo.pipeline.matched_grid import CompiledGrid

    rng = np.random.default_rng(31)
    idle = 0
    for n, nc, visited, min_counts in [(300, 40, 0.03, 3), (120, 12, 0.1, 0), (60, 30, 1.0, 2)]:
        g = _candidate_grid(rng, CompiledGrid, n, nc, visited)
        h, w = 21, 9
        sums, flat = _window(g, h, w, min_counts)
        D, B = g.counts(0, n, 0, nc), g.background(0, n, 0, nc)
        with monkeypatch.context() as mp:
            mp.setattr(mb, "compiled_kernel", lambda *a, **k: None)
            N_box, B_box, valid = mb.valid_boxes(D, B, h, w, min_counts)
        rows = slice(h // 2, n - h // 2)
        assert np.array_equal(sums[0, rows].view(np.int64), N_box[rows].view(np.int64))
        full = sums[0, rows] >= min_counts
        assert np.array_equal(sums[1, rows][full], B_box[rows][full])
        assert np.all(np.isin(flat, valid))  # (the screen keeps a subset)
        window = np.lib.stride_tricks.sliding_window_view(
            np.pad(D, ((h // 2, h // 2), (w // 2, w // 2))), (h, w)).sum(axis=(2, 3))
        assert np.array_equal(sums[0, rows], window[rows])
        idle += int(np.sum(np.all(sums[0, rows] == 0, axis=1)))
    assert idle > 50  # rows of boxes without a visited step were met


def _boxes(rng, n, m, tail_one=False):
    """Box sums (n, m) of counts and background; ``tail_one``: backgrounds so large
    that every box's Poisson tail is 1."""
    N = rng.integers(1, 12, (n, m)).astype(np.float64)
    B = rng.uniform(0.2, 6.0, (n, m)) + (1e4 if tail_one else 0.0)
    return N, B


def _reference(wins):
    """``BoxGrid.best``'s choice over windows, each by ``pick_box`` (NumPy)."""
    out = None
    for (N, B, flat, j0, k0) in wins:
        r = mb.pick_box(N, B, flat)
        if r is not None and (out is None or r.p < out.p):
            out = mb.BestBox(r.p, r.j + j0, r.k + k0, r.count, r.background)
    return out


@pytest.mark.parametrize("case", ["plain", "first_all_one", "every_one", "nan_first",
                                  "nan_later", "empty_window"])
def test_choose_box_is_best_over_pick_box(case):
    """The one-call search's choice from its windows' boxes: the same box and p as
    ``pick_box`` per window then ``best``'s first-smallest over windows, in the cases
    where pick_box falls back (every tail 1: box (0, 0); a NaN tail)."""
    from mems_stereo.pipeline.matched_best_kernel import choose_box

    rng = np.random.default_rng(len(case))
    wins = []
    for w in range(3):
        N, B = _boxes(rng, 6, 5, tail_one=(case == "every_one"
                                           or (case == "first_all_one" and w == 0)))
        flat = np.flatnonzero(rng.random(N.size) < 0.5)
        if case == "nan_first" and w == 0 or case == "nan_later" and w == 2:
            B.ravel()[flat[1]] = np.nan
        if case == "empty_window" and w == 1:
            flat = flat[:0]
        wins.append((N, B, flat, int(rng.integers(0, 50)), int(rng.integers(0, 9))))
    rows = np.concatenate([np.column_stack([np.full(f.size, w), j0 + f // N.shape[1],
                                            k0 + f % N.shape[1], N.ravel()[f], B.ravel()[f]])
                           for w, (N, B, f, j0, k0) in enumerate(wins)])
    heads = np.array([[j0, k0, N[0, 0], B[0, 0]] for N, B, _, j0, k0 in wins])
    got, want = choose_box(rows, heads), _reference(wins)
    assert (got.j, got.k, got.count) == (want.j, want.k, want.count)
    assert np.array_equal([got.p, got.background], [want.p, want.background], equal_nan=True)
    # independent: away from the fallbacks the box holds the smallest tail of all
    if case in ("plain", "first_all_one", "empty_window"):
        assert got.p == pdtrc(rows[:, 3] - 1, rows[:, 4]).min() < 1.0
    assert choose_box(rows[:0], heads) is None


def test_firing_kernels_equal_numpy(monkeypatch):
    """The first-photon likelihood's compiled firing sums and log-odds against NumPy's:
    within 1e-13 relative (the same C-library ``expm1``/``log``/``log1p`` where NumPy has
    no vectorised float64 forms of them, as on this project's machines: then the same
    bits), and against the log-probability of no firing written directly."""
    rng = np.random.default_rng(7)
    f = np.where(rng.random(3000) < 0.3, 0.0, rng.random(3000) ** 3)
    row = np.sort(rng.integers(0, 25, f.size))
    n = rng.integers(1, 9, f.size).astype(np.float64)
    assert fp.firing_kernels() is not None
    fast = fp.band_log_miss_rows(25, row, n, f), fp.detection_log_odds(f.reshape(30, 100))
    monkeypatch.setattr(fp, "firing_kernels", lambda: None)
    ref = fp.band_log_miss_rows(25, row, n, f), fp.detection_log_odds(f.reshape(30, 100))
    for x, y in zip(fast, ref):
        assert x.shape == y.shape
        np.testing.assert_allclose(x, y, rtol=1e-13, atol=0)
    e = fp.OUTLIER_PROBABILITY
    p = np.minimum(e + (1 - e) * (1 - np.exp(-fp.MU_GRID * f[:, None])), 1 - 1e-12)
    direct = np.zeros((25, fp.MU_GRID.size))
    for r in range(25):
        direct[r] = np.sum(n[row == r, None] * np.log(1 - p[row == r]), axis=0)
    np.testing.assert_allclose(fast[0], direct, rtol=1e-9)
    np.testing.assert_allclose(fast[1].reshape(-1, fp.MU_GRID.size), np.log(p / (1 - p)),
                               rtol=1e-9, atol=1e-12)


def test_candidate_intervals_kernel_equals_numpy():
    """A candidate's accepted codes over a range of steps and their figures (steps that
    accept a code, lowest and highest code, area, widest): the compiled loop against
    NumPy's, and against the figures written out step by step (integers: equal)."""
    from types import SimpleNamespace

    from mems_stereo.pipeline.matched import _CandidateSearch

    rng = np.random.default_rng(11)
    S, P = 700, 9
    lo_t = rng.integers(1, 900, (S, P)).astype(np.uint16)
    hi_t = (lo_t.astype(np.int64) + rng.integers(-60, 300, (S, P))).clip(0, 1023)
    nps = np.where(rng.random(S) < 0.6, rng.integers(1, 5, S), 0).astype(np.float64)
    for a, b, pix in [(0, S - 1, 3), (100, 180, 0), (650, 699, 8), (5, 5, 2), (20, 24, 1)]:
        nps_ab = nps.copy()
        if b - a < 6:
            nps_ab[a:b + 1] = 0.0  # no valid shots: nothing accepted
        out = []
        for compiled in (True, False):
            me = SimpleNamespace(n_per_step=nps_ab, filled=True, pix=np.full(10, pix),
                                 compiled=compiled,
                                 table=SimpleNamespace(lo=lo_t, hi=hi_t.astype(np.uint16)))
            out.append(_CandidateSearch.intervals(me, 0, a, b))
        (lo, hi, acc), (lo_n, hi_n, acc_n) = out
        assert np.array_equal(lo, lo_n) and np.array_equal(hi, hi_n)
        assert np.array_equal(acc, acc_n) and lo.dtype == hi.dtype == np.int64
        steps = [j for j in range(a, b + 1) if nps_ab[j] > 0 and lo_t[j, pix] <= hi_t[j, pix]]
        widths = [int(hi_t[j, pix]) - int(lo_t[j, pix]) + 1 for j in steps]
        assert acc[0] == len(steps) and acc[3] == sum(widths)
        if steps:
            assert (acc[1], acc[2], acc[4]) == (min(int(lo_t[j, pix]) for j in steps),
                                                max(int(hi_t[j, pix]) for j in steps),
                                                max(widths))
