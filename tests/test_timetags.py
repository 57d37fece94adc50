"""Time-tagged input: histograms, timing spread, signal and background on synthetic scenes."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import erf

from mems_stereo.errors import FormatError
from mems_stereo.pipeline.timetags import (
    estimate_timing_spread,
    histogram_from_timetags,
    pixel_of_photon,
    signal_background_from_timetags,
    window_counts_from_timetags,
)

GATE = (0.0, 200e3)          # ps, as the real data
SIGMA = 470.0                # ps, return's timing spread


def synthetic_scene(rng, H=48, W=48, signal_mean=1.2, bg_per_pixel=8.6, sigma=SIGMA,
                    return_depth=False):
    """Uniform background (spatially varying rate) + one return per pixel on a sloped surface.

    Returns CSR time tags, the truth (signal photons, background photons) per pixel
    and, with ``return_depth``, the (H, W) true return times (ps).
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
    if return_depth:
        return np.concatenate(times), offsets, n_s, n_b, depth
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


# --------------------------------------------------------------------------- window counts
def test_timing_spread_mean_offset_near_zero(rng):
    t, o, _, _ = synthetic_scene(rng)
    ts = estimate_timing_spread(t, o, (48, 48), *GATE, coarse_bin=1000.0)
    assert abs(ts.mu) < 0.2 * SIGMA            # symmetric return: window centred on it


def test_window_counts_match_brute_force(rng):
    t, o, _, _ = synthetic_scene(rng, 12, 10)
    w = window_counts_from_timetags(t, o, (12, 10), *GATE, 900.0, 1000.0, offset=37.0)
    assert w.window == 1800.0
    ref = np.array([np.sum(np.abs(t[o[i]:o[i + 1]] - w.centre.ravel()[i]) <= 900.0)
                    for i in range(120)]).reshape(12, 10)
    np.testing.assert_array_equal(w.signal, ref)
    assert w.n_total == t.size
    assert w.mean_signal == pytest.approx(ref.sum() / 120)
    assert w.sbr == pytest.approx(ref.sum() / (t.size - ref.sum()))


def test_window_count_is_signal_in_window_plus_background_in_window(rng):
    """Closed form: E[count_i] = n_s,i · P(|d_i + σZ − c_i| ≤ h) + n_b,i · 2h / T."""
    H = W = 48
    t, o, n_s, n_b, depth = synthetic_scene(rng, H, W, return_depth=True)
    h = 2 * SIGMA
    w = window_counts_from_timetags(t, o, (H, W), *GATE, h, 1000.0)
    d = depth - w.centre
    p_in = 0.5 * (erf((h - d) / (SIGMA * np.sqrt(2))) + erf((h + d) / (SIGMA * np.sqrt(2))))
    expect = (n_s * p_in).sum() + n_b.sum() * 2 * h / (GATE[1] - GATE[0])
    # Poisson spread of the counted photons given n_s, n_b: binomial ≤ √expect
    assert w.signal.sum() == pytest.approx(expect, abs=3 * np.sqrt(expect))
    # the neighbours place the window well: ≥ 90 % of the signal inside ±2σ (Gaussian: 95.4 %)
    assert (n_s * p_in).sum() / n_s.sum() > 0.9
    # the convention counts background as signal: more than the true signal in the window
    assert w.signal.sum() > (n_s * p_in).sum()


def test_window_counts_validate_input(rng):
    t, o, _, _ = synthetic_scene(rng, 4, 4)
    with pytest.raises(FormatError, match="half_width"):
        window_counts_from_timetags(t, o, (4, 4), *GATE, 0.0, 1000.0)
    with pytest.raises(FormatError, match="shape"):
        window_counts_from_timetags(t, o, (4, 5), *GATE, 900.0, 1000.0)
