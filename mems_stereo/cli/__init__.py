"""The ``mems-stereo`` command line: thin wrappers that parse, call the API, report.

Each command lives in its own module exposing ``NAME``, ``HELP``,
``EXAMPLE`` (one command line or a list of them, run in order from an empty
folder: tests/test_docs.py executes them), ``add_arguments(parser)`` and
``run(args) -> int``.  User mistakes (:class:`~mems_stereo.errors.MemsStereoError`,
missing files, bad options) are printed on stderr as one line (with an
indented advice line where there is advice), exit code 2 and no traceback;
:func:`mems_stereo.cli._common.run_command` checks options, inputs and
outputs before any work and commits all outputs together
(docs/reliability.md).

Every command module loads when the parser is built, so a command imports
the pipeline, the calibration, the simulator, the viz writers and the
format readers inside ``run``: a command loads only what it uses.  The
helper modules form layers (``_signals``, ``_ux``, ``_writes``, ``_pathcheck`` →
``_options``, ``_outputs`` → ``_common`` → ``_twoaxis`` → the commands);
each imports only those before it.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import signal
import sys

from mems_stereo.cli import _signals
from mems_stereo.cli._common import add_safety_arguments, run_command
from mems_stereo.cli._ux import HelpfulParser, epilog, examples

COMMAND_MODULES = [
    "info", "simulate", "process", "calibrate", "export", "view", "render", "plot", "demo",
    "import_",
    "samples", "live",
]


def _load_commands():
    cmds = []
    for name in COMMAND_MODULES:
        try:
            mod = importlib.import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as e:
            if e.name == f"{__name__}.{name}":
                continue  # command not built yet
            raise
        cmds.append(mod)
    return cmds


def build_parser() -> argparse.ArgumentParser:
    parser = HelpfulParser(
        prog="mems-stereo",
        description="Calibrate a MEMS-scanner / SPAD-receiver pair, turn raw TDC frames "
                    "into classified detections and point clouds, and look at them.",
        epilog="start with:\n  mems-stereo samples -o samples    # the bundled recordings\n"
               "  mems-stereo demo -o demo-output   # the whole chain on them\n"
               "mems-stereo COMMAND --help shows an example of each command",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version="mems-stereo 0.1.0")
    verb = parser.add_mutually_exclusive_group()
    verb.add_argument("-q", "--quiet", action="store_true", help="print only errors")
    verb.add_argument("-v", "--verbose", action="store_true", help="print more detail")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for mod in _load_commands():
        p = sub.add_parser(mod.NAME, help=mod.HELP, description=mod.HELP,
                           epilog=epilog(examples(mod)),
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        p.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS,
                       help="print only errors")
        p.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS,
                       help="print more detail")
        add_safety_arguments(p)
        mod.add_arguments(p)
        p.set_defaults(command_run=mod.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command line ``argv`` (default: the program's) and return its exit code.

    As the program itself (``argv`` None: the ``mems-stereo`` executable) it
    does not return: it ends the process with the exit code (128 + signal
    when interrupted, also by a signal that arrives while it exits), see
    :func:`mems_stereo.cli._signals.exit_now`.
    """
    if argv is not None:
        return _main(argv)
    try:
        rc = _main(argv)
    except SystemExit as e:  # usage errors and --help (argparse)
        rc = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
        if not isinstance(e.code, (int, type(None))):
            print(e.code, file=sys.stderr)
    _signals.exit_now(rc)
    return rc  # not reached


#: libraries whose log records would reach stderr through Python's last-resort
#: handler (ptufile warns about damaged PTU tags): the command's own one line says
#: what is wrong with the input
QUIET_LOGGERS = ("ptufile", "h5py", "numba", "distributed", "laspy")


def _quiet_library_loggers() -> None:
    for name in QUIET_LOGGERS:
        lg = logging.getLogger(name)
        if not any(isinstance(h, logging.NullHandler) for h in lg.handlers):
            lg.addHandler(logging.NullHandler())


def _main(argv: list[str] | None) -> int:
    _quiet_library_loggers()

    # first: an interrupt while loading the commands is handled too
    with _signals.signal_guard(final=argv is None):
        try:
            parser = build_parser()
            args = parser.parse_args(argv)  # usage errors: one line, SystemExit(2)
            if not getattr(args, "command", None):
                parser.print_help()
                return 2
            return run_command(args)
        except BaseException as e:  # noqa: BLE001
            sig = e.signum if isinstance(e, _signals.Interrupted) else _signals.received()
            if sig is None or isinstance(e, SystemExit):
                raise
            if _signals.nested():
                if isinstance(e, _signals.Interrupted):
                    raise
                raise _signals.Interrupted(sig) from None
            print(f"mems-stereo: interrupted by {signal.Signals(sig).name} "
                  f"{_signals.late_state()}", file=sys.stderr)
            return 128 + sig


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
