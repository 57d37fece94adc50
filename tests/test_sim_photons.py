"""Photon statistics of the simulator against theory and brute-force Monte Carlo."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from mems_stereo.model.system import burkard2022
from mems_stereo.sim import (
    LinkBudget,
    PulseShape,
    Scene,
    SimulationOptions,
    SpotModel,
    background_first_arrivals,
    emitted_photons,
    first_photon_cdf,
    first_photon_mean_delay,
    first_signal_arrival,
    scene_from_dict,
    shot_returns,
    simulate,
)

BW = 312.5e-12
NBINS = 4096
WINDOW = BW * NBINS


def brute_force_first_background(rate, n, window, rng):
    """Generate every photon of a Poisson process in [0, window); keep the first."""
    counts = rng.poisson(rate * window, size=n)
    first = np.full(n, np.inf)
    has = counts > 0
    # the minimum of c uniform times: draw them all
    idx = np.repeat(np.flatnonzero(has), counts[has])
    t = rng.random(idx.size) * window
    np.minimum.at(first, idx, t)
    return first


@pytest.mark.parametrize("rate", [1e5, 6e6, 2.5e7])
def test_background_detection_probability(rate):
    rng = np.random.default_rng(10)
    n = 200_000
    idx, tau = background_first_arrivals(rate, n, WINDOW, rng)
    p = 1.0 - math.exp(-rate * WINDOW)
    sd = math.sqrt(p * (1 - p) / n) + 1e-12
    assert abs(idx.size / n - p) < 5 * sd + 1e-9
    assert np.all(np.diff(idx) > 0) and idx.min() >= 0 and idx.max() < n
    assert np.all((tau >= 0) & (tau < WINDOW))


@pytest.mark.parametrize("rate", [1e6, 6e6])
def test_background_first_arrival_matches_brute_force(rate):
    rng = np.random.default_rng(11)
    n = 40_000
    _, tau = background_first_arrivals(rate, n, WINDOW, rng)
    ref = brute_force_first_background(rate, n, WINDOW, rng)
    ref = ref[np.isfinite(ref)]
    assert stats.ks_2samp(tau, ref).pvalue > 1e-3


def test_pile_up_codes_are_geometric():
    """Under constant background the first-photon code is geometric, truncated to the window."""
    sysm = burkard2022()
    rate = 6e6
    # a scene the beam never reaches: only background and dark counts
    scene = scene_from_dict({"objects": [{"type": "plane", "center": [0, 0, -5],
                                          "normal": [0, 0, 1], "size": [1, 1],
                                          "reflectivity": 0.5}]})
    rec = simulate(sysm, scene, 400, rng=np.random.default_rng(3), background_hz=rate,
                   dark_count_hz=0.0, options=SimulationOptions(phase=0.0))
    codes = rec.bins[rec.bins > 0].astype(np.int64)
    assert np.all(rec.truth["label"][rec.bins > 0] == 2)
    n_total = rec.bins.size
    p_any = 1 - math.exp(-rate * WINDOW)
    assert abs(codes.size / n_total - p_any) < 5 * math.sqrt(p_any * (1 - p_any) / n_total)
    q = math.exp(-rate * BW)
    edges = np.arange(1, NBINS + 2, 128)  # groups of 128 codes
    obs, _ = np.histogram(codes, bins=edges)
    cdf = lambda n: (1 - q ** (n - 1)) / (1 - q ** NBINS)  # noqa: E731  P(code < n)
    expected = codes.size * (cdf(edges[1:]) - cdf(edges[:-1]))
    keep = expected > 5
    chi = stats.chisquare(obs[keep], expected[keep] * obs[keep].sum() / expected[keep].sum())
    assert chi.pvalue > 1e-3
    # pile-up: the first group holds far more than a flat share
    assert obs[0] > 5 * obs[-1]


def brute_force_first_signal(mu, delay, sigma, window, rng, n):
    counts = rng.poisson(mu, size=n)
    first = np.full(n, np.inf)
    idx = np.repeat(np.arange(n), counts)
    t = delay + rng.normal(0.0, sigma, size=idx.size)
    ok = (t >= 0) & (t < window)
    np.minimum.at(first, idx[ok], t[ok])
    return first


@pytest.mark.parametrize("mu,delay", [(0.3, 30e-9), (2.0, 30e-9), (3.0, 4e-9), (1.0, 1.2e-6)])
def test_first_signal_photon_against_brute_force(mu, delay):
    fwhm, jitter = 14.9e-9, 50e-12
    pulse = PulseShape.gaussian(fwhm, jitter)
    sigma = math.hypot(fwhm / (2 * math.sqrt(2 * math.log(2))), jitter)
    rng = np.random.default_rng(12)
    n = 40_000
    tau, m = first_signal_arrival(np.full(n, mu), np.full(n, delay), pulse, WINDOW, rng)
    # detection probability: 1 - exp(-mu * p_window)
    p_win = stats.norm.cdf((WINDOW - delay) / sigma) - stats.norm.cdf(-delay / sigma)
    p_det = 1 - math.exp(-mu * p_win)
    det = np.isfinite(tau)
    assert np.array_equal(det, m > 0)
    assert abs(det.mean() - p_det) < 5 * math.sqrt(p_det * (1 - p_det) / n)
    ref = brute_force_first_signal(mu, delay, sigma, WINDOW, rng, n)
    assert stats.ks_2samp(tau[det], ref[np.isfinite(ref)]).pvalue > 1e-3


def test_first_photon_mean_delay_against_monte_carlo():
    pulse = PulseShape.gaussian(14.9e-9, 0.0)
    rng = np.random.default_rng(5)
    n = 100_000
    for mu in (0.05, 1.0, 4.0):
        tau, _ = first_signal_arrival(np.full(n, mu), np.full(n, 100e-9), pulse, WINDOW, rng)
        s = tau[np.isfinite(tau)] - 100e-9
        pred = float(first_photon_mean_delay(mu, pulse))
        assert abs(s.mean() - pred) < 5 * s.std() / math.sqrt(s.size)
        # its CDF at the pulse centre: (1 - exp(-mu/2)) / (1 - exp(-mu))
        assert abs(first_photon_cdf(0.0, mu, pulse) - (1 - math.exp(-mu / 2))
                   / (1 - math.exp(-mu))) < 1e-6
    assert float(first_photon_mean_delay(1e-6, pulse)) == pytest.approx(0.0, abs=2e-12)
    assert float(first_photon_mean_delay(4.0, pulse)) < -3e-9  # pile-up: earlier


def test_sampled_pulse_matches_gaussian():
    fwhm = 14.9e-9
    sig = fwhm / (2 * math.sqrt(2 * math.log(2)))
    t = np.linspace(-6 * sig, 6 * sig, 301)
    sampled = PulseShape.from_samples(t, 3.0 * np.exp(-0.5 * (t / sig) ** 2), jitter=0.5e-9)
    ref = PulseShape.gaussian(fwhm, 0.5e-9)
    grid = np.linspace(-30e-9, 30e-9, 121)
    assert np.max(np.abs(sampled.cdf_at(grid) - ref.cdf_at(grid))) < 2e-3
    assert sampled.energy_time == pytest.approx(fwhm * math.sqrt(math.pi / (4 * math.log(2))),
                                                rel=1e-3)
    # an asymmetric (rectangular) pulse: its quantiles are linear
    rect = PulseShape.from_samples([0.0, 1e-12, 20e-9, 20.001e-9], [0, 1, 1, 0])
    assert rect.ppf(0.25) == pytest.approx(5e-9, abs=5e-11)
    with pytest.raises(ValueError):
        PulseShape.from_samples([0.0, 1.0], [0.0, 0.0])


def _wall(z=2.0, refl=0.4):
    return scene_from_dict({"objects": [{"type": "plane", "center": [0, 0, z],
                                         "normal": [0, 0, -1], "size": [20, 4],
                                         "reflectivity": refl}]})


def test_link_budget_by_hand():
    """Mean signal photons per shot from an independent hand calculation."""
    sysm = burkard2022()
    z, refl = 2.0, 0.4
    theta = np.array([sysm.scanner.theta0 + 0.05])
    link, spot = LinkBudget(), SpotModel()
    pulse = PulseShape.gaussian(sysm.laser.pulse_fwhm)
    ret = shot_returns(sysm, _wall(z, refl), theta, link=link, spot=spot,
                       n_emitted=emitted_photons(link, pulse, sysm.laser.wavelength))
    x = ret["point"][0]
    # by hand
    h, c0 = 6.62607015e-34, 299792458.0
    e_pulse = 0.080 * 14.9e-9 * 1.0644670194  # Gaussian: P * FWHM * sqrt(pi / (4 ln 2))
    n_emit = e_pulse / (h * c0 / 659e-9) * 0.8125
    r = np.linalg.norm(x)
    cos_e = x[2] / r  # wall normal -z, direction to the receiver -x / r
    a_ap = math.pi * (8e-3 / 2 / 2) ** 2
    fill = 4 * math.pi * 6e-6 ** 2 / (40.56e-6 * 209.6e-6)
    mu = n_emit * refl * cos_e / math.pi * a_ap * cos_e / r ** 2 * 0.7 * 0.5 * 0.2 * fill
    assert x[2] == pytest.approx(z, abs=1e-5)
    assert ret["mu"][0] == pytest.approx(mu, rel=1e-6)
    assert 0.5 < mu < 20  # about one photon per shot: the paper's regime


def test_mean_signal_counts_per_shot_monte_carlo():
    """Without background, detections per shot = sum over pixels of 1 - exp(-mu_pixel);
    at low flux this is the link budget's mean."""
    sysm = burkard2022()
    link = LinkBudget(peak_power=0.002)  # ~0.05 photons per shot
    n = 20_000
    rec = simulate(sysm, _wall(2.0), n, rng=np.random.default_rng(4), background_hz=0.0,
                   dark_count_hz=0.0, options=SimulationOptions(link=link, phase=0.4))
    det = int((rec.truth["label"] == 1).sum())
    assert int((rec.truth["label"] == 2).sum()) == 0
    mu = rec.truth["signal_mean"]
    assert 0.01 < mu.mean() < 0.2
    expected = np.sum(1 - np.exp(-mu))  # upper bound of the sum over pixels
    lower = np.sum(mu - mu ** 2 / 2)
    assert lower - 5 * math.sqrt(expected) < det < expected + 5 * math.sqrt(expected)
    assert det == pytest.approx(mu.sum(), rel=0.15)


def test_window_loses_early_photons():
    """A return whose pulse centre sits at the window's opening loses half its photons."""
    sysm = burkard2022()
    scene: Scene = _wall(2.0)
    link = LinkBudget(peak_power=0.004)
    n = 20_000
    kw = dict(background_hz=0.0, dark_count_hz=0.0,
              options=SimulationOptions(link=link, phase=0.4, timing_jitter=0.0))
    ref = simulate(sysm, scene, n, rng=np.random.default_rng(8), **kw)
    L = ref.truth["path_length"]
    # shift the TDC so that tau = L/c + offset = 0 for a mean path length
    off = -float(np.mean(L)) / sysm.speed_of_light
    cut = simulate(sysm, scene, n, rng=np.random.default_rng(8),
                   true_system=sysm.with_params(tdc_offset=off), **kw)
    a = (ref.truth["label"] == 1).sum()
    b = (cut.truth["label"] == 1).sum()
    # low flux: each shot keeps the share Phi((L/c + off) / sigma) of its photons
    sigma = sysm.laser.pulse_fwhm / (2 * math.sqrt(2 * math.log(2)))
    mu = ref.truth["signal_mean"]
    kept = stats.norm.cdf((L / sysm.speed_of_light + off) / sigma)
    assert b / a == pytest.approx(np.sum(mu * kept) / np.sum(mu), abs=0.04)
    assert 0.4 < b / a < 0.6
