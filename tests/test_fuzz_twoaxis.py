"""Two-axis recordings (FORMAT v1 extension) through the same safe reader as one-axis ones.

* The bundled two-axis samples read exactly as their raw HDF5 content (an
  independent plain h5py reading): the shared reader changed nothing.
* Malformed two-axis recordings through ``process``: exit 2, one line naming
  the file, no traceback, nothing created (the rules of tests/test_fuzz.py).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
from fuzz_cases import external_link, rep
from test_fuzz import check_refused

from mems_stereo.io.recording2d import read_recording_2d

SAMPLES = Path(__file__).resolve().parents[1] / "samples"


@pytest.mark.parametrize("name", ["lissajous64.h5", "raster128x96.h5",
                                  "lissajous64_calib_1.5m.h5"])
def test_two_axis_samples_read_as_stored(name):
    rec = read_recording_2d(SAMPLES / name)
    with h5py.File(SAMPLES / name, "r") as f:
        assert json.loads(f["system"][()]) is not None
        np.testing.assert_array_equal(rec.shot_time, f["shots/time"][()])
        np.testing.assert_array_equal(rec.zero_crossings, f["scanner/zero_crossings"][()])
        np.testing.assert_array_equal(rec.rising, f["scanner/rising"][()])
        assert rec.rising.dtype == np.uint8
        a2 = f["scanner/axis2"]
        if "zero_crossings" in a2:
            np.testing.assert_array_equal(rec.monitor2.zero_crossings, a2["zero_crossings"][()])
            np.testing.assert_array_equal(rec.monitor2.rising, a2["rising"][()])
        else:
            np.testing.assert_array_equal(rec.monitor2.time, a2["time"][()])
            np.testing.assert_array_equal(rec.monitor2.position, a2["position"][()])
        ra = f["readout"].attrs
        assert rec.readout["mode"] == (ra["mode"].decode() if isinstance(ra["mode"], bytes)
                                       else ra["mode"])
        for k in ("r_min", "r_max", "half_width"):
            if k in ra:
                assert rec.readout[k] == float(ra[k])
        for attr, path in (("read_count", "readout/count"), ("event_shot", "events/shot"),
                           ("event_pixel", "events/pixel"), ("event_code", "events/code")):
            np.testing.assert_array_equal(getattr(rec, attr), f[path][()])
        assert rec.event_code.dtype == np.uint16 and rec.event_shot.dtype == np.int64
        for k, v in f["truth"].items():
            np.testing.assert_array_equal(rec.truth[k], v[()])
        for k, v in f["truth"].attrs.items():
            np.testing.assert_array_equal(rec.truth[k], v)


def _attr(obj, key, value):
    def m(f, d):
        (f if obj == "/" else f[obj]).attrs[key] = value
    return m


CASES_2D = [
    ("version-abc", _attr("/", "version", "abc")),
    ("version-nan", _attr("/", "version", np.nan)),
    ("scan-axes-nan", _attr("/", "scan_axes", np.nan)),
    ("scan-axes-3", _attr("/", "scan_axes", 3)),
    ("system-void", rep("system", np.void(b"\xff\xfe"))),
    ("system-missing", lambda f, d: f.__delitem__("system")),
    ("external-link", external_link),
    ("soft-dangling", lambda f, d: f.__setitem__("y", h5py.SoftLink("/nowhere"))),
    ("time-float16", rep("shots/time", lambda f: f["shots/time"][()].astype(np.float16))),
    ("time-nan", rep("shots/time", lambda f: np.where(
        np.arange(f["shots/time"].shape[0]) == 5, np.nan, f["shots/time"][()]))),
    ("zc-spacing-x2", rep("scanner/zero_crossings",
                           lambda f: f["scanner/zero_crossings"][()] * 2)),
    ("rising-all", rep("scanner/rising", lambda f: np.ones_like(f["scanner/rising"][()]))),
    ("axis2-rising-all", rep("scanner/axis2/rising",
                              lambda f: np.ones_like(f["scanner/axis2/rising"][()]))),
    ("axis2-zc-float32", rep("scanner/axis2/zero_crossings",
                              lambda f: f["scanner/axis2/zero_crossings"][()].astype(np.float32))),
    ("readout-missing", lambda f, d: f.__delitem__("readout")),
    ("readout-mode-bogus", _attr("readout", "mode", "bogus")),
    ("readout-rmin-str", _attr("readout", "r_min", "abc")),
    ("readout-rmin-nan", _attr("readout", "r_min", np.nan)),
    ("readout-rmax-array", _attr("readout", "r_max", np.array([1.0, 2.0]))),
    ("readout-count-2d", rep("readout/count", np.ones((2, 3), np.uint16))),
    ("readout-count-float", rep("readout/count",
                                 lambda f: f["readout/count"][()].astype(np.float64))),
    ("events-shot-float", rep("events/shot", lambda f: f["events/shot"][()].astype(float))),
    ("events-pixel-short", rep("events/pixel", lambda f: f["events/pixel"][()][:-1])),
    ("events-code-int32", rep("events/code", lambda f: f["events/code"][()].astype(np.int32))),
    ("events-code-0", rep("events/code", lambda f: np.where(
        np.arange(f["events/code"].shape[0]) == 7, 0, f["events/code"][()]).astype(np.uint16))),
    ("events-unsorted", rep("events/shot", lambda f: f["events/shot"][()][::-1])),
    ("events-pixel-huge", rep("events/pixel", lambda f: f["events/pixel"][()] + 10**6)),
]


def _tiny_chunks(f, d):
    a = f["events/code"][()]
    del f["events/code"]
    f.create_dataset("events/code", data=a, chunks=(1,))


CASES_2D.append(("events-chunks-tiny", _tiny_chunks))



@pytest.mark.parametrize("name,mut", CASES_2D, ids=[c[0] for c in CASES_2D])
def test_two_axis_refused(name, mut, tmp_path):
    shutil.copy(SAMPLES / "lissajous64.h5", tmp_path / "m.h5")
    with h5py.File(tmp_path / "m.h5", "r+") as f:
        mut(f, tmp_path)
    check_refused(tmp_path, ["process", "{d}/m.h5", "-o", "{d}/o.ply"], "m.h5")


def test_two_axis_position_channel_refused(tmp_path):
    shutil.copy(SAMPLES / "raster128x96.h5", tmp_path / "m.h5")
    with h5py.File(tmp_path / "m.h5", "r+") as f:
        p = f["scanner/axis2/position"][()]
        del f["scanner/axis2/position"]
        f["scanner/axis2/position"] = np.where(np.arange(p.size) == 3, np.nan, p)
    check_refused(tmp_path, ["process", "{d}/m.h5", "-o", "{d}/o.ply"], "m.h5")


def _other_system(src: str, change):
    def b(d: Path):
        shutil.copy(SAMPLES / src, d / "m.h5")
        with h5py.File(d / "m.h5", "r+") as f:
            s = json.loads(f["system"][()])
            change(s)
            del f["system"]
            f["system"] = json.dumps(s)
    return b


SYSTEM_CHANGES = [("theta0", lambda s: s["scanner"].__setitem__("theta0",
                                                                 s["scanner"]["theta0"] + 0.01)),
                  ("f_mech", lambda s: s["scanner"].__setitem__("f_mech",
                                                                s["scanner"]["f_mech"] * 1.001)),
                  ("bin_width", lambda s: s["tdc"].__setitem__("bin_width",
                                                               s["tdc"]["bin_width"] * 2))]


@pytest.mark.parametrize("axes", [1, 2])
@pytest.mark.parametrize("what,change", SYSTEM_CHANGES, ids=[c[0] for c in SYSTEM_CHANGES])
def test_calibrate_recordings_of_one_system(axes, what, change, tmp_path):
    """``calibrate`` cross-checks every recording's /system against the first's (group 3)."""
    first, other = (("calib_1.5m.h5", "calib_2.5m.h5") if axes == 1 else
                    ("lissajous64_calib_1.5m.h5", "lissajous64_calib_2.5m.h5"))
    _other_system(other, change)(tmp_path)
    check_refused(tmp_path, ["calibrate", f"{{s}}/{first}", "{d}/m.h5", "-o", "{d}/c.json"],
                  "m.h5")


def _invert(*paths):
    def m(f, d):
        for p in paths:
            f[p][...] = 1 - f[p][()]
    return m


POLARITY_2D = [("axis1", ("scanner/rising",), "/scanner/rising"),
               ("axis2", ("scanner/axis2/rising",), "/scanner/axis2/rising"),
               ("both", ("scanner/rising", "scanner/axis2/rising"),
                "/scanner/rising and /scanner/axis2/rising")]


@pytest.mark.parametrize("axes,paths,field", POLARITY_2D, ids=[c[0] for c in POLARITY_2D])
@pytest.mark.parametrize("command", ["process", "calibrate"])
def test_two_axis_inverted_polarity_refused(command, axes, paths, field, tmp_path):
    """Group 3: an inverted zero-crossing polarity keeps the crossings alternating
    and spaced for f_mech; the detections outside the recomputed gate show it,
    and the refusal names the flag whose inversion puts them back inside."""
    src = "lissajous64.h5" if command == "process" else "lissajous64_calib_2.5m.h5"
    shutil.copy(SAMPLES / src, tmp_path / "m.h5")
    with h5py.File(tmp_path / "m.h5", "r+") as f:
        _invert(*paths)(f, tmp_path)
    argv = (["process", "{d}/m.h5", "-o", "{d}/o.ply"] if command == "process" else
            ["calibrate", "{s}/lissajous64_calib_1.5m.h5", "{d}/m.h5", "-o", "{d}/c.json"])
    err = check_refused(tmp_path, argv, "m.h5")  # the run's stderr: it is not run again
    assert f"{field}: the zero-crossing polarity looks inverted" in err, err
