"""System description: load/validate/save round trips and clear errors."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from mems_stereo.errors import FormatError
from mems_stereo.model.system import (
    burkard2022,
    load_system,
    preset,
    save_system,
    system_from_dict,
    system_to_dict,
)

FORMAT_EXAMPLE = {
    "format": "mems-stereo/system",
    "version": 1,
    "receiver": {
        "camera_matrix": [[197.2387, 0.0, 95.5], [0.0, 38.1679, 0.0], [0.0, 0.0, 1.0]],
        "dist_coeffs": [0.0, 0.0, 0.0, 0.0, 0.0],
        "image_size": [192, 1],
        "pixel_pitch": [40.56e-6, 209.6e-6],
        "spad_diameter": 12e-6,
    },
    "scanner": {
        "position": [-0.125, 0.0, 0.0],
        "normal_basis": [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]],
        "laser_direction": [-1.0, 0.0, 0.0],
        "theta0": 0.760419,
        "f_mech": 1570.0,
        "theta_mech_max": 0.207694,
    },
    "laser": {"f_rep": 20000.0, "pulse_fwhm": 14.9e-9, "wavelength": 659e-9},
    "tdc": {"bin_width": 312.5e-12, "n_bins": 4096, "offset": 0.0},
    "speed_of_light": 299704644.5,
}


def test_format_example_loads_and_matches_preset():
    s = system_from_dict(FORMAT_EXAMPLE)
    p = burkard2022()
    np.testing.assert_allclose(s.receiver.camera_matrix, p.receiver.camera_matrix, atol=1e-4)
    assert s.scanner.theta0 == pytest.approx(p.scanner.theta0, abs=1e-6)
    assert s.scanner.theta_mech_max == pytest.approx(math.radians(11.9), abs=1e-6)
    assert s.receiver.image_size == (192, 1)


def test_round_trip_through_file(tmp_path):
    s = preset("burkard2022").with_params(tdc_offset=1e-9, baseline_z=0.003)
    path = save_system(s, tmp_path / "sys.json")
    t = load_system(path)
    assert system_to_dict(t) == system_to_dict(s)
    assert list(tmp_path.iterdir()) == [path]  # no temporary file left


def _broken(path: str, value):
    d = json.loads(json.dumps(FORMAT_EXAMPLE))
    node = d
    keys = path.split(".")
    for k in keys[:-1]:
        node = node[k]
    if value is KeyError:
        del node[keys[-1]]
    else:
        node[keys[-1]] = value
    return d


@pytest.mark.parametrize("field,value,expect", [
    ("format", "something", "expected 'mems-stereo/system'"),
    ("version", 2, "expected 1"),
    ("receiver.camera_matrix", [[1, 0, 0], [0, 1, 0]], "expected shape (3, 3), found (2, 3)"),
    ("receiver.camera_matrix", [[-1, 0, 0], [0, 1, 0], [0, 0, 1]], "positive focal"),
    ("receiver.dist_coeffs", [0, 0, 0], "found 3"),
    ("receiver.image_size", [192], "[width, height]"),
    ("scanner.normal_basis", [[1, 0, 0], [0, 0, 2]], "unit vector"),
    ("scanner.normal_basis", [[1, 0, 0], [1, 0, 0]], "orthogonal"),
    ("scanner.laser_direction", [-2, 0, 0], "unit vector"),
    ("scanner.theta0", "abc", "expected a number"),
    ("laser.f_rep", -5, "positive"),
    ("tdc.n_bins", 4096.5, "integer"),
    ("tdc", KeyError, "required field is missing"),
    ("scanner.f_mech", KeyError, "required field is missing"),
])
def test_bad_fields_name_the_field(field, value, expect):
    with pytest.raises(FormatError) as e:
        system_from_dict(_broken(field, value), source="sys.json")
    msg = str(e.value)
    assert msg.startswith("sys.json: ")
    assert e.value.field.startswith(field.split(".")[0])
    assert expect in msg


def test_malformed_json_reports_line(tmp_path):
    p = tmp_path / "bad.json"
    p.write_text('{\n  "format": "mems-stereo/system",\n  "version": 1,\n}')
    with pytest.raises(FormatError, match=r"bad.json: not valid JSON.*line 4"):
        load_system(p)


def test_missing_file_is_a_format_error(tmp_path):
    with pytest.raises(FormatError, match="cannot read"):
        load_system(tmp_path / "nope.json")


def test_with_params_and_get_param_agree():
    s = burkard2022()
    for name, v in [("theta0", 0.7), ("tdc_offset", 1e-9), ("baseline_x", -0.12),
                    ("baseline_z", 0.01), ("phase_offset", 0.01), ("fx", 200.0), ("cx", 96.0)]:
        assert s.with_params(**{name: v}).get_param(name) == pytest.approx(v)
    with pytest.raises(KeyError):
        s.with_params(nonsense=1.0)
