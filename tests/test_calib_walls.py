"""Calibration of the bundled wall samples with the shipped measured distances, end to end.

One ``mems-stereo calibrate`` run (from a foreign working directory) on
samples/calib_{1.5,2.5,4.0}m.h5 with samples/calib_distances.json: the
written system JSON must read back, every estimate must lie within 3 of its
reported σ of samples/calib_true_system.json (θ0 within 0.3 mrad), the σ
targets must be met, and the pipeline's points of each wall must
lie at least 5x closer to the true plane (from the scene JSON) than with the
nominal system.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from mems_stereo.calib.calibrate import read_target_distances

from mems_stereo.cli import main
from mems_stereo.errors import FormatError
from mems_stereo.model.system import load_system
from mems_stereo.pipeline.run import process_recording

SAMPLES = Path(__file__).resolve().parents[1] / "samples"
WALLS = ("1.5", "2.5", "4.0")
PATHS = [SAMPLES / f"calib_{d}m.h5" for d in WALLS]
DIST_FILE = SAMPLES / "calib_distances.json"


def _wall(d):
    """Unit normal and a point of the true wall plane of sample ``d`` (camera frame, m)."""
    obj = json.loads((SAMPLES / f"calib_{d}m_scene.json").read_text())["objects"][0]
    n = np.asarray(obj["normal"], float)
    return n / np.linalg.norm(n), np.asarray(obj["center"], float)


# one pytest-xdist worker runs this module with the other users of the bundled walls'
# calibration (tests/conftest.py: ``share_heavy_results``, XDIST_GROUPS)


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """(system read back, CLI stdout, exit code) of one CLI calibration run (its fit is
    that of ``mems-stereo demo``'s and tests/test_cli_outputs.py's, computed once)."""
    import contextlib
    import io
    import os

    from conftest import share_heavy_results

    work = tmp_path_factory.mktemp("elsewhere")
    out = work / "cal.json"
    buf = io.StringIO()
    cwd = os.getcwd()
    os.chdir(work)  # the command must not depend on the working directory
    try:
        with contextlib.redirect_stdout(buf), pytest.MonkeyPatch.context() as mp:
            share_heavy_results(mp)
            rc = main(["calibrate", *map(str, PATHS), "-o", "cal.json",
                       "--target-distances-file", str(DIST_FILE)])
    finally:
        os.chdir(cwd)
    return load_system(out), buf.getvalue(), rc


def test_shipped_distances_are_optical_axis_measurements():
    """The file's distances agree with the true walls' optical-axis distances
    (z where the wall meets the camera z axis: n·c / n_z) within 3 of its σ."""
    dists, stds, kind = read_target_distances(DIST_FILE, PATHS)
    assert kind == "axis"
    for d, (meas, sd) in zip(WALLS, zip(dists, stds)):
        n, c = _wall(d)
        z_axis = (n @ c) / n[2]
        assert 1e-3 <= sd <= 2e-3
        assert abs(meas - z_axis) < 3 * sd, (d, meas, z_axis)


def test_cli_calibration_within_3_sigma_of_truth(calibrated):
    system, text, rc = calibrated
    assert rc == 0, text
    true = load_system(SAMPLES / "calib_true_system.json")
    cal = system.calibration
    assert cal["converged"]
    params = cal["parameters"]
    assert {"theta0", "theta_mech_max", "phase_offset", "tdc_offset", "baseline_x",
            "baseline_z"} <= set(params)
    for name, p in params.items():
        assert p["std"] is not None and math.isfinite(p["std"]) and p["std"] > 0, name
        assert system.get_param(name) == pytest.approx(p["value"], rel=1e-12, abs=1e-15)
        err = p["value"] - true.get_param(name)
        assert abs(err) < 3 * p["std"], (name, err, p["std"])
    assert abs(system.scanner.theta0 - true.scanner.theta0) < 0.3e-3
    # the σ targets, met with the measured distances
    assert params["baseline_x"]["std"] <= 2e-3
    assert params["tdc_offset"]["std"] <= 0.2e-9
    # what the data cannot tell is said, not estimated
    assert cal["unobservable"] == ["baseline_y"]
    assert "baseline_y" not in params
    assert "not observable from these data: baseline_y" in text
    for name in ("theta0", "tdc_offset", "baseline_x", "RMS residual"):
        assert name in text
    # the fitted optical-axis distances agree with the measured ones within their σ
    dists, stds, _ = read_target_distances(DIST_FILE, PATHS)
    for t, d, sd in zip(cal["targets"], dists, stds):
        assert abs(t["distance_axis"] - d) < 3 * math.hypot(sd, t["distance_axis_std"])


def test_calibrated_points_lie_on_the_walls(calibrated):
    """Pipeline points (one per histogram peak): median |distance| to the true wall
    plane at least 5x smaller with the calibrated system than with the nominal."""
    system, _, _ = calibrated
    for d, path in zip(WALLS, PATHS):
        n, c = _wall(d)
        med = [float(np.median(np.abs((process_recording(path, system=s).cloud.points - c) @ n)))
               for s in (None, system)]
        assert med[0] > 5 * med[1], (d, med)


def test_distances_file_matches_by_name_and_rejects_bad_files(tmp_path):
    # matched by file name: order, directories and unknown entries do not matter
    rev = [Path("x") / p.name for p in PATHS[::-1]] + [Path("calib_9m.h5")]
    dists, stds, _ = read_target_distances(DIST_FILE, rev)
    ref, _, _ = read_target_distances(DIST_FILE, PATHS)
    assert dists == ref[::-1] + [None]
    assert stds[-1] > 0
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"format": "mems-stereo/system"}))
    with pytest.raises(FormatError, match="format"):
        read_target_distances(bad, PATHS)
    bad.write_text(json.dumps({"format": "mems-stereo/target-distances", "version": 1,
                               "targets": [{"recording": "other.h5", "distance": 2.0}]}))
    with pytest.raises(FormatError, match="at least one of the recordings"):
        read_target_distances(bad, PATHS)
    bad.write_text(json.dumps({"format": "mems-stereo/target-distances", "version": 1,
                               "targets": [{"recording": "calib_1.5m.h5", "distance": -1}]}))
    with pytest.raises(FormatError, match=r"targets\[0\].distance"):
        read_target_distances(bad, PATHS)
