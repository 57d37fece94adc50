"""Time-tagged input: histograms, timing spread, signal and background on synthetic scenes."""

from __future__ import annotations

import numpy as np
import pytest

from mems_stereo.errors import FormatError
from mems_stereo.timetags import (
    estimate_timing_spread,
    histogram_from_timetags,
    pixel_of_photon,
    signal_background_from_timetags,
)

GATE = (0.0, 200e3)          # ps, as the real data
SIGMA = 470.0                # ps, return's timing spread


def synthetic_scene(rng, H=48, W=48, signal_mean=1.2, bg_per_pixel=8.6, sigma=SIGMA):
    """Uniform background (spatially varying rate) + one return per pixel on a sloped surface.

    Returns CSR time tags, the truth (signal photons, background photons) per pixel.
    """
    yy, xx = np.mgrid[:H, :W]
    depth = 40e3 + 150.0 * xx + 100.0 * yy + np.where(xx > W // 2, 30e3, 0.0)   # ps
    bg_mean = bg_per_pixel * (1 + 0.3 * np.sin(yy / 7.0))
    n_s = rng.poisson(signal_mean, size=(H, W))
    n_b = rng.poisson(bg_mean)
    times = []
    for i in range(H * W):
        y, x = divmod(i, W)
        ts = depth[y, x] + sigma * rng.standard_normal(n_s[y, x])
        tb = rng.uniform(*GATE, size=n_b[y, x])
        t = np.concatenate([ts, tb])
        times.append(t[(t >= GATE[0]) & (t < GATE[1])])
    offsets = np.r_[0, np.cumsum([t.size for t in times])].astype(np.int64)
    return np.concatenate(times), offsets, n_s, n_b


def test_histogram_matches_numpy_per_pixel(rng):
    t, o, _, _ = synthetic_scene(rng, 6, 5)
    h = histogram_from_timetags(t, o, 1000.0, *GATE)
    assert h.shape == (30, 200)
    for i in range(30):
        ref, _ = np.histogram(t[o[i]:o[i + 1]], bins=np.arange(GATE[0], GATE[1] + 1, 1000.0))
        np.testing.assert_array_equal(h[i], ref)


def test_histogram_drops_photons_outside_window():
    h = histogram_from_timetags(np.array([-1.0, 0.0, 9.99, 10.0]), np.array([0, 4]), 5.0, 0, 10)
    np.testing.assert_array_equal(h, [[1, 1]])


def test_offsets_are_validated():
    with pytest.raises(FormatError, match="never decrease"):
        pixel_of_photon(np.array([0, 3, 2]))
    with pytest.raises(FormatError, match="timestamps"):
        histogram_from_timetags(np.zeros(5), np.array([0, 2, 4]), 1.0, 0, 10)
    np.testing.assert_array_equal(pixel_of_photon(np.array([0, 2, 2, 3])), [0, 0, 2])


def test_timing_spread_recovers_sigma(rng):
    t, o, _, _ = synthetic_scene(rng)
    ts = estimate_timing_spread(t, o, (48, 48), *GATE, coarse_bin=1000.0)
    # the gentle slope (≤ 0.15 ns per pixel) widens the stack only a little
    assert ts.sigma == pytest.approx(SIGMA, rel=0.2)
    # 99 % extents (Gaussian: 2.33σ); ~1400 return photons make the 1 % tails noisy
    assert 1.5 * SIGMA < ts.tail < 9 * SIGMA
    assert 1.5 * SIGMA < ts.lead < 9 * SIGMA


def test_signal_and_sbr_recovered(rng):
    t, o, n_s, n_b = synthetic_scene(rng)
    ts = estimate_timing_spread(t, o, (48, 48), *GATE, coarse_bin=1000.0)
    est = signal_background_from_timetags(t, o, (48, 48), *GATE, ts.fwhm, ts.lead, ts.tail)
    true_mean = n_s.mean()                 # realised signal photons (all inside the gate)
    true_sbr = n_s.sum() / n_b.sum()
    assert est.mean_signal == pytest.approx(true_mean, abs=3 * est.mean_signal_std + 0.02)
    assert est.sbr == pytest.approx(true_sbr, abs=3 * est.sbr_std + 0.003)
    # the background rests on most of the window: σ ≈ √(background photons)/P
    expect_std = np.sqrt(n_b.sum() / est.free_fraction) / n_b.size
    assert est.mean_signal_std == pytest.approx(expect_std, rel=0.3)
    assert 0.5 < est.free_fraction < 1.0
    # the background rate follows its spatial variation (rows)
    rate_rows = est.background_rate.mean(1) * (GATE[1] - GATE[0])
    true_rows = n_b.mean(1)
    assert np.corrcoef(rate_rows, true_rows)[0, 1] > 0.8


def test_background_only_gives_no_signal(rng):
    t, o, n_s, n_b = synthetic_scene(rng, signal_mean=0.0)
    est = signal_background_from_timetags(t, o, (48, 48), *GATE, 1100.0, 1100.0, 3300.0)
    assert abs(est.mean_signal) < 3 * est.mean_signal_std + 0.01


def test_shape_must_match_offsets(rng):
    t, o, _, _ = synthetic_scene(rng, 4, 4)
    with pytest.raises(FormatError, match="shape"):
        signal_background_from_timetags(t, o, (4, 5), *GATE, 1000.0, 1000.0, 3000.0)
