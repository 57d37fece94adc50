"""Propagated covariances against Monte-Carlo samples of every spread."""

from __future__ import annotations

import numpy as np
import pytest

from mems_stereo.geometry.triangulation import path_length_of_point
from mems_stereo.geometry.uncertainty import (
    paper_polar_uncertainty,
    paper_spreads,
    polar_from_cartesian,
    propagate,
    spreads_for,
    stereo_point_est,
    tof_pixel_point,
    tof_point,
)
from mems_stereo.model.camera import project_points
from mems_stereo.model.scanner import scan_direction
from mems_stereo.physics.pulse import FWHM_PER_SIGMA


def _truth(system, dist, dtheta=0.03):
    th = np.array([system.scanner.theta0 + dtheta])
    d = scan_direction(th, system.scanner)
    x = system.scanner.position + dist * d
    uv = project_points(x, system.receiver.camera_matrix)
    return th, x, uv, path_length_of_point(x, system.scanner.position)


def test_spreads_components(system):
    sp = spreads_for(system, timing_jitter=50e-12, sigma_theta=2e-4)
    assert np.isclose(sp.sigma_t_pulse, 14.9e-9 / FWHM_PER_SIGMA)
    assert np.isclose(sp.sigma_t_quant, 312.5e-12 / np.sqrt(12))
    assert np.isclose(sp.sigma_t ** 2, sp.sigma_t_pulse ** 2 + 50e-12 ** 2 + sp.sigma_t_quant ** 2)
    # one detection's path length spreads by about 1.9 m (issue text)
    assert 1.85 < sp.sigma_L(system) < 1.95
    ps = paper_spreads(system)
    assert np.isclose(ps.sigma_u, 12e-6 / 40.56e-6 / np.sqrt(12)) and ps.sigma_theta == 0


@pytest.mark.parametrize("fn,dist", [(tof_point, 8.0), (tof_pixel_point, 8.0),
                                     (stereo_point_est, 1.5), (stereo_point_est, 3.0)])
def test_propagated_covariance_matches_monte_carlo(system, rng, fn, dist):
    """Uniform pixel extent, Gaussian timing and angle: sample covariance ≈ J Σ Jᵀ.

    In the first-order regime: ToF beyond a few σ_L of the baseline, stereo
    while the pixel extent is small against the disparity (docs/pipeline.md
    gives the growth of the second-order term with range).
    """
    sp = spreads_for(system, spot_sigma=0.0, sigma_theta=2e-4)
    th, x, uv, L = _truth(system, dist)
    n = 20000
    u = uv[0, 0] + rng.uniform(-0.5, 0.5, n)  # uniform over the pixel: σ = 1/√12
    v = uv[0, 1] + rng.uniform(-0.5, 0.5, n)
    Ls = L[0] + rng.normal(0, sp.sigma_L(system), n)
    ts = th[0] + rng.normal(0, sp.sigma_theta, n)
    xs = fn(system, u, v, Ls, ts)
    xs = xs[np.all(np.isfinite(xs), 1)]
    C_mc = np.cov(xs.T)
    x0, C = propagate(fn, system, uv[:, 0], uv[:, 1], L, th, sp)
    assert np.allclose(x0[0], x[0], atol=1e-9)
    # compare the dominant variances (diagonal entries that are not ~0)
    dmc, dpr = np.diag(C_mc), np.diag(C[0])
    big = dpr > 1e-2 * dpr.max()
    assert np.all(np.abs(np.sqrt(dmc[big] / dpr[big]) - 1) < 0.08), (dmc, dpr)


def test_calibration_covariance_adds(system):
    th, x, uv, L = _truth(system, 3.0)
    sp0 = spreads_for(system)
    sp1 = spreads_for(system, param_names=("baseline_x", "theta0"),
                      param_cov=np.diag([0.002 ** 2, 0.001 ** 2]))
    _, C0 = propagate(stereo_point_est, system, uv[:, 0], uv[:, 1], L, th, sp0)
    _, C1 = propagate(stereo_point_est, system, uv[:, 0], uv[:, 1], L, th, sp1)
    assert np.trace(C1[0]) > np.trace(C0[0])
    # check the added part by finite differences of the system itself
    h = 1e-5
    xp = stereo_point_est(system.with_params(baseline_x=-0.125 + h), uv[:, 0], uv[:, 1], L, th)
    xm = stereo_point_est(system.with_params(baseline_x=-0.125 - h), uv[:, 0], uv[:, 1], L, th)
    g = (xp - xm)[0] / (2 * h)
    t0 = system.scanner.theta0
    xp = stereo_point_est(system.with_params(theta0=t0 + h), uv[:, 0], uv[:, 1], L, th)
    xm = stereo_point_est(system.with_params(theta0=t0 - h), uv[:, 0], uv[:, 1], L, th)
    g2 = (xp - xm)[0] / (2 * h)
    added = np.outer(g, g) * 0.002 ** 2 + np.outer(g2, g2) * 0.001 ** 2
    assert np.allclose(C1[0] - C0[0], added, rtol=1e-3, atol=1e-12)


def test_paper_polar_uncertainty_matches_monte_carlo(system, rng):
    """Paper Eqs. 14–17: (u, t) → (r, φ), uniform pixel over a SPAD and uniform bin."""
    th, x, uv, L = _truth(system, 2.0)
    code = np.floor(L / system.speed_of_light / system.tdc.bin_width + 1.0)
    pol = paper_polar_uncertainty(system, uv[:, 0], code, th)
    mu_r, s_r, s_phi = pol.r, pol.sigma_r, pol.sigma_phi
    sp = paper_spreads(system)
    n = 20000
    from mems_stereo.geometry.uncertainty import paper_point
    from mems_stereo.model.tdc import path_length_from_codes

    u = uv[0, 0] + rng.uniform(-0.5, 0.5, n) * sp.sigma_u * np.sqrt(12)
    t = (path_length_from_codes(code, system.tdc, system.speed_of_light)[0]
         + system.speed_of_light * rng.uniform(-0.5, 0.5, n) * system.tdc.bin_width)
    mc = polar_from_cartesian(paper_point(system, u, 0.0, t, np.full(n, th[0])))
    r, phi = mc.r, mc.phi
    assert abs(np.std(r) / s_r[0] - 1) < 0.05
    assert abs(np.std(phi) / s_phi[0] - 1) < 0.05
    assert abs(np.mean(r) - mu_r[0]) < 3 * s_r[0] / np.sqrt(n) + 1e-6
