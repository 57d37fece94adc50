"""Shared helpers of the CLI commands: output verbosity, progress bars and the run guard."""

from __future__ import annotations

import argparse
import os
import signal
import sys

from mems_stereo.cli import _signals
from mems_stereo.cli._crosscheck import check_polarity
from mems_stereo.cli._options import check_options
from mems_stereo.cli._outputs import OutputPlan, emit, translate
from mems_stereo.cli._ux import format_error, progress_bar
from mems_stereo.cli._writes import PARENTS_HELP
from mems_stereo.errors import FormatError, MemsStereoError
from mems_stereo.io.recording import read_header
from mems_stereo.io.recording2d import is_two_axis_recording, read_recording_2d
from mems_stereo.model.system import resolve_system, save_system, system_to_dict
from mems_stereo.util.limits import limits, parse_size


class Reporter:
    """Prints according to ``--quiet`` / ``--verbose``; progress on stderr."""

    def __init__(self, args):
        self.quiet = bool(getattr(args, "quiet", False))
        self.verbose = bool(getattr(args, "verbose", False))

    def info(self, msg: str = "") -> None:
        if not self.quiet:
            emit(msg)

    def detail(self, msg: str) -> None:
        if self.verbose and not self.quiet:
            emit(msg)

    def progress(self, total: int, desc: str, unit: str = "shot"):
        """A tqdm progress bar on stderr (disabled when quiet or not a terminal)."""
        return progress_bar(total, desc, unit, quiet=self.quiet)


# ------------------------------------------------------------------ the run guard

def add_safety_arguments(p) -> None:
    """``--max-memory`` and ``--allow-external``, on every command."""
    p.add_argument("--max-memory", default=argparse.SUPPRESS, metavar="SIZE",
                   help="memory budget: inputs whose sizes would need more are refused before "
                        "any allocation (e.g. 4G; default: half the physical memory)")
    p.add_argument("--allow-external", action="store_true", default=argparse.SUPPRESS,
                   help="follow HDF5 external storage/links and virtual datasets, and scene "
                        "meshes outside the scene's folder (refused by default)")


def add_parents_argument(p) -> None:
    """``--parents``, on every command that writes files."""
    p.add_argument("--parents", action="store_true", help=PARENTS_HELP)


def save_system_output(system, path, result=None):
    """Write a calibrated system by its suffix: ``.yml``/``.yaml``/``.xml`` the OpenCV
    FileStorage form (with ``result``'s covariance and RMS), else the system JSON."""
    from pathlib import Path

    if Path(path).suffix.lower() in (".yml", ".yaml", ".xml"):
        from mems_stereo.calib.opencv_io import write_opencv_system

        return write_opencv_system(path, system, result)
    return save_system(system, path)


def check_color_by(cloud, color_by: str, source) -> None:
    """Refuse, naming the cloud file, a ``--color-by`` attribute the cloud lacks (the
    default ``range`` is missing from clouds written by other software)."""
    if color_by in cloud.attributes or color_by in ("x", "y", "z"):
        return
    have = ", ".join(sorted(cloud.attributes)) or "no attributes"
    choices = ", ".join(sorted(set(cloud.attributes)) + ["x", "y", "z"])
    raise FormatError(f"no attribute {color_by!r} to colour by (the file has "
                      f"{have}); expected --color-by one of {choices}", source=str(source))


def command_key(args) -> str:
    """``process``, or ``plot histograms`` for commands with sub-figures."""
    fig = getattr(args, "figure", None)
    return f"{args.command} {fig}" if args.command == "plot" and fig else args.command


def _one_line(text: str) -> str:
    return " ".join(str(text).split("\n")).strip()


def error_line(command: str, message: str) -> None:
    """The one line on stderr of a refused run."""
    print(f"mems-stereo {command}: error: {_one_line(translate(message))}", file=sys.stderr)


def _file_error(e: OSError, plan=None) -> str:
    """One line for an OSError; on a file the run writes (a staged output or a
    writer's temporary beside it): "cannot write TARGET (reason)"."""
    name = e.filename if e.filename is not None else ""
    if name and plan is not None and plan.names_staged(str(name)):
        o = plan.option_of(str(name))
        return (f"{o + ': ' if o else ''}cannot write {plan.translate(str(name))} "
                f"({e.strerror or type(e).__name__})")
    what = "file not found" if isinstance(e, FileNotFoundError) else (e.strerror or str(e))
    return f"{name}: {what}" if name else what


def run_command(args) -> int:
    """Run one parsed command under the validation layer; returns the exit code.

    Options are checked (:mod:`mems_stereo.cli._options`), inputs and outputs
    planned (:class:`mems_stereo.cli._outputs.OutputPlan`) before any work;
    the command writes to staged paths, committed together when it returns 0.
    Refused input: one line on stderr, exit 2.  SIGINT/SIGTERM/SIGHUP: the
    staged and temporary files are removed, one line says what was kept,
    exit 128 + signal.
    """
    cmd = args.command
    plan = None
    with _signals.signal_guard():  # nests inside main()'s
        try:
            mm = getattr(args, "max_memory", None)
            budget = parse_size(mm) if mm is not None else None
            with limits(max_memory=budget, allow_external=getattr(args, "allow_external", None)):
                key = command_key(args)
                check_options(key, args)
                plan = OutputPlan(key, args).check()
                check_input_consistency(key, args)
                with plan:
                    plan.stage()
                    rc = int(args.command_run(args) or 0)
                    sig = _signals.received()
                    if sig is not None:  # a library swallowed the interrupt
                        raise _signals.Interrupted(sig)
                    if rc == 0:
                        plan.commit()
                    elif plan.spec.on_failure:  # diagnostics of a failed run are kept
                        plan.commit(plan.spec.on_failure)
                _signals.finished(rc)
                return rc
        except BaseException as e:  # noqa: BLE001 - every outcome becomes one line
            sig = e.signum if isinstance(e, _signals.Interrupted) else _signals.received()
            if sig is not None and not isinstance(e, SystemExit):
                # an interrupt, also when a library turned it into another error
                # (an ImportError from a lazy import, a swallowed KeyboardInterrupt)
                if _signals.nested(2 if _signals.depth() > 1 else 1):
                    if isinstance(e, _signals.Interrupted):
                        raise
                    raise _signals.Interrupted(sig) from None
                return _report_interrupt(cmd, plan, sig)
            if isinstance(e, MemsStereoError):
                print(format_error(cmd, e, bool(getattr(args, "verbose", False))),
                      file=sys.stderr)
            elif isinstance(e, OSError):
                error_line(cmd, _file_error(e, plan))
            elif isinstance(e, MemoryError):
                error_line(cmd, "out of memory; lower --chunk-shots or --max-memory")
            elif isinstance(e, Exception) and not os.environ.get("MEMS_STEREO_DEBUG"):
                # a bug: one line, and the traceback on request
                error_line(cmd, f"internal error: {type(e).__name__}: {e} (set "
                                "MEMS_STEREO_DEBUG=1 for the traceback; please report it)")
                _signals.finished(1)
                return 1
            else:
                raise
            _signals.finished(2)
            return 2


def _report_interrupt(cmd: str, plan, sig: int) -> int:
    """The one line of an interrupted run (what was kept, truthfully); 128 + signal."""
    kept = plan.committed if plan is not None else []
    in_place = [p for _n, p, k in (plan.outputs if plan else []) if k == "dir"]
    if in_place:
        what = (f"the outputs of the finished steps were kept in {in_place[0]}; the "
                "interrupted step wrote nothing")
    elif kept:
        what = "after every output was written: " + ", ".join(map(str, kept))
    elif plan is not None and plan.outputs:
        what = "no output was written (temporary files removed)"
    else:
        what = "nothing was written"
    print(f"mems-stereo {cmd}: interrupted by {signal.Signals(sig).name}; {what}",
          file=sys.stderr)
    return 128 + sig


def check_input_consistency(command: str, args) -> None:
    """Cross-checks of the inputs' redundant data, before any work.

    * ``process`` and ``calibrate``: the zero-crossing polarity of every
      one-axis recording against its detections
      (:func:`mems_stereo.cli._crosscheck.check_polarity`);
    * ``calibrate``: the ``--target-distances-file`` (read first: cheap); every
      recording's /system must agree.
    """
    if command == "calibrate" and getattr(args, "target_distances_file", None):
        from mems_stereo.calib.calibrate import read_target_distances

        read_target_distances(args.target_distances_file, args.recordings)  # cheap: first
    if command in ("process", "calibrate"):
        _check_polarities(command, args)
    if command != "calibrate" or len(args.recordings) < 2:
        return

    def flat(d, pre=""):
        for k, v in d.items():
            if isinstance(v, dict):
                yield from flat(v, f"{pre}{k}.")
            else:
                yield f"{pre}{k}", v

    def system_of(path):
        if is_two_axis_recording(path):  # the two-axis extension (docs/formats.md §5)
            return read_recording_2d(path, truth=False).system
        return read_header(path).system

    ref = dict(flat(system_to_dict(system_of(args.recordings[0]))))
    for r in args.recordings[1:]:
        other = dict(flat(system_to_dict(system_of(r))))
        diff = sorted(k for k in set(ref) | set(other) if ref.get(k) != other.get(k))
        if diff:
            raise FormatError(f"differs from {args.recordings[0]}'s in {', '.join(diff[:4])}; "
                              "expected the recordings of one system", source=str(r),
                              field="/system")


def _check_polarities(command: str, args) -> None:
    system = settings = None
    if command == "process":
        from mems_stereo.pipeline.settings import Settings

        # the run's consistency settings: the check shares the run's interval table
        settings = Settings(confidence=args.confidence, min_range=args.min_range)
        if getattr(args, "system", None):
            system = resolve_system(args.system)
    quiet = bool(getattr(args, "quiet", False))

    def warn(text: str) -> None:
        if not quiet:
            print(f"mems-stereo {command}: warning: {text}", file=sys.stderr)

    for r in args.recordings:
        if not is_two_axis_recording(r):
            check_polarity(r, system, warn, settings)


def report_peaks_truth_outputs(rep: Reporter, res, outputs=()) -> None:
    """The common tail of a processing report (one- and two-axis): peaks and points,
    scores against the truth, outputs written, stage timings (with ``-v``)."""
    c = res.counts
    rep.info(f"  peaks {c['peaks']}, points {c['points']}")
    if res.truth is not None:
        t = res.truth
        rep.info(f"  against the truth: signal recall {t['recall']:.4f}, noise rejection "
                 f"{t['noise_rejection']:.4f} ({t['true_signal']} laser returns, "
                 f"{t['true_background']} background detections)")
    for o in outputs:
        rep.info(f"  wrote {o}")
    rep.detail("  timings: " + ", ".join(f"{k} {v:.2f} s" for k, v in res.timings.items()))
