"""Per-pixel TDC offsets (calib/pixel_offsets.py): the first-photon law's expected
information of the return time (calib/expected_info.py, which they use) against its
closed form and against the cell scores' variance, the score
test's calibration and the estimates' pulls on cells drawn from the model itself,
the offsets' spread, and pixels without data."""

from __future__ import annotations

import math

import numpy as np
import pytest
from mems_stereo.calib.expected_info import cell_fisher
from mems_stereo.calib.pixel_offsets import offset_spread, pixel_offsets, with_pixel_offsets
from mems_stereo.calib.problem import Cells, Layout, Problem, cell_terms
from scipy import stats

from mems_stereo.model.system import burkard2022

SIGMA = 1e-9


def test_information_weak_return_is_m_over_sigma_squared():
    # no background, a return far from the window's ends, m → 0: i = m/σ² (the
    # Gaussian's information about its mean, times the chance m of a photon)
    i = cell_fisher(np.array([30e-9]), np.array([1e-4]), np.array([0.0]), 60e-9, SIGMA)[:, 0]
    assert i[0] == pytest.approx(1e-4 / SIGMA ** 2, rel=1e-3)
    # the window's end halves it when it cuts the return at its centre (the
    # integrand is even about the centre)
    h = cell_fisher(np.array([30e-9]), np.array([1e-4]), np.array([0.0]), 30e-9, SIGMA)[:, 0]
    assert h[0] == pytest.approx(0.5 * i[0], rel=2e-3)


@pytest.mark.parametrize("m, lam, pulse", [(0.3, 1e6, None), (2.0, 1e5, None),
                                           (1.0, 1e6, (0.3, 2e-9))])
def test_information_is_the_variance_of_the_cell_score(m, lam, pulse):
    """E[s²] of the cell score ∂ℓ/∂τ of :func:`cell_terms` over first photons drawn
    from the cell's law equals the expected information."""
    rng = np.random.default_rng(5)
    n, tau, t_max = 40000, 20e-9, 50e-9
    k = rng.poisson(m, n)
    t = tau + SIGMA * rng.standard_normal((n, 6))
    if pulse is not None:
        t += np.where(rng.random((n, 6)) < pulse[0], rng.exponential(pulse[1], (n, 6)), 0.0)
    t[np.arange(6)[None, :] >= k[:, None]] = np.inf
    t = np.minimum(t.min(axis=1), rng.exponential(1.0 / lam, n))
    t = np.where(t <= t_max, t, np.nan)
    cells = Cells(np.zeros(n, np.int64), np.zeros(n), np.zeros(n), t, np.full(n, lam),
                  t_max, np.zeros(1, np.int64), 0.0)
    pred = np.tile([tau, 0.0, 0.0, 0.0], (n, 1))
    # m photons on the pixel: log μ with the whole spot on pixel 0 (spot σ 0.12 px)
    _, d = cell_terms(cells, pred, math.log(m / 0.99999), math.log(0.12), SIGMA, False,
                      pulse=pulse)
    info = cell_fisher(np.array([tau]), np.array([m]), np.array([lam]), t_max, SIGMA,
                       pulse)[0, 0]
    assert abs(float(np.mean(d[:, 0]))) < 4 * math.sqrt(info / n)  # a score: mean 0
    assert float(np.mean(d[:, 0] ** 2)) == pytest.approx(info, rel=0.04)


def _problem(rng, offsets, n_shots=3000, mu=0.3):
    """One wall's cells (5 pixels around the beam, first photons drawn from the
    model with per-pixel ``offsets``), the fitted point at the truth."""
    sys0 = burkard2022()
    lay = Layout(["theta0", "tdc_offset"], 1, False)
    prob = Problem([None], sys0, lay, SIGMA)
    shots = np.arange(n_shots)
    u = rng.uniform(2.5, 188.5, n_shots)
    cols = (np.rint(u)[:, None] + np.arange(-2, 3)[None, :]).ravel()
    sh = np.repeat(shots, 5)
    s = 0.6
    share = stats.norm.cdf((cols + 0.5 - u[sh]) / s) - stats.norm.cdf((cols - 0.5 - u[sh]) / s)
    k = rng.poisson(mu * share)
    tau = 10e-9 + offsets[cols.astype(int)]
    t = tau[:, None] + SIGMA * rng.standard_normal((sh.size, 4))
    t[np.arange(4)[None, :] >= k[:, None]] = np.inf
    t = np.minimum(t.min(axis=1), rng.exponential(1e-3, sh.size))
    t = np.where(t <= 40e-9, t, np.nan)
    prob.cells[0] = Cells(sh, cols, np.zeros_like(cols), t, np.full(sh.size, 1e3), 40e-9,
                          shots, 0.0)
    pred = np.stack([np.full(n_shots, 10e-9), u, np.zeros(n_shots), np.zeros(n_shots)], 1)
    prob.predictions = lambda x, j, shots=None, steps=False: (pred, np.ones(n_shots, bool),
                                                              None)
    x = lay.pack({"theta0": sys0.scanner.theta0, "tdc_offset": 0.0},
                 np.array([[0.0, 0.0, 1.0, math.log(mu), math.log(s)]]))
    return prob, x


def test_no_offsets_not_selected_and_one_step_pulls_unbiased():
    rng = np.random.default_rng(11)
    lms, pulls = [], []
    for _ in range(4):
        prob, x = _problem(rng, np.zeros(192))
        po = pixel_offsets(prob, x)
        assert not po.test.selected
        lms.append(po.test.lm / po.test.dof)
        pulls.append(po.estimate[po.covered] / po.estimate_std[po.covered])
    p = np.concatenate(pulls)
    assert np.mean(lms) == pytest.approx(1.0, abs=0.1)  # χ² / dof under no offsets
    assert abs(p.mean()) < 0.1 and p.std() == pytest.approx(1.0, abs=0.1)


def test_offsets_found_with_honest_sigma_and_uncovered_pixels_at_the_spread():
    rng = np.random.default_rng(12)
    true = rng.normal(0.0, 0.4e-9, 192)
    true -= true.mean()
    prob, x = _problem(rng, true, n_shots=20000)
    W = 192
    keep = prob.cells[0].col != 100  # pixel 100 sees no cell
    c = prob.cells[0]
    prob.cells[0] = Cells(c.shot[keep], c.col[keep], c.row[keep], c.t[keep], c.lam[keep],
                          c.t_max, c.shots, c.log_gref)
    po = pixel_offsets(prob, x)
    assert po.test.selected and po.spread == pytest.approx(0.4e-9, rel=0.3)
    assert not po.covered[100] and po.value[100] == 0.0
    assert po.std[100] == pytest.approx(po.spread, rel=1e-12)
    cov = po.covered
    w = 1.0 / po.std[cov] ** 2
    t = true[cov] - np.sum(w * true[cov]) / np.sum(w)
    pull = (po.value[cov] - t) / po.std[cov]
    assert abs(pull.mean()) < 0.25 and pull.std() == pytest.approx(1.0, abs=0.25)
    s2 = with_pixel_offsets(burkard2022(), po)
    assert s2.tdc.pixel_offsets.shape == (W,) and np.all(s2.tdc.pixel_offsets_std > 0)


def test_spread_recovers_a_known_population():
    rng = np.random.default_rng(3)
    var = rng.uniform(0.5, 4.0, 3000) ** 2
    est = rng.normal(0.0, np.sqrt(var + 1.5 ** 2))
    assert offset_spread(est, var, 20.0) == pytest.approx(1.5, rel=0.1)
    assert offset_spread(rng.normal(0.0, np.sqrt(var)), var, 20.0) < 0.4
