"""``mems-stereo calibrate``: argument checks (the full run is benchmarks/bench_calibrate.py)."""

from __future__ import annotations

import pytest

from mems_stereo.cli import main


def test_target_distance_count_must_match(tmp_path, capsys):
    rc = main(["calibrate", "a.h5", "b.h5", "-o", str(tmp_path / "s.json"),
               "--target-distance", "1.0"])
    assert rc == 2
    err = capsys.readouterr().err
    assert "--target-distance" in err and "one distance per recording (2)" in err
    assert not (tmp_path / "s.json").exists()


def test_missing_recording_is_reported(tmp_path, capsys):
    rc = main(["calibrate", str(tmp_path / "nope.h5"), "-o", str(tmp_path / "s.json")])
    assert rc == 2
    assert "nope.h5" in capsys.readouterr().err


def test_distances_file_errors_name_the_file(tmp_path, capsys):
    rc = main(["calibrate", "a.h5", "-o", str(tmp_path / "s.json"),
               "--target-distances-file", str(tmp_path / "none.json")])
    assert rc == 2
    assert "none.json" in capsys.readouterr().err
    assert not (tmp_path / "s.json").exists()


def test_distance_inputs_are_exclusive(tmp_path):
    with pytest.raises(SystemExit) as e:
        main(["calibrate", "a.h5", "-o", str(tmp_path / "s.json"), "--target-distance", "1.0",
              "--target-distances-file", "d.json"])
    assert e.value.code == 2


def test_distance_std_must_be_positive(tmp_path, capsys):
    rc = main(["calibrate", "a.h5", "-o", str(tmp_path / "s.json"), "--target-distance", "1.0",
               "--distance-std", "0"])
    assert rc == 2
    assert "--distance-std" in capsys.readouterr().err


SAMPLES = __import__("pathlib").Path(__file__).resolve().parents[1] / "samples"


# the failed fit of room.h5 + floodlight.h5 runs once for the two tests that write its
# report and docs/interchange.md's failed calibration (tests/conftest.py:
# ``shared_results``; one pytest-xdist worker runs them: XDIST_GROUPS).  The ideal model's
# fit: it fails in about 14 CPU s; the full model (the default) first tries its hardware
# terms on the non-walls, forward selection and a joint fit from a new start search,
# about 85 CPU s, before failing: that run is
# test_the_full_models_rescue_fails_cleanly_on_non_walls (pytest -m stress)
NOT_WALLS = [str(SAMPLES / "room.h5"), str(SAMPLES / "floodlight.h5")]


def test_recordings_that_are_not_flat_walls_fail_cleanly(tmp_path, capsys, shared_results):
    """The room and floodlight recordings are no calibration walls: exit 1,
    one line saying why, no system file; the report says why too."""
    _fails_cleanly(tmp_path, capsys, ["--model", "ideal"])


@pytest.mark.stress
def test_the_full_models_rescue_fails_cleanly_on_non_walls(tmp_path, capsys):
    """As above with the default model: its rescue (hardware terms fitted in rounds,
    then at once from a new start search) finds no fit of the non-walls either."""
    _fails_cleanly(tmp_path, capsys, [])


def _fails_cleanly(tmp_path, capsys, model: list) -> None:
    out, rep = tmp_path / "s.json", tmp_path / "r.json"
    rc = main(["calibrate", *NOT_WALLS, *model, "-o", str(out), "--report", str(rep)])
    err = capsys.readouterr().err
    assert rc in (1, 2)
    assert "calibration failed" in err and len(err.strip().splitlines()) == 1
    assert not out.exists()
    import json

    doc = json.loads(rep.read_text())
    assert doc["ok"] is False and doc["reason"] in err


def test_failed_calibration_writes_the_pdf_report(tmp_path, capsys, shared_results):
    """--report X.pdf on a failure: exit non-zero, no system file, a 2-page PDF saying why."""
    import re

    out, rep = tmp_path / "s.json", tmp_path / "r.pdf"
    rc = main(["calibrate", *NOT_WALLS, "--model", "ideal", "-o", str(out), "--report",
               str(rep)])
    assert rc in (1, 2) and not out.exists()
    assert "calibration failed" in capsys.readouterr().err
    data = rep.read_bytes()
    assert data.startswith(b"%PDF") and b"(FAILED)" in data
    assert len(re.findall(rb"/Type\s*/Page[^s]", data)) == 2


def test_contradicting_distance_named_no_file(tmp_path, capsys):
    """Wall 1's measured distance 15 cm off (26σ): exit 1, no file, the error and the
    warning name that wall's file.  Three simulated walls (tests/test_calib_fit.py's
    ``GOOD``, 1500 shots each, written as recordings): the same command path and
    leave-one-out check as on the bundled walls at about a third of their CPU time."""
    import math

    from mems_stereo.calib.family import Case, Wall, simulate_case

    from mems_stereo.io.recording import write_recording
    from mems_stereo.model.system import burkard2022

    ws = [Wall(d, math.radians(yaw), math.radians(pitch), 0.5, flux, 1500, 2e5)
          for d, yaw, pitch, flux in ((1.2, 8, 3, 1.0), (2.5, -10, -2, 0.5), (4.0, 5, 0, 0.8))]
    case = Case(ws, {"theta0": 6e-3, "baseline_x": 4e-3, "baseline_z": -3e-3,
                     "tdc_offset": 1.5e-9, "theta_mech_max_rel": 0.005, "phase_offset": 0.01},
                7, [w.distance for w in ws])
    walls = []
    for i, r in enumerate(simulate_case(case, burkard2022())):
        walls.append(str(write_recording(tmp_path / f"wall{i}.h5", r.system, r.shot_time,
                                         r.bins, r.zero_crossings, r.rising)))
    dists = list(case.measured)
    dists[1] += 0.15
    out = tmp_path / "s.json"
    rc = main(["calibrate", *walls, "-o", str(out), "--target-distance", *map(str, dists),
               "--distance-std", "0.002"])
    cap = capsys.readouterr()
    assert rc == 1 and not out.exists()
    assert "measured distance of wall 1" in cap.err and "wall1.h5" in cap.err
    assert "warning: the measured distance of wall 1" in cap.out


def test_report_json_on_the_bundled_walls(tmp_path, capsys):
    """``--report R.json`` with ``--operator`` and a system carrying ``device_id``: the
    header (date, version, device, operator, input files with SHA-256), the checks
    measured beside fitted, and the time residuals with the first-photon shift removed:
    centred on the bundled walls (they sit at −5.0 / −3.6 / −1.5 ns against the pulse
    centre)."""
    import datetime as dt
    import hashlib
    import json
    import math

    import mems_stereo as ms
    from mems_stereo.io.recording import read_system

    walls = [SAMPLES / f"calib_{d}m.h5" for d in ("1.5", "2.5", "4.0")]
    dists = SAMPLES / "calib_distances.json"
    sys_path = tmp_path / "nominal.json"
    ms.save_system(read_system(walls[0]).replace(device_id="LAB-SN-0042"), sys_path)
    out, rep = tmp_path / "cal.json", tmp_path / "r.json"
    t0 = dt.datetime.now(dt.timezone.utc).replace(microsecond=0)
    assert main(["calibrate", "-q", *map(str, walls), "--target-distances-file", str(dists),
                 "--system", str(sys_path), "-o", str(out), "--report", str(rep),
                 "--operator", "A. Lab"]) == 0
    doc = json.loads(rep.read_text())
    h = doc["header"]
    when = dt.datetime.strptime(h["date_utc"], "%Y-%m-%dT%H:%M:%SZ").replace(
        tzinfo=dt.timezone.utc)
    assert t0 <= when <= dt.datetime.now(dt.timezone.utc)
    assert (h["version"], h["device_id"], h["operator"]) == (ms.__version__, "LAB-SN-0042",
                                                             "A. Lab")
    assert [f["role"] for f in h["inputs"]] == ["recording"] * 3 + ["system", "distances"]
    for f, path in zip(h["inputs"], [*walls, sys_path, dists]):
        assert f["sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
    assert ms.load_system(out).device_id == "LAB-SN-0042"  # carried into the result
    # measured beside fitted, one unit per quantity
    want = json.loads(dists.read_text())
    rows = {r["name"]: r for r in doc["checks"]}
    for j in range(len(walls)):
        r = rows[f"wall {j} distance"]
        assert r["unit"] == "m" and f"measured {r['measured']:.4f} m, fitted" in r["text"]
        assert r["fitted"] == pytest.approx(doc["walls"][j]["distance_axis_m"])
        assert rows[f"wall {j} tilt"]["unit"] == "mrad"
        assert abs(rows[f"wall {j} tilt"]["fitted"]) == pytest.approx(
            abs(doc["walls"][j]["tilt_mrad"]))
        assert doc["walls"][j]["signal_explained_pct"] <= 100.0
    assert [rows[f"wall {j} distance"]["measured"] for j in range(3)] == [
        t["distance"] for t in want["targets"]]
    assert not any("baseline_y" in t for t in doc["record_next"])  # fixed already
    # residuals after the first-photon shift: centred.  Each wall within 2.5 standard
    # errors of 0 (0.12 ns at 4 m: 3,500 detections, 6.9 ns spread); all pooled within 0.1 ns
    res = doc["residuals"]
    n = sum(r["inliers"] for r in res)
    pooled = sum(r["time_mean_ns"] * r["inliers"] for r in res) / n
    assert abs(pooled) < 0.1
    for r in res:
        assert r["first_photon_removed"] and r["inliers"] > 3000
        se = r["time_rms_ns"] / math.sqrt(r["inliers"])
        assert abs(r["time_mean_ns"]) < 2.5 * se and abs(r["pixel_mean_px"]) < 0.05
    fit_means = [w["time_residual_mean_ns"] for w in doc["walls"]]
    assert max(abs(v) for v in fit_means) < 0.15
    # the headline RMS is computed the same way: between the walls' own RMS values
    rms = [w["time_residual_rms_ns"] for w in doc["walls"]]
    assert min(rms) < doc["rms"]["time_ns"] < max(rms)

