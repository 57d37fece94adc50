"""The first hour's API: bundled data, an API that takes what it returns, one-line reprs,
conversions, and a command line that helps."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mems_stereo.viz import cloud_to_open3d

import mems_stereo as ms
from mems_stereo.cli import main

ROOT = Path(__file__).resolve().parents[1]


def test_data_finds_the_source_trees_samples():
    # in a source checkout (editable install) the samples are the repository's samples/
    assert ms.data.root() == ROOT / "samples"
    names = ms.data.list()
    on_disk = sorted(p.name for p in (ROOT / "samples").iterdir()
                     if p.suffix in ms.data.SAMPLE_SUFFIXES)
    assert names == on_disk and "room.h5" in names and "make_samples.py" not in names
    assert ms.data.path("room.h5") == ROOT / "samples" / "room.h5"
    with pytest.raises(ValueError, match="did you mean 'room.h5'"):
        ms.data.path("rom.h5")


def test_data_from_another_folder(tmp_path):
    code = ("import mems_stereo as ms; p = ms.data.path('room.h5'); "
            "print(p.is_absolute() and p.exists(), len(ms.data.list()))")
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True,
                         text=True, check=True).stdout.split()
    assert out == ["True", str(len(ms.data.list()))]


@pytest.fixture(scope="module")
def room():
    return ms.read_recording(ms.data.path("room.h5"))


def test_process_takes_a_path_a_recording_or_chunks(room):
    a = ms.process_recording(ms.data.path("room.h5"))
    b = ms.process_recording(room)
    cuts = [0, 130, 400, 800]
    chunks = [ms.Recording(room.system, room.shot_time[i:j], room.bins[i:j], room.zero_crossings,
                           room.rising, {"label": room.truth["label"][i:j]}, "chunk")
              for i, j in zip(cuts[:-1], cuts[1:])]
    c = ms.process_recording(iter(chunks))
    assert dict(a.counts) == dict(b.counts) == dict(c.counts)
    assert np.array_equal(a.cloud.points, b.cloud.points)
    assert np.array_equal(a.cloud.points, c.cloud.points)
    assert a.truth == b.truth == c.truth
    with pytest.raises(ValueError, match="expected a recording path, a Recording or chunks"):
        ms.process_recording(42)


def test_one_counts_type_same_numbers(room):
    """classify_recording and process_recording: same type, keys and numbers on room.h5."""
    cl = ms.classify_recording(room)
    pr = ms.process_recording(room)
    assert type(cl.counts) is type(pr.counts) and list(cl.counts) == list(pr.counts)
    for k in ("shots", "shots_unknown_angle", "raw", "signal", "noise"):
        assert cl.counts[k] == pr.counts[k], k
    assert cl.counts.peaks is None and pr.counts.points == len(pr.cloud)
    # independent count of the labels
    assert cl.counts.signal == np.count_nonzero(cl.labels == 1)
    assert cl.counts.raw == np.count_nonzero(room.bins[cl.valid])
    assert cl.truth == pr.truth


def test_one_line_reprs(room):
    res = ms.process_recording(room)
    for obj in (res, res.cloud, res.system, room, ms.classify_recording(room), res.counts):
        r = repr(obj)
        assert "\n" not in r and len(r) < 400, r
    assert f"{len(res.cloud)} points" in repr(res.cloud)
    assert f"{res.counts['signal']} signal" in repr(res)


def test_cloud_conversions(room):
    cloud = ms.process_recording(room).cloud
    a = cloud.to_structured()
    assert a.shape == (len(cloud),) and a.dtype.names[:3] == ("x", "y", "z")
    assert np.array_equal(a["z"], cloud.points[:, 2]) and np.array_equal(a["range"],
                                                                         cloud["range"])
    pcd = cloud_to_open3d(cloud, color_by="range")
    assert np.allclose(np.asarray(pcd.points), cloud.points)
    col = np.asarray(pcd.colors)
    assert col.shape == (len(cloud), 3)
    # colours follow the attribute: the nearest and the farthest point differ
    assert not np.allclose(col[np.argmin(cloud["range"])], col[np.argmax(cloud["range"])])
    assert len(cloud_to_open3d(cloud, color_by=None).colors) == 0
    try:
        import pandas  # noqa: F401
    except ImportError:
        with pytest.raises(ImportError, match="to_structured"):
            cloud.to_pandas()
    else:
        assert list(cloud.to_pandas().columns) == list(a.dtype.names)


def test_unknown_preset_lists_the_presets(capsys):
    with pytest.raises(ValueError, match="presets: burkard2022"):
        ms.preset("burkard2023")
    with pytest.raises(KeyError):  # version 0.1 raised KeyError: still caught as one
        ms.preset("nope")
    assert main(["info", "--system", "burkard2023"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 2 and "--system: unknown preset 'burkard2023'" in err[0]
    assert "did you mean 'burkard2022'?" in err[1]


def test_did_you_mean_for_commands_and_options(capsys):
    with pytest.raises(SystemExit) as e:
        main(["procss"])
    assert e.value.code == 2
    assert "did you mean 'process'?" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["process", "x.h5", "-o", "y.ply", "--sytem", "a.json"])
    assert "did you mean --system" in capsys.readouterr().err


def test_long_errors_are_cut_with_advice():
    from mems_stereo.cli._ux import format_error

    text = format_error("calibrate", ValueError("x" * 2000 + "\nfix it so"))
    lines = text.splitlines()
    assert len(lines[0]) < 360 and lines[1] == "  fix it so" and "-v" in lines[2]
    assert len(format_error("calibrate", ValueError("y" * 2000), verbose=True)) > 2000


def test_progress_bar_is_off_when_not_a_terminal_or_quiet():
    from mems_stereo.cli._ux import progress_bar

    assert progress_bar(10, "x").disable  # pytest's stderr is not a terminal
    assert progress_bar(10, "x", quiet=True).disable


def test_samples_command_copies(tmp_path, capsys):
    assert main(["samples", "-o", str(tmp_path / "s"), "room.h5"]) == 0
    assert (tmp_path / "s" / "room.h5").read_bytes() == ms.data.path("room.h5").read_bytes()
    assert main(["samples", "-o", str(tmp_path / "s"), "rooom.h5"]) == 2
    assert "did you mean 'room.h5'" in capsys.readouterr().err


def test_simulate_of_a_recording_says_it_is_not_a_scene(tmp_path, capsys):
    assert main(["simulate", str(ms.data.path("room.h5")), "-o", str(tmp_path / "x.h5")]) == 2
    err = capsys.readouterr().err
    assert "expected a JSON text file, found binary data (an HDF5 file)" in err
    assert "Traceback" not in err and not (tmp_path / "x.h5").exists()


def test_not_observable_gets_advice():
    from mems_stereo.cli._ux import format_error
    from mems_stereo.errors import NotObservableError

    lines = format_error("calibrate", NotObservableError("theta0: σ = 7e6 mrad " * 40)).splitlines()
    assert lines[0].startswith("mems-stereo calibrate: error: theta0") and len(lines[0]) < 360
    assert "more distances" in lines[1] and "-v" in lines[2]
