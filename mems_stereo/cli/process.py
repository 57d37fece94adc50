"""``mems-stereo process``: classify detections, form histograms, find peaks, write the cloud."""

from __future__ import annotations

import sys
from pathlib import Path

from mems_stereo.cli import _twoaxis
from mems_stereo.cli._common import Reporter, add_parents_argument, report_peaks_truth_outputs
from mems_stereo.cli._writes import suffix_help
from mems_stereo.errors import FormatError
from mems_stereo.io.histograms import write_histograms
from mems_stereo.io.recording2d import is_two_axis_recording
from mems_stereo.model.system import resolve_system

NAME = "process"
HELP = ("classify every detection as signal or noise, form the signal/noise histograms, "
        "find the peaks and write the point cloud")
EXAMPLE = ["mems-stereo samples -o samples",
           "mems-stereo process samples/room.h5 -o room.ply --labels room_labels.h5 "
           "--histograms room_hist.h5",
           "mems-stereo process samples/room.h5 -o room_true.ply "
           "--system samples/calib_true_system.json    # or your calibrated system "
           "(mems-stereo calibrate --help)"]


#: defaults of the options the two-axis pipeline has no use for (refused when changed)
CONFIDENCE, CHUNK_SHOTS = 0.997, 8192


def add_arguments(p):
    p.add_argument("recordings", nargs="+", metavar="REC.h5",
                   help="recording(s) in FORMAT v1 (HDF5)")
    p.add_argument("-o", "--output", required=True,
                   help=f"point cloud to write ({suffix_help('process', 'output')}); with "
                        "several recordings a folder that receives <name>.ply for each")
    p.add_argument("--system", default=None,
                   help="system JSON to process with (e.g. a calibrated one; default: the "
                        "recording's /system)")
    p.add_argument("--labels", default=None,
                   help=f"write the event labels here ({suffix_help('process', 'labels')})")
    p.add_argument("--histograms", default=None,
                   help="write the raw/signal/noise histograms here "
                        f"({suffix_help('process', 'histograms')})")
    add_parents_argument(p)
    p.add_argument("--confidence", type=float, default=CONFIDENCE,
                   help="two-sided coverage of the consistency bound (default 0.997 = 3 sigma; "
                        "line-sensor recordings)")
    p.add_argument("--min-range", type=float, default=None,
                   help="optional prior: no target nearer than this, m (default: none)")
    p.add_argument("--false-alarm", type=float, default=1e-3,
                   help="per-pixel false-alarm probability of the peak threshold (default 0.001)")
    p.add_argument("--chunk-shots", type=int, default=CHUNK_SHOTS,
                   help="shots read per chunk; memory does not grow with the recording "
                        "(default 8192; line-sensor recordings)")
    p.add_argument("--scheduler", default=None,
                   help="Dask scheduler address; 'local' starts a LocalCluster (default: "
                        "process here, one recording after the other)")
    p.add_argument("--workers", type=int, default=2,
                   help="workers of the LocalCluster with --scheduler local (default 2)")


def _settings(args):
    from mems_stereo.pipeline.settings import Settings

    return Settings(confidence=args.confidence, min_range=args.min_range,
                    chunk_shots=args.chunk_shots, false_alarm=args.false_alarm)


def report_result(rep: Reporter, res, outputs=()) -> None:
    """Print the headline numbers of a :class:`~mems_stereo.pipeline.run.ProcessResult`."""
    c = res.counts
    rep.info(f"{res.source}: {c['shots']} shots"
             + (f" ({c['shots_unknown_angle']} of unknown scan angle, left out)"
                if c["shots_unknown_angle"] else ""))
    rep.info(f"  raw counts {c['raw']}, classified signal {c['signal']}, noise {c['noise']}")
    report_peaks_truth_outputs(rep, res, outputs)
    from mems_stereo.pipeline.goodness import stereo_tof_agreement  # named misfit (issue 30)

    for line in stereo_tof_agreement(res.cloud).warnings:
        if not rep.quiet:
            print(f"mems-stereo process: warning: {res.source}: {line}", file=sys.stderr)


def run(args) -> int:
    # the pipeline and the writers load on use: every command module loads at start-up
    from mems_stereo.pipeline.run import process_recording

    rep = Reporter(args)
    system = resolve_system(args.system) if args.system else None
    settings = _settings(args)
    recs = [Path(r) for r in args.recordings]
    for r in recs:
        if not r.exists():
            raise FileNotFoundError(2, "file not found", str(r))
    two = [is_two_axis_recording(r) for r in recs]
    if any(two):  # two-axis recordings: cli/_twoaxis.py
        if not all(two):
            raise FormatError("expected all one-axis or all two-axis recordings, found both",
                              field="REC.h5")
        for name, default in (("confidence", CONFIDENCE), ("chunk_shots", CHUNK_SHOTS)):
            if getattr(args, name) != default:
                o = "--" + name.replace("_", "-")
                raise FormatError(f"{o} is not used for two-axis recordings (their "
                                  "classification width and reading are fixed: "
                                  "docs/two_axis.md)", field=o)
        return _twoaxis.process(args, rep, recs, system)
    many = len(recs) > 1
    if many and (args.labels or args.histograms):
        raise FormatError("--labels and --histograms take one recording at a time",
                          field="--labels/--histograms")
    out = Path(args.output)
    targets = [out / f"{r.stem}.ply" for r in recs] if many else [out]

    if args.scheduler:
        from mems_stereo.pipeline.distributed import process_many

        results = process_many(recs, system=system, settings=settings,
                               scheduler=args.scheduler, n_workers=args.workers)
    else:
        results = []
        for r in recs:
            with rep.progress(total=None, desc=r.name) as bar:
                def tick(n, bar=bar):
                    bar.update(n)
                results.append(process_recording(r, system=system, settings=settings,
                                                 labels_path=args.labels, progress=tick))
    from mems_stereo.viz.export import write_cloud

    for res, target in zip(results, targets):
        outputs = [write_cloud(target, res.cloud)]
        if args.labels:
            outputs.append(Path(args.labels))
        if args.histograms:
            h = res.histograms
            outputs.append(write_histograms(args.histograms, h["raw"], h["signal"], h["noise"],
                                            attrs={"source": str(res.source)}))
        report_result(rep, res, outputs)
    return 0
