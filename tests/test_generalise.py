"""Processing that generalises (issue 13): one seeded test per fix.

* window sums of the peak detector are exact integers (a float sum of 7 read as
  7.000000000000001 passed a threshold of 7 and made false peaks);
* the ToF point continues below |b| of path (code-1 returns of a near surface
  are kept, not dropped as NaN);
* ``min_counts`` counts detections, not their background-subtracted sum;
* near-range, few-count peaks: every return of the band is an inlier and the
  point's error/σ is about 1 over seeds;
* peak-level fusion: a stereo mean with a σ of metres leaves the ToF alone;
* a return seen only where the scan turns gives no biased point.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from mems_stereo.model.scanner import scan_direction
from mems_stereo.model.system import burkard2022
from mems_stereo.pipeline.detections import TOF_LINEAR_BELOW, tof_on_scanner_ray
from mems_stereo.pipeline.peak_means import fuse_along_ray
from mems_stereo.pipeline.peaks import strongest_window
from mems_stereo.pipeline.run import process_recording
from mems_stereo.pipeline.settings import Settings
from mems_stereo.sim import scene_from_dict, simulate


def test_window_sums_are_exact_integers():
    """Seven counts over an expected 1.02 at 1e-3 / 42.5 windows: the threshold is 7 and
    seven counts must not pass it (the float moving sum gave 7.000000000000001)."""
    width = 51
    bg = np.full((1, 2168), 1.019 / width)
    counts = np.zeros((1, 2168))
    counts[0, [1000, 1003, 1010, 1021, 1030, 1034, 1047]] = 1  # seven in one footprint
    ws = strongest_window(counts, bg, width, bg > 0, Settings())
    cnt, keep = ws.cnt, ws.keep
    assert cnt[0] == 7.0 and float(cnt[0]).is_integer()
    assert not keep[0]
    counts[0, 1040] = 1  # an eighth: now significant
    assert strongest_window(counts, bg, width, bg > 0, Settings()).keep[0]


def test_window_sums_are_not_rescaled_at_the_ends():
    """Near the ends of a row the sum is what it is (the moving average rescaled it up)."""
    bg = np.full((1, 200), 0.001)
    counts = np.zeros((1, 200))
    counts[0, :3] = 1
    cnt = strongest_window(counts, bg, 51, bg > 0, Settings()).cnt
    assert cnt[0] == 3.0


def test_tof_on_ray_exact_above_and_c1_below():
    s = burkard2022()
    p = np.asarray(s.scanner.position)
    b = float(np.linalg.norm(p))
    d = scan_direction(np.array([s.scanner.theta0] * 5), s.scanner)
    L = np.array([0.5, 1.0, 2.0, 5.0, 10.0])
    x, t = tof_on_scanner_ray(p, d, L)
    np.testing.assert_allclose(np.linalg.norm(x - p, axis=1) + np.linalg.norm(x, axis=1), L,
                               rtol=1e-12)
    Lc = TOF_LINEAR_BELOW * b
    eps = 1e-7
    L3 = np.array([Lc - 2 * eps, Lc - eps, Lc, Lc + eps, Lc + 2 * eps])
    _, t3 = tof_on_scanner_ray(p, d, L3)
    slopes = np.diff(t3) / eps
    np.testing.assert_allclose(slopes, slopes[0], rtol=1e-4)  # C¹ at L_c
    Llow = np.array([-0.2, 0.0, 0.5 * b, b, 1.5 * b])
    xl, tl = tof_on_scanner_ray(p, d, Llow)
    assert np.all(np.isfinite(tl)) and np.all(np.diff(tl) > 0)  # monotone, finite


def test_fuse_along_ray_leaves_a_useless_stereo_out():
    x_st = np.array([[0.0, 0.0, 4.9], [0.0, 0.0, 2.0]])
    x_tf = np.array([[0.0, 0.0, 4.4], [0.0, 0.0, 2.1]])
    C_st = np.zeros((2, 3, 3))
    C_tf = np.zeros((2, 3, 3))
    C_st[0, 2, 2], C_tf[0, 2, 2] = 89.0 ** 2, 0.18 ** 2  # stereo near the vanishing point
    C_st[1, 2, 2], C_tf[1, 2, 2] = 0.01 ** 2, 0.5 ** 2
    x, C, w = fuse_along_ray((x_st, C_st), (x_tf, C_tf))
    assert abs(x[0, 2] - 4.4) < 1e-3 and math.sqrt(C[0, 2, 2]) < 0.181
    assert w[1] > 0.99 and abs(x[1, 2] - 2.0) < 1e-3
    x, C, w = fuse_along_ray((np.full((1, 3), np.nan), C_st[:1]), (x_tf[:1], C_tf[:1]))
    assert w[0] == 0.0 and x[0, 2] == 4.4


def _near_scene(rng):
    d = float(rng.uniform(0.55, 0.9))
    return {"objects": [
        {"type": "plane", "center": [0.0, 0.0, 6.0], "normal": [0, 0, -1], "size": [20, 3],
         "reflectivity": 0.3},
        {"type": "box", "center": [float(rng.uniform(-0.1, 0.1)), 0.0, d + 0.2],
         "size": [0.5, 1.0, 0.4], "rotation_deg": [0, float(rng.uniform(-30, 30)), 0],
         "reflectivity": float(rng.uniform(0.2, 0.8))}]}


def _process(scene_dict, shots, seed, bg):
    s = burkard2022()
    scene = scene_from_dict(scene_dict)
    rec = simulate(s, scene, shots, rng=np.random.default_rng(seed), background_hz=bg,
                   dark_count_hz=1e3)
    res = process_recording(rec)
    c = res.cloud
    if not len(c):
        return scene, rec, res, np.zeros(0), np.zeros(0)
    return scene, rec, res, _error(scene, c), c["sigma_r"]


def _error(scene, c):
    """(N,) m: range − the true surface's along the point's ray, capped at twice the
    distance to the nearest surface (an object's edge point whose ray just misses
    it is not charged the wall behind; as benchmarks/bench_scenarios.py)."""
    import open3d as o3d

    d = c.points / np.linalg.norm(c.points, axis=1, keepdims=True)
    err = c["range"] - scene.cast(np.zeros(3), d).t
    q = o3d.core.Tensor(np.ascontiguousarray(c.points, dtype=np.float32))
    near = scene._raycaster().compute_distance(q).numpy().astype(np.float64)
    return np.sign(err) * np.minimum(np.abs(err), 2.0 * near)


def test_near_range_few_count_peaks_error_over_sigma_about_one():
    """Boxes at 0.55–0.9 m, 500 shots (3–10 detections a pixel): the near peaks keep their
    band's returns (points in most lit box pixels) and error/σ has an RMS of about 1."""
    rng = np.random.default_rng(1313)
    z, n_near, n_lit = [], 0, 0
    for seed in range(6):
        scene, rec, res, err, sig = _process(_near_scene(rng), 500, 4000 + seed, 1e5)
        near = np.abs(res.cloud["range"]) < 1.0 if len(res.cloud) else np.zeros(0, bool)
        z.append(err[near] / sig[near])
        n_near += int(near.sum())
        t = np.linalg.norm(np.nan_to_num(rec.truth["point"], nan=1e9), axis=1)
        lab = rec.truth["label"].reshape(len(t), -1)
        n_lit += int(np.sum(np.any((lab == 1) & (t[:, None] < 1.0), axis=0)))
    z = np.concatenate(z)
    rms = float(np.sqrt(np.mean(z ** 2)))
    print(f"near points {n_near} of ~{n_lit} lit near pixels, RMS error/σ {rms:.2f}")
    assert n_near >= 0.6 * n_lit
    assert 0.5 <= rms <= 1.5
    assert np.mean(np.abs(z) > 3) <= 0.02


#: scenario-sweep case 13047 (benchmarks/bench_scenarios.py): a wall at 2.5 m, 15°, a
#: cylinder and a box in front; the right-hand pixels see the wall where the scan turns
BX, BZ = -0.1602129033203651, 0.00819680361187981  # case 13047's mirror position, m
_CASE_13047 = {"objects": [
    {"type": "plane", "center": [0.0, 0.0, 2.5018209398877915],
     "normal": [-0.2558506639199022, 0.0, -0.9667163171125981],
     "size": [8.4698942585356, 3.0], "reflectivity": 0.4120601483348891},
    {"type": "cylinder", "center": [-0.16635805661203804, 0.0, 2.410793134826455],
     "radius": 0.2509185741713306, "height": 1.2, "axis": [0, 1, 0],
     "reflectivity": 0.2104489743894633},
    {"type": "box", "center": [-0.10959123931119208, 0.0, 1.6091436151313534],
     "size": [0.306943813190355, 1.0, 0.6449441482811828],
     "rotation_deg": [0.0, -14.297028587330097, 0.0], "reflectivity": 0.25829773706902104}]}


def _sweep_case(bx, bz, theta0, k1, scene_dict, n_shots, seed, background_hz):
    """(scene, cloud) of one case of benchmarks/bench_scenarios.py, rebuilt from its
    drawn parameters (system, k1 distortion, scene, shots, seed, background)."""
    from dataclasses import replace

    s = burkard2022().with_params(baseline_x=bx, baseline_z=bz, theta0=theta0)
    dist = np.zeros(5)
    dist[0] = k1
    s = replace(s, receiver=replace(s.receiver, dist_coeffs=dist))
    scene = scene_from_dict(scene_dict)
    rec = simulate(s, scene, n_shots, rng=np.random.default_rng(seed),
                   background_hz=background_hz, dark_count_hz=1e3)
    return scene, process_recording(rec).cloud


@pytest.mark.slow
def test_turning_point_return_gives_no_biased_point():
    """Sweep case 13047 (37,648 shots, 0.16 MHz): pixel 174 sees the wall only where the
    scan turns, its shots bunched at the footprint's edge (the stereo mean was 16 cm
    behind, 8σ); a turning peak's stereo now carries a systematic σ
    (tests/test_turning_points.py): pixel 174 is no false point, and the false points
    are ≤ 1 % (one object-edge pixel)."""
    scene, c = _sweep_case(BX, BZ, 0.7758342622745028, 0.0381451198377582, _CASE_13047,
                           37648, 13047, 160047.31962008242)
    assert len(c) > 150
    bad = np.abs(_error(scene, c)) > np.maximum(3 * c["sigma_r"], 0.10)
    assert 174 not in set(c["pixel"][bad].tolist())
    assert bad.sum() <= 0.01 * len(c)


_CASE_13001 = {"objects": [
    {"type": "plane", "center": [0.0, 0.0, 4.377931045717893],
     "normal": [0.12533931203843274, 0.0, -0.9921139334057013],
     "size": [13.031825323452146, 3.0], "reflectivity": 0.1302554204818665},
    {"type": "box", "center": [1.0393621109147761, 0.0, 4.265109335960867],
     "size": [0.48956358740984857, 1.0, 0.6586775728791059],
     "rotation_deg": [0.0, -7.628591284284269, 0.0], "reflectivity": 0.541486251892519},
    {"type": "cylinder", "center": [-0.19545183200060365, 0.0, 1.1251795899207249],
     "radius": 0.22840006534200463, "height": 1.2, "axis": [0, 1, 0],
     "reflectivity": 0.05360492418760285}]}


@pytest.mark.slow
def test_depth_edge_pixels_give_no_false_point():
    """Sweep case 13001 (24,664 shots, 24 kHz): a dark cylinder at 1.1 m before a wall at
    4.4 m and a box's edge.  Pixels at the silhouettes see part of the spot on one
    surface (pixel 18: the wall's returns while its ray meets the cylinder; its point
    was 24 cm from any surface at σ 6 cm); at a depth edge of the cloud the stereo
    carries a quarter pixel more, and no point is false (farther than max(3σ, 10 cm))."""
    scene, c = _sweep_case(-0.12287688194275999, -0.014952558300030953, 0.7606194112088224,
                           0.02712997221388018, _CASE_13001, 24664, 13001, 23698.211205348547)
    assert len(c) > 150
    err = _error(scene, c)
    bad = np.abs(err) > np.maximum(3 * c["sigma_r"], 0.10)
    assert not np.any(bad), list(zip(c["pixel"][bad], err[bad], c["sigma_r"][bad]))
    z = err / c["sigma_r"]
    assert 0.5 <= float(np.sqrt(np.mean(z ** 2))) <= 1.5
