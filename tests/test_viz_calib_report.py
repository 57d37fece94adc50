"""The calibration report: renders for a result and for a failure; residuals, verdict, advice;
the header a lab files (date, version, device, operator, input hashes), checks measured
beside fitted with units, pulls on a ±5σ axis, the first-photon shift removed."""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import math
import re

import mems_stereo.viz.calib_report as cr
import numpy as np
import pytest
from mems_stereo.calib.checks import first_photon_mean
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
from mems_stereo.viz.calib_report_checks import check_rows
from mems_stereo.viz.calib_report_data import ADVICE_DISTANCES_GIVEN
from mems_stereo.viz.calib_report_header import report_header

import mems_stereo
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
    targets[0].update(distance_measured=1.2, distance_measured_std=2e-3, distance_kind="axis",
                      distance_fitted=targets[0]["distance_axis"], signal_share=1.013)
    checks = {"wall 0 tilt": (0.05, 1.047, True),
              "wall 0 distance": (targets[0]["distance_axis"], 0.2, True),
              "wall 0 signal explained": (1.013, 0.5, True),
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
    # baseline_y, the line sensor's blind spot, is fixed already: no advice to fix it
    assert "baseline_y" in d.fixed and record_next(d) == []
    d.fixed = ["fx", "cx"]
    assert record_next(d) == [ADVICE["baseline_y"]]
    weak = report_data_from_result(_result(std_scale=20.0)[0])
    head, lines = verdict(weak)
    assert head == "CONVERGED, WEAK"
    assert any("tdc_offset" in x for x in lines)  # 1.8 ns > half the 3 ns tolerance
    # the distances were measured and given: no advice to give them
    assert ADVICE_DISTANCES_GIVEN["tdc_offset"] in record_next(weak)
    assert not any("--target-distances-file" in t for t in record_next(weak))
    for t in weak.walls:
        t.pop("distance_measured", None)
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
def test_report_for_the_bundled_walls(tmp_path, shared_results):
    """The calibration is made with the arguments ``mems-stereo calibrate`` gives for the
    bundled walls and their distances file, so that it is computed once with
    ``mems-stereo demo``'s and tests/test_cli_outputs.py's (tests/conftest.py:
    ``shared_results``, XDIST_GROUPS)."""
    from pathlib import Path

    import mems_stereo.calib.calibrate as calib_mod
    from mems_stereo.calib.calibrate import read_target_distances
    from mems_stereo.calib.model import DEFAULT_FREE

    root = Path(__file__).resolve().parents[1] / "samples"
    recs = [root / f"calib_{d}m.h5" for d in ("1.5", "2.5", "4.0")]
    dists, stds, kind = read_target_distances(root / "calib_distances.json", recs)
    res = calib_mod.calibrate_system(recs, None, fix=[], free=list(DEFAULT_FREE),
                                     target_distances=dists, distance_std=stds,
                                     distance_kind=kind, on_unobservable="raise",
                                     model="full", harmonics=(2, 3, 4, 5),
                                     inflate_sigma=False)
    assert res
    import mems_stereo.viz.calib_report as report_mod  # drawn once per process (shared_results)

    p = report_mod.write_calibration_report(res, tmp_path / "walls.pdf", recordings=recs)
    n, data = _pdf_pages(p)
    assert n >= 5 and b"CONVERGED" in data  # page 1's text continued, the hardware page
    # the recomputed residuals of the real walls: centred, about a pixel's spread
    from mems_stereo.calib.association import wall_data
    from mems_stereo.viz.calib_report import inliers

    from mems_stereo.io.recording import read_recording

    for j, r in enumerate(recs):
        rr = wall_residuals(res.system, wall_data(read_recording(r, truth=False)),
                            res.planes[j], target=res.targets[j])
        ok = inliers(rr)
        assert ok.sum() > 1000
        assert abs(np.median(rr.res_pixel[ok])) < 0.1
        assert np.std(rr.res_pixel[ok]) < 1.0


def _header(tmp_path):
    files = []
    for name, body in (("wall_a.h5", b"abc" * 1000), ("dist.json", b'{"x": 1}')):
        (tmp_path / name).write_bytes(body)
        files.append((name, hashlib.sha256(body).hexdigest(), len(body)))
    h = report_header([("recording", tmp_path / "wall_a.h5"), ("distances", tmp_path / "dist.json"),
                       ("system", "burkard2022")], device_id="LAB-SN-0042", operator="A. Lab",
                      now=dt.datetime(2026, 11, 27, 9, 14, 3, tzinfo=dt.timezone.utc))
    return h, files


def test_header_on_page_one_and_in_the_json(tmp_path, monkeypatch):
    h, files = _header(tmp_path)
    assert h["date_utc"] == "2026-11-27T09:14:03Z" and h["version"] == mems_stereo.__version__
    for (name, digest, size), f in zip(files, h["inputs"]):
        assert f["path"].endswith(name) and (f["sha256"], f["bytes"]) == (digest, size)
    assert h["inputs"][2] == {"role": "system", "path": "burkard2022", "bytes": None,
                              "sha256": None}  # a preset: named, no file to hash
    # page 1: the text the PDF builder is given
    pages = []
    real = cr._text_page

    def spy(pdf, title, blocks, *a, **k):
        pages.append((title, blocks))
        return real(pdf, title, blocks, *a, **k)
    monkeypatch.setattr(cr, "_text_page", spy)
    res, walls, nominal = _result()
    write_calibration_report(res, tmp_path / "r.pdf", nominal=nominal, header=h)
    title, blocks = pages[0]
    assert title.startswith("Calibration report") and blocks[0][0] == "Record"
    text = "\n".join(blocks[0][1])
    for want in ("2026-11-27T09:14:03Z", f"mems-stereo {mems_stereo.__version__}",
                 "LAB-SN-0042", "A. Lab", files[0][1], files[1][1], "wall_a.h5"):
        assert want in text, want
    # the same content for machines
    p = write_calibration_report(res, tmp_path / "r.json", nominal=nominal, header=h)
    doc = json.loads(p.read_text())
    assert doc["format"] == "mems-stereo/calibration-report" and doc["header"] == h
    assert doc["verdict"] == "CONVERGED" and doc["result"]["ok"] is True
    assert [r["text"] for r in doc["checks"]] == [r["text"] for r in cr.checks_of(
        cr.report_data(res, nominal=nominal))]
    assert {p_["name"] for p_ in doc["parameters"]} == set(NAMES)


def test_checks_show_measured_beside_fitted_with_units():
    res, _, nominal = _result()
    d = report_data_from_result(res, nominal=nominal)
    rows = {r["name"]: r for r in check_rows(d.checks, d.walls, d.nominal, d.system)}
    fitted = res.targets[0]["distance_axis"]
    dist = rows["wall 0 distance"]
    assert (dist["unit"], dist["measured"], dist["fitted"], dist["limit"]) == ("m", 1.2, fitted,
                                                                               0.2)
    assert dist["text"] == f"wall 0 distance: measured 1.2000 m, fitted {fitted:.4f} m, " \
                           "limit ≥ 0.2000 m: ok"
    tilt = rows["wall 0 tilt"]  # mrad, as the wall rows and the estimates
    assert tilt["unit"] == "mrad" and tilt["fitted"] == pytest.approx(50.0)
    assert "fitted 50 mrad, limit ≤ 1047 mrad: ok" in tilt["text"]
    share = rows["wall 0 signal explained"]  # 101.3 % of a Poisson excess: at most 100 %
    assert share["fitted"] == 100.0 and "101" not in share["text"]
    base = rows["baseline length / nominal"]
    assert "nominal 125.00 mm" in base["text"] and base["passed"] is True
    assert "FAILED" in check_rows({"x": (3.0, (0.5, 2.0), False)}, [])[0]["text"]


def test_pulls_on_a_five_sigma_axis():
    res, _, nominal = _result()
    d = report_data_from_result(res, nominal=nominal)
    d.values["theta0"] = d.initial["theta0"] + 350 * d.std["theta0"]  # a 350σ shift
    figs = []

    class Pdf:
        def savefig(self, fig):
            figs.append(fig)
    cr._estimates_page(Pdf(), d)
    ax = figs[0].axes[0]
    assert ax.get_xlim() == (-5.5, 5.5)
    z = {n: (d.values[n] - d.initial[n]) / d.std[n] for n in d.names}
    far = [f"{v:+.0f}σ" for v in z.values() if abs(v) > 5]
    assert "+350σ" in far and len(far) < len(z)
    # beyond ±5σ: clipped to the edge and marked with the value; the rest drawn as is
    assert [t.get_text() for t in ax.texts] == far
    drawn = np.concatenate([ln.get_xdata() for ln in ax.lines if len(ln.get_xdata())])
    assert np.all(np.abs(drawn) <= 5.0 + 1e-12)


def test_first_photon_mean_against_monte_carlo_and_limits():
    rng = np.random.default_rng(7)
    for m, z0 in ((10.0, -8.0), (1.0, -1.7), (3.0, -0.5)):
        n = rng.poisson(m, 60000)
        z = np.full(n.size, np.inf)
        for i in range(int(n.max())):
            s = rng.standard_normal(n.size)
            z = np.where((i < n) & (s >= z0), np.minimum(z, s), z)  # the gate opens at z0
        z = z[np.isfinite(z)]
        assert abs(first_photon_mean(m, z0) - z.mean()) < 4 * z.std() / math.sqrt(z.size)
    # m → 0: the truncated normal's mean φ(z0) / (1 − Φ(z0))
    from scipy.stats import norm

    assert first_photon_mean(1e-9, -1.0) == pytest.approx(norm.pdf(-1) / norm.sf(-1), abs=2e-3)
    assert first_photon_mean(10.0, -8.0) == pytest.approx(-1.5045, abs=2e-3)


def test_time_residuals_have_the_first_photon_shift_removed():
    """Exact returns at 10 photons per shot, each detection the first of its Poisson
    photons: against the pulse centre the residuals sit 1.5σ early; with the wall's
    fitted signal they are centred."""
    nominal, true = _true_system()
    rng = np.random.default_rng(3)
    sigma = 2e-9
    a, d = PLANES[1]
    w = _wall(true, a, d, 4000, rng, "w")
    from mems_stereo.calib.model import code_time

    ok = w.bins > 0
    n = rng.poisson(10.0 * 0.9999, ok.sum())  # the spot's share on its pixel ≈ 1 (σ 0.1 px)
    first = np.array([rng.standard_normal(k).min() if k else np.inf for k in n])
    keep = np.isfinite(first)
    t = code_time(w.bins[ok], w.bin_width)[keep] + sigma * first[keep]
    bins = np.zeros_like(w.bins)
    idx = np.flatnonzero(ok.ravel())[keep]
    bins.ravel()[idx] = np.floor(t / w.bin_width + 0.5) + 1  # t − ½ bin rounds to its code
    w2 = WallData(w.phase, bins, w.background, w.bin_width, "w")
    target = {"mu": 10.0, "spot_px": 0.12, "log_gref": 0.0, "pulse_sigma": sigma}
    from mems_stereo.calib.problem import shot_model

    lg = shot_model(true, {}, np.array([a, 0.0, d, 0.0, 0.0]), w.phase)[0][:, 3]
    target["log_gref"] = float(np.median(lg))  # μ at this wall's typical gain
    raw = wall_residuals(true, w2, (a, 0.0, d), window=20e-9)
    fixed = wall_residuals(true, w2, (a, 0.0, d), window=20e-9, target=target)
    assert fixed.first_photon and not raw.first_photon
    assert np.mean(raw.res_time) < -1.2 * sigma
    assert abs(np.mean(fixed.res_time)) < 0.1 * sigma


def test_two_axis_report_carries_the_same_header(tmp_path, monkeypatch):
    import mems_stereo.viz.calib_report_2d as r2

    h, files = _header(tmp_path)
    d = r2.two_axis_failure_dict("no wall return", recordings=["a.h5"], header=h)
    assert d["header"] == h and json.loads(json.dumps(d))["header"]["device_id"] == "LAB-SN-0042"
    pages = []
    real = r2._text_page
    monkeypatch.setattr(r2, "_text_page", lambda pdf, title, blocks: (
        pages.append(blocks), real(pdf, title, blocks)))
    r2.write_two_axis_report(d, tmp_path / "f.pdf")
    text = "\n".join(pages[0][0][1])
    assert pages[0][0][0] == "record" and files[0][1] in text and "A. Lab" in text
