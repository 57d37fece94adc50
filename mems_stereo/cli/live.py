"""``mems-stereo live``: frames of a live source, processed and written as they come."""

from __future__ import annotations

import contextlib
import math
import signal
import sys
import threading
import types
from pathlib import Path

from mems_stereo.cli._common import Reporter, add_parents_argument
from mems_stereo.cli._writes import FRAME_BAG_SUFFIXES, FRAME_FORMATS
from mems_stereo.errors import OptionError
from mems_stereo.model.system import resolve_system
from mems_stereo.viz.live_viewer import VIEWERS

NAME = "live"
HELP = ("frames of a live source (a recording replayed at its own pace, a recording or PTU "
        "file being written, a ZeroMQ socket) processed and written as they come")
EXAMPLE = ["mems-stereo samples -o samples",
           "mems-stereo live --replay samples/room.h5 --rate max --frame-rate 50 -o frames/    "
           "# frames/room_000000.ply, ... as process --frame-rate (docs/live.md)",
           "mems-stereo live --replay samples/room.h5 --rate 1 --frame-rate 100 --workers 2 "
           "-o room.mcap    # each frame's pixels across two worker processes"]

#: ZeroMQ transports a SOURCE may name
ZMQ_SCHEMES = ("tcp://", "ipc://", "inproc://")


def add_arguments(p):
    p.add_argument("source", nargs="?", metavar="SOURCE",
                   help="a recording being written (HDF5 SWMR), a PTU file being written "
                        "(with --map) or a ZeroMQ address tcp://HOST:PORT (docs/live.md)")
    p.add_argument("--replay", default=None, metavar="REC.h5",
                   help="replay a recording as a live source instead")
    p.add_argument("--rate", default="1",
                   help="replay speed: 1 = real time (paced by the recording's clock), X = X "
                        "times faster, max = as fast as processing goes (nothing dropped)")
    p.add_argument("-o", "--output", default=None,
                   help="a folder DIR/ (trailing slash or existing folder: one cloud file per "
                        f"frame, --frame-format) or a ROS 2 bag ({', '.join(FRAME_BAG_SUFFIXES)}"
                        ": one PointCloud2 per frame); frames appear as they are finished")
    add_parents_argument(p)
    p.add_argument("--view", nargs="?", const="auto", default=None, choices=VIEWERS,
                   metavar="KIND",
                   help="show the frames as they come: open3d (a window), browser (a page "
                        "served on http://127.0.0.1:PORT/, self-contained: open it in any "
                        "browser of this machine), foxglove (a Foxglove WebSocket server, "
                        "pip install 'mems-stereo[live-viewer]'); --view alone: open3d where "
                        "there is a display, else browser (docs/live.md)")
    p.add_argument("--view-keep", action="store_true",
                   help="keep the viewer open after the stream ends, until Ctrl-C (to look "
                        "at the last frame of a replay)")
    p.add_argument("--view-port", type=int, default=8765, metavar="PORT",
                   help="TCP port of the browser page or the Foxglove server on 127.0.0.1 "
                        "(default 8765; 0: a free one, printed)")
    g = p.add_argument_group("frames (docs/frames.md)")
    g.add_argument("--frame-rate", type=float, default=None, metavar="HZ",
                   help="a cloud every 1/HZ s of the source's clock")
    g.add_argument("--frame-shots", type=int, default=None, metavar="N",
                   help="a cloud every N shots (instead of --frame-rate)")
    g.add_argument("--frame-format", default="ply", choices=FRAME_FORMATS,
                   help="file format of the frames in a folder (default ply)")
    g.add_argument("--no-temporal", action="store_true",
                   help="every frame on its own (no temporal fusion of the pixels' history)")
    p.add_argument("--system", default=None,
                   help="system JSON or preset to process with (default: the source's; a PTU "
                        "file: its mapping's)")
    p.add_argument("--map", default=None, metavar="MAP.json",
                   help="channel mapping of a PTU source (format mems-stereo/tttr-map)")
    _add_worker_arguments(p)
    p.add_argument("--queue-frames", type=int, default=3,
                   help="frames waiting for processing at most; when full, the oldest waiting "
                        "frame is dropped for the newest, and counted (default 3)")
    p.add_argument("--idle-timeout", type=float, default=10.0,
                   help="end when a growing file or a socket brings nothing new for this many "
                        "seconds (default 10; 0: wait until Ctrl-C)")
    p.add_argument("--confidence", type=float, default=0.997,
                   help="two-sided coverage of the consistency bound (default 0.997)")
    p.add_argument("--min-range", type=float, default=None,
                   help="optional prior: no target nearer than this, m (default: none)")
    p.add_argument("--false-alarm", type=float, default=1e-3,
                   help="per-pixel false-alarm probability of the peak threshold (default 0.001)")


def _add_worker_arguments(p) -> None:
    """``--workers``, ``--split``."""
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="worker processes for the frame stages, the same frames (default: "
                        "one per available core, at most 4, where a clock runs; 1 for "
                        "--rate max; 1: all in this process; docs/live.md)")
    p.add_argument("--split", default=None, choices=("pixels", "frames"),
                   help="how frames go to the workers: pixels, each frame's pixels across "
                        "all of them (the lowest latency); frames, consecutive frames in "
                        "parallel (the most frames per second) (default: pixels where a "
                        "clock runs, frames for --rate max)")


def _check(args) -> None:
    """Cross-option checks (before any work)."""
    if (args.source is None) == (args.replay is None):
        raise OptionError("expected a SOURCE or --replay REC.h5 (one of them)", field="SOURCE")
    if (args.frame_rate is None) == (args.frame_shots is None):
        raise OptionError("expected one of --frame-rate HZ and --frame-shots N",
                          field="--frame-rate")
    if args.frame_rate is not None and not (math.isfinite(args.frame_rate)
                                            and args.frame_rate > 0):
        raise OptionError(f"expected a positive number of Hz, found {args.frame_rate!r}",
                          field="--frame-rate")
    if args.output is None and args.view is None:
        raise OptionError("expected -o DIR/ or OUT.mcap, or --view", field="--output")
    if args.view_keep and args.view is None:
        raise OptionError("keeps a viewer open: add --view", field="--view-keep")
    if not 0 <= args.view_port <= 65535:
        raise OptionError(f"expected a TCP port 0-65535, found {args.view_port}",
                          field="--view-port")
    if args.workers is not None and args.workers < 1:
        raise OptionError(f"expected a positive number of processes, found {args.workers}",
                          field="--workers")
    if args.replay is None and args.rate != "1":
        raise OptionError("--rate paces a --replay only", field="--rate")
    is_ptu = args.source is not None and Path(args.source).suffix.lower() == ".ptu"
    if is_ptu and args.map is None:
        raise OptionError("a PTU source needs its channel mapping: --map MAP.json",
                          field="--map")
    if args.map is not None and not is_ptu:
        raise OptionError("--map is for a PTU source", field="--map")


def open_source(args):
    """The live source the arguments name (:mod:`mems_stereo.io.live_sources`)."""
    from mems_stereo.io.live_sources import ReplaySource, parse_rate

    idle = None if args.idle_timeout == 0 else args.idle_timeout
    if args.replay is not None:
        return ReplaySource(args.replay, parse_rate(args.rate))
    src = str(args.source)
    if src.startswith(ZMQ_SCHEMES):
        from mems_stereo.io.live_zmq import ZmqSource

        return ZmqSource(src, idle_timeout=idle)
    if not Path(src).exists():
        raise FileNotFoundError(2, "file not found", src)
    if Path(src).suffix.lower() == ".ptu":
        from mems_stereo.io.live_ptu import PtuTailSource
        from mems_stereo.io.tttr_map import load_map

        m = load_map(args.map)
        system = resolve_system(args.system) if args.system else m.system
        if system is None:
            raise OptionError("the mapping names no system; give --system", field="--system")
        return PtuTailSource(src, m, system, idle_timeout=idle)
    from mems_stereo.io.live_h5 import GrowingH5Source

    return GrowingH5Source(src, idle_timeout=idle)


@contextlib.contextmanager
def stop_on_signals(run):
    """SIGINT and SIGTERM end ``run`` cleanly (:meth:`LiveRun.stop`); a second one
    interrupts as in every other command.  Yields the list of signals received."""
    got: list = []
    if threading.current_thread() is not threading.main_thread():
        yield got
        return
    sigs = (signal.SIGINT, signal.SIGTERM)
    old = {s: signal.getsignal(s) for s in sigs}

    def handler(signum, frame):  # noqa: ARG001 - signal handler signature
        got.append(signum)
        for s, h in old.items():  # the next one interrupts
            signal.signal(s, h)
        run.stop()

    for s in sigs:
        signal.signal(s, handler)
    try:
        yield got
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def _open_viewer(args, rep: Reporter):
    """The viewer ``--view`` asks for, or None; one that listens says where, on stdout,
    before the first frame."""
    if args.view is None:
        return None
    from mems_stereo.viz.live_viewer import open_viewer

    viewer = open_viewer(args.view, port=args.view_port)
    if getattr(viewer, "url", None):
        what = "Foxglove WebSocket" if args.view == "foxglove" else "browser viewer"
        rep.info(f"{what}: {viewer.url}")
        sys.stdout.flush()  # read by whoever waits for it before the run ends
    return viewer


def _run_frames(args, rep: Reporter, source, proc, viewer):
    """Run the live source through ``proc`` into ``-o`` and the viewer; the outputs are
    complete when it returns.  Returns (LiveStats, the signals that stopped it)."""
    from mems_stereo.pipeline.live_queue import LiveRun

    src = str(args.replay or args.source)
    stem = "live" if src.startswith(ZMQ_SCHEMES) else (Path(src).stem or "live")
    with contextlib.ExitStack() as stack:
        sinks = []
        if args.output is not None:
            from mems_stereo.viz.export_frames import open_frame_sink

            sinks.append(stack.enter_context(open_frame_sink(args.output, stem,
                                                             args.frame_format)))
        if viewer is not None:
            sinks.append(viewer)  # closed by the caller (it may stay open)
        bar = stack.enter_context(rep.progress(total=None, desc=source.source, unit="frame"))

        def write(frame):
            for s in sinks:
                s.write(frame)

        def progress(st):
            bar.update(1)
            bar.set_postfix_str(f"dropped {st.frames_dropped}", refresh=False)

        live = LiveRun(source, proc, write, max_queued=args.queue_frames, on_progress=progress)
        with stop_on_signals(live) as got:
            stats = live.run()
    return stats, got


def _hold(rep: Reporter) -> None:
    """``--view-keep``: the viewer stays until Ctrl-C or SIGTERM."""
    rep.info("the viewer stays open: Ctrl-C ends")
    sys.stdout.flush()
    done = threading.Event()
    with stop_on_signals(types.SimpleNamespace(stop=done.set)):
        while not done.wait(0.2):
            pass


def _output_kind(args) -> str:
    out = str(args.output)
    return "bag" if Path(out).suffix.lower() in FRAME_BAG_SUFFIXES and not out.endswith("/") \
        and not Path(out).is_dir() else "folder"


def run(args) -> int:
    from mems_stereo.pipeline.frame_workers import frame_processor
    from mems_stereo.pipeline.live_warmup import warm_up
    from mems_stereo.pipeline.settings import Settings

    _check(args)
    rep = Reporter(args)
    source = open_source(args)
    system = resolve_system(args.system) if args.system else source.system
    settings = Settings(confidence=args.confidence, min_range=args.min_range,
                        false_alarm=args.false_alarm)
    workers = args.workers or (1 if source.can_wait else None)  # None: one per core
    split = args.split or ("frames" if source.can_wait else "pixels")
    proc = frame_processor(system, workers=workers, split=split, frame_rate=args.frame_rate,
                           frame_shots=args.frame_shots, settings=settings,
                           fusion=not args.no_temporal)
    if not source.can_wait and not proc.workers:  # a clock runs: kernels and tables ready
        warm_up(proc)                             # before it starts (workers warm up alone)
    with contextlib.ExitStack() as keep:
        keep.enter_context(proc)
        viewer = _open_viewer(args, rep)
        if viewer is not None:
            keep.enter_context(viewer)
        stats, got = _run_frames(args, rep, source, proc, viewer)
        how = f" (stopped by {signal.Signals(got[0]).name})" if got else ""
        rep.info(f"{source.source}: {stats.summary()}{how}")
        if args.output is not None:
            rep.info(f"  wrote {args.output}"
                     + (" (one PointCloud2 per frame)" if _output_kind(args) == "bag" else ""))
        if viewer is not None and args.view_keep and not got:
            _hold(rep)
    return 0
