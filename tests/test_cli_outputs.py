"""Outputs are what their names say (issue 32).

Every command × every output suffix it documents (``cli/_writes.py:WRITES``,
the table the help texts list) × each input kind (line sensor: room.h5,
calib_*.h5; two-axis: lissajous64*.h5): the file written is of that format,
read back by its own library (PLY/PCD by Open3D, LAS/LAZ by laspy, ROS 2 bags
by the package's reader, JSON by json, YAML/XML by cv2.FileStorage, HDF5 by
h5py, NPZ by numpy, PDF/PNG/SVG by their header), or the command is refused
before any work (exit 2, nothing written).  A suffix a command does not write
is refused naming the option and the suffixes it accepts; a missing output
folder is refused unless ``--parents``, and no folder is created then.

The fits and the processing run once per input kind (module fixtures); the
cases reuse their results, so each case runs the command's writers only.
"""

from __future__ import annotations

import argparse
import importlib
import json
import re
from pathlib import Path

import cv2
import h5py
import mems_stereo.calib.calibrate as calib_mod
import mems_stereo.calib.twoaxis as twoaxis_mod
import numpy as np
import pytest

import mems_stereo.pipeline.run as run_mod
import mems_stereo.pipeline.twoaxis as pipe2d_mod
from mems_stereo import data
from mems_stereo.cli import build_parser, main
from mems_stereo.cli._outputs import IO
from mems_stereo.cli._writes import CLOUD_SUFFIXES, PLOT_SUFFIXES, WRITES
from mems_stereo.model.system import load_system

S = data.root()
WALLS = {"line": [str(S / f"calib_{d}m.h5") for d in ("1.5", "2.5", "4.0")],
         "two": [str(S / f"lissajous64_calib_{d}m.h5") for d in ("1.5", "2.5", "4.0")]}
RECS = {"line": str(S / "room.h5"), "two": str(S / "lissajous64.h5")}
SYSTEMS = {"line": "burkard2022", "two": str(S / "lissajous64_system.json")}
#: (command, option, input kind) the command refuses before any work, by design
REFUSED = {("process", "histograms", "two")}
_PROCESS = run_mod.process_recording
# one pytest-xdist worker: ``ctx`` once, and its calibrations shared with tests/test_demo.py
# (tests/conftest.py: XDIST_GROUPS)


# ----------------------------------------------------------------- fixtures

@pytest.fixture(scope="module")
def ctx(tmp_path_factory):
    """One real calibration and one processing per input kind; their results cached."""
    d = tmp_path_factory.mktemp("outputs")
    got: dict = {}

    def spy(mod, name, key):
        real = getattr(mod, name)

        def f(*a, **k):
            got[key] = real(*a, **k)
            return got[key]
        return f

    from conftest import share_heavy_results

    with pytest.MonkeyPatch.context() as mp:
        share_heavy_results(mp)  # the calibrations are the demo's (tests/test_demo.py)
        mp.setattr(calib_mod, "calibrate_system", spy(calib_mod, "calibrate_system", "cal_line"))
        mp.setattr(twoaxis_mod, "calibrate_two_axis",
                   spy(twoaxis_mod, "calibrate_two_axis", "cal_two"))
        mp.setattr(run_mod, "process_recording", spy(run_mod, "process_recording", "proc_line"))
        mp.setattr(pipe2d_mod, "process_recording_2d",
                   spy(pipe2d_mod, "process_recording_2d", "proc_two"))
        assert main(["calibrate", "-q", *WALLS["line"], "--target-distances-file",
                     str(S / "calib_distances.json"), "-o", str(d / "cal_line.json")]) == 0
        assert main(["calibrate", "-q", *WALLS["two"], "-o", str(d / "cal_two.json")]) == 0
        assert main(["process", "-q", RECS["line"], "-o", str(d / "line.ply"),
                     "--histograms", str(d / "line_hist.h5")]) == 0
        assert main(["process", "-q", RECS["two"], "-o", str(d / "two.ply")]) == 0
    got.update(dir=d, clouds={"line": str(d / "line.ply"), "two": str(d / "two.ply")},
               hist=str(d / "line_hist.h5"))
    return got


@pytest.fixture
def cached(ctx, monkeypatch):
    """The fits and the processing answer from the module's results."""
    monkeypatch.setattr(calib_mod, "calibrate_system", lambda *a, **k: ctx["cal_line"])
    monkeypatch.setattr(twoaxis_mod, "calibrate_two_axis", lambda *a, **k: ctx["cal_two"])
    def process(*a, **k):  # the labels are written by the pipeline itself; frames (a
        # table passed) are each a small recording of their own
        real = k.get("labels_path") or k.get("table") is not None
        return _PROCESS(*a, **k) if real else ctx["proc_line"]

    monkeypatch.setattr(run_mod, "process_recording", process)
    monkeypatch.setattr(pipe2d_mod, "process_recording_2d", lambda *a, **k: ctx["proc_two"])
    import mems_stereo.viz.calib_report as report_mod
    from conftest import memoised_report

    # the report PDF of the bundled walls is drawn once with the demo's (same result object)
    real = report_mod.write_calibration_report
    monkeypatch.setattr(report_mod, "write_calibration_report",
                        memoised_report(getattr(real, "__wrapped_real__", real)))
    return ctx


def _argv(cmd: str, opt: str, kind: str, out: str, c: dict, tmp: Path) -> list | None:
    """A command line of ``cmd`` writing ``out`` through ``opt`` for input ``kind``
    (None: the command takes no input of that kind)."""
    if cmd == "calibrate":
        base = ["calibrate", *WALLS[kind]]
        if kind == "line":
            base += ["--target-distances-file", str(S / "calib_distances.json")]
        return base + (["-o", out] if opt == "output"
                       else ["-o", str(tmp / "cal.json"), "--report", out])
    if cmd == "process":
        if opt == "output":
            return ["process", RECS[kind], "-o", out]
        return ["process", RECS[kind], "-o", str(tmp / "c.ply"), f"--{opt}", out]
    if cmd == "simulate":
        if kind == "line":
            return ["simulate", str(S / "room_scene.json"), "--shots", "40", "-o", out]
        return ["simulate", str(S / "twoaxis_scene.json"), "--system", "lissajous64",
                "--shots", "100", "-o", out]
    if cmd == "import":
        if kind == "two":
            return None  # time-tagger files map to line-sensor recordings
        return ["import", str(S / "room48.ptu"), "--map", str(S / "room48_map.json"), "-o", out,
                *(["--all-photons"] if out.endswith(".npz") else [])]
    if cmd in ("export", "render"):
        # a PLY carries no acquisition time: a ROS 2 bag from it is stamped with --stamp
        stamp = ["--stamp", "2026-11-27T08:00:00Z"] if cmd == "export" and \
            Path(out).suffix in (".mcap", ".db3") else []
        return [cmd, c["clouds"][kind], "-o", out, *stamp]
    if cmd == "plot cloud":
        return ["plot", "cloud", c["clouds"][kind], "-o", out]
    if cmd == "plot histograms":
        return None if kind == "two" else ["plot", "histograms", c["hist"], "--max-code", "64",
                                         "-o", out]
    if cmd == "plot acquisition":
        return ["plot", "acquisition", "--shots", "50", "--system", SYSTEMS[kind], "-o", out]
    if cmd == "info":
        return ["info", "--shots", "50", "--system", SYSTEMS[kind], "--plot", out]
    if cmd == "live":  # frames of a line-sensor recording replayed
        return ["live", "--replay", RECS["line"], "--rate", "max", "--frame-shots", "400",
                "-o", out]
    raise AssertionError(f"no command line for {cmd} {opt}")


def _cases():
    for (cmd, opt), w in sorted(WRITES.items()):
        for sfx in w.suffixes:
            for kind in ("line", "two"):
                if (cmd, kind) in (("import", "two"), ("plot histograms", "two"),
                                   ("live", "two")):
                    continue  # no input of that kind exists for the command
                yield pytest.param(cmd, opt, sfx, kind, id=f"{cmd}-{opt}-{kind}{sfx}")


# ------------------------------------------------------------------ readers

def _read_back(path: Path, sfx: str) -> None:
    """Open ``path`` with the library of its format; fail if it is not of that format."""
    if sfx in (".ply", ".pcd"):
        import open3d as o3d

        pc = o3d.t.io.read_point_cloud(str(path))
        assert len(pc.point.positions) > 0
        assert path.read_bytes()[:4] == (b"ply\n" if sfx == ".ply" else b"# .P")
    elif sfx in (".las", ".laz"):
        import laspy

        las = laspy.read(str(path))
        assert len(las.points) > 0
        assert (las.header.are_points_compressed) == (sfx == ".laz")
    elif sfx in (".mcap", ".db3"):
        from mems_stereo.viz.export import read_cloud

        bag = path.with_suffix("")
        assert bag.is_dir() and any(p.suffix == sfx for p in bag.iterdir())
        assert len(read_cloud(path)) > 0
    elif sfx == ".json":
        assert isinstance(json.loads(path.read_text()), dict)
    elif sfx in (".yml", ".yaml", ".xml"):
        head = path.read_bytes()[:5]
        assert head == (b"<?xml" if sfx == ".xml" else b"%YAML")
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        try:
            assert fs.isOpened()
            assert fs.getNode("format").string() == "mems-stereo/opencv-system"
            assert fs.getNode("camera_matrix").mat().shape == (3, 3)
            n = fs.getNode("covariance_parameters").size()
            assert n > 0 and fs.getNode("covariance").mat().shape == (n, n)
            assert fs.getNode("rms_pixel").real() > 0
            assert np.isfinite(fs.getNode("theta0_std").real())
        finally:
            fs.release()
    elif sfx == ".h5":
        with h5py.File(path, "r") as f:
            assert len(f.keys()) > 0
    elif sfx == ".npz":
        with np.load(path) as z:
            assert len(z.files) > 0
    elif sfx == ".pdf":
        assert path.read_bytes()[:5] == b"%PDF-"
    elif sfx == ".png":
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    elif sfx == ".svg":
        assert b"<svg" in path.read_bytes()[:400]
    else:
        raise AssertionError(f"no reader for {sfx}")


def _files(d: Path) -> set:
    return {p.relative_to(d) for p in d.rglob("*")}


# -------------------------------------------------------------------- tests

@pytest.mark.parametrize("cmd, opt, sfx, kind", list(_cases()))
def test_every_suffix_writes_its_format(cmd, opt, sfx, kind, cached, tmp_path, capsys):
    if cmd == "render":
        from mems_stereo.viz.render import render_available

        ok, why = render_available()
        if not ok:
            pytest.skip(f"headless OpenGL unavailable: {why}")
    out = tmp_path / f"out{sfx}"
    argv = _argv(cmd, opt, kind, str(out), cached, tmp_path)
    rc = main(argv)
    err = capsys.readouterr().err
    if (cmd, opt, kind) in REFUSED:
        assert rc == 2 and "error:" in err, err
        assert _files(tmp_path) == set(), "a refused run wrote something"
        return
    assert rc == 0, err
    _read_back(out, sfx)


def test_calibrate_yaml_reads_back_as_the_json_system(cached, tmp_path):
    """``-o cal.yml`` and ``-o cal.json`` hold the same system (one- and two-axis)."""
    from mems_stereo.calib.opencv_io import read_opencv_covariance, read_opencv_system

    from mems_stereo.model.system import system_to_dict

    for kind in ("line", "two"):
        base = ["calibrate", "-q", *WALLS[kind]]
        if kind == "line":
            base += ["--target-distances-file", str(S / "calib_distances.json")]
        assert main([*base, "-o", str(tmp_path / f"{kind}.json")]) == 0
        assert main([*base, "-o", str(tmp_path / f"{kind}.xml")]) == 0
        js = load_system(tmp_path / f"{kind}.json")
        cv = read_opencv_system(tmp_path / f"{kind}.xml")
        a, b = system_to_dict(js), system_to_dict(cv)
        assert a["scanner"].get("axis2") == b["scanner"].get("axis2")
        assert np.allclose(a["scanner"]["position"], b["scanner"]["position"], atol=1e-12)
        names, cov = read_opencv_covariance(tmp_path / f"{kind}.xml")
        assert names and cov.shape == (len(names), len(names))


def _bad_suffix_cases():
    for (cmd, opt), w in sorted(WRITES.items()):
        if w.suffixes:
            yield pytest.param(cmd, opt, id=f"{cmd}-{opt}")


@pytest.mark.parametrize("cmd, opt", list(_bad_suffix_cases()))
@pytest.mark.parametrize("bad", [".txt", ""])
def test_unwritable_suffix_refused_before_any_work(cmd, opt, bad, ctx, tmp_path, capsys):
    argv = _argv(cmd, opt, "line", str(tmp_path / f"out{bad}"), ctx, tmp_path)
    rc = main(argv)
    err = capsys.readouterr().err
    assert rc == 2, err
    flag = "--output" if opt == "output" else f"--{opt}"
    line = err.strip().splitlines()[0]
    assert flag in line and ", ".join(WRITES[(cmd, opt)].suffixes) in line, line
    assert _files(tmp_path) == set()


def _folder_cases():
    for (cmd, opt), w in sorted(WRITES.items()):
        yield pytest.param(cmd, opt, (w.suffixes or ("",))[0], id=f"{cmd}-{opt}")


def _folder_argv(cmd, opt, out, c, tmp):
    if cmd == "samples":
        return ["samples", "room_scene.json", "-o", out]
    if cmd == "demo":
        return ["demo", "--no-render", "-o", out]
    return _argv(cmd, opt, "line", out, c, tmp)


@pytest.mark.parametrize("cmd, opt, sfx", list(_folder_cases()))
def test_missing_folder_refused_without_parents(cmd, opt, sfx, ctx, tmp_path, capsys):
    out = tmp_path / "nosuch" / "dir" / f"out{sfx}"
    rc = main(_folder_argv(cmd, opt, str(out), ctx, tmp_path))
    err = capsys.readouterr().err
    assert rc == 2, err
    flag = "--output" if opt == "output" else f"--{opt}"
    assert flag in err and "--parents" in err and "does not exist" in err, err
    assert _files(tmp_path) == set(), "a folder was created without --parents"


@pytest.mark.parametrize("argv, made", [
    (["info", "--parents", "--plot", "{d}/a/b/fig.svg"], "a/b/fig.svg"),
    (["samples", "--parents", "room_scene.json", "-o", "{d}/a/b"], "a/b/room_scene.json"),
    (["plot", "cloud", "{cloud}", "--parents", "-o", "{d}/a/top.pdf"], "a/top.pdf"),
    (["export", "{cloud}", "--parents", "-o", "{d}/a/b/c.pcd"], "a/b/c.pcd"),
])
def test_parents_makes_the_folders(argv, made, ctx, tmp_path):
    argv = [a.format(d=tmp_path, cloud=ctx["clouds"]["line"]) for a in argv]
    assert main(argv) == 0
    assert (tmp_path / made).is_file()


def test_a_folder_output_may_be_new_but_not_its_parent(tmp_path):
    assert main(["samples", "-q", "room_scene.json", "-o", str(tmp_path / "new")]) == 0
    assert (tmp_path / "new" / "room_scene.json").is_file()


@pytest.mark.parametrize("sfx", [".json", ".pdf"])
def test_two_axis_failed_calibration_still_writes_the_report(sfx, tmp_path, monkeypatch,
                                                             capsys):
    from mems_stereo.errors import NotObservableError

    def fail(*a, **k):
        raise NotObservableError("two-axis calibration: singular normal matrix")

    monkeypatch.setattr(twoaxis_mod, "calibrate_two_axis", fail)
    rep = tmp_path / f"r{sfx}"
    rc = main(["calibrate", *WALLS["two"], "-o", str(tmp_path / "c.json"), "--report", str(rep)])
    assert rc == 2 and "singular" in capsys.readouterr().err
    assert not (tmp_path / "c.json").exists()
    _read_back(rep, sfx)
    if sfx == ".json":
        assert json.loads(rep.read_text())["ok"] is False


@pytest.mark.parametrize("argv, flag", [
    (["process", RECS["two"], "--confidence", "0.9"], "--confidence"),
    (["process", RECS["two"], "--chunk-shots", "100"], "--chunk-shots"),
    (["calibrate", *WALLS["two"], "--distance-std", "0.01"], "--distance-std"),
    (["calibrate", *WALLS["two"], "--allow-unobservable"], "--allow-unobservable"),
])
def test_two_axis_refuses_options_it_cannot_honour(argv, flag, tmp_path, capsys):
    """An option that would do nothing for two-axis input is refused, not ignored."""
    out = tmp_path / ("c.ply" if argv[0] == "process" else "c.json")
    assert main([*argv, "-o", str(out)]) == 2
    assert flag in capsys.readouterr().err
    assert _files(tmp_path) == set()


def test_two_axis_min_range_is_used(cached, tmp_path, monkeypatch):
    seen = {}

    def spy(rec, system=None, settings=None):
        seen["r_min"] = settings.r_min
        return cached["proc_two"]

    monkeypatch.setattr(pipe2d_mod, "process_recording_2d", spy)
    assert main(["process", "-q", RECS["two"], "--min-range", "0.7", "-o",
                 str(tmp_path / "c.ply")]) == 0
    assert seen["r_min"] == 0.7


# ------------------------------------------------- the table, the help, the writers

def _subparser(parser: argparse.ArgumentParser, key: str) -> argparse.ArgumentParser:
    for word in key.split():
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        parser = sub.choices[word]
    return parser


def test_help_lists_exactly_the_suffixes_written():
    parser = build_parser()
    for (cmd, opt), w in WRITES.items():
        p = _subparser(parser, cmd)
        action = next(a for a in p._actions if a.dest == opt)
        listed = set(re.findall(r"(?<![\w/])\.[a-z0-9]+\b", action.help))
        if w.folder and not w.suffixes:
            assert not listed, (cmd, opt, action.help)
        else:
            assert listed == set(w.suffixes), (cmd, opt, action.help)
        assert any(a.dest == "parents" for a in p._actions), f"{cmd} has no --parents"


def test_table_covers_every_output_and_names_real_writers():
    outputs = {(cmd, o) for cmd, spec in IO.items() for o in spec.outputs}
    assert outputs == set(WRITES)
    for w in WRITES.values():
        for writer in set(w.writers.values()):
            mod, _, fn = writer.partition(":")
            assert callable(getattr(importlib.import_module(mod), fn)), writer


def test_table_agrees_with_the_writers():
    from matplotlib.figure import Figure
    from mems_stereo.viz.export import FORMATS

    assert CLOUD_SUFFIXES == FORMATS
    types = Figure().canvas.get_supported_filetypes()
    assert all(s[1:] in types for s in PLOT_SUFFIXES)
