"""``mems-stereo calibrate``: estimate the system from flat-wall recordings.

Exit codes: 0 — calibrated, the system written to ``-o``; 1 — the estimate
failed (the fit did not converge, or its result failed a plausibility check:
wall poses, signal explained, flat-wall consistency, a contradicting measured
distance); 2 — bad input (unreadable files or options, recordings without a
usable wall return, parameters the data cannot determine).  On 1 and 2 no
file is written at ``-o``; one line on stderr says why, and ``--report``
holds what the fit learnt.  ``-o`` ending in ``.json`` writes the package's
system JSON, ``.yml``/``.yaml``/``.xml`` the OpenCV FileStorage form
(:mod:`mems_stereo.calib.opencv_io`, with σ, covariance and RMS); ``--report``
ending in ``.pdf`` the PDF report, ``.json`` the same for machines (two-axis
walls: :mod:`mems_stereo.viz.calib_report_2d`).
"""

from __future__ import annotations

import math
import sys
import time

from mems_stereo.cli import _twoaxis
from mems_stereo.cli._common import Reporter, add_parents_argument, save_system_output
from mems_stereo.cli._ux import StatusProgress
from mems_stereo.cli._writes import suffix_help
from mems_stereo.errors import FormatError
from mems_stereo.io.recording2d import is_two_axis_recording

NAME = "calibrate"
HELP = ("estimate baseline, theta0, TDC offset, scan phase and amplitude (with σ) from "
        "recordings of a flat target at several distances")
EXAMPLE = ["mems-stereo samples -o samples",
           "mems-stereo calibrate samples/calib_1.5m.h5 samples/calib_2.5m.h5 "
           "samples/calib_4.0m.h5 --target-distances-file samples/calib_distances.json "
           "-o calibrated.json",
           "mems-stereo process samples/room.h5 -o room.ply --system calibrated.json"]


def add_arguments(p):
    p.add_argument("recordings", nargs="+", metavar="REC.h5",
                   help="FORMAT v1 recordings, one per target pose")
    p.add_argument("-o", "--output", required=True,
                   help=f"calibrated system to write ({suffix_help('calibrate', 'output')}: "
                        "the package's system JSON, or OpenCV FileStorage YAML/XML with σ, "
                        "covariance and RMS)")
    add_parents_argument(p)
    p.add_argument("--system", default=None,
                   help="nominal system JSON or preset (default: the first recording's)")
    p.add_argument("--fix", nargs="+", default=[], metavar="NAME",
                   help="hold these parameters at their nominal value (theta0, theta_mech_max, "
                        "phase_offset, tdc_offset, baseline_x, baseline_y, baseline_z)")
    p.add_argument("--free", nargs="+", default=[], metavar="NAME",
                   help="estimate these too (fx, cx: refine the receiver)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--target-distance", nargs="+", type=float, default=None, metavar="D",
                   help="measured distance (m) of each recording's target from the receiver's "
                        "projection centre along its optical axis, in the order of the "
                        "recordings (nan: unknown)")
    g.add_argument("--target-distances-file", default=None, metavar="FILE.json",
                   help="measured target distances per recording file name "
                        "(format: samples/calib_distances.json, docs/calibration.md)")
    p.add_argument("--distance-std", type=float, default=None, metavar="M",
                   help="σ of a measured distance, m (default: the file's, else 0.001)")
    p.add_argument("--allow-unobservable", action="store_true",
                   help="warn instead of failing when a parameter is not observable")
    p.add_argument("--model", choices=["full", "ideal"], default="full",
                   help="full (default): also estimate the hardware terms the walls call for "
                        "(mirror trajectory harmonics, monitor edge delay, per-pixel TDC "
                        "offsets: docs/calibration.md); ideal: the cosine mirror and ideal TDC")
    p.add_argument("--harmonics", type=int, default=5, metavar="K",
                   help="highest harmonic order of the mirror's trajectory tested (default 5)")
    p.add_argument("--inflate-sigma", action="store_true",
                   help="when the residuals show structure the model does not explain, write "
                        "the result with σ inflated to cover it (and say so) instead of failing")
    p.add_argument("--report", default=None, metavar="PATH",
                   help="write a calibration report, also for a failed calibration "
                        f"({suffix_help('calibrate', 'report')}): the PDF report (estimates "
                        "with σ against nominal, correlations, residuals, walls from above, "
                        "checks, what to record next; for a failure why), or the same as "
                        "JSON; page 1 and the JSON's header: date (UTC), version, the "
                        "system's device_id, --operator, input files with SHA-256")
    p.add_argument("--operator", default=None, metavar="NAME",
                   help="who calibrated, recorded in the report's header (default: none)")


def _write_report(res, args, rep) -> None:
    """``--report``: the calibration report, PDF or (``.json``) the same for machines."""
    from mems_stereo.viz.calib_report import write_calibration_report
    from mems_stereo.viz.calib_report_header import calibration_header

    write_calibration_report(res, args.report, recordings=args.recordings,
                             header=calibration_header(
                                 args.recordings, system_spec=args.system,
                                 distances_file=args.target_distances_file,
                                 operator=args.operator, system=res.system if res else None))
    rep.info(f"wrote report {args.report}")


def run(args) -> int:
    # the calibration loads on use: every command module loads at start-up
    from mems_stereo.calib.calibrate import calibrate_system, read_target_distances
    from mems_stereo.calib.model import DEFAULT_FREE

    rep = Reporter(args)
    if any(is_two_axis_recording(r) for r in args.recordings):  # two-axis: cli/_twoaxis.py
        return _twoaxis.calibrate(args, rep)
    dists, stds, kind = None, 1e-3, "axis"
    if args.distance_std is not None and not args.distance_std > 0:
        raise FormatError(f"expected a positive σ in m, found {args.distance_std}",
                          field="--distance-std")
    if args.target_distance is not None:
        if len(args.target_distance) != len(args.recordings):
            raise FormatError(f"expected one distance per recording ({len(args.recordings)}),"
                              f" found {len(args.target_distance)}", field="--target-distance")
        dists = [None if math.isnan(d) else d for d in args.target_distance]
        stds = 1e-3 if args.distance_std is None else args.distance_std
    elif args.target_distances_file is not None:
        dists, stds, kind = read_target_distances(args.target_distances_file, args.recordings)
        if args.distance_std is not None:
            stds = args.distance_std
    if dists is not None:
        sd = stds if isinstance(stds, list) else [stds] * len(dists)
        known = ", ".join("unknown" if d is None else f"{d:.4f} ± {s * 1e3:.1f} mm"
                          for d, s in zip(dists, sd))
        rep.info(f"measured target distances ({'optical axis' if kind == 'axis' else kind}):"
                 f" {known}")
    free = list(DEFAULT_FREE) + [n for n in args.free if n not in DEFAULT_FREE]
    t0 = time.perf_counter()
    with StatusProgress("calibrating", rep.quiet, rep.verbose) as status:
        res = calibrate_system(args.recordings, args.system, fix=args.fix, free=free,
                               target_distances=dists, distance_std=stds, distance_kind=kind,
                               on_unobservable="warn" if args.allow_unobservable else "raise",
                               progress=status, model=args.model,
                               harmonics=tuple(range(2, max(args.harmonics, 1) + 1)),
                               inflate_sigma=args.inflate_sigma)
    elapsed = time.perf_counter() - t0
    for w in res.warnings:
        rep.info(f"warning: {w}")
    if args.report:
        _write_report(res, args, rep)
    if not res:
        print(f"mems-stereo calibrate: error: calibration failed: {res.reason}",
              file=sys.stderr)
        return 2 if res.kind == "input" else 1
    out = save_system_output(res.system, args.output, res)
    rep.info(res.report)
    rep.info(f"calibrated in {elapsed:.1f} s; wrote {out}")
    return 0
