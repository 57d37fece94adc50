"""σ of a full-model calibration where its likelihood is not the quadratic its
information says: a held candidate block's posterior second moment in the σ
(calib/held_blocks.py) and the pulse tail's share from its profile likelihood
(calib/tail_profile.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from mems_stereo.calib import observability as obs
from mems_stereo.calib.hardware_fit import extended_problem
from mems_stereo.calib.held_blocks import PRESENT_PROB, held_covariance, held_moment, prior_std
from mems_stereo.calib.problem import Cells, Layout, Problem, WallData
from mems_stereo.calib.solver import FitState, newton
from mems_stereo.calib.tail_profile import LEVEL, interval_end, share_profile
from scipy import stats
from test_hardware_fit import _synthetic_problem

from mems_stereo.model.scanner import phase_from_zero_crossings
from mems_stereo.model.system import burkard2022

FIT = ["theta0", "phase_offset", "tdc_offset", "edge_rising_delay"]
H2 = ["harmonic2_cos", "harmonic2_sin"]
H2_TRUE = 0.005  # a second harmonic, relative to the mirror's amplitude
N_DRAWS = 2000  # draws of the linear-Gaussian toy
WALL = np.array([[0.0, 0.0, 1.5, math.log(0.3), math.log(0.6)]])


def _harmonic_walls(rng, h2_cos: float, n_shots: int = 4000):
    """One wall at 1.5 m seen by a mirror with a second harmonic ``h2_cos`` (its cos
    term, relative), cells drawn from the model (1 ns pulse); the problem fits
    :data:`FIT` (the edge delay free, the harmonic held at 0) from the truth."""
    zc = np.arange(0, 0.2, 0.5 / 1570.0) + 1e-4
    rising = (np.arange(zc.size) % 2).astype(bool)
    t = np.sort(rng.uniform(zc[0] + 1e-5, zc[-1] - 1e-5, n_shots))
    sys0 = burkard2022()
    w = WallData(phase_from_zero_crossings(t, zc, rising)[0],
                 np.zeros((n_shots, 1, 192), np.uint16), np.full((1, 192), 1e5), 3.125e-10,
                 "w", t, zc, rising)
    gen = Layout(FIT + H2, 1, False)
    truth = {**{n: sys0.get_param(n) for n in FIT + H2}, "harmonic2_cos": h2_cos}
    pred, ok, _ = Problem([w], sys0, gen, 1e-9).predictions(gen.pack(truth, WALL), 0)
    shots = np.flatnonzero(ok & (pred[:, 1] > 3) & (pred[:, 1] < 188))
    cols = (np.rint(pred[shots, 1])[:, None] + np.arange(-2, 3)[None, :]).ravel()
    sh = np.repeat(shots, 5)
    share = np.exp(-0.5 * ((cols - pred[sh, 1]) / 0.6) ** 2) / (0.6 * math.sqrt(2 * math.pi))
    fired = rng.random(sh.size) < -np.expm1(-0.5 * share)
    times = np.where(fired, pred[sh, 0] + rng.normal(0.0, 1e-9, sh.size), np.nan)
    lay = Layout(FIT, 1, False)
    prob = Problem([w], sys0, lay, 1e-9)
    prob.cells[0] = Cells(sh, cols, np.zeros_like(cols), times, np.full(sh.size, 1e3), 60e-9,
                          shots, float(np.median(pred[shots, 3])))
    return prob, lay.pack({n: sys0.get_param(n) for n in FIT}, WALL)


def _spike_slab_moment(eta_hat, V, tau, present):
    """E[η ηᵀ | η̂] of terms each present with probability ``present`` (then N(0, τ²))
    or absent (0) on its own, from their estimate η̂ ~ N(η, V): over the subsets A of
    present terms, η̂ ~ N(0, V + τ² D_A) (D_A the indicator of A) weighs the Gaussian
    posterior of prior covariance τ² D_A (Kalman form: it allows the singular prior)."""
    k = eta_hat.size
    total, weight = np.zeros((k, k)), 0.0
    for mask in range(1 << k):
        P0 = tau ** 2 * np.diag([(mask >> b) & 1 for b in range(k)]).astype(float)
        w = (present ** bin(mask).count("1") * (1 - present) ** (k - bin(mask).count("1"))
             * stats.multivariate_normal(np.zeros(k), V + P0).pdf(eta_hat))
        G = P0 @ np.linalg.inv(V + P0)
        m = G @ eta_hat
        total += w * (P0 - G @ P0 + np.outer(m, m))
        weight += w
    return total / weight


def test_held_block_covariance_is_the_posterior_moment_and_covers_its_bias():
    """A 0.5 % second harmonic held at 0 beside a fitted edge delay (bench_real_hardware
    seed 1071's case): held_covariance equals S E[η ηᵀ | η̂] Sᵀ written out from the
    extended information (S = −I_xx⁻¹ I_xη, η̂ the held terms' one-step estimate with
    covariance V = (I_ηη − I_ηx I_xx⁻¹ I_xη)⁻¹, E from η̂'s densities with each term
    present or absent); the edge delay's move when the harmonic is fitted at its truth
    instead (one wall: a weak case) is beyond 1.2 of the held fit's σ, within 2 of the
    σ that include the block."""
    prob, x = _harmonic_walls(np.random.default_rng(3), H2_TRUE)
    st = FitState()
    x0 = newton(prob, x, st).x
    assert st.converged
    D = held_covariance(prob, x0, H2)
    p2, x2 = extended_problem(prob, x0, H2)
    _, g, I = p2.score(x2)
    e = np.array([p2.layout.names.index(n) for n in H2])
    k = np.array([p2.layout.names.index(n) for n in FIT] + list(range(p2.layout.n_sys,
                                                                      p2.layout.size)))
    Ixx = I[np.ix_(k, k)]
    S = -np.linalg.solve(Ixx, I[np.ix_(k, e)])
    V = np.linalg.inv(I[np.ix_(e, e)] + I[np.ix_(e, k)] @ S)
    eta_hat = V @ (g[e] + S.T @ g[k])
    tau = prior_std(H2)[0]
    assert tau == pytest.approx(3e-3 / math.sqrt(PRESENT_PROB))
    want = S @ _spike_slab_moment(eta_hat, V, tau, PRESENT_PROB) @ S.T
    sc = prob.layout.scales
    np.testing.assert_allclose(D / sc[:, None] / sc[None, :], want / sc[:, None] / sc[None, :],
                               atol=1e-6 * np.max(np.abs(want / sc[:, None] / sc[None, :])))
    C = obs.covariance(Ixx, sc)[0]
    # the fit with the harmonic at its truth (the same cells)
    fixed = Problem(prob.walls, prob.system.with_params(harmonic2_cos=H2_TRUE), prob.layout,
                    prob.sigma)
    fixed.cells = prob.cells
    st = FitState()
    x1 = newton(fixed, x0, st).x
    assert st.converged
    i = FIT.index("edge_rising_delay")
    move = abs(x1[i] - x0[i])
    assert D[i, i] > 0.0
    assert move > 1.2 * math.sqrt(C[i, i]), (move, math.sqrt(C[i, i]))
    assert move < 2.0 * math.sqrt(C[i, i] + D[i, i]), (move, math.sqrt(C[i, i] + D[i, i]))


def test_held_moment_scalar_spike_and_slab_closed_form():
    """One term, present (N(0, τ²)) with probability π or absent: E[η² | η̂] =
    p·(v + m²), p the posterior probability of present from η̂'s two normal densities,
    v = (σ⁻² + τ⁻²)⁻¹, m = v·η̂/σ²; a term always present gets v + m² (a Gaussian prior)."""
    sig, tau = 0.7, 1.3
    for pi in (0.2, 0.5):
        for eh in (0.0, 0.5, 2.0, -4.0):
            E = held_moment([[sig ** -2]], [eh / sig ** 2], [tau], [[0]], present=pi)[0, 0]
            a = pi * stats.norm.pdf(eh, 0.0, math.hypot(sig, tau))
            b = (1 - pi) * stats.norm.pdf(eh, 0.0, sig)
            v = 1.0 / (sig ** -2 + tau ** -2)
            assert E == pytest.approx(a / (a + b) * (v + (v * eh / sig ** 2) ** 2), rel=1e-12)
    E = held_moment([[sig ** -2]], [1.0], [tau], [[0]], always=1)[0, 0]
    v = 1.0 / (sig ** -2 + tau ** -2)
    assert E == pytest.approx(v + v * v, rel=1e-12)


def test_held_moment_gives_honest_sigma_in_a_linear_gaussian_toy():
    """y = Xβ + Zη + ε (ε ~ N(0, 1)), β fitted with η held at 0: two groups of two
    terms each present with probability ½ (then N(0, τ²)), a fifth term always
    present, Z partly collinear with X.  σ² = [(XᵀX)⁻¹ + S E[ηηᵀ|y] Sᵀ]_ii
    (S = −(XᵀX)⁻¹XᵀZ) is the posterior's second moment about the held estimate, so the
    mean of pull² over draws from the prior is 1 (exactly, in expectation; 2000 draws
    give ±0.15: pull² is heavy-tailed); the posterior variance under a Gaussian prior
    of the same RMS (the σ before) is wider where the groups are absent and misses the
    bias where present."""
    rng = np.random.default_rng(30)
    n, tau = 60, np.array([0.5, 0.5, 0.5, 0.5, 0.1])
    t = np.linspace(-1.0, 1.0, n)
    X = np.stack([np.ones(n), t, t ** 2], axis=1)
    Z = np.stack([t ** 2 + 0.3 * np.cos(3 * t), np.sin(2 * t), np.cos(5 * t), t ** 3,
                  np.cos(2 * t)], axis=1) * 4.0
    A = np.linalg.inv(X.T @ X)
    S = -A @ X.T @ Z
    J = Z.T @ Z + Z.T @ X @ S
    groups = [[0, 1], [2, 3], [4]]
    gauss = np.linalg.inv(J + np.diag(1.0 / (tau ** 2 * np.array([0.5] * 4 + [1.0]))))
    p_new, p_old, absent = [], [], []
    for _ in range(N_DRAWS):
        on = rng.random(2) < 0.5
        eta = rng.normal(0.0, tau) * np.array([on[0], on[0], on[1], on[1], True])
        beta = rng.normal(0.0, 1.0, 3)
        y = X @ beta + Z @ eta + rng.normal(0.0, 1.0, n)
        b_h = A @ X.T @ y
        u = Z.T @ (y - X @ b_h)
        E = held_moment(J, u, tau, groups, always=1)
        sd_new = np.sqrt(np.diag(A + S @ E @ S.T))
        sd_old = np.sqrt(np.diag(A + S @ gauss @ S.T))
        p_new.append((b_h - beta) / sd_new)
        p_old.append((b_h - beta) / sd_old)
        absent.append(not on.any())
    p_new, p_old, absent = np.array(p_new), np.array(p_old), np.array(absent)
    ms = np.mean(p_new ** 2, axis=0)
    assert np.all(np.abs(ms - 1.0) < 0.15), ms
    # the Gaussian prior's posterior variance alone: too wide where the groups are
    # absent, too narrow on average (it leaves out the bias of holding η at 0)
    assert np.all(np.std(p_old[absent], axis=0) < np.std(p_new[absent], axis=0))
    assert np.max(np.mean(p_old ** 2, axis=0)) > 1.3


class _SkewedProfile:
    """A profile likelihood of known shape: 2·Δlog L = (d/a)² above the estimate
    0.1 and (d/b)² + (d/b)⁴ below (d the distance), for :func:`interval_end`."""

    def __init__(self, a: float, b: float):
        self.x, self.i, self.a, self.b, self.calls = np.array([0.1, 7.0]), 0, a, b, 0

    def at(self, w: float):
        self.calls += 1
        d = w - 0.1
        e = (d / self.a) ** 2 if d > 0 else (d / self.b) ** 2 + (d / self.b) ** 4
        return e, np.array([w, 7.0 - 2.0 * d])


def test_interval_end_finds_the_level_crossing_on_each_side():
    """Upper side quadratic: the end is exactly 0.1 + 2a (√ is linear there); lower
    side quartic: within 1 % of the root of u² + u⁴ = 4 (u = 1.2496); a bound inside
    the interval leaves it open; the outer point's refit comes back."""
    pf = _SkewedProfile(0.05, 0.02)
    hi, xo, closed = interval_end(pf, 1.0, 0.01, 0.95)
    assert closed and hi == pytest.approx(0.2, rel=1e-9) and xo[0] >= hi
    lo, _, closed = interval_end(pf, -1.0, 0.01, 0.0)
    u = math.sqrt((math.sqrt(17.0) - 1.0) / 2.0)
    assert closed and lo == pytest.approx(0.1 - 0.02 * u, rel=1e-2)
    assert pf.calls < 20
    end, xo, closed = interval_end(_SkewedProfile(0.5, 0.02), 1.0, 0.1, 0.95)
    assert not closed and end == 0.95 and xo[0] == 0.95


def test_share_profile_interval_ends_where_the_likelihood_falls_by_the_level():
    """A 30 % tail of 0.7 ns on the 1 ns pulse (a decay shorter than the core: the
    ridge of the family's pulses), 2000 shots: the profile interval's upper end,
    refitted with the share held there (every other parameter free), lies at
    2·Δlog L = LEVEL; the interval is skewed towards larger shares (its σ beyond the
    local one, from the upper side) and the ridge moves the TDC offset against the
    share (the mean delay w·τ kept).  About 2 s of CPU."""
    prob0, x = _synthetic_problem(np.random.default_rng(11), tail=(0.3, 0.7e-9))
    c = prob0.cells[0]
    m = c.shot < 2000
    names = ["tdc_offset", "pulse_tail_fraction", "pulse_tail_decay"]
    lay = Layout(names, 1, False)
    prob = Problem(prob0.walls, prob0.system, lay, prob0.sigma)
    prob.cells[0] = Cells(c.shot[m], c.col[m], c.row[m], c.t[m], c.lam[m], c.t_max,
                          c.shots[c.shots < 2000], c.log_gref)
    _, walls = prob0.layout.unpack(x)
    st = FitState()
    nr = newton(prob, lay.pack({"tdc_offset": -0.1e-9, "pulse_tail_fraction": 0.2,
                                "pulse_tail_decay": 1e-9}, walls), st)
    assert st.converged
    cov = obs.covariance(nr.info, lay.scales)[0]
    prof = share_profile(prob, nr.x, cov)
    assert prof is not None and prof.closed
    assert prof.lower < prof.share < prof.upper
    assert prof.upper - prof.share > prof.share - prof.lower  # skewed to larger shares
    assert prof.std == (prof.upper - prof.share) / math.sqrt(LEVEL) > prof.local_std
    assert prof.move[1] == 1.0 and prof.move[0] < 0.0
    # independent: the share held at the upper end in a problem that does not free it
    held = Problem(prob.walls, prob.system, Layout(["tdc_offset", "pulse_tail_decay"], 1,
                                                   False), prob.sigma)
    held.cells = prob.cells
    held.pulse_fixed = (prof.upper, 1e-9)
    mean = nr.x[1] * nr.x[2]
    start = np.concatenate([[nr.x[0], mean / prof.upper], nr.x[3:]])
    r = newton(held, start, FitState(), max_iter=60)
    assert abs(2.0 * (nr.loglik - r.loglik) - LEVEL) < 0.3, nr.loglik - r.loglik
