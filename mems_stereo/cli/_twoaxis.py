"""Two-axis dispatch of the ``simulate`` and ``process`` commands (docs/two_axis.md).

The commands call these when the system has ``scanner.axis2`` (simulate) or
the recording carries ``scan_axes = 2`` (process); everything else about the
commands is unchanged.
"""

from __future__ import annotations

import sys
from pathlib import Path

import h5py
import numpy as np

from mems_stereo.cli._common import report_peaks_truth_outputs, save_system_output
from mems_stereo.errors import FormatError, MemsStereoError
from mems_stereo.io.recording2d import write_recording_2d
from mems_stereo.model.scanner2d import require_two_axis
from mems_stereo.model.system import resolve_any_system
from mems_stereo.util.atomic import atomic_output


def simulate(args, rep, system, true_system, scene) -> int:
    """``mems-stereo simulate`` for a two-axis system: gated event recording."""
    from mems_stereo.sim.simulate2d import simulate_2d

    if args.drift or args.crosstalk:
        raise FormatError("--drift and --crosstalk are not modelled for two-axis systems",
                          field="--drift/--crosstalk")
    with rep.progress(args.shots, "simulating") as bar:
        rec = simulate_2d(system, scene, args.shots, rng=np.random.default_rng(args.seed),
                          background_hz=args.background, dark_count_hz=args.dark,
                          true_system=true_system, progress=bar.update)
    out = write_recording_2d(args.output, rec)
    lab = rec.truth["label"]
    k = rec.n_shots
    w, h = system.receiver.image_size
    rep.info(f"wrote {out}: {k} shots (two-axis, {w} x {h} array, "
             f"{rec.read_count.mean() / (w * h):.2%} of the pixels read per shot), "
             f"{int((lab == 1).sum())} laser-return detections, {int((lab == 2).sum())} "
             f"background detections; laser returns outside the gate: "
             f"{int(rec.truth['signal_lost'])} of {int(rec.truth['signal_total'])}")
    return 0


def process(args, rep, recs, system) -> int:
    """``mems-stereo process`` for two-axis recordings: per-pixel peaks → cloud."""
    from mems_stereo.pipeline.twoaxis import Settings2D, process_recording_2d
    from mems_stereo.viz.export import write_cloud
    from mems_stereo.viz.export_ros2 import cloud_stamp_ns

    if args.histograms or args.scheduler:
        raise FormatError("--histograms and --scheduler are not available for two-axis "
                          "recordings", field="--histograms/--scheduler")
    many = len(recs) > 1
    if many and args.labels:
        raise FormatError("--labels takes one recording at a time", field="--labels")
    out = Path(args.output)
    settings = Settings2D(false_alarm=args.false_alarm, r_min=args.min_range)
    for r in recs:
        target = out / f"{r.stem}.ply" if many else out
        res = process_recording_2d(r, system=system, settings=settings)
        if len(res.cloud) == 0:
            raise FormatError("no peak passed the threshold: no point cloud written", str(r))
        outputs = [write_cloud(target, res.cloud,
                               stamp_ns=cloud_stamp_ns(target, args.stamp, r))]
        if args.labels:
            outputs.append(_write_labels(args.labels, res))
        c = res.counts
        rep.info(f"{res.source}: {c['shots']} shots (two-axis)"
                 + (f" ({c['shots_unknown_angle']} of unknown scan angle, left out)"
                    if c["shots_unknown_angle"] else ""))
        rep.info(f"  read {c['read_fraction']:.2%} of the pixel slots; events {c['events']}, "
                 f"classified signal {c['signal']}, noise {c['noise']}")
        report_peaks_truth_outputs(rep, res, outputs)
    return 0


def _write_labels(path, res) -> Path:
    with atomic_output(path) as tmp, h5py.File(tmp, "w") as f:
        f.create_dataset("event_label", data=res.labels, compression="gzip")
        f.create_dataset("theta1", data=res.theta1)
        f.create_dataset("theta2", data=res.theta2)
    return Path(path)


def calibrate(args, rep) -> int:
    """``mems-stereo calibrate`` for two-axis wall recordings (calib/twoaxis.py).

    The receiver's intrinsics come from ``--system`` (e.g. a ChArUco result
    written into it); ``--free fx fy cx cy`` refines them in the joint fit;
    ``--fix`` holds parameters.  Target distances are not used (the walls'
    poses are estimated).
    """
    from mems_stereo.calib.twoaxis import TWO_AXIS_PARAMS, calibrate_two_axis

    if args.target_distance is not None or args.target_distances_file is not None:
        raise FormatError("two-axis calibration estimates the walls' poses: target distances "
                          "are not used", field="--target-distance(s-file)")
    if args.distance_std is not None:
        raise FormatError("two-axis calibration estimates the walls' poses: target distances "
                          "(and their σ) are not used", field="--distance-std")
    if args.allow_unobservable:
        raise FormatError("two-axis calibration fails when a parameter is not observable; "
                          "hold it with --fix instead", field="--allow-unobservable")
    system = resolve_any_system(args.system) if args.system else None
    if system is not None:
        require_two_axis(system, "--system")
    free = [n for n in TWO_AXIS_PARAMS if n not in args.fix]
    if system is not None and system.scanner.axis2.mode != "resonant":
        free = [n for n in free if n not in ("theta_mech_max_2", "phase_offset_2")]
    free += [n for n in args.free if n in ("fx", "fy", "cx", "cy") and n not in free]
    try:
        res = calibrate_two_axis(args.recordings, system, free=tuple(free))
    except MemsStereoError as e:
        if not args.report:
            raise
        _write_report_2d(args, rep, None, str(e).partition("\n")[0])
        print(f"mems-stereo calibrate: error: calibration failed: {e}".partition("\n")[0],
              file=sys.stderr)
        return 2
    out = save_system_output(res.system, args.output, res)
    rep.info(res.report())
    if args.report:
        _write_report_2d(args, rep, res, nominal=system)
    rep.info(f"wrote {out}")
    return 0


def _write_report_2d(args, rep, res, reason: str = "", nominal=None) -> None:
    """``--report`` of a two-axis calibration: JSON, or the PDF for ``.pdf``."""
    import json

    from mems_stereo.io.recording2d import read_recording_2d
    from mems_stereo.viz.calib_report_2d import (
        two_axis_failure_dict,
        two_axis_report_dict,
        write_two_axis_report,
    )
    from mems_stereo.viz.calib_report_header import calibration_header

    header = calibration_header(args.recordings, system_spec=args.system,
                                operator=getattr(args, "operator", None),
                                system=res.system if res is not None else None)
    if res is None:
        d = two_axis_failure_dict(reason, recordings=args.recordings, header=header)
    else:
        if nominal is None:
            nominal = read_recording_2d(args.recordings[0], truth=False).system
        d = two_axis_report_dict(res, recordings=args.recordings, nominal=nominal,
                                 header=header)
    if str(args.report).lower().endswith(".pdf"):
        write_two_axis_report(d, args.report)
    else:
        Path(args.report).write_text(json.dumps(d, indent=1))
    rep.info(f"wrote report {args.report}")
