"""``mems-stereo process``: classify detections, form histograms, find peaks, write the cloud."""

from __future__ import annotations

import math
import sys
from pathlib import Path

from mems_stereo.cli import _twoaxis
from mems_stereo.cli._common import Reporter, add_parents_argument, report_peaks_truth_outputs
from mems_stereo.cli._writes import FRAME_BAG_SUFFIXES, FRAME_FORMATS, suffix_help
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
           "(mems-stereo calibrate --help)",
           "mems-stereo process samples/room.h5 --frame-rate 50 -o frames/    "
           "# frames/room_000000.ply, ... (docs/frames.md)",
           "mems-stereo process samples/room.h5 --frame-shots 400 -o room_frames.mcap"]


#: defaults of the options the two-axis pipeline has no use for (refused when changed)
CONFIDENCE, CHUNK_SHOTS = 0.997, 8192


def add_arguments(p):
    p.add_argument("recordings", nargs="+", metavar="REC.h5",
                   help="recording(s) in FORMAT v1 (HDF5)")
    p.add_argument("-o", "--output", required=True,
                   help=f"point cloud to write ({suffix_help('process', 'output')}); with "
                        "several recordings a folder that receives <name>.ply for each")
    p.add_argument("--system", default=None,
                   help="system JSON or preset to process with (e.g. a calibrated one; "
                        "default: the recording's /system)")
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
    p.add_argument("--stamp", default=None, metavar="TIME",
                   help="the time of a ROS 2 bag's cloud (-o .mcap/.db3): ISO 8601 with a time "
                        "zone, seconds since 1970-01-01 UTC, or 'now' (default: the recording's "
                        "shot clock at its first shot)")
    add_frame_arguments(p)


def add_frame_arguments(p) -> None:
    """``--frame-rate``, ``--frame-shots``, ``--frame-format``, ``--no-temporal``."""
    g = p.add_argument_group("frames (docs/frames.md)")
    g.add_argument("--frame-rate", type=float, default=None, metavar="HZ",
                   help="a cloud every 1/HZ s of the recording: -o DIR/ (a trailing slash or "
                        "an existing folder) receives DIR/<name>_<index:06d>.ply per frame, "
                        f"-o OUT{' or OUT'.join(FRAME_BAG_SUFFIXES)} one PointCloud2 per frame; "
                        "points carry t (s) and age (frames)")
    g.add_argument("--frame-shots", type=int, default=None, metavar="N",
                   help="a cloud every N shots (instead of --frame-rate)")
    g.add_argument("--frame-format", default="ply", choices=FRAME_FORMATS,
                   help="file format of the frames in a folder (default ply)")
    g.add_argument("--no-temporal", action="store_true",
                   help="every frame on its own (no temporal fusion of the pixels' history)")


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
    from mems_stereo.viz.export_ros2 import check_stamp_option

    rep = Reporter(args)
    check_stamp_option(args.output, args.stamp)  # refused before any work
    system = resolve_system(args.system) if args.system else None
    settings = _settings(args)
    recs = [Path(r) for r in args.recordings]
    for r in recs:
        if not r.exists():
            raise FileNotFoundError(2, "file not found", str(r))
    two = [is_two_axis_recording(r) for r in recs]
    if args.frame_rate is not None or args.frame_shots is not None:
        return run_frames(args, rep, recs, system, settings, any(two))
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
    from mems_stereo.viz.export_ros2 import cloud_stamp_ns

    for res, target in zip(results, targets):
        outputs = [write_cloud(target, res.cloud,
                               stamp_ns=cloud_stamp_ns(target, args.stamp, res.source))]
        if args.labels:
            outputs.append(Path(args.labels))
        if args.histograms:
            h = res.histograms
            outputs.append(write_histograms(args.histograms, h["raw"], h["signal"], h["noise"],
                                            attrs={"source": str(res.source)}))
        report_result(rep, res, outputs)
    return 0


def _check_frame_options(args, recs, two_axis: bool) -> bool:
    """Refuse what frames do not take (before any work); returns whether the frames go
    to a ROS 2 bag (else to a folder)."""
    from mems_stereo.cli._outputs import translate

    if args.frame_rate is not None and args.frame_shots is not None:
        raise FormatError("expected one of --frame-rate and --frame-shots, found both",
                          field="--frame-rate")
    if args.frame_rate is not None and not (math.isfinite(args.frame_rate)
                                            and args.frame_rate > 0):
        raise FormatError(f"expected a positive number of Hz, found {args.frame_rate:g}",
                          field="--frame-rate")
    if args.frame_shots is not None and args.frame_shots < 1:
        raise FormatError(f"expected a positive number of shots, found {args.frame_shots}",
                          field="--frame-shots")
    if two_axis:
        raise FormatError("frames are made of line-sensor recordings; two-axis recordings "
                          "are processed whole", field="--frame-rate")
    # a frame's message is stamped with the frame's start on the recording's clock
    for name in ("labels", "histograms", "scheduler", "stamp"):
        if getattr(args, name, None):
            raise FormatError(f"--{name} is not used with frames", field=f"--{name}")
    out = Path(args.output)
    named_bag = Path(translate(str(out))).suffix.lower() in FRAME_BAG_SUFFIXES
    if named_bag and len(recs) > 1:
        raise FormatError("a bag of frames takes one recording; give a folder (DIR/)",
                          field="--output")
    bag = named_bag and not out.is_dir()
    if not bag and not out.is_dir():
        raise FormatError(f"with frames expected a folder (DIR/) or a "
                          f"{' or '.join(FRAME_BAG_SUFFIXES)} bag, found "
                          f"{translate(str(out))}",
                          field="--output")
    return bag


def run_frames(args, rep: Reporter, recs, system, settings, two_axis: bool) -> int:
    """``process --frame-rate/--frame-shots``: each recording's frames
    (:func:`~mems_stereo.pipeline.frames.iter_frames`) to a folder or a bag."""
    from mems_stereo.pipeline.frames import iter_frames
    from mems_stereo.viz.export_frames import FrameBagSink, FrameFolderSink

    bag = _check_frame_options(args, recs, two_axis)
    for r in recs:
        sink = (FrameBagSink(args.output) if bag
                else FrameFolderSink(args.output, r.stem, args.frame_format))
        n_frames = n_points = 0
        with sink, rep.progress(total=None, desc=r.name) as bar:
            for frame in iter_frames(r, system, frame_rate=args.frame_rate,
                                     frame_shots=args.frame_shots, settings=settings,
                                     fusion=not args.no_temporal,
                                     chunk_shots=settings.chunk_shots):
                where = sink.write(frame)
                n_frames += 1
                n_points += len(frame.cloud)
                bar.update(frame.counts.shots)
        rep.info(f"{r}: {n_frames} frames, {n_points} points")
        rep.info(f"wrote {where if bag else Path(args.output)}")
    return 0
