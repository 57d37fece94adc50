"""The ex-gaussian pulse in the calibration's first-photon likelihood
(mems_stereo.calib.problem.cell_terms with ``pulse``) and its expected information."""

import numpy as np
import pytest
from mems_stereo.calib.expected_info import cell_fisher
from mems_stereo.calib.problem import Cells, cell_terms

SIG = 6.3e-9


def _cells(t, t_max=45e-9, lam=1e5):
    n = t.size
    return Cells(np.arange(n), np.zeros(n), np.zeros(n), t, np.full(n, lam), t_max,
                 np.arange(n), 0.0)


def _random_cells(seed=1, n=60):
    rng = np.random.default_rng(seed)
    t = rng.uniform(5e-9, 40e-9, n)
    t[::5] = np.nan
    c = _cells(t)
    c.col[:] = rng.integers(0, 5, n)
    pred = np.stack([rng.uniform(10e-9, 30e-9, n), rng.uniform(0, 4, n), np.zeros(n),
                     np.zeros(n)], 1)
    return c, pred


def test_no_tail_is_the_gaussian_likelihood():
    c, pred = _random_cells()
    ll0, d0 = cell_terms(c, pred, 0.1, 0.2, SIG, False)
    ll1, d1 = cell_terms(c, pred, 0.1, 0.2, SIG, False, pulse=(0.0, 2e-9))
    np.testing.assert_allclose(ll1, ll0, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(d1[:, :5], d0, rtol=1e-9, atol=1e-9 * np.abs(d0).max())


@pytest.mark.parametrize("col, step, arg", [(0, 1e-13, "tau"), (3, 1e-6, "logmu"),
                                            (4, 1e-6, "logspot"), (5, 1e-6, "w"),
                                            (6, 1e-13, "decay")])
def test_derivatives_match_finite_differences(col, step, arg):
    c, pred = _random_cells()
    p = {"tau": 0.0, "logmu": 0.1, "logspot": 0.2, "w": 0.3, "decay": 3e-9}
    _, d = cell_terms(c, pred, p["logmu"], p["logspot"], SIG, False, pulse=(p["w"], p["decay"]))

    def ll(delta):
        q = dict(p)
        q[arg] += delta
        pr = pred.copy()
        pr[:, 0] += q["tau"]
        return cell_terms(c, pr, q["logmu"], q["logspot"], SIG, False,
                          pulse=(q["w"], q["decay"]))[0]

    fd = (ll(step) - ll(-step)) / (2 * step)
    assert np.max(np.abs(fd - d[:, col])) < 1e-6 * np.max(np.abs(d[:, col]))


def test_first_photon_density_integrates_to_one():
    """P(fire at t ≤ T) + P(no fire) = 1 under the shaped intensity (λ = 0 and λ > 0;
    ℓ leaves out the background's own −λ·t, a constant of the fit, added here)."""
    grid = np.linspace(0.0, 45e-9, 20001)
    for lam in (0.0, 2e7):
        c = _cells(np.concatenate([grid, [np.nan]]), lam=lam)
        pred = np.tile([12e-9, 0.0, 0.0, 0.0], (grid.size + 1, 1))
        ll, _ = cell_terms(c, pred, np.log(2.0), np.log(1.0), SIG, False, pulse=(0.35, 5e-9))
        ll = ll - lam * np.concatenate([grid, [45e-9]])
        dens = np.exp(ll[:-1])
        total = np.trapezoid(dens, grid) + np.exp(ll[-1])
        assert total == pytest.approx(1.0, abs=2e-4)


def test_shaped_fisher_tends_to_the_gaussian_and_matches_the_scores():
    tau = np.array([8e-9, 15e-9, 30e-9])
    m = np.array([0.2, 1.0, 3.0])
    lam = np.full(3, 1e5)
    g = cell_fisher(tau, m, lam, 45e-9, SIG)
    s = cell_fisher(tau, m, lam, 45e-9, SIG, pulse=(0.3, 1e-13))
    np.testing.assert_allclose(s, g, rtol=2e-3)
    # the expected information of τ equals the mean squared score over simulated cells
    rng = np.random.default_rng(5)
    w, dec, n = 0.3, 4e-9, 40000
    arr = 15e-9 + rng.normal(0, SIG, (n, 8)) + np.where(rng.random((n, 8)) < w,
                                                         rng.exponential(dec, (n, 8)), 0)
    k = rng.poisson(1.0, n)
    arr[np.arange(8)[None, :] >= k[:, None]] = np.inf
    arr[arr < 0] = np.inf
    first = arr.min(axis=1)
    first = np.where(first <= 45e-9, first, np.nan)  # background neglected: λ tiny
    c = _cells(first, lam=1e-3)
    pred = np.tile([15e-9, 0.0, 0.0, 0.0], (n, 1))
    _, d = cell_terms(c, pred, 0.0, np.log(1e-3), SIG, False, pulse=(w, dec))
    F = cell_fisher(np.array([15e-9]), np.array([1.0]), np.array([1e-3]), 45e-9, SIG,
                    pulse=(w, dec))
    assert np.mean(d[:, 0] ** 2) == pytest.approx(F[0, 0], rel=0.05)


def test_a_huge_spot_trial_is_the_largest_spot_not_an_overflow():
    """A Newton trial step may put log s anywhere: beyond exp's range it is the largest
    spot (SPOT_MAX), as a large finite one is, instead of an OverflowError."""
    from mems_stereo.calib.problem import SPOT_MAX
    c, pred = _random_cells()
    ll_big, _ = cell_terms(c, pred, 0.1, 1000.0, SIG, False)
    ll_max, _ = cell_terms(c, pred, 0.1, float(np.log(SPOT_MAX)) + 1.0, SIG, False)
    np.testing.assert_array_equal(ll_big, ll_max)


def test_every_spot_size_from_a_wall_is_clipped_not_an_overflow():
    """A failed fit's wall may hold any log s: the expected-information rows (used by
    the goodness test and the checks) take it as the largest spot, not an
    OverflowError."""
    import math

    from mems_stereo.calib.expected_info import wall_rows
    from mems_stereo.calib.problem import SPOT_MAX, SPOT_MIN, spot_px
    assert spot_px(1e4) == SPOT_MAX and spot_px(-1e4) == SPOT_MIN
    assert spot_px(math.log(1.5)) == pytest.approx(1.5, rel=1e-15)
    c, pred = _random_cells()
    ok = np.ones(pred.shape[0], bool)
    Jc = np.random.default_rng(2).normal(size=(pred.shape[0], 4, 3))
    big = wall_rows(c, pred, ok, Jc, 0.1, 1000.0, False)
    top = wall_rows(c, pred, ok, Jc, 0.1, math.log(SPOT_MAX) + 1.0, False)
    np.testing.assert_array_equal(big.m, top.m)
    np.testing.assert_array_equal(big.a, top.a)
