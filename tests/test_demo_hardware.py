"""The bundled imperfect-hardware samples: the full model beats nominal and the ideal model.

Calibrates samples/imperfect_calib_<d>m.h5 with the ideal and the full model once
(module fixture, about 12 s on one core) and processes imperfect_room.h5 with each.
"""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest

import mems_stereo as ms
from mems_stereo.cli.demo_hardware import IMPERFECT_ROOM, IMPERFECT_WALLS
from mems_stereo.io.recording import read_recording
from mems_stereo.model.system import load_system, system_to_dict

SAMPLES = Path(__file__).resolve().parents[1] / "samples"


# one pytest-xdist worker runs this module with tests/test_demo.py (tests/conftest.py:
# XDIST_GROUPS)


@pytest.fixture(scope="module")
def comparison():
    """The comparison, computed once with ``mems-stereo demo``'s step 7 (tests/test_demo.py;
    tests/conftest.py: ``share_heavy_results``)."""
    from conftest import share_heavy_results

    import mems_stereo.cli.demo_hardware as hw_mod

    with pytest.MonkeyPatch.context() as mp:
        share_heavy_results(mp)
        return hw_mod.hardware_comparison(SAMPLES)


def _row(comp, system):
    return next(r for r in comp["rows"] if r["system"] == system)


def test_full_model_beats_nominal_and_ideal(comparison):
    nominal = _row(comparison, "nominal")
    ideal = _row(comparison, "calibrated, ideal model")
    full = _row(comparison, "calibrated, full model")
    assert full["calibration"] == "accepted"
    assert full["median_error"] < ideal["median_error"] < nominal["median_error"]
    # the full model's σ describe its errors; the refused ideal fit's σ, inflated to cover
    # its misfit, reach the points through the calibration covariance and cover its larger
    # errors; the nominal system's σ know nothing of its errors
    assert 0.6 < full["rms_pull"] < 1.5 and 0.6 < ideal["rms_pull"] < 1.5
    assert nominal["rms_pull"] > 3.0
    assert full["false_points"] <= ideal["false_points"] < nominal["false_points"]
    assert full["coverage"] >= ideal["coverage"] - 0.02


def test_ideal_model_is_refused_naming_the_harmonic_and_its_sigma_inflated(comparison):
    """calib's contract: the goodness test fails the ideal fit; with inflate_sigma the
    result is kept with every σ inflated and a warning saying so."""
    ideal = _row(comparison, "calibrated, ideal model")
    assert ideal["calibration"].startswith("refused: the model does not fit these walls")
    assert "third harmonic of the mirror" in ideal["calibration"]
    assert any(w.startswith("σ inflated ×") for w in comparison["ideal_warnings"])
    assert "median_error" in ideal  # the inflated-σ system was scored


def test_full_model_recovers_the_third_harmonic(comparison):
    h3 = comparison["harmonic3"]
    assert h3 is not None and h3["true"] == pytest.approx(0.003)
    assert 0 < h3["std"] < 0.1 * h3["true"]
    assert abs(h3["estimate"] - h3["true"]) <= 3 * h3["std"]


def test_imperfect_samples_are_bundled_and_json_safe(comparison):
    names = ms.data.list()
    for n in (*IMPERFECT_WALLS, IMPERFECT_ROOM, "imperfect_true_system.json",
              "imperfect_calib_distances.json"):
        assert n in names
    json.dumps(comparison)  # goes into demo_summary.json as it is
    assert sum((SAMPLES / n).stat().st_size for n in names if n.startswith("imperfect_")) \
        < 2.5e6


def _make_samples_module():
    spec = importlib.util.spec_from_file_location("make_samples", SAMPLES / "make_samples.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["make_samples"] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def test_imperfect_samples_regenerate_bit_for_bit(tmp_path):
    mk = _make_samples_module()
    wall = next(s for s in mk.IMPERFECT_SAMPLES if s.name == "imperfect_calib_4.0m")
    a = read_recording(mk.make_sample(wall, tmp_path, "imperfect"))
    shipped = read_recording(SAMPLES / "imperfect_calib_4.0m.h5")
    for f in ("bins", "shot_time", "zero_crossings", "rising"):
        np.testing.assert_array_equal(getattr(a, f), getattr(shipped, f))
    np.testing.assert_array_equal(a.truth["label"], shipped.truth["label"])
    true = mk.with_hardware(mk.calib_true_system(), "imperfect")
    assert system_to_dict(load_system(SAMPLES / "imperfect_true_system.json")) == \
        system_to_dict(true)
    assert not true.ideal_hardware
    d = mk.imperfect_distances(tmp_path)
    assert d.read_bytes() == (SAMPLES / "imperfect_calib_distances.json").read_bytes()
