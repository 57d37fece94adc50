"""The goodness tests' null by drawn cells (calib/goodness_null.py): the first-photon
draw follows its law; scores of cells drawn from the model have unit variance."""

from __future__ import annotations

import numpy as np
import pytest
from mems_stereo.calib.goodness_null import first_events
from scipy import stats
from scipy.special import ndtr


def test_first_events_follow_the_first_photon_law():
    """First events under I(t) = λ + m·φ((t − τ)/σ)/σ on [0, T]: P(t_first ≤ t) =
    1 − exp(−Λ(t)) with Λ(t) = λt + m(Φ((t − τ)/σ) − Φ(−τ/σ)), no event with
    probability exp(−Λ(T)); for each of three cells (weak return over background,
    strong return with pile-up, a return cut by the window's start)."""
    rng = np.random.default_rng(3)
    sigma, t_max, n = 1e-9, 60e-9, 20000
    for tau, m, lam in ((20e-9, 0.05, 2e6), (30e-9, 3.0, 1e5), (0.5e-9, 1.0, 1e6)):
        t = first_events(np.full(n, tau), np.full(n, m), np.full(n, lam), t_max, sigma,
                         None, rng)

        def cdf(s, tau=tau, m=m, lam=lam):
            return 1.0 - np.exp(-(lam * s + m * (ndtr((s - tau) / sigma) - ndtr(-tau / sigma))))

        p_fire = cdf(t_max)
        fired = np.isfinite(t)
        assert fired.mean() == pytest.approx(p_fire, abs=4 * np.sqrt(p_fire / n))
        assert np.all((t[fired] >= 0) & (t[fired] <= t_max))
        ks = stats.kstest(t[fired], lambda s, p=p_fire: cdf(s) / p)
        assert ks.pvalue > 1e-3, (tau, m, ks)


def test_drawn_cells_have_the_expected_information_as_score_variance():
    """Cells drawn from the model at x (1,500 shots of the synthetic wall of
    ``test_hardware_fit``): each score over √ of its expected information
    (:func:`~mems_stereo.calib.expected_info.cell_fisher`) has unit variance, the time
    score's and the column score's, pooled over six draws by information weight
    (standard error about 0.05 per draw set)."""
    from dataclasses import replace

    from mems_stereo.calib.goodness import cell_residuals
    from mems_stereo.calib.goodness_null import resampled
    from test_hardware_fit import _synthetic_problem

    prob, x = _synthetic_problem(np.random.default_rng(2))
    c = prob.cells[0]
    k = c.shot < 1500
    prob.cells[0] = replace(c, shot=c.shot[k], col=c.col[k], row=c.row[k], t=c.t[k],
                            lam=c.lam[k], shots=c.shots[c.shots < 1500])
    rng = np.random.default_rng(7)
    num, den = np.zeros(2), np.zeros(2)
    pixels = cell_residuals(prob, x).pixel
    for _ in range(6):
        r = cell_residuals(resampled(prob, x, rng), x)
        assert np.array_equal(r.pixel, pixels)  # the same cells
        num += [np.sum(r.time ** 2 * r.time_info), np.sum(r.column ** 2 * r.column_info)]
        den += [np.sum(r.time_info), np.sum(r.column_info)]
    np.testing.assert_allclose(num / den, 1.0, atol=0.15)
