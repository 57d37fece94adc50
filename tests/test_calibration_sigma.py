"""The calibration covariance's share of a fused point's σ (pipeline/calibration_sigma.py):
added once per point as J Σ Jᵀ, checked against processing with shifted systems."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from mems_stereo.io.recording import read_recording
from mems_stereo.model.system import load_system
from mems_stereo.pipeline.calibration_sigma import calibration_point_covariance
from mems_stereo.pipeline.run import process_recording
from mems_stereo.pipeline.scan_dwell import DwellSkew
from mems_stereo.pipeline.temporal import TemporalFusion

SAMPLES = Path(__file__).resolve().parents[1] / "samples"
#: a rank-1 covariance Σ = s sᵀ over two parameters (correlation −1: the cross term counts)
NAMES = ("theta0", "baseline_z")
S = np.array([2e-4, -3e-3])  # rad, m
#: attributes that must not change with the covariance (detection, fusion, selection)
SAME = ("range", "counts", "pixel", "row", "range_stereo", "sigma_r_stereo", "range_tof",
        "sigma_r_tof", "weight_stereo")


@pytest.fixture(scope="module")
def base():
    rec = read_recording(SAMPLES / "imperfect_room.h5")
    system = load_system(SAMPLES / "imperfect_true_system.json")
    result = process_recording(rec, system=system)
    pk = result.peaks
    turning = {(int(r), int(c)) for r, c in zip(pk.row[pk.turning], pk.col[pk.turning])}
    cloud = result.cloud
    at_turn = np.array([(int(r), int(c)) in turning
                        for r, c in zip(cloud["row"], cloud["pixel"])], bool)
    return rec, system, cloud, at_turn


def _with_cov(system, names, cov):
    cal = dict(system.calibration or {})
    cal["covariance"] = {"names": list(names), "matrix": np.asarray(cov).tolist()}
    return system.replace(calibration=cal)


def test_without_covariance_output_is_unchanged(base):
    rec, system, c0, _ = base
    cal = dict(system.calibration or {}, converged=True)
    c1 = process_recording(rec, system=system.replace(calibration=cal)).cloud
    assert calibration_point_covariance(system.replace(calibration=cal), c0.points,
                                        c0["row"], c0["pixel"], c0["weight_stereo"],
                                        c0["counts"]) is None
    assert np.array_equal(c0.points, c1.points)
    for k in c0.attributes:
        assert np.array_equal(c0[k], c1[k], equal_nan=True), k


def test_added_variance_is_j_sigma_jt_of_shifted_processing(base):
    """σ_r² grows by (J s)², J s the range's change per unit step along s, from
    processing with the system shifted by ±δ·s (an independent derivation: the whole
    pipeline, peaks and fusion included); points and their selection stay the same."""
    rec, system, c0, _ = base
    c1 = process_recording(rec, system=_with_cov(system, NAMES, np.outer(S, S))).cloud
    assert np.array_equal(c0.points, c1.points)
    for k in SAME:
        assert np.array_equal(c0[k], c1[k], equal_nan=True), k
    added = c1["sigma_r"] ** 2 - c0["sigma_r"] ** 2
    d = 0.1
    v0 = np.array([system.get_param(n) for n in NAMES])
    shifted = [process_recording(rec, system=system.with_params(
        **dict(zip(NAMES, v0 + sign * d * S)))).cloud for sign in (1, -1)]
    key = [c["row"].astype(np.int64) * 100000 + c["pixel"] for c in (c0, *shifted)]
    both = np.intersect1d(np.intersect1d(key[0], key[1]), key[2])
    assert both.size >= 0.95 * len(c0)
    idx = [np.flatnonzero(np.isin(k, both)) for k in key]
    Js = (shifted[0]["range"][idx[1]] - shifted[1]["range"][idx[2]]) / (2 * d)
    ratio = np.sqrt(added[idx[0]]) / np.abs(Js)
    assert np.all(added >= 0) and np.median(added) > 0
    assert 0.97 < np.median(ratio) < 1.03, np.median(ratio)
    assert np.mean(np.abs(ratio - 1) < 0.15) > 0.9


def test_phase_offset_moves_the_two_sweeps_oppositely(base):
    """A pure-cosine trajectory: a common phase shift moves the two sweeps' angles by
    ±, so the even part vanishes and what is left is the odd part over n (binomial
    split of the detections between the sweeps).  Where the scan turns inside a
    peak's footprint the two sweeps meet and a phase shift moves its angle only to
    second order: zero there is right."""
    _, system, c0, at_turn = base
    sc = system.scanner
    ideal = system.replace(scanner=dataclasses.replace(sc, harmonics=(), monitor=None))
    sd = 1e-3
    sysc = _with_cov(ideal, ("phase_offset",), [[sd * sd]])
    args = (c0.points, c0["row"], c0["pixel"], c0["weight_stereo"])
    var_n1 = calibration_point_covariance(sysc, *args, np.ones(len(c0)))
    var_n4 = calibration_point_covariance(sysc, *args, np.full(len(c0), 4.0))
    tr = np.trace(var_n1, axis1=1, axis2=2)
    assert np.all(tr[~at_turn] > 0) and np.all(tr >= 0)
    np.testing.assert_allclose(var_n4, var_n1 / 4, rtol=1e-6, atol=1e-18)


def test_frames_do_not_average_the_calibration_share_down(base):
    """Temporal fusion of 16 frames holding the same cloud: the calibration's share of
    σ_r is common to every frame, so the fused σ_r stays at or above it (with the dwell
    skew alone as the common part it falls below it at some points)."""
    rec, system, _, _ = base
    cal = _with_cov(system, NAMES, np.outer(S, S))
    cloud = process_recording(rec, system=cal).cloud
    cloud.attributes["step_lo"] = np.zeros(len(cloud), np.int64)
    cloud.attributes["step_hi"] = np.ones(len(cloud), np.int64)
    cloud.attributes["t"] = np.zeros(len(cloud))
    C = calibration_point_covariance(cal, cloud.points, cloud["row"], cloud["pixel"],
                                     cloud["weight_stereo"], cloud["counts"])
    u = cloud.points / np.linalg.norm(cloud.points, axis=1, keepdims=True)
    s_cal = np.sqrt(np.einsum("qi,qij,qj->q", u, C, u))
    assert np.median(s_cal / cloud["sigma_r"]) > 0.3  # the share matters here
    h, w = system.receiver.height, system.receiver.width
    fused = {}
    for name, fusion in (("shared", TemporalFusion(h, w, system=cal)),
                         ("dwell", TemporalFusion(h, w, system=cal,
                                                  systematic=DwellSkew(cal).systematic))):
        for _ in range(16):
            out = fusion.update(cloud)
        assert out["age"].min() == 16
        fused[name] = out["sigma_r"]
    assert np.all(fused["shared"] >= s_cal * (1 - 1e-9))
    assert np.mean(fused["dwell"] < 0.9 * s_cal) > 0.5
