"""First-photon bias of the time-of-flight estimate: model, posterior, correction."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import ndtr, ndtri

from mems_stereo.geometry.triangulation import path_length_of_point
from mems_stereo.model.scanner import scan_direction
from mems_stereo.physics.first_photon import (
    MU_GRID,
    _table_lookup,
    detection_log_odds,
    firing_probability,
    first_photon_delay,
    first_photon_moments,
)
from mems_stereo.physics.spot import DEFAULT_SPOT_SIGMA, spot_fraction
from mems_stereo.pipeline.fusion import points_from_peak_detections
from mems_stereo.pipeline.fusion_inputs import FusionEntries, FusionOptions, FusionPeaks
from mems_stereo.pipeline.peak_accumulator import PeakAccumulator


def _fuse(system, shot, peak, code, theta, rows, cols, min_counts=1, **options):
    """:func:`points_from_peak_detections` of detections and peaks given as arrays."""
    return points_from_peak_detections(system, FusionEntries(shot, peak, code, theta),
                                       FusionPeaks(rows, cols), FusionOptions(**options),
                                       min_counts)

def _first_arrivals(rng, mu_w, a, size):
    """Monte-Carlo first photons (σ units): Poisson(μ_w) arrivals from N(0, 1) cut to u ≥ a;
    returns the first of each shot (NaN: no photon)."""
    m = rng.poisson(mu_w, size)
    out = np.full(size, np.nan)
    for k in np.unique(m[m > 0]):
        sel = m == k
        # inverse CDF of the truncated normal
        g = ndtr(a) + rng.random((sel.sum(), k)) * (1 - ndtr(a))
        out[sel] = ndtri(g).min(axis=1)
    return out


@pytest.mark.parametrize("a, mu", [(-np.inf, 0.35), (-np.inf, 4.0), (-1.5, 2.0), (0.0, 1.0)])
def test_moments_against_monte_carlo(rng, a, mu):
    u = _first_arrivals(rng, mu, a, 200_000)
    u = u[np.isfinite(u)]
    mean, var = first_photon_moments(a, mu)
    se = math.sqrt(var / u.size)
    assert abs(u.mean() - mean) < 4 * se, (u.mean(), mean)
    assert abs(u.var() / var - 1) < 0.03


def test_moments_against_sim():
    from mems_stereo.physics.first_photon import first_photon_mean_delay
    from mems_stereo.physics.pulse import PulseShape

    sigma = 14.9e-9 / (2 * math.sqrt(2 * math.log(2)))
    pulse = PulseShape.gaussian(14.9e-9)
    for mu in (0.35, 1.0, 4.0):
        m, _ = first_photon_moments(-np.inf, mu)
        ref = first_photon_mean_delay(mu, pulse)
        assert abs(m * sigma - ref) < 2e-12, (mu, m * sigma, ref)
    # the brief's figures: -0.6, -1.8, -5.9 ns
    got = [float(first_photon_moments(-np.inf, mu)[0]) * sigma * 1e9 for mu in (0.35, 1, 4)]
    np.testing.assert_allclose(got, [-0.62, -1.76, -5.92], atol=0.02)


def test_table_matches_quadrature(rng):
    a = rng.uniform(-6, 4, 300)
    lm = rng.uniform(math.log(1e-3), math.log(80), 300)
    m, v = _table_lookup(a, lm)
    m0, v0 = first_photon_moments(a, np.exp(lm))
    assert np.max(np.abs(m - m0)) < 3e-3
    assert np.max(np.abs(v - v0)) < 3e-3


def _synthetic_peaks(rng, Q, mu0, a, sigma):
    """Peaks whose band of shots has spot shares f (a flat top with soft edges):
    returns log-likelihoods (Q, J), f_band, n_band, mean arrival (s) and counts."""
    B = 40
    steps = np.arange(B) - (B - 1) / 2
    f = np.clip(1.2 - np.abs(steps) / 14.0, 0.0, 1.0)  # 1 in the middle, ramps to 0
    f_band = np.broadcast_to(f, (Q, B)).copy()
    n_band = rng.integers(0, 2, (Q, B)).astype(float)  # 0 or 1 valid shot per step
    ll = np.zeros((Q, MU_GRID.size))
    tau_mean = np.full(Q, np.nan)
    n_det = np.zeros(Q)
    for q in range(Q):
        shots = np.repeat(np.arange(B), n_band[q].astype(int))
        t = np.concatenate([_first_arrivals(rng, mu0 * f[s], a, 1) for s in shots])
        hit = np.isfinite(t)
        n_det[q] = hit.sum()
        ll[q] = (detection_log_odds(f[shots[hit]]).sum(axis=0)
                 + (n_band[q][:, None] * np.log1p(-firing_probability(f))).sum(axis=0))
        tau_mean[q] = (t[hit].mean() - a) * sigma if hit.any() else np.nan
    return ll, f_band, n_band, tau_mean, n_det


@pytest.mark.parametrize("mu0, a", [(0.5, -8.0), (3.0, -8.0), (8.0, -1.6)])
def test_corrected_mean_is_unbiased_within_its_sigma(rng, mu0, a):
    """Known μ0 and pulse: the corrected mean TDC time of each peak lands on the pulse
    centre within its reported σ; the uncorrected mean does not (for strong returns)."""
    sigma = 6.33e-9
    tau0 = -a * sigma
    Q = 150
    ll, fb, nb, tau_mean, n = _synthetic_peaks(rng, Q, mu0, a, sigma)
    ok = n >= 3
    d, sd, var, mu = first_photon_delay(ll[ok], fb[ok], nb[ok], np.full(ok.sum(), tau0), sigma)
    err = tau_mean[ok] - d - tau0
    s = np.sqrt(var / n[ok] + sd ** 2)
    z = err / s
    assert abs(np.mean(z)) < 4 / math.sqrt(z.size), np.mean(z)
    assert 0.75 < np.std(z) < 1.33, np.std(z)
    # μ0 is recovered (posterior mean, across peaks)
    assert abs(np.median(mu) / mu0 - 1) < 0.35, np.median(mu)
    if mu0 >= 3:  # the uncorrected mean is biased by more than its own σ/√Q
        z0 = (tau_mean[ok] - tau0) / np.sqrt(sigma ** 2 / n[ok])
        assert abs(np.mean(z0)) > 8 / math.sqrt(z0.size)


def test_spot_fraction_matches_simulator(system):
    from mems_stereo.model.camera import project_points
    from mems_stereo.physics.spot import spot_fractions

    th = system.scanner.theta0 + np.array([-0.1, 0.0, 0.07])
    r = np.array([1.5, 3.0, 5.0])
    p = system.scanner.position
    d = scan_direction(th, system.scanner)
    pd = d @ p
    s = -pd + np.sqrt(pd * pd - p @ p + r ** 2)
    x = p + s[:, None] * d
    np.testing.assert_allclose(np.linalg.norm(x, axis=1), r)
    uv = project_points(x, system.receiver.camera_matrix)
    # the simulator's spot size at each point (beam, defocus, lens blur)
    from mems_stereo.physics.link_budget import LinkBudget
    from mems_stereo.physics.spot import SpotModel

    sig_m = SpotModel().sigma(s, x[:, 2], LinkBudget())
    sig = sig_m[:, None] / np.asarray(system.receiver.pixel_pitch)[None, :]
    assert sig_m.min() < 0.95 * sig_m.max()  # the size does vary with range
    rows, cols, frac = spot_fractions(uv, sig, system.receiver.image_size, radius=2)
    for k in range(3):
        for i, rr in enumerate(rows[k]):
            for j, cc in enumerate(cols[k]):
                if rr < 0 or cc < 0:
                    continue
                got = spot_fraction(system, rr, cc, th[k], r[k])
                assert abs(got - frac[k, i, j]) < 1e-9


def _wall_detections(system, rng, mu0, Z=2.0, K=4000):
    """First-photon detections of a wall at z = Z, a narrow Gaussian spot and μ0 photons
    per shot (whole pulse) spread over the pixels: (shot, peak, code, theta), the peaks'
    pixels and the path lengths; shots at uniform angles, no background."""
    from mems_stereo.model.camera import project_points

    th = system.scanner.theta0 + rng.uniform(-0.05, 0.05, K)
    p = system.scanner.position
    d = scan_direction(th, system.scanner)
    x = p + ((Z - p[2]) / d[:, 2])[:, None] * d
    u = project_points(x, system.receiver.camera_matrix)[:, 0]
    L = path_length_of_point(x, p)
    sc = DEFAULT_SPOT_SIGMA / system.receiver.pixel_pitch[0]
    sigma = system.laser.pulse_fwhm / (2 * math.sqrt(2 * math.log(2)))
    shot, col, code = [], [], []
    for c in np.unique(np.rint(u)).astype(int):
        f = ndtr((c + 0.5 - u) / sc) - ndtr((c - 0.5 - u) / sc)
        lit = np.flatnonzero(f > 1e-4)
        # the TDC starts at τ = 0: photons before it are lost (a = −τ0/σ)
        tau0 = L[lit] / system.speed_of_light + system.tdc.offset
        t = np.array([_first_arrivals(rng, mu0 * f[k] * ndtr(tau0[i] / sigma),
                                      -tau0[i] / sigma, 1)[0] for i, k in enumerate(lit)])
        hit = np.isfinite(t)
        tau = tau0[hit] + t[hit] * sigma
        shot.append(lit[hit])
        col.append(np.full(hit.sum(), c))
        code.append(np.floor(tau / system.tdc.bin_width).astype(int) + 1)
    shot, col, code = map(np.concatenate, (shot, col, code))
    cols = np.unique(col)
    peak = np.searchsorted(cols, col)
    return shot, peak, code, th, cols, L


def test_wall_points_corrected_and_unchanged_without_shots(system):
    rng = np.random.default_rng(7)
    shot, peak, code, th, cols, L = _wall_detections(system, rng, mu0=4.0)
    dtheta = 5e-5
    t0 = th.min() - 10 * dtheta
    steps = np.rint((th - t0) / dtheta).astype(int)
    th_snap = t0 + steps * dtheta  # the angle each shot is classified with
    sps = np.bincount(steps, minlength=steps.max() + 2)
    rows = np.zeros_like(cols)
    args = (system, shot, peak, code, th_snap, rows, cols)
    kw = {"min_counts": 5, "spot_sigma": DEFAULT_SPOT_SIGMA}  # the spot the data were made with
    # (the angle grid alone adds its quantisation to the stereo σ: both runs know it)
    plain = _fuse(*args, **kw, step_grid=(t0, dtheta))
    off = _fuse(*args, **kw, shots_per_step=sps, step_grid=(t0, dtheta), first_photon=False)
    on = _fuse(*args, **kw, shots_per_step=sps, step_grid=(t0, dtheta))
    # without the shot counts (or switched off) the result is the uncorrected one
    assert set(plain.attributes) == set(off.attributes)
    for k in plain.attributes:
        np.testing.assert_array_equal(plain[k], off[k])
    assert "tof_delay" in on.attributes and "tof_delay" not in plain.attributes
    # truth: the wall's range along each point's direction
    Z = 2.0
    for cl in (plain, on):
        dirs = cl.points / np.linalg.norm(cl.points, axis=1)[:, None]
        cl.attributes["true"] = Z / dirs[:, 2]
    # the stereo moves only by the mean angle's expected bias (the shot density across
    # the footprint: first_photon_correction.mean_angle_bias), towards the truth
    es0 = plain["range_stereo"] - plain["true"]
    es1 = on["range_stereo"] - on["true"]
    assert np.sqrt(np.mean(es1 ** 2)) <= np.sqrt(np.mean(es0 ** 2))
    assert np.max(np.abs(on["range_stereo"] - plain["range_stereo"])) < 0.05
    e0 = plain["range_tof"] - plain["true"]
    e1 = on["range_tof"] - on["true"]
    z1 = e1 / on["sigma_r_tof"]
    assert np.mean(e0) < -0.3  # first photons of μ0 = 4: about -0.8 m of range
    assert abs(np.mean(z1)) < 4 / math.sqrt(z1.size), (np.mean(e1), np.mean(z1))
    # σ carries the model's systematic allowance (first_photon_correction.MODEL_DELAY_FRACTION,
    # SATURATED_EDGE_SIGMA): on data that follow the model exactly it over-covers
    assert 0.4 < np.sqrt(np.mean(z1 ** 2)) < 1.5
    assert abs(np.median(on["signal_photons"]) / 4.0 - 1) < 0.35
    # the fused point moves by the ToF share only, and not away from the truth
    # (by more than a millimetre: the stereo share dominates at 2 m)
    ef0 = np.median(np.abs(plain["range"] - plain["true"]))
    ef1 = np.median(np.abs(on["range"] - on["true"]))
    assert ef1 <= ef0 * 1.05 + 1e-3


def test_streamed_halves_equal_one_pass(system):
    rng = np.random.default_rng(11)
    shot, peak, code, th, cols, _ = _wall_detections(system, rng, mu0=2.0, K=1500)
    dtheta = 5e-5
    t0 = th.min() - 10 * dtheta
    steps = np.rint((th - t0) / dtheta).astype(int)
    th = t0 + steps * dtheta
    sps = np.bincount(steps, minlength=steps.max() + 2)
    rows = np.zeros_like(cols)
    kw = dict(shots_per_step=sps, step_grid=(t0, dtheta))
    one = _fuse(system, shot, peak, code, th, rows, cols, min_counts=3, **kw)
    acc = PeakAccumulator(system, FusionPeaks(rows, cols), FusionOptions(**kw))
    half = np.arange(shot.size) % 2 == 0
    parts = [acc.empty_copy(), acc.empty_copy()]
    for part, sel in zip(parts, (half, ~half)):
        part.add_mode(shot[sel], peak[sel], code[sel], th)
    acc.mode = (parts[0] + parts[1]).mode
    acc.finish_mode()
    parts = [acc.empty_copy(), acc.empty_copy()]
    for part, sel in zip(parts, (half, ~half)):
        part.add_inliers(shot[sel], peak[sel], code[sel], th)
    two = (parts[0] + parts[1]).cloud(3)
    for k in ("range", "range_tof", "sigma_r_tof", "tof_delay", "signal_photons"):
        np.testing.assert_allclose(two[k], one[k], rtol=1e-9, atol=1e-12)


def _snapped(system, mu0, seed, K=4000):
    """:func:`_wall_detections` with each shot at its angle step's grid angle, and the
    valid shots per step: ``(args, step kwargs, true range per point function)``."""
    rng = np.random.default_rng(seed)
    shot, peak, code, th, cols, _ = _wall_detections(system, rng, mu0=mu0, K=K)
    dtheta = 5e-5
    t0 = th.min() - 10 * dtheta
    steps = np.rint((th - t0) / dtheta).astype(int)
    sps = np.bincount(steps, minlength=steps.max() + 2)
    args = (system, shot, peak, code, t0 + steps * dtheta, np.zeros_like(cols), cols)
    return args, {"shots_per_step": sps, "step_grid": (t0, dtheta)}


def test_mu_pinned_at_the_grid_top_keeps_the_mean_angles_scatter_spread(system, monkeypatch):
    """Firings that reach further from the pixel than the model's spot allows (here a
    spot model 4× narrower than the data's; on hardware, a surface whose range changes
    across the band) pin μ0 at the top of its grid: the binomial reduction of the mean
    angle's variance, which rests on the model's firing probabilities, is then not
    applied (first_photon_correction.MU_PINNED_FRACTION, MU_BEYOND_GRID), and σ_stereo
    covers the error."""
    import mems_stereo.pipeline.first_photon_correction as fpc
    from mems_stereo.physics.first_photon import MU_MAX

    args, kw = _snapped(system, mu0=60.0, seed=5)
    kw.update(min_counts=5, spot_sigma=DEFAULT_SPOT_SIGMA / 4)
    on = _fuse(*args, **kw)
    assert np.median(on["signal_photons"]) >= fpc.MU_PINNED_FRACTION * MU_MAX
    monkeypatch.setattr(fpc, "MU_PINNED_FRACTION", np.inf)
    off = _fuse(*args, **kw)
    assert len(on) == len(off)
    np.testing.assert_array_equal(on["pixel"], off["pixel"])
    # (not every point: a depth edge (PeakMeans.cloud) is marked where neighbours differ
    # by more than their σ, and adds the pixel's span to it)
    ratio = on["sigma_r_stereo"] / off["sigma_r_stereo"]
    assert np.median(ratio) > 1.2, np.median(ratio)
    dirs = on.points / np.linalg.norm(on.points, axis=1)[:, None]
    z = (on["range_stereo"] - 2.0 / dirs[:, 2]) / on["sigma_r_stereo"]
    z_off = (off["range_stereo"] - 2.0 / dirs[:, 2]) / off["sigma_r_stereo"]
    # (seed 5: RMS error/σ_stereo 0.81 with the guard, 1.38 without)
    assert np.sqrt(np.mean(z ** 2)) < min(1.2, np.sqrt(np.mean(z_off ** 2)))
    # with the model's own spot, μ0 is found (not pinned) and the reduction applies;
    # a return stronger than the grid's top (μ0 4× it) is pinned but explained: it too
    monkeypatch.undo()
    for mu0, pinned in ((8.0, False), (4 * MU_MAX, True)):
        args, kw = _snapped(system, mu0=mu0, seed=6)
        kw.update(min_counts=5, spot_sigma=DEFAULT_SPOT_SIGMA)
        good = _fuse(*args, **kw)
        assert (np.median(good["signal_photons"]) >= fpc.MU_PINNED_FRACTION * MU_MAX) == pinned
        monkeypatch.setattr(fpc, "MU_PINNED_FRACTION", np.inf)
        same = _fuse(*args, **kw)
        monkeypatch.undo()
        np.testing.assert_array_equal(good["sigma_r_stereo"], same["sigma_r_stereo"])


@pytest.mark.parametrize("a", [-8.0, -1.2])
def test_delay_sensitivity_to_the_signal_level(a):
    """``first_photon_delay(..., mu_factor=F)``'s fifth result is half the change of the
    band's delay between μ0/F and μ0·F: checked against the delays of posteriors
    concentrated at those two grid points (F = three grid steps)."""
    sigma = 6.33e-9
    f = 0.6 * np.exp(-0.5 * np.linspace(-3, 3, 13) ** 2)  # a spot's shares across the band
    f_band = np.tile(f, (3, 1))
    n_band = np.full_like(f_band, 40.0)
    j = np.array([10, 22, 30])  # μ0 ≈ 0.06, 1, 4
    F = MU_GRID[j[0] + 3] / MU_GRID[j[0]]

    def sharp(jj):  # log-likelihood with all its weight at grid point jj
        ll = np.full((3, MU_GRID.size), -1e4)
        ll[np.arange(3), jj] = 0.0
        return ll

    tau0 = np.full(3, -a * sigma)
    d_hi = first_photon_delay(sharp(j + 3), f_band, n_band, tau0, sigma)[0]
    d_lo = first_photon_delay(sharp(j - 3), f_band, n_band, tau0, sigma)[0]
    out = first_photon_delay(sharp(j), f_band, n_band, tau0, sigma, mu_factor=F)
    assert len(out) == 5
    np.testing.assert_allclose(out[4], 0.5 * np.abs(d_hi - d_lo), rtol=1e-6, atol=1e-15)
    # strong returns are the sensitive ones (pile-up moves the first photon)
    assert out[4][2] > out[4][0]
    assert len(first_photon_delay(sharp(j), f_band, n_band, tau0, sigma)) == 4
