"""``mems-stereo calibrate``: estimate the system from flat-target recordings."""

from __future__ import annotations

import warnings

from ..system import save_system
from ._common import Reporter

NAME = "calibrate"
HELP = ("estimate baseline, theta0, TDC offset, scan phase and amplitude (with σ) from "
        "recordings of a flat target at several distances")
EXAMPLE = ("mems-stereo calibrate samples/calib_1.5m.h5 samples/calib_2.5m.h5 "
           "samples/calib_4.0m.h5 -o calibrated.json")


def add_arguments(p):
    p.add_argument("recordings", nargs="+", metavar="REC.h5",
                   help="FORMAT v1 recordings, one per target pose")
    p.add_argument("-o", "--output", required=True, help="calibrated system JSON to write")
    p.add_argument("--system", default=None,
                   help="nominal system JSON or preset (default: the first recording's)")
    p.add_argument("--fix", nargs="+", default=[], metavar="NAME",
                   help="hold these parameters at their nominal value (theta0, theta_mech_max, "
                        "phase_offset, tdc_offset, baseline_x, baseline_y, baseline_z)")
    p.add_argument("--free", nargs="+", default=[], metavar="NAME",
                   help="estimate these too (fx, cx: refine the receiver)")
    p.add_argument("--target-distance", nargs="+", type=float, default=None, metavar="D",
                   help="known distance (m) of each recording's target plane from the "
                        "receiver, in the order of the recordings (use nan for unknown)")
    p.add_argument("--distance-std", type=float, default=1e-3,
                   help="σ of a known target distance, m (default 0.001)")
    p.add_argument("--confidence", type=float, default=0.997,
                   help="confidence of the classifier's consistency test (default 0.997)")
    p.add_argument("--allow-unobservable", action="store_true",
                   help="warn instead of failing when a parameter is not observable")


def run(args) -> int:
    import math

    from calib.calibrate import calibrate_system
    from calib.model import DEFAULT_FREE

    rep = Reporter(args)
    dists = None
    if args.target_distance is not None:
        if len(args.target_distance) != len(args.recordings):
            from ..errors import FormatError

            raise FormatError(f"expected one distance per recording ({len(args.recordings)}),"
                              f" found {len(args.target_distance)}", field="--target-distance")
        dists = [None if math.isnan(d) else d for d in args.target_distance]
    free = list(DEFAULT_FREE) + [n for n in args.free if n not in DEFAULT_FREE]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = calibrate_system(args.recordings, args.system, fix=args.fix, free=free,
                               target_distances=dists, distance_std=args.distance_std,
                               confidence=args.confidence,
                               on_unobservable="warn" if args.allow_unobservable else "raise",
                               progress=rep.detail)
    for w in caught:
        rep.info(f"warning: {w.message}")
    out = save_system(res.system, args.output)
    rep.info(res.report)
    rep.info(f"wrote {out}")
    return 0 if res.converged else 1
