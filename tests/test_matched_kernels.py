"""The matched filter's box search, fast forms: the compiled box sums and background
give the NumPy forms' numbers bit for bit, and the Poisson tail evaluated only at the
boxes that can hold the minimum gives the box (and p-value) of the exhaustive search."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import pdtrc

import mems_stereo.pipeline.matched_boxes as mb
from mems_stereo.util.lazy_numba import compiled_kernel

numba = pytest.importorskip("numba")


def _grid(rng, n, m, lam):
    """Poisson counts with a planted cluster, a smooth positive background."""
    D = rng.poisson(lam, (n, m)).astype(float)
    j, k = rng.integers(0, n), rng.integers(0, m)
    D[max(0, j - 3):j + 3, max(0, k - 2):k + 2] += rng.poisson(5.0, (min(n, j + 3)
                                                                  - max(0, j - 3),
                                                                  min(m, k + 2)
                                                                  - max(0, k - 2)))
    B = rng.gamma(2.0, lam / 2.0, (n, m))
    return D, B


def test_compiled_box_sums_equal_numpy_and_window_sums(rng):
    kernel = compiled_kernel(mb.box_sums_py)
    for n, m, h, w in [(17, 40, 5, 7), (60, 33, 51, 49), (3, 9, 11, 1)]:
        D, B = _grid(rng, n, m, 0.4)
        A = np.stack([D, B])
        # the NumPy form: padded array, running sums along steps then cells
        a = np.zeros((2, n + h, m + w))
        a[:, h // 2 + 1:h // 2 + 1 + n, w // 2 + 1:w // 2 + 1 + m] = A
        c = np.cumsum(np.cumsum(a, axis=1), axis=2)
        want = c[:, h:, w:] - c[:, :-h, w:] - c[:, h:, :-w] + c[:, :-h, :-w]
        np.testing.assert_array_equal(kernel(A, h, w), want)
        # independently: each box summed over its window (counts: exact integers)
        np.testing.assert_array_equal(want[0], box_sums(D, h, w))


def test_compiled_background_equals_closed_form(rng):
    kernel = compiled_kernel(mb._background_py)
    for _ in range(20):
        n, nc, cell = int(rng.integers(1, 60)), int(rng.integers(1, 30)), int(rng.integers(1, 6))
        lo = rng.integers(1, 400, n)
        hi = lo + rng.integers(-20, 200, n)
        nps = rng.integers(0, 9, n).astype(float)
        c_lo, L = int(rng.integers(1, 300)), float(np.log1p(-rng.uniform(1e-5, 0.1)))
        e_lo = c_lo + cell * np.arange(nc)
        e_hi = e_lo + cell - 1
        a = np.maximum(e_lo[None, :], lo[:, None])
        b = np.minimum(e_hi[None, :], hi[:, None])
        # P(first background photon in codes a..b) = (1 − h)^(a−1) − (1 − h)^b
        want = nps[:, None] * np.where(b >= a, np.exp((a - 1.0) * L) - np.exp(b * L), 0.0)
        k0 = max(int(e_lo.min()), int(lo.min())) - 1
        k1 = max(k0, min(int(e_hi.max()), int(hi.max())))
        got = kernel(lo, hi, nps, e_lo, e_hi, np.exp(np.arange(k0, k1 + 1) * L), k0)
        np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("prefilter", [False, True])
def test_pruned_tail_finds_the_exhaustive_minimum(rng, monkeypatch, prefilter):
    found = 0
    for _ in range(40):
        n, m = int(rng.integers(20, 90)), int(rng.integers(10, 60))
        D, B = _grid(rng, n, m, float(rng.choice([0.05, 0.5, 3.0])))
        got = mb.smallest_p(D, B, 7, 5, 3, prefilter=prefilter)
        with monkeypatch.context() as mp:
            mp.setattr(mb, "PRUNE_MIN_BOXES", np.inf)  # the tail at every valid box
            want = mb.smallest_p(D, B, 7, 5, 3, prefilter=prefilter)
        assert (got is None) == (want is None)
        if want is None:
            continue
        found += 1
        assert (got.p, got.j, got.k, got.count, got.background) == (
            want.p, want.j, want.k, want.count, want.background)
        if not prefilter:  # against the tail of every box, box sums by window (the
            # background's sums round differently: p to 1e-9, the same box)
            N, Bx = box_sums(D, 7, 5), box_sums(B, 7, 5)
            ok = np.zeros(N.shape, bool)
            ok[3:n - 3] = True
            ok &= (N >= 3) & (N > Bx)
            p = np.where(ok, pdtrc(np.maximum(N - 1, 0), np.maximum(Bx, 1e-12)), 1.0)
            assert got.p == pytest.approx(p.min(), rel=1e-9)
            assert (got.j, got.k) == divmod(int(np.argmin(p)), m)
    assert found >= 30


def box_sums(A, h, w):
    """Box sums by window (independent of the running sums)."""
    pad = np.pad(A, ((h // 2, h // 2), (w // 2, w // 2)))
    return np.lib.stride_tricks.sliding_window_view(pad, (h, w)).sum(axis=(2, 3))


def _candidate_grid(rng, cls, n_steps, n_cell, visited):
    """A candidate's grid as the search builds it: a share ``visited`` of the steps
    holds shots (1–6 each; the rest none, accepted interval empty), accepted intervals
    of varying width, background h ~ 1e-3 per code, Poisson counts of it plus a planted
    return; cells of 3 codes from code 40."""
    cell, c_lo = 3, 40
    shot = rng.random(n_steps) < visited
    nps = np.where(shot, rng.integers(1, 7, n_steps), 0).astype(float)
    lo = np.where(shot, c_lo + rng.integers(0, 40, n_steps), 1)
    hi = np.where(shot, lo + rng.integers(-5, cell * n_cell, n_steps), 0)
    log1mh = float(np.log1p(-rng.uniform(2e-4, 3e-3)))
    ref = mb.BoxGrid(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), lo, hi, nps,
                     c_lo, cell, log1mh, n_cell)
    D = rng.poisson(ref.background(0, n_steps, 0, n_cell))
    j0, k0 = int(rng.integers(0, n_steps)), int(rng.integers(0, n_cell))
    for _ in range(int(rng.integers(0, 40))):
        j, k = j0 + int(rng.integers(-8, 9)), k0 + int(rng.integers(-3, 4))
        if 0 <= j < n_steps and 0 <= k < n_cell and shot[j]:
            D[j, k] += 1
    ds, dc = np.nonzero(D)
    return cls(ds.astype(np.int64), dc.astype(np.int64), D[ds, dc].astype(float), lo, hi, nps,
               c_lo, cell, log1mh, n_cell)


@pytest.mark.parametrize("full_cells", [10 ** 9, 2_000])
def test_compiled_grid_finds_the_numpy_grids_box_bit_for_bit(rng, full_cells):
    """The one-kernel window search (counts, background, box sums, screened valid boxes)
    and the one-call search of every window (:class:`BestBoxGrid`) against the NumPy
    stages: the same box, p, count and background, bit for bit, over grids searched
    whole and coarse to fine, steps visited densely and sparsely."""
    from mems_stereo.pipeline.matched_best_kernel import BestBoxGrid
    from mems_stereo.pipeline.matched_grid import CompiledGrid

    found = 0
    for _ in range(24):
        n, nc = int(rng.integers(30, 400)), int(rng.integers(5, 60))
        seed = int(rng.integers(1 << 30))
        visited = float(rng.choice([0.05, 0.3, 1.0]))
        grids = [_candidate_grid(np.random.default_rng(seed), cls, n, nc, visited)
                 for cls in (mb.BoxGrid, CompiledGrid, BestBoxGrid)]
        want, *fast = (g.best(21, 9, 3, full_cells) for g in grids)
        for got in fast:  # one kernel per window; the whole search in one call
            assert (got is None) == (want is None)
            if want is not None:
                assert (got.p, got.j, got.k, got.count, got.background) == (
                    want.p, want.j, want.k, want.count, want.background)
        found += want is not None
    assert found >= 12


@pytest.mark.parametrize("mode", [0, 1, 2])
def test_screened_boxes_keep_the_choice(rng, mode):
    """pick_box over the boxes the kernel keeps chooses as over every valid box (ranks
    of the coarse search, the refinement's near-maximum deviances, the smallest tail),
    and the screen does leave boxes out."""
    from mems_stereo.pipeline.matched_grid import screened_boxes

    top, prefilter = (4 if mode == 1 else 0), mode == 2
    left_out = 0
    for _ in range(30):
        n, m = int(rng.integers(20, 90)), int(rng.integers(10, 60))
        D, B = _grid(rng, n, m, float(rng.choice([0.05, 0.5, 3.0])))
        N_box, B_box, flat = mb.valid_boxes(D, B, 7, 5, 3)
        kept = screened_boxes(np.stack([N_box, B_box]), flat, mode, top)
        left_out += flat.size - kept.size
        assert np.all(np.isin(kept, flat)) and np.all(np.diff(kept) > 0)
        want = mb.pick_box(N_box, B_box, flat, top, prefilter)
        got = mb.pick_box(N_box, B_box, kept, top, prefilter)
        if top:
            assert got == want
        else:
            assert (got is None) == (want is None)
            if want is not None:
                assert (got.p, got.j, got.k, got.count, got.background) == (
                    want.p, want.j, want.k, want.count, want.background)
    assert left_out > 0
