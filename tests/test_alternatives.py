"""The evaluation helpers of benchmarks/bench_pipeline.py (the alternatives and the truth checks)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from mems_stereo.geometry.triangulation import path_length_of_point
from mems_stereo.model.tdc import path_length_from_codes
from mems_stereo.sim.scene import scene_from_dict

_SPEC = importlib.util.spec_from_file_location(
    "bench_pipeline", Path(__file__).resolve().parents[1] / "benchmarks" / "bench_pipeline.py")
bp = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(bp)


def first_photon_histograms(rng, n_pix, n_shots, rate_hz, bin_width, n_bins, ret_code=None,
                            ret_prob=0.0, ret_sigma_bins=20.0):
    """(1, n_pix, n_bins) histograms and (n_shots, 1, n_pix) codes of first photons.

    Background: exponential first arrivals at ``rate_hz``; a return (pixels
    whose ``ret_code`` > 0) arrives with probability ``ret_prob`` per shot,
    Gaussian around ``ret_code``; the earlier of the two is recorded.
    """
    t_bg = rng.exponential(1.0 / rate_hz, size=(n_shots, n_pix)) / bin_width
    t = t_bg
    if ret_code is not None:
        has = (rng.random((n_shots, n_pix)) < ret_prob) & (ret_code[None] > 0)
        t_ret = np.where(has, ret_code[None] - 0.5 + ret_sigma_bins
                         * rng.standard_normal((n_shots, n_pix)), np.inf)
        t = np.minimum(t_bg, np.maximum(t_ret, 0.0))
    codes = np.floor(t).astype(np.int64) + 1
    codes[codes > n_bins] = 0
    hist = np.zeros((n_pix, n_bins + 1), np.int64)
    np.add.at(hist, (np.broadcast_to(np.arange(n_pix), codes.shape), codes), 1)
    return hist[None, :, 1:], codes[:, None, :].astype(np.uint16)


def test_raw_histogram_peaks_under_floodlight_pileup(rng):
    """6 MHz pile-up: the returns are found near their code, background-only pixels stay empty."""
    bw, n_bins, n_shots, width = 312.5e-12, 4096, 3200, 49
    n_pix = 120
    ret = np.where(np.arange(n_pix) < 20, rng.integers(60, 800, n_pix), 0)
    hist, codes = first_photon_histograms(rng, n_pix, n_shots, 6e6, bw, n_bins, ret, 0.3)
    code, rate = bp.raw_histogram_peaks(hist, n_shots, bw, width, 1e-2 * width / n_bins)
    # the return pixels: found, within half the filter width of the true code
    assert np.all(code[0, :20] > 0)
    assert np.all(np.abs(code[0, :20] - ret[:20]) <= width // 2)
    # background-only pixels: nominally 0.01 false peaks per pixel (the window
    # positions are correlated, so "n_bins / width independent windows" is a
    # little optimistic: 0.025 per pixel measured over 400 pixels)
    assert np.count_nonzero(code[0, 20:]) <= 6
    # the background MLE (return window excluded): every shot detects, so its
    # relative spread is about 1/sqrt(n_shots) per pixel; unbiased when pooled
    rel = rate[0] / 6e6 - 1
    assert np.all(np.abs(rel) < 4 / np.sqrt(n_shots))
    assert abs(np.mean(rel)) < 3 / np.sqrt(n_shots * n_pix)


def test_window_labels_match_a_loop(rng):
    bins = rng.integers(0, 30, size=(50, 2, 3)).astype(np.uint16)
    code = np.array([[10, 0, 25], [1, 5, 29]])
    lab = bp.window_labels(bins, code, 4)
    for k, r, c in np.ndindex(bins.shape):
        b = int(bins[k, r, c])
        want = 0 if b == 0 else (1 if code[r, c] > 0 and abs(b - code[r, c]) <= 4 else 2)
        assert lab[k, r, c] == want


def test_scores_count_truth_classes():
    truth = np.array([1, 1, 1, 1, 2, 2, 2, 2, 2, 0])
    lab = np.array([1, 1, 2, 1, 2, 2, 1, 2, 2, 0])
    rc, rj = bp.scores(truth, lab)
    assert rc == pytest.approx(3 / 4) and rj == pytest.approx(4 / 5)


def test_detection_points_lie_on_pixel_rays_at_their_path_length(system, rng):
    bins = np.zeros((30, 1, 192), np.uint16)
    k = rng.integers(0, 30, 200)
    c = rng.integers(0, 192, 200)
    bins[k, 0, c] = rng.integers(30, 4000, 200)
    pts, (kk, rr, cc) = bp.detection_pixel_points(system, bins)
    L = path_length_from_codes(bins[kk, rr, cc], system.tdc, system.speed_of_light)
    np.testing.assert_allclose(path_length_of_point(pts, system.scanner.position), L,
                               rtol=1e-9)
    # each point projects back onto its own pixel
    uv = (system.receiver.camera_matrix @ (pts / pts[:, 2:3]).T).T
    np.testing.assert_allclose(uv[:, 0], cc, atol=1e-6)
    np.testing.assert_allclose(uv[:, 1], rr, atol=1e-6)


def test_sor_keeps_a_dense_surface_and_drops_isolated_points(system, rng):
    """Returns around one code in every pixel (a surface) plus sparse far codes."""
    K = 40
    code_surface = 60  # about 2.8 m of path, ~1.4 m of range
    bins = np.clip(code_surface + rng.normal(0, 15, (K, 1, 192)), 1, 4096).astype(np.uint16)
    far = rng.random((K, 1, 192)) < 0.02
    bins[far] = rng.integers(1000, 4096, int(far.sum()))
    lab = bp.sor_labels(system, bins)
    assert np.mean(lab[~far] == 1) > 0.9
    assert np.mean(lab[far] == 2) > 0.9


def test_sor_drops_exact_duplicates(system):
    """Open3D 0.20 removes points whose mean neighbour distance is 0 (>= 21 copies).

    Recorded because it matters for per-detection points: detections of one
    pixel in one code are identical points.
    """
    bins = np.full((40, 1, 192), 60, np.uint16)
    lab = bp.sor_labels(system, bins)
    assert np.all(lab == 2)


def test_true_ranges_on_a_plane():
    """A wall at z = 3 m: the range along a direction is 3 / cos(angle to z)."""
    scene = scene_from_dict({"objects": [{"type": "plane", "center": [0, 0, 3.0],
                                          "normal": [0, 0, -1], "size": [20, 20],
                                          "reflectivity": 0.5}]})
    d = np.array([[0.0, 0.0, 1.0], [0.3, 0.0, 1.0], [-0.2, 0.1, 1.0], [0.0, 0.0, -1.0]])
    r = bp.true_ranges(scene, 2.0 * d)
    cos = d[:3, 2] / np.linalg.norm(d[:3], axis=1)
    np.testing.assert_allclose(r[:3], 3.0 / cos, rtol=1e-6)
    assert np.isinf(r[3])


def test_sigma_ratios_of_gaussian_errors(rng):
    sigma = rng.uniform(0.01, 0.5, 20000)
    e = sigma * rng.standard_normal(sigma.size)
    rms, med = bp.sigma_ratios(e, sigma)
    assert rms == pytest.approx(1.0, abs=0.03)
    assert med == pytest.approx(1.0, abs=0.03)
    rms2, med2 = bp.sigma_ratios(2 * e, sigma)
    assert rms2 == pytest.approx(2 * rms) and med2 == pytest.approx(2 * med)
