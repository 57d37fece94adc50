"""Calibration of the two-axis system (calib/twoaxis.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from mems_stereo.calib.intrinsics import IntrinsicsResult
from mems_stereo.calib.twoaxis import (
    TWO_AXIS_PARAMS,
    WallObservations,
    calibrate_two_axis,
    get_param_2d,
    predict_wall,
    with_params_2d,
)

from mems_stereo.errors import NotObservableError
from mems_stereo.model.presets import lissajous64

ROOT = Path(__file__).resolve().parents[1]
OFFSETS = {"theta0": 3e-3, "theta0_2": -2e-3, "theta_mech_max": 8e-4,
           "theta_mech_max_2": -1e-3, "phase_offset": 0.01, "phase_offset_2": -0.015,
           "baseline_x": 0.004, "baseline_y": 0.003, "baseline_z": 0.002, "tdc_offset": 1e-9}
WALLS = [(0.2, 0.1, 1.5), (-0.15, -0.12, 2.5), (0.1, 0.15, 4.0)]


def _true():
    nom = lissajous64()
    return nom, with_params_2d(nom, **{k: get_param_2d(nom, k) + v for k, v in OFFSETS.items()})


def test_named_parameters_round_trip():
    s = lissajous64()
    for n in TWO_AXIS_PARAMS + ("fx", "fy", "cx", "cy"):
        v = get_param_2d(s, n) + 0.001
        assert get_param_2d(with_params_2d(s, **{n: v}), n) == pytest.approx(v, abs=1e-15)
    t = with_params_2d(s, theta0_2=0.01)
    assert t.scanner.axis2.theta0 == 0.01 and s.scanner.axis2.theta0 == 0.0


def _synthetic(true, rng, m=600, s_uv=0.3, s_L=0.04):
    obs = []
    for wall in WALLS:
        o = WallObservations(rng.uniform(0, 2 * np.pi, m), rng.uniform(0, 2 * np.pi, m),
                             np.full(m, np.nan), np.zeros((m, 2)), np.ones(m, np.int64),
                             np.zeros(m), 0.0, "synthetic")
        uv, L = predict_wall(true, o, np.array(wall))
        ok = np.all((uv > 0) & (uv < 63), axis=1)
        o = WallObservations(o.phase1[ok], o.phase2[ok], o.theta2_mech[ok],
                             uv[ok] + rng.normal(0, s_uv, (ok.sum(), 2)), o.n[ok],
                             L[ok] + rng.normal(0, s_L, ok.sum()), 0.0, "synthetic")
        obs.append(o)
    return obs


def test_fit_recovers_the_true_system_with_honest_sigma():
    nom, true = _true()
    pulls = []
    for seed in range(2):
        obs = _synthetic(true, np.random.default_rng(seed))
        res = calibrate_two_axis(None, nom, observations=obs, timing_jitter=0.0,
                                 spot_sigma_px=np.sqrt(0.09 - 1 / 12))
        assert 0.7 < res.chi2_dof < 1.3
        for n, v, sd in zip(res.names, res.values, res.std):
            pulls.append((v - get_param_2d(true, n)) / sd)
        np.testing.assert_allclose(res.walls[:, 2], [w[2] for w in WALLS], atol=0.05)  # ~ TDC offset
        std = dict(zip(res.names, res.std))
        assert max(std[n] for n in ("theta0", "theta0_2", "theta_mech_max",
                                    "theta_mech_max_2")) < 5e-4
        assert max(std[n] for n in ("baseline_x", "baseline_y", "baseline_z")) < 5e-3
    pulls = np.array(pulls)
    assert np.all(np.abs(pulls) < 4.5)
    assert 0.5 < np.sqrt(np.mean(pulls ** 2)) < 1.5


def test_intrinsics_from_charuco_are_refined_under_their_prior():
    nom, true = _true()
    obs = _synthetic(true, np.random.default_rng(11))
    K = nom.receiver.camera_matrix.copy()
    K[0, 0] *= 0.97
    K[1, 1] *= 0.97
    K[0, 2] += 1.0
    intr = IntrinsicsResult(0.4, K, np.zeros(5), np.array([4.0, 4.0, 2.0, 2.0]), 30)
    res = calibrate_two_axis(None, nom, observations=obs, intrinsics=intr, timing_jitter=0.0,
                             spot_sigma_px=np.sqrt(0.09 - 1 / 12))
    v = dict(zip(res.names, res.values))
    assert abs(v["fx"] - true.receiver.camera_matrix[0, 0]) < 1.0  # started 3.6 px off
    assert abs(v["baseline_y"] - get_param_2d(true, "baseline_y")) < 2e-3


def test_one_wall_is_refused():
    nom, true = _true()
    obs = _synthetic(true, np.random.default_rng(1))
    with pytest.raises(NotObservableError):
        calibrate_two_axis(None, nom, observations=obs[:1])
    with pytest.raises(NotObservableError):
        calibrate_two_axis([ROOT / "samples" / "lissajous64_calib_1.5m.h5"])


@pytest.mark.slow
def test_cli_calibrates_the_sample_walls(tmp_path, shared_results):
    """The fit is ``mems-stereo demo``'s two-axis step's (tests/test_demo.py; computed once:
    tests/conftest.py's ``shared_results``)."""
    from mems_stereo.cli import main
    from mems_stereo.model.system import load_system

    out = tmp_path / "cal.json"
    recs = sorted(str(p) for p in (ROOT / "samples").glob("lissajous64_calib_*m.h5"))
    assert main(["calibrate", *recs, "-o", str(out)]) == 0
    est = load_system(out)
    true = load_system(ROOT / "samples" / "lissajous64_calib_true_system.json")
    for n in ("theta0", "theta0_2", "theta_mech_max", "theta_mech_max_2"):
        assert abs(get_param_2d(est, n) - get_param_2d(true, n)) < 3e-4
    for n in ("baseline_x", "baseline_y", "baseline_z"):
        assert abs(get_param_2d(est, n) - get_param_2d(true, n)) < 2e-3


def test_charuco_intrinsics_feed_the_raster_calibration():
    """Rendered ChArUco views of the 128 x 96 array → calibrate_charuco → the joint fit."""
    import cv2
    from mems_stereo.calib.intrinsics import calibrate_charuco, make_board, synthetic_charuco_views

    from mems_stereo.model.presets import raster128x96

    nom = raster128x96()
    offs = {"theta0": 2e-3, "theta0_2": -1.5e-3, "baseline_x": 0.003, "baseline_y": -0.002,
            "baseline_z": 0.002, "tdc_offset": 5e-10}
    true = with_params_2d(nom, **{k: get_param_2d(nom, k) + v for k, v in offs.items()})
    board = make_board((5, 4), 0.04, 0.03)
    rng = np.random.default_rng(0)
    poses = []
    for _ in range(40):
        r = rng.uniform(-0.5, 0.5, 3)
        r[2] *= 0.5
        poses.append((r, np.array([-0.1 + rng.uniform(-0.03, 0.03),
                                   -0.08 + rng.uniform(-0.03, 0.03), 0.3 * rng.uniform(0.9, 1.2)])))
    views = synthetic_charuco_views(board, true.receiver.camera_matrix, (128, 96), poses,
                                    px_per_m=4000)
    flags = (cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST
             | cv2.CALIB_FIX_ASPECT_RATIO)
    intr = calibrate_charuco(views, board, flags=flags, min_corners=4)
    fx_true = true.receiver.camera_matrix[0, 0]
    assert abs(intr.camera_matrix[0, 0] - fx_true) > 1.0  # a 128 x 96 board fit is coarse
    a2 = nom.scanner.axis2
    obs = []
    for wall in WALLS:
        m = 800
        o = WallObservations(rng.uniform(0, 2 * np.pi, m), np.full(m, np.nan),
                             rng.uniform(-a2.theta_mech_max, a2.theta_mech_max, m),
                             np.zeros((m, 2)), np.ones(m, np.int64), np.zeros(m), 0.0, "syn")
        uv, L = predict_wall(true, o, np.array(wall))
        ok = np.all((uv > 0) & (uv < [127, 95]), axis=1)
        obs.append(WallObservations(o.phase1[ok], o.phase2[ok], o.theta2_mech[ok],
                                    uv[ok] + rng.normal(0, 0.3, (ok.sum(), 2)), o.n[ok],
                                    L[ok] + rng.normal(0, 0.04, ok.sum()), 0.0, "syn"))
    res = calibrate_two_axis(None, nom, observations=obs, intrinsics=intr, timing_jitter=0.0,
                             spot_sigma_px=np.sqrt(0.09 - 1 / 12))
    v = dict(zip(res.names, res.values))
    s = dict(zip(res.names, res.std))
    assert "theta_mech_max_2" not in v  # raster: the position channel gives θ2_mech
    assert abs(v["fx"] - fx_true) < max(1.0, 4 * s["fx"])
    for n in ("baseline_x", "baseline_y", "baseline_z", "theta0", "theta0_2"):
        assert abs(v[n] - get_param_2d(true, n)) < 4 * s[n]


def _make_samples_2d():
    import importlib.util
    import sys

    spec = importlib.util.spec_from_file_location("make_samples_2d",
                                                  ROOT / "samples" / "make_samples_2d.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["make_samples_2d"] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def test_lissajous_sample_and_walls_share_one_true_system():
    """lissajous64.h5 and its walls: one true system (the shipped JSON, the script's
    offsets), the nominal preset in the files; the recording's laser returns are all
    classified with the true system and a sixth of them lost with the nominal one."""
    from dataclasses import replace

    from mems_stereo.io.recording2d import read_recording_2d
    from mems_stereo.model.system import load_system, system_to_dict
    from mems_stereo.pipeline.twoaxis import process_recording_2d

    mod = _make_samples_2d()
    true = load_system(ROOT / "samples" / "lissajous64_calib_true_system.json")
    assert system_to_dict(true) == system_to_dict(mod.calib_true_system())
    assert {s.name: s.true_system for s in mod.SAMPLES_2D} == {"lissajous64": "calib",
                                                               "raster128x96": "nominal"}
    for d in ("1.5", "2.5", "4.0"):  # the walls carry the nominal preset too
        wall = read_recording_2d(ROOT / "samples" / f"lissajous64_calib_{d}m.h5", truth=False)
        assert system_to_dict(wall.system) == system_to_dict(lissajous64())
    rec = read_recording_2d(ROOT / "samples" / "lissajous64.h5")
    assert system_to_dict(rec.system) == system_to_dict(lissajous64())
    k = int(np.searchsorted(rec.event_shot, 8000))  # the first 8000 shots
    sub = replace(rec, shot_time=rec.shot_time[:8000], read_count=rec.read_count[:8000],
                  event_shot=rec.event_shot[:k], event_pixel=rec.event_pixel[:k],
                  event_code=rec.event_code[:k],
                  truth={**rec.truth, "label": rec.truth["label"][:k]})
    assert process_recording_2d(sub, system=true).truth["recall"] > 0.999
    assert process_recording_2d(sub).truth["recall"] < 0.9
