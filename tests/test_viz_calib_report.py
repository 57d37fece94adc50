"""The calibration report: renders for a result and for a failure; residuals, verdict, advice."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from mems_stereo.calib.model import beam_hits, plane_normal
from mems_stereo.calib.problem import WallData
from mems_stereo.calib.result import CalibrationFailure, CalibrationResult
from mems_stereo.viz.calib_report import (
    ADVICE,
    record_next,
    report_data_from_failure,
    report_data_from_result,
    verdict,
    wall_residuals,
    write_calibration_report,
)

from mems_stereo.errors import FormatError, NotObservableError
from mems_stereo.model.system import burkard2022

NAMES = ["theta0", "theta_mech_max", "phase_offset", "tdc_offset", "baseline_x", "baseline_z"]
PLANES = [(0.05, 1.2), (-0.1, 2.0), (0.02, 3.5)]


def _true_system():
    nominal = burkard2022()
    true = nominal.with_params(theta0=nominal.scanner.theta0 + 2e-3, baseline_x=-0.122,
                               tdc_offset=1.5e-9)
    return nominal, true


def _wall(system, alpha, dist, n_shots, rng, source):
    """WallData whose only detections are the exact returns, rounded to pixel and TDC bin."""
    H, W = 1, system.receiver.width
    phase = rng.uniform(0, 2 * np.pi, n_shots)
    hits = beam_hits(system, {}, phase, plane_normal(alpha), dist)
    tau = hits.path / system.speed_of_light + system.tdc.offset
    bins = np.zeros((n_shots, H, W), np.uint16)
    col = np.rint(hits.pixel[:, 0])
    ok = hits.ok & (col >= 0) & (col < W)
    code = np.floor(tau / system.tdc.bin_width) + 1  # (code − ½)·bw within ½ bin of τ
    bins[np.flatnonzero(ok), 0, col[ok].astype(int)] = code[ok]
    return WallData(phase, bins, np.full((H, W), 1e3), system.tdc.bin_width, source)


def _result(std_scale=1.0, check_ok=True):
    """A CalibrationResult shaped as fit_walls returns it, from the true system (no fit)."""
    nominal, true = _true_system()
    rng = np.random.default_rng(11)
    walls = [_wall(true, a, d, 300, rng, f"wall_{d}m") for a, d in PLANES]
    std = {"theta0": 3e-5, "theta_mech_max": 1e-4, "phase_offset": 4e-5,
           "tdc_offset": 9e-11, "baseline_x": 3e-4, "baseline_z": 2e-3}
    std = {k: v * std_scale for k, v in std.items()}
    C = np.eye(6)
    C[0, 4] = C[4, 0] = 0.92
    s = np.array([std[n] for n in NAMES])
    targets = [{"source": w.source, "distance_axis": d / math.cos(a),
                "distance_axis_std": 1e-3, "mu": 3.0, "spot_px": 0.25, "tilt": abs(a),
                "consistency_p": 0.5, "time_shifts": [0.0] * 4, "column_shifts": [0.0] * 4,
                "signal_expected": 290.0, "signal_share": 1.0}
               for (a, d), w in zip(PLANES, walls)]
    checks = {"wall 0 tilt": (0.05, 1.047, True),
              "baseline length / nominal": (0.98 if check_ok else 3.0, (0.5, 2.0), check_ok)}
    res = CalibrationResult(
        system=true, names=NAMES, values={n: true.get_param(n) for n in NAMES}, std=std,
        initial={n: nominal.get_param(n) for n in NAMES}, covariance=C * np.outer(s, s),
        correlation=C, rms={"pixel": 0.29, "time": 5e-9}, n_detections=870,
        fixed=["baseline_y", "fx", "cx"], unobservable=["baseline_y"],
        tradeoffs=[("theta0", "baseline_x", 0.92)],
        planes=np.array([[a, 0.0, d] for a, d in PLANES]), planes_std=np.full((3, 3), 1e-3),
        targets=targets, checks=checks)
    return res, walls, nominal


def _pdf_pages(path):
    data = path.read_bytes()
    assert data.startswith(b"%PDF")
    return len(re.findall(rb"/Type\s*/Page[^s]", data)), data


def test_report_renders_every_page(tmp_path):
    res, walls, nominal = _result()
    p = write_calibration_report(res, tmp_path / "r.pdf", targets=walls, nominal=nominal)
    n, data = _pdf_pages(p)
    assert n == 4  # summary, estimates + correlation, residuals, planes from above
    assert b"(CONVERGED)" in data  # the verdict in the document's Subject
    # without recordings the result's own per-wall values stand in for the residuals
    n, _ = _pdf_pages(write_calibration_report(res, tmp_path / "s.pdf"))
    assert n == 4


def test_residuals_and_triangulation_against_the_true_planes():
    res, walls, _ = _result()
    bw = res.system.tdc.bin_width
    for (a, d), w in zip(PLANES, walls):
        r = wall_residuals(res.system, w, (a, 0.0, d))
        assert r.pixel.size > 200
        # the detections are the rounded projections: |residual| <= 1/2 px, 1/2 bin
        assert np.max(np.abs(r.res_pixel)) <= 0.5 + 1e-9
        assert np.max(np.abs(r.res_time)) <= 0.5 * bw + 1e-15
        # the triangulated points lie on the plane within the pixel quantisation's depth
        # error z²/(f·b)·Δpx for |Δpx| ≤ ½ (first order, plus the tilt): uniform within it
        off = r.points @ plane_normal(a) - d
        bound = d**2 / (197.2 * 0.122) * 0.5
        assert np.nanmax(np.abs(off)) < 1.3 * bound
        assert 0.3 * bound < np.nanmedian(np.abs(off)) < 0.7 * bound
    # a wrong plane (10 cm farther) shows as a time residual of about 2·10 cm / c
    a, d = PLANES[1]
    r = wall_residuals(res.system, walls[1], (a, 0.0, d + 0.1), radius=10, window=5e-9)
    assert r.res_time.size > 100 and -0.9e-9 < np.median(r.res_time) < -0.4e-9


def test_verdict_and_what_to_record_next():
    res, _, nominal = _result()
    d = report_data_from_result(res, nominal=nominal)
    head, lines = verdict(d)
    assert head == "CONVERGED"
    assert record_next(d) == [ADVICE["baseline_y"]]  # only the line sensor's blind spot
    weak = report_data_from_result(_result(std_scale=20.0)[0])
    head, lines = verdict(weak)
    assert head == "CONVERGED, WEAK"
    assert any("tdc_offset" in x for x in lines)  # 1.8 ns > half the 3 ns tolerance
    assert ADVICE["tdc_offset"] in record_next(weak)
    bad = report_data_from_result(_result(check_ok=False)[0])
    head, lines = verdict(bad)
    assert head == "CONVERGED, WEAK" and any("baseline length" in x for x in lines)


def test_failed_calibration_renders_two_pages_and_says_why(tmp_path):
    _, walls, nominal = _result()
    fail = CalibrationFailure(
        "not observable from these data: tdc_offset: σ = 2.8 ns > 1 ns", "input",
        {"values": {"theta0": 0.76, "tdc_offset": 1e-9}, "std": {"tdc_offset": 2.8e-9},
         "walls": [[0.01, 0.0, 2.0, 1.0, -1.0]],
         "checks": {"wall 0 tilt": (0.01, 1.047, True)},
         "targets": [{"source": "wall_2.0m", "distance_axis": 2.0, "signal_share": 0.2}]})
    p = write_calibration_report(fail, tmp_path / "f.pdf", targets=walls[:1], nominal=nominal)
    n, data = _pdf_pages(p)
    assert n == 2 and b"(FAILED)" in data  # why + advice, and what the fit learnt
    d = report_data_from_failure(fail, nominal=nominal)
    assert verdict(d)[0] == "FAILED" and d.kind == "input"
    assert d.initial["theta0"] == nominal.get_param("theta0")
    todo = record_next(d)
    assert ADVICE["tdc_offset"] in todo and any("at least 3" in t for t in todo)
    assert any("20%" in t for t in todo)  # the wall the fit explains badly
    # an exception and no data: still two pages
    err = NotObservableError("no wall return found")
    assert _pdf_pages(write_calibration_report(err, tmp_path / "g.pdf"))[0] == 2


def test_report_path_must_be_pdf(tmp_path):
    res, _, _ = _result()
    with pytest.raises(FormatError, match="pdf"):
        write_calibration_report(res, tmp_path / "r.png")
    assert not (tmp_path / "r.png").exists()


@pytest.mark.slow
def test_report_for_the_bundled_walls(tmp_path):
    from pathlib import Path

    from mems_stereo.calib.calibrate import calibrate_system, read_target_distances

    root = Path(__file__).resolve().parents[1] / "samples"
    recs = [root / f"calib_{d}m.h5" for d in ("1.5", "2.5", "4.0")]
    dists, stds, kind = read_target_distances(root / "calib_distances.json", recs)
    res = calibrate_system(recs, target_distances=dists, distance_std=stds,
                           distance_kind=kind)
    assert res
    p = write_calibration_report(res, tmp_path / "walls.pdf", recordings=recs)
    n, data = _pdf_pages(p)
    assert n == 5 and b"CONVERGED" in data  # + the hardware page (issue 30)
    # the recomputed residuals of the real walls: centred, about a pixel's spread
    from mems_stereo.calib.association import wall_data
    from mems_stereo.viz.calib_report import inliers

    from mems_stereo.io.recording import read_recording

    for j, r in enumerate(recs):
        rr = wall_residuals(res.system, wall_data(read_recording(r, truth=False)),
                            res.planes[j])
        ok = inliers(rr)
        assert ok.sum() > 1000
        assert abs(np.median(rr.res_pixel[ok])) < 0.1
        assert np.std(rr.res_pixel[ok]) < 1.0
