"""Stereo, ToF and fused points: errors against their own reported uncertainty."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from oracles import peak_points

from mems_stereo.geometry.triangulation import path_length_of_point
from mems_stereo.geometry.uncertainty import polar_from_cartesian, spreads_for
from mems_stereo.model.camera import project_points
from mems_stereo.model.scanner import scan_direction
from mems_stereo.model.tdc import codes_from_path_length
from mems_stereo.pipeline.cloud import REQUIRED_ATTRIBUTES
from mems_stereo.pipeline.detections import detection_points

SAMPLES = Path(__file__).resolve().parents[1] / "samples"


def _shots(system, rng, K, Z):
    """Wall at z = Z: true points, pixel where the photon lands (uniform over the
    pixel around the true image), Gaussian path length, noisy recorded angle."""
    sp = spreads_for(system, spot_sigma=0.0)
    th = system.scanner.theta0 + rng.uniform(-0.15, 0.15, K)
    p = system.scanner.position
    d = scan_direction(th, system.scanner)
    x = p + ((Z - p[2]) / d[:, 2])[:, None] * d
    u = project_points(x, system.receiver.camera_matrix)[:, 0]
    col = np.rint(u).astype(int)
    L = path_length_of_point(x, p) + rng.normal(0, sp.sigma_L(system), K)
    code = np.floor(codes_from_path_length(L, system.tdc, system.speed_of_light) + 0.5)
    th_meas = th + rng.normal(0, sp.sigma_theta, K)
    ok = (col >= 0) & (col < system.receiver.width) & (code >= 1)
    return sp, x[ok], col[ok], code[ok].astype(int), th_meas[ok]


@pytest.mark.parametrize("Z", [1.5, 4.0])
def test_each_estimate_within_1p5x_of_its_uncertainty(system, rng, Z):
    sp, x, col, code, th = _shots(system, rng, 3000, Z)
    n = x.shape[0]
    dp = detection_points(system, np.arange(n), np.zeros(n, int), col, code, th, sp)
    assert dp.ok.mean() > 0.99
    # every estimate lies on the scanner ray: compare along it (the range from the
    # projection centre is insensitive to errors near the mirror, at short range)
    dirn = scan_direction(th, system.scanner)[dp.ok]
    rms = {}
    for name in ("stereo", "tof", "fused"):
        pts, cov = getattr(dp, name)[dp.ok], getattr(dp, "cov_" + name)[dp.ok]
        e = np.sum((pts - x[dp.ok]) * dirn, axis=1)
        s = np.sqrt(np.einsum("ni,nij,nj->n", dirn, cov, dirn))
        z = e / s
        assert 1 / 1.5 < np.std(z) < 1.5, (name, np.std(z))
        rms[name] = np.sqrt(np.mean(e ** 2))
    # the fusion is at least as good as the better estimate (within sampling noise)
    assert rms["fused"] <= 1.05 * min(rms["stereo"], rms["tof"])
    assert np.all((dp.weight_stereo[dp.ok] >= 0) & (dp.weight_stereo[dp.ok] <= 1))


def test_peak_points_on_a_wall(system, rng):
    Z = 3.0
    sp, x, col, code, th = _shots(system, rng, 6000, Z)
    n = x.shape[0]
    W = system.receiver.width
    bins = np.zeros((n, 1, W), np.uint16)
    bins[np.arange(n), 0, col] = code
    labels = (bins > 0).astype(np.uint8)
    cols = np.unique(col)
    med = np.array([np.median(code[col == c]) for c in cols])
    half = int(np.ceil(3 * sp.sigma_t / system.tdc.bin_width))
    pc = peak_points(system, bins, labels, th, np.zeros_like(cols), cols,
                     (med - half).astype(int), (med + half).astype(int), sp, min_counts=5)
    assert not pc.missing_required()
    for a in REQUIRED_ATTRIBUTES + ("sigma_x", "sigma_y", "sigma_z", "range_stereo",
                                    "range_tof", "sigma_r_stereo", "sigma_r_tof"):
        assert np.all(np.isfinite(pc[a])), a
    dist = np.abs(pc.points[:, 2] - Z)  # distance to the wall
    assert np.median(dist) <= 0.03, np.median(dist)
    z = (pc.points[:, 2] - Z) / pc["sigma_z"]
    assert np.std(z) < 1.5
    assert np.all(pc["counts"] <= pc["counts_window"])


@pytest.mark.skipif(not (SAMPLES / "room.h5").exists(), reason="samples/room.h5 not built")
def test_room_sample_detection_accuracy():
    """Simulated room: each estimate's range errors within 1.5x of its own σ."""
    from mems_stereo.io.recording import read_recording
    from mems_stereo.model.system import load_system
    from mems_stereo.pipeline import classify_recording

    rec = read_recording(SAMPLES / "room.h5")
    true = load_system(SAMPLES / "calib_true_system.json")  # the system that recorded it
    res = classify_recording(rec, system=true)
    tr = rec.truth
    assert np.mean(res.labels[tr["label"] == 1] == 1) >= 0.98
    assert np.mean(res.labels[tr["label"] == 2] == 2) >= 0.97
    k, r, c = np.nonzero((res.labels == 1) & (tr["label"] == 1))
    dp = detection_points(true, k, r, c, rec.bins[k, r, c], res.theta)
    X = tr["point"][k]
    g = dp.ok & np.all(np.isfinite(X), 1) & (np.linalg.norm(X, axis=1) < 6)
    # path lengths below 2|b| (codes at the TDC start, clipped there) have no ellipsoid
    # root: their ToF is the linear continuation the peak means need, not an
    # estimate with the pulse's σ (before, they were NaN and left out here too)
    from mems_stereo.model.tdc import path_length_from_codes
    from mems_stereo.pipeline.detections import TOF_LINEAR_BELOW

    L = path_length_from_codes(rec.bins[k, r, c], true.tdc, true.speed_of_light)
    g &= L >= TOF_LINEAR_BELOW * np.linalg.norm(true.scanner.position)
    for name in ("stereo", "tof", "fused"):
        pol = polar_from_cartesian(getattr(dp, name)[g], getattr(dp, "cov_" + name)[g])
        rr, sr = pol.r, pol.sigma_r
        z = (rr - np.linalg.norm(X[g], axis=1)) / sr
        assert np.sqrt(np.mean(z ** 2)) < 1.5, name


@pytest.mark.skipif(not (SAMPLES / "room.h5").exists(), reason="samples/room.h5 not built")
def test_room_peaks_tof_first_photon_correction():
    """Room sample, one point per peak: with the valid shots per angle step the ToF range
    loses its first-photon bias and its errors come within 1.5x of its σ (without: 1.4x);
    the fused estimate keeps its ≤ 3 cm median error."""
    from mems_stereo.model.system import load_system
    from mems_stereo.pipeline.fusion import points_from_counts
    from mems_stereo.pipeline.intervals import interval_table, shots_per_step
    from mems_stereo.pipeline.pass2 import peak_counts_range
    from mems_stereo.pipeline.run import process_recording
    from mems_stereo.pipeline.settings import Settings
    from mems_stereo.pipeline.shot_range import ShotRange
    from mems_stereo.sim import load_scene

    path = SAMPLES / "room.h5"
    res = process_recording(path, system=load_system(SAMPLES / "calib_true_system.json"))
    st = Settings()
    th, va = np.nan_to_num(res.theta), res.valid
    sps = shots_per_step(interval_table(res.system, st.confidence, min_range=st.min_range),
                         th, va)
    counts = peak_counts_range(path, res.system, ShotRange(th, va), st, res.peaks)
    scene = load_scene(SAMPLES / "room_scene.json")
    ratios = {}
    for corrected in (False, True):
        c = points_from_counts(res.system, res.peaks, counts, st,
                               shots_per_step=sps if corrected else None)
        x = c.points
        t = scene.cast(np.zeros_like(x), x / np.linalg.norm(x, axis=1)[:, None]).t
        near = np.isfinite(t) & (t <= 6.0)
        e_tof = (c["range_tof"] - t)[near]
        z = e_tof / c["sigma_r_tof"][near]
        ratios[corrected] = (np.median(np.abs(z)) / 0.6745,
                             np.sqrt(np.mean(e_tof ** 2) / np.mean(c["sigma_r_tof"][near] ** 2)))
        if corrected:  # (uncorrected: 3.1 cm on the room sample recorded by the true system)
            assert np.median(np.abs(c["range"] - t)[near]) <= 0.03
    assert ratios[False][0] > 1.2 * ratios[True][0]  # the bias the correction removes
    for r in ratios[True]:
        assert 1 / 1.5 < r < 1.5, ratios


@pytest.mark.parametrize("share, expect_point", [(0.2, True), (0.97, False)])
def test_no_point_from_inliers_consistent_with_background(system, rng, share, expect_point):
    """A peak's mean is a ratio over its inliers' background-subtracted count: where
    their detections are not significant against the background subtracted from
    them (Poisson, at the confidence), there is no point; 20 % background leaves one."""
    from mems_stereo.pipeline.fusion import points_from_peak_detections
    from mems_stereo.pipeline.fusion_inputs import FusionEntries, FusionPeaks

    _, x, col, code, th = _shots(system, rng, 20000, 3.0)
    c0 = np.bincount(col).argmax()
    sel = np.flatnonzero(col == c0)
    n = sel.size
    assert n > 50
    # each detection entry with a background entry at the same shot and code
    shot = np.concatenate([sel, sel])
    code2 = np.concatenate([code[sel], code[sel]])
    weight = np.concatenate([np.ones(n), np.full(n, -share)])
    bg = np.concatenate([np.zeros(n), np.full(n, share)])
    entries = FusionEntries(shot, np.zeros(2 * n, np.int64), code2, th, weight=weight,
                            background=bg)
    pc = points_from_peak_detections(system, entries, FusionPeaks(np.array([0]), np.array([c0])))
    assert (len(pc) == 1) is expect_point
