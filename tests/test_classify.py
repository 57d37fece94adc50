"""The consistency classifier on synthetic detections: a flat wall plus uniform background."""

from __future__ import annotations

import numpy as np
import pytest

from mems_stereo.geometry.triangulation import path_length_of_point
from mems_stereo.geometry.uncertainty import spreads_for
from mems_stereo.io.recording import Recording
from mems_stereo.model.camera import project_points
from mems_stereo.model.scanner import scan_direction
from mems_stereo.model.tdc import codes_from_path_length
from mems_stereo.pipeline.consistency import (
    accepted_code_intervals,
    classify_bins,
    classify_detections,
    k_from_confidence,
)


def _wall(system, rng, K=400, Z=3.0, p_bg=0.3):
    """Shots over the scan, a wall at z = Z, a return per shot in the pixel the spot
    lands in (uniform landing over the pixel) with Gaussian timing, uniform background."""
    th = system.scanner.theta0 + system.scanner.theta_mech_max * np.cos(
        2 * np.pi * 0.0785 * np.arange(K))
    p = system.scanner.position
    d = scan_direction(th, system.scanner)
    x = p + ((Z - p[2]) / d[:, 2])[:, None] * d
    u = project_points(x, system.receiver.camera_matrix)[:, 0]
    col = np.rint(u).astype(int)
    on = (col >= 0) & (col < system.receiver.width)
    sp = spreads_for(system)
    L = path_length_of_point(x, p) + rng.normal(0, sp.sigma_L(system), K)
    code = np.floor(codes_from_path_length(L, system.tdc, system.speed_of_light) + 0.5)
    bins = np.zeros((K, 1, system.receiver.width), np.uint16)
    truth = np.zeros(bins.shape, np.uint8)
    bg = rng.random(bins.shape) < p_bg
    bins[bg] = rng.integers(1, system.tdc.n_bins + 1, int(bg.sum()))
    truth[bg] = 2
    k = np.flatnonzero(on & (code >= 1))
    bins[k, 0, col[k]] = code[k]
    truth[k, 0, col[k]] = 1
    return th, bins, truth


def test_k_from_confidence():
    assert np.isclose(k_from_confidence(0.9973), 3.0, atol=2e-3)
    assert np.isclose(k_from_confidence(0.95), 1.95996, atol=1e-4)
    with pytest.raises(ValueError):
        k_from_confidence(1.0)


def test_wall_recall_and_rejection(system, rng):
    th, bins, truth = _wall(system, rng)
    lab = classify_bins(system, bins, th, np.ones(th.size, bool))
    assert lab.dtype == np.uint8 and lab.shape == bins.shape
    assert np.all((lab == 0) == (bins == 0))
    recall = np.mean(lab[truth == 1] == 1)
    rejection = np.mean(lab[truth == 2] == 2)
    assert recall >= 0.99, recall
    assert rejection >= 0.97, rejection


def test_intervals_shape_and_consistency(system, rng):
    th, bins, truth = _wall(system, rng, K=50)
    lo, hi = accepted_code_intervals(system, th)
    assert lo.shape == hi.shape == bins.shape and lo.dtype == np.int32
    assert np.all(lo >= 1) and np.all(hi <= system.tdc.n_bins)
    # pixels to the right of the beam's vanishing point see it only behind: nothing accepted
    K = system.receiver.camera_matrix
    d = scan_direction(th, system.scanner)
    c_inf = K[0, 2] + K[0, 0] * d[:, 0] / d[:, 2]
    cols = np.arange(system.receiver.width)
    far_right = cols[None, :] > c_inf[:, None] + 2
    assert np.all(lo[:, 0][far_right] > hi[:, 0][far_right])
    # a wider confidence accepts a superset
    lo2, hi2 = accepted_code_intervals(system, th, confidence=0.9999)
    some = lo <= hi
    assert np.all(lo2[some] <= lo[some]) and np.all(hi2[some] >= hi[some])


def test_invalid_shots_are_left_out(system, rng):
    th, bins, truth = _wall(system, rng, K=40)
    valid = np.ones(40, bool)
    valid[::3] = False
    th2 = th.copy()
    th2[1] = np.nan
    lab = classify_bins(system, bins, th2, valid)
    assert np.all(lab[~valid] == 0) and np.all(lab[1] == 0)


def test_reference_form_agrees(system, rng):
    th, bins, truth = _wall(system, rng, K=200)
    lab = classify_bins(system, bins, th)
    k, r, c = np.nonzero(bins)
    ref = classify_detections(system, k, r, c, bins[k, r, c], th)
    assert np.mean(ref == (lab[k, r, c] == 1)) > 0.99


def test_classify_recording_counts_unknown_angles(system, rng):
    th, bins, truth = _wall(system, rng, K=200)
    f = system.scanner.f_mech
    t = np.arange(200) / system.laser.f_rep
    # zero crossings consistent with θ_mech = A cos(2π f t): falling at φ = π/2
    zc = (0.25 + 0.5 * np.arange(40)) / f
    rising = (np.arange(40) % 2).astype(np.uint8)
    keep = zc > 0.002  # the first shots lie before the first crossing
    rec = Recording(system, t, bins, zc[keep], rising[keep])
    from mems_stereo.pipeline import classify_recording, process_recording

    res = classify_recording(rec)
    n_unknown = int(np.count_nonzero(t < zc[keep][0]))
    assert res.counts["shots_unknown_angle"] == n_unknown > 0
    assert np.all(res.labels[~res.valid] == 0)
    c = res.counts
    assert c.signal + c.noise == c.raw == np.count_nonzero(bins[res.valid])
    assert c.signal == np.count_nonzero(res.labels == 1) > 0
    # one counts type: processing the same recording gives the same keys and numbers
    pc = process_recording(rec).counts
    assert type(pc) is type(c) and list(pc) == list(c)
    assert all(pc[k] == c[k] for k in ("shots", "shots_unknown_angle", "raw", "signal", "noise"))
    # the reference on exact (not step-snapped) angles agrees on nearly every detection
    ref = classify_bins(system, bins, np.nan_to_num(res.theta), res.valid)
    det = bins > 0
    assert np.mean(ref[det] == res.labels[det]) > 0.995
    exp = system.scanner.theta0 + system.scanner.theta_mech_max * np.cos(2 * np.pi * f * t)
    assert np.allclose(res.theta[res.valid], exp[res.valid], atol=1e-9)
