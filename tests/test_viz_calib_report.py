"""The calibration report: renders for a result and for a failure; residuals, verdict, advice."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from mems_stereo.calib.fit import CalibrationResult
from mems_stereo.calib.model import plane_normal
from mems_stereo.calib.synth import synthetic_target
from mems_stereo.viz.calib_report import (
    ADVICE,
    record_next,
    report_data_from_failure,
    report_data_from_result,
    target_residuals,
    verdict,
    write_calibration_report,
)

from mems_stereo.errors import FormatError, NotObservableError
from mems_stereo.model.system import burkard2022

NAMES = ["theta0", "theta_mech_max", "phase_offset", "tdc_offset", "baseline_x", "baseline_z"]
PLANES = [(0.05, 1.2), (-0.1, 2.0), (0.02, 3.5)]


def _result(std_scale=1.0, converged=True):
    """A CalibrationResult as the fit returns it, built from the true system (no fit)."""
    nominal = burkard2022()
    true = nominal.with_params(theta0=nominal.scanner.theta0 + 2e-3, baseline_x=-0.122,
                               tdc_offset=1.5e-9)
    rng = np.random.default_rng(11)
    targets = [synthetic_target(true, a, d, 400, rng, mu=3.0, source=f"{d} m")
               for a, d in PLANES]
    std = {"theta0": 3e-5, "theta_mech_max": 1e-4, "phase_offset": 4e-5,
           "tdc_offset": 9e-11, "baseline_x": 3e-4, "baseline_z": 2e-3}
    std = {k: v * std_scale for k, v in std.items()}
    C = np.eye(6)
    C[0, 4] = C[4, 0] = 0.92
    s = np.array([std[n] for n in NAMES])
    res = CalibrationResult(
        system=true, names=NAMES, values={n: true.get_param(n) for n in NAMES}, std=std,
        initial={n: nominal.get_param(n) for n in NAMES}, covariance=C * np.outer(s, s),
        correlation=C, rms={"pixel": 0.29, "time": 5e-9},
        n_detections=sum(t.n_detections for t in targets), fixed=["baseline_y", "fx", "cx"],
        unobservable=["baseline_y"], tradeoffs=[("theta0", "baseline_x", 0.92)],
        planes=np.array([[a, 0.0, d, 0.0] for a, d in PLANES]),
        planes_std=np.full((3, 4), 1e-3), converged=converged,
        message="" if converged else "the solver stopped after 100 iterations")
    return res, targets, nominal


def _pdf_pages(path):
    data = path.read_bytes()
    assert data.startswith(b"%PDF")
    return len(re.findall(rb"/Type\s*/Page[^s]", data)), data


def test_report_renders_every_page(tmp_path):
    res, targets, nominal = _result()
    p = write_calibration_report(res, tmp_path / "r.pdf", targets=targets, nominal=nominal)
    n, data = _pdf_pages(p)
    assert n == 4  # summary, estimates + correlation, residuals, planes from above
    assert b"CONVERGED" in data  # the verdict in the document's Subject


def test_residuals_and_triangulation_against_the_true_planes():
    res, targets, _ = _result()
    for (a, d), t in zip(PLANES, targets):
        r = target_residuals(res.system, t, (a, 0.0, d))
        # the synthetic detections are the rounded projections: |residual| <= 1/2 px
        assert np.nanmax(np.abs(r["res_pixel"])) <= 0.5 + 1e-9
        # the triangulated points lie on the plane within the pixel quantisation's depth
        # error z²/(f·b)·Δpx for |Δpx| ≤ ½ (first order, plus the tilt): uniform within it
        n = plane_normal(a)
        off = r["points"] @ n - d
        bound = d**2 / (197.2 * 0.122) * 0.5
        assert np.nanmax(np.abs(off)) < 1.3 * bound
        assert 0.3 * bound < np.nanmedian(np.abs(off)) < 0.7 * bound
        # time residual: first-photon time minus the return centre, within the pulse (σ 6.3 ns)
        assert abs(np.nanmedian(r["res_time"])) < 10e-9


def test_verdict_and_what_to_record_next():
    res, targets, nominal = _result()
    d = report_data_from_result(res, targets=targets, nominal=nominal)
    head, lines = verdict(d)
    assert head == "CONVERGED"
    todo = record_next(d)
    assert todo == [ADVICE["baseline_y"]]  # only the line sensor's blind spot
    weak = report_data_from_result(_result(std_scale=6.0)[0], targets=targets)
    head, lines = verdict(weak)
    assert head == "CONVERGED, WEAK"
    assert any("tdc_offset" in x for x in lines)
    assert ADVICE["tdc_offset"] in record_next(weak)
    nc = report_data_from_result(_result(converged=False)[0])
    assert verdict(nc)[0] == "NOT CONVERGED" and "100 iterations" in nc.reason


def test_failed_calibration_renders_and_says_why(tmp_path):
    _, targets, nominal = _result()
    err = NotObservableError("not observable from these data: tdc_offset: σ = 2.8 ns > 1 ns")
    p = write_calibration_report(err, tmp_path / "f.pdf", targets=targets[:1], nominal=nominal)
    n, data = _pdf_pages(p)
    assert n == 2 and b"FAILED" in data  # why + advice, and the data from above
    d = report_data_from_failure(err, nominal=nominal, targets=targets[:1])
    todo = record_next(d)
    assert ADVICE["tdc_offset"] in todo and any("at least 3" in t for t in todo)
    # without any data the failure page still renders
    assert _pdf_pages(write_calibration_report(err, tmp_path / "g.pdf"))[0] == 1


def test_report_path_must_be_pdf(tmp_path):
    res, _, _ = _result()
    with pytest.raises(FormatError, match="pdf"):
        write_calibration_report(res, tmp_path / "r.png")
    assert not math.isnan(res.std["theta0"])


@pytest.mark.slow
def test_report_for_the_bundled_walls(tmp_path):
    import warnings
    from pathlib import Path

    from mems_stereo.calib.calibrate import calibrate_system, read_target_distances

    root = Path(__file__).resolve().parents[1] / "samples"
    recs = [root / f"calib_{d}m.h5" for d in ("1.5", "2.5", "4.0")]
    dists, stds, kind = read_target_distances(root / "calib_distances.json", recs)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = calibrate_system(recs, target_distances=dists, distance_std=stds,
                               distance_kind=kind, n_iter=1)
    p = write_calibration_report(res, tmp_path / "walls.pdf", recordings=recs)
    n, data = _pdf_pages(p)
    assert n == 4 and b"CONVERGED" in data
    # one wall, no distances: calibration refuses (tdc_offset unobservable); the report says so
    err = NotObservableError("not observable from these data: tdc_offset (one wall)")
    p = write_calibration_report(err, tmp_path / "one_wall.pdf", recordings=recs[1:2],
                                 nominal=burkard2022())
    assert _pdf_pages(p)[0] == 2
