"""The matched filter's frame kernel (mems_stereo/pipeline/matched_frame_kernel.py): its
box search and choice give the per-window compiled search's box bit for bit (the same
sums, SciPy's own pdtrc), ties included; the vectorised scan p-value equals the scalar
one; and a frame's candidates in one call equal the per-candidate path."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import pdtrc

from mems_stereo.pipeline import matched_frame_kernel as fk
from mems_stereo.pipeline.matched import scan_box_sf
from mems_stereo.pipeline.matched_best_kernel import BestBoxGrid

numba = pytest.importorskip("numba")


def _grid(rng, n_steps, n_cell, entries, plateau):
    """A candidate's grid as a floodlight frame makes it: few counted entries over a
    long band, the valid shots and accepted codes repeating over runs of ``plateau``
    steps (a box sliding along them keeps its count and background: ties), some
    steps without shots; cells of 2 codes from code 5."""
    cell, c_lo = 2, 5
    runs = -(-n_steps // plateau)
    lo = np.repeat(rng.integers(c_lo, c_lo + n_cell, runs), plateau)[:n_steps]
    hi = np.minimum(lo + np.repeat(rng.integers(n_cell // 2, 2 * n_cell, runs),
                                   plateau)[:n_steps], c_lo + cell * n_cell + 3)
    nps = np.repeat(rng.integers(0, 4, runs), plateau)[:n_steps].astype(np.float64)
    ds = np.sort(rng.integers(0, n_steps, entries))
    dc = rng.integers(-1, n_cell + 1, entries)  # (a few outside the grid's cells)
    cnt = rng.integers(1, 4, entries).astype(np.float64)
    log1mh = np.log1p(-rng.uniform(2e-4, 2e-2))
    return BestBoxGrid(ds.astype(np.int64), dc.astype(np.int64), cnt, lo.astype(np.int64),
                       hi.astype(np.int64), nps, c_lo, cell, log1mh, n_cell)


@pytest.mark.parametrize("full_cells", [10 ** 9, 3_000])
def test_frame_kernel_finds_the_compiled_grids_box_bit_for_bit(full_cells):
    """Random floodlight-like grids, searched whole (every box) and coarse to fine: the
    frame kernel's box (p, step, cell, count, background) is the one BestBoxGrid.best
    chooses, bit for bit (the same window sums, SciPy's pdtrc itself); plateaus of
    equal boxes make ties, where the first smallest tail in search order wins."""
    rng = np.random.default_rng(31)
    found = 0
    for trial in range(24):
        n, nc = int(rng.integers(40, 400)), int(rng.integers(8, 60))
        g = _grid(rng, n, nc, int(rng.integers(5, 120)), int(rng.integers(1, 30)))
        box_s, box_c = int(rng.integers(2, 12)) * 2 + 1, int(rng.integers(1, 6)) * 2 + 1
        ref = g.best(box_s, box_c, 3, full_cells)
        out = fk.search_grid(g, box_s, box_c, 3, full_cells)
        assert out[0] != fk.FALLBACK, trial
        if ref is None:
            assert out[0] == fk.NO_BOX, trial
            continue
        found += 1
        assert out[0] == fk.BOX, trial
        assert (out[1], int(out[2]), int(out[3]), out[4], out[5]) == (
            ref.p, ref.j, ref.k, ref.count, ref.background), trial
        # the tail is SciPy's at the box's count and background
        assert out[1] == pdtrc(max(out[4] - 1, 0), max(out[5], 1e-12))
    assert found >= 12


def test_linked_pdtrc_is_scipys():
    """SciPy's pdtrc called from the compiled code is SciPy's, bit for bit."""
    rng = np.random.default_rng(5)
    k = rng.integers(0, 60, 400).astype(np.float64)
    m = rng.gamma(2.0, 5.0, 400) + 1e-12
    pd = fk.scipy_pdtrc()

    @numba.njit
    def tails(k, m):
        out = np.empty(k.size)
        for i in range(k.size):
            out[i] = pd(k[i], m[i])
        return out

    assert np.array_equal(tails(k, m), pdtrc(k, m))


def _scan_box_sf_scalar(k, mu, n_windows, n_code_pos) -> float:
    """scan_box_sf as it was written for one box (the reference)."""
    from mems_stereo.pipeline.peak_support import scan_sf

    tail = float(pdtrc(max(k - 1, 0), max(mu, 1e-12)))
    if tail <= 0.0:
        return 0.0
    c_w = float(scan_sf(k, max(mu, 1e-12), n_windows)) / tail
    c_c = float(scan_sf(k, max(mu, 1e-12), n_code_pos)) / tail
    return min(1.0, tail * c_w * c_c)


def test_vectorised_scan_p_value_equals_the_scalar_one():
    """scan_box_sf on arrays gives the one-box formula's value bit for bit (the same
    ufuncs elementwise), including a tail that underflows (p 0) and the clip at 1."""
    rng = np.random.default_rng(7)
    k = rng.integers(1, 40, 200).astype(np.float64)
    mu = rng.gamma(1.5, 3.0, 200)
    mu[:3] = (1e-14, 0.0, 1e-300)
    k[3] = 4000.0  # the tail underflows: p 0
    nw = rng.uniform(1.0, 5000.0, 200)
    ncp = rng.uniform(1.0, 30.0, 200)
    vec = scan_box_sf(k, mu, nw, ncp)
    one = np.array([_scan_box_sf_scalar(float(a), float(b), float(c), float(d))
                    for a, b, c, d in zip(k, mu, nw, ncp)])
    assert np.array_equal(vec, one)
    assert scan_box_sf(float(k[5]), float(mu[5]), float(nw[5]), float(ncp[5])) == one[5]
    assert vec[3] == 0.0 and np.all((vec >= 0) & (vec <= 1)) and np.any(vec == 1.0)
