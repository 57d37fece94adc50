"""``mems-stereo demo``: the main job on the bundled samples, end to end.

It runs the commands a user would type, in order, and prints their output:
``info`` (Fig. 2), ``calibrate`` (the calibration walls, with the PDF
calibration report ``calibration_report.pdf``), ``process`` (room
light and floodlight, with the calibrated system), ``export`` (LAS),
``render`` (PNG, offscreen) and ``plot`` (Figs. 8 and 9, top views), plus the
Fig. 5 uncertainty bounds.  Every bundled recording was made by one true
system that differs from the nominal one written in the files, as real
hardware does; the demo processes the room and floodlight recordings with
the nominal and with the calibrated system and prints the gain against the
samples' truth (median point error, signal recall, coverage of the
illuminated pixels).  The two-axis step does the same for the Lissajous
scanner: its walls calibrate the true system that recorded ``lissajous64.h5``.
Its last step does the same on the samples recorded by
imperfect hardware, with the ideal and the full hardware model
(:mod:`mems_stereo.cli.demo_hardware`).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from mems_stereo.cli import main
from mems_stereo.cli._common import Reporter, add_parents_argument
from mems_stereo.cli._pathcheck import samples_dir
from mems_stereo.errors import MemsStereoError
from mems_stereo.io.recording import read_recording
from mems_stereo.model.system import load_system, preset
from mems_stereo.model.tdc import path_length_from_codes

NAME = "demo"
HELP = "run the whole chain on the bundled samples and print where every output is"
EXAMPLE = "mems-stereo demo -o demo-output"


def add_arguments(p):
    p.add_argument("-o", "--output", default="demo-output",
                   help="folder for every output, created if missing; its parent must exist "
                        "unless --parents (default: demo-output)")
    add_parents_argument(p)
    p.add_argument("--samples", default=None,
                   help="directory of the sample recordings (default: the bundled samples, "
                        "mems_stereo.data)")
    p.add_argument("--no-render", action="store_true",
                   help="skip the offscreen renders (machines without OpenGL)")


def calibration_gain(smp: Path, calibrated, names=("room", "floodlight")) -> list[dict]:
    """Process the sample recordings with the nominal and the calibrated system, score both.

    Returns one dict per (scene, system): ``scene``, ``system`` ("nominal" /
    "calibrated") and :func:`mems_stereo.sim.score.score_result`'s figures
    (``median_error`` m, ``recall``, ``coverage``, ...).
    """
    # the pipeline, simulator and figures load on use: every command module loads at start-up
    from mems_stereo.pipeline.run import process_recording
    from mems_stereo.sim import load_scene
    from mems_stereo.sim.score import score_result

    rows = []
    for name in names:
        rec = read_recording(smp / f"{name}.h5")
        scene = load_scene(smp / "room_scene.json")
        for label, system in (("nominal", rec.system), ("calibrated", calibrated)):
            res = process_recording(rec, system=system)
            rows.append({"scene": name, "system": label,
                         **score_result(res, rec.truth["label"], scene)})
    return rows


def gain_verdicts(rows: list[dict]) -> dict:
    """Per scene: is the calibrated system better on median point error and coverage, and
    not worse on recall?  ``{scene: {"median_error": bool, "coverage": bool, "recall": bool}}``."""
    out = {}
    for r in rows:
        if r["system"] != "calibrated":
            continue
        n = next(x for x in rows if x["scene"] == r["scene"] and x["system"] == "nominal")
        out[r["scene"]] = {"median_error": r["median_error"] < n["median_error"],
                           "coverage": r["coverage"] > n["coverage"],
                           "recall": r["recall"] >= n["recall"]}
    return out


def format_gain(rows: list[dict]) -> list[str]:
    """The gain table as text lines."""
    lines = [f"  {'scene':11s} {'system':11s} {'median point error':>19s} {'recall':>7s} "
             f"{'coverage':>9s}  (points / illuminated pixels)"]
    for r in rows:
        lines.append(f"  {r['scene']:11s} {r['system']:11s} {r['median_error'] * 100:16.1f} cm "
                     f"{r['recall']:7.4f} {r['coverage']:9.2f}  ({r['covered']} / "
                     f"{r['illuminated']})")
    return lines


def _step(rep, title):
    rep.info("")
    rep.info(f"== {title} ==")


def _call(argv, rep) -> None:
    flags = ["-q"] if rep.quiet else (["-v"] if rep.verbose else [])
    code = main([argv[0], *flags, *argv[1:]])
    if code not in (0,):
        raise MemsStereoError(f"step '{' '.join(argv[:1])}' failed with exit code {code}")


def _fig5(out: Path) -> Path:
    """Fig. 5: propagated uncertainty ellipses for several pixels and TDC codes."""
    from mems_stereo.geometry.uncertainty import paper_spreads, propagate, tof_pixel_point
    from mems_stereo.viz.plots import plot_uncertainty_bounds

    s = preset("burkard2022")
    cols = np.array([20.0, 60.0, 96.0, 130.0, 170.0])
    codes = np.array([16, 24, 32, 48])
    u, n = np.meshgrid(cols, codes)
    u, n = u.ravel(), n.ravel()
    L = path_length_from_codes(n, s.tdc, s.speed_of_light)
    x, C = propagate(tof_pixel_point, s, u, np.zeros_like(u), L, np.full(u.shape, s.scanner.theta0),
                     paper_spreads(s))
    ok = np.all(np.isfinite(x), axis=1)
    means = x[ok][:, [0, 2]]
    cov = C[ok][:, [0, 2]][:, :, [0, 2]]
    labels = [f"u={int(a)}, N={int(b)}" for a, b in zip(u[ok], n[ok])]
    return plot_uncertainty_bounds(means, cov, out, n_sigma=(1.0, 3.0), labels=labels,
                                   scale=20.0,
                                   title="Fig. 5: pixel + TDC quantisation (paper's model), "
                                         "ellipses x20")


def _calibrate(rep, out: Path, smp: Path) -> tuple[Path, list[Path]]:
    """Step 2: calibrate from the sample walls; the system file and what was written."""
    _step(rep, "2. calibration from three flat-wall recordings (true system differs from "
               "the nominal one in the files)")
    cal = out / "calibrated_system.json"
    calib_recs = sorted(str(p) for p in smp.glob("calib_*m.h5"))
    cal_report = out / "calibration_report.pdf"
    argv = ["calibrate", *calib_recs, "-o", str(cal), "--report", str(cal_report)]
    dist_file = smp / "calib_distances.json"
    if dist_file.exists():
        argv += ["--target-distances-file", str(dist_file)]
    _call(argv, rep)
    true_file = smp / "calib_true_system.json"
    if true_file.exists():
        est, true = load_system(cal), load_system(true_file)
        rep.info("  estimate - truth: " + ", ".join(
            f"{n} {est.get_param(n) - true.get_param(n):+.3g}"
            for n in ("theta0", "baseline_x", "baseline_z", "tdc_offset", "phase_offset")))
    return cal, [cal, cal_report]


def _process(rep, out: Path, smp: Path, cal: Path) -> tuple[dict, list[Path]]:
    """Step 3: process room and floodlight; their clouds and what was written."""
    _step(rep, "3. processing with the calibrated system: classification, histograms, peaks, "
               "point clouds")
    clouds, written = {}, []
    for name, fig in (("room", "fig8"), ("floodlight", "fig9")):
        rec = smp / f"{name}.h5"
        ply = out / f"{name}.ply"
        hist = out / f"{name}_histograms.h5"
        labels = out / f"{name}_labels.h5"
        _call(["process", str(rec), "-o", str(ply), "--system", str(cal), "--labels",
               str(labels), "--histograms", str(hist)], rep)
        clouds[name] = ply
        written += [ply, labels, hist]
        _call(["export", str(ply), "-o", str(out / f"{name}.las")], rep)
        written.append(out / f"{name}.las")
        _call(["plot", "histograms", str(hist), "-o", str(out / f"{fig}_{name}_histograms.png"),
               "--max-code", "256"], rep)
        _call(["plot", "cloud", str(ply), "-o", str(out / f"{name}_topview.png")], rep)
        written += [out / f"{fig}_{name}_histograms.png", out / f"{name}_topview.png"]
    return clouds, written


def _report_gain(rep, gain: dict) -> dict:
    """Print the nominal-vs-calibrated table of ``gain`` and its verdicts; returns them."""
    for line in format_gain(gain):
        rep.info(line)
    verdicts = gain_verdicts(gain)
    for scene, v in verdicts.items():
        rep.info(f"  {scene}: calibrated better on median point error: "
                 f"{'yes' if v['median_error'] else 'NO'}, on coverage: "
                 f"{'yes' if v['coverage'] else 'NO'}; recall not worse: "
                 f"{'yes' if v['recall'] else 'NO'}")
    return verdicts


def _gain(rep, smp: Path, cal: Path) -> tuple[dict, dict]:
    """Step 4: nominal vs calibrated system against the samples' truth."""
    _step(rep, "4. the gain of calibration: nominal vs calibrated system, against the samples' "
               "truth (points whose true surface is within 6 m)")
    gain = calibration_gain(smp, load_system(cal))
    verdicts = _report_gain(rep, gain)
    return gain, verdicts


def _figures(rep, out: Path, clouds: dict, render: bool) -> list[Path]:
    """Step 5: Fig. 5 and the renders of the clouds."""
    _step(rep, "5. figures and renders")
    written = [_fig5(out / "fig5_uncertainty.png")]
    rep.info(f"  wrote {written[-1]}")
    if render:
        for name, ply in clouds.items():
            png = out / f"{name}_render.png"
            _call(["render", str(ply), "-o", str(png), "--point-size", "6",
                   "--color-by", "range"], rep)
            written.append(png)
    return written


def two_axis_calibration_gain(smp: Path, calibrated, name: str = "lissajous64"):
    """Process the two-axis sample ``name`` with the nominal and the calibrated system.

    Returns ``(rows, results)``: rows as :func:`calibration_gain`'s (``scene`` is
    ``name``; figures of :func:`mems_stereo.sim.score.score_result_2d`, scored
    against ``twoaxis_scene.json``) and ``{"nominal" | "calibrated": Result2D}``.
    """
    from mems_stereo.io.recording2d import read_recording_2d
    from mems_stereo.pipeline.twoaxis import process_recording_2d
    from mems_stereo.sim import load_scene
    from mems_stereo.sim.score import score_result_2d

    rec = read_recording_2d(smp / f"{name}.h5")
    scene = load_scene(smp / "twoaxis_scene.json")
    rows, results = [], {}
    for label, system in (("nominal", rec.system), ("calibrated", calibrated)):
        results[label] = process_recording_2d(rec, system=system)
        rows.append({"scene": name, "system": label,
                     **score_result_2d(results[label], rec, scene)})
    return rows, results


def _two_axis_gain(rep, out: Path, smp: Path, walls: list[Path]) -> tuple[list, dict, Path]:
    """Step 6, Lissajous scanner: calibrate from its walls, process lissajous64.h5 with the
    nominal and the calibrated system, print the gain; the rows, verdicts and cloud."""
    from mems_stereo.calib.twoaxis import get_param_2d
    from mems_stereo.viz.export import write_cloud

    cal = out / "lissajous64_calibrated_system.json"
    _call(["calibrate", *map(str, walls), "-o", str(cal)], rep)
    est = load_system(cal)
    true_file = smp / "lissajous64_calib_true_system.json"
    if true_file.exists():
        true = load_system(true_file)
        rep.info("  estimate - truth: " + ", ".join(
            f"{n} {get_param_2d(est, n) - get_param_2d(true, n):+.3g}"
            for n in ("theta0", "theta0_2", "baseline_x", "baseline_y", "baseline_z",
                      "tdc_offset")))
    gain, results = two_axis_calibration_gain(smp, est)
    ply = write_cloud(out / "lissajous64.ply", results["calibrated"].cloud)
    rep.info(f"  wrote {ply} (calibrated system)")
    rep.info("  lissajous64.h5, nominal vs calibrated system, against the sample's truth:")
    verdicts = _report_gain(rep, gain)
    return gain, verdicts, cal


def _two_axis(rep, out: Path, smp: Path, render: bool) -> tuple[list[Path], list, dict]:
    """Step 6: the two-axis samples processed (and rendered from two views); the
    Lissajous recording with the system calibrated from its walls, against the nominal."""
    _step(rep, "6. two-axis scanners with 2-D SPAD arrays (docs/two_axis.md); the Lissajous "
               "scanner calibrated from its three walls")
    written, gain, verdicts = [], [], {}
    for name in ("lissajous64", "raster128x96"):
        rec = smp / f"{name}.h5"
        if not rec.exists():
            continue
        ply = out / f"{name}.ply"
        walls = sorted(smp.glob(f"{name}_calib_*m.h5"))
        if walls and (smp / "twoaxis_scene.json").exists():  # a true system to calibrate
            gain, verdicts, cal = _two_axis_gain(rep, out, smp, walls)
            written.append(cal)
        else:
            _call(["process", str(rec), "-o", str(ply)], rep)
        written.append(ply)
        if render:
            for view in ("camera", "oblique"):
                png = out / f"{name}_{view}_render.png"
                _call(["render", str(ply), "-o", str(png), "--view", view, "--point-size", "4",
                       "--color-by", "range"], rep)
                written.append(png)
    return written, gain, verdicts


def _imperfect_hardware(rep, smp: Path) -> dict | None:
    """Step 7: the imperfect-hardware samples, nominal vs ideal vs full model
    (:mod:`mems_stereo.cli.demo_hardware`); None when the samples lack them."""
    from mems_stereo.cli import demo_hardware as dh

    if not (smp / dh.IMPERFECT_ROOM).exists():
        return None
    _step(rep, "7. imperfect hardware (docs/hardware.md): nominal vs calibrated with the ideal "
               "and with the full model, against the truth")
    comp = dh.hardware_comparison(smp)
    for line in dh.format_comparison(comp):
        rep.info(line)
    return comp


def run(args) -> int:
    rep = Reporter(args)
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    smp = samples_dir(args.samples)
    t_start = time.perf_counter()
    rep.info("mems-stereo demo: the paper's system, calibration, processing, clouds and "
             f"figures (samples: {smp})")

    _step(rep, "1. the system and its acquisition statistics (paper Sec. 2.1, Fig. 2)")
    _call(["info", "--shots", "400", "--ratio", "0.0785", "--distance", "2.5",
           "--plot", str(out / "fig2_acquisition.png")], rep)
    written: list[Path] = [out / "fig2_acquisition.png"]
    cal, files = _calibrate(rep, out, smp)
    written += files
    clouds, files = _process(rep, out, smp, cal)
    written += files
    gain, verdicts = _gain(rep, smp, cal)
    written += _figures(rep, out, clouds, not args.no_render)
    files, gain2d, verdicts2d = _two_axis(rep, out, smp, not args.no_render)
    written += files
    hardware = _imperfect_hardware(rep, smp)

    _step(rep, "outputs")
    missing = [p for p in written if not Path(p).exists()]
    for p in written:
        rep.info(f"  {p}")
    summary = {"outputs": [str(p) for p in written], "seconds": time.perf_counter() - t_start,
               "calibration_gain": gain, "calibration_gain_verdicts": verdicts,
               "two_axis_calibration_gain": gain2d,
               "two_axis_calibration_gain_verdicts": verdicts2d,
               "imperfect_hardware": hardware}
    (out / "demo_summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    rep.info(f"done in {summary['seconds']:.0f} s; every output is in {out}/")
    if missing:
        raise MemsStereoError(f"missing outputs: {', '.join(map(str, missing))}")
    return 0
