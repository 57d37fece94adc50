"""The ``mems-stereo`` command line: thin wrappers that parse, call the API, report.

Each command lives in its own module exposing ``NAME``, ``HELP``,
``EXAMPLE`` (one command line or a list of them, run in order from an empty
folder: tests/test_docs.py executes them), ``add_arguments(parser)`` and
``run(args) -> int``.  User mistakes (:class:`~mems_stereo.errors.MemsStereoError`,
missing files) are printed on stderr as one line, with the advice on a
second, exit code 2 and no traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from mems_stereo.cli._ux import HelpfulParser, format_error
from mems_stereo.errors import MemsStereoError

COMMAND_MODULES = [
    "info", "simulate", "process", "calibrate", "export", "view", "render", "plot", "demo",
    "import_",
    "samples",
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


def examples(mod) -> list[str]:
    """A command module's example command lines (``EXAMPLE``: a string or a list)."""
    ex = mod.EXAMPLE
    return [ex] if isinstance(ex, str) else list(ex)


def epilog(lines: list[str]) -> str:
    """The ``--help`` epilog: one example command per line."""
    return ("examples (run in order from any folder):\n" if len(lines) > 1 else "example:\n") \
        + "\n".join("  " + x for x in lines)


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
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return 2
    try:
        return int(args._run(args) or 0)
    except MemsStereoError as e:
        print(format_error(args.command, e, bool(getattr(args, "verbose", False))),
              file=sys.stderr)
        return 2
    except FileNotFoundError as e:
        print(f"mems-stereo {args.command}: error: {e.filename}: file not found",
              file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"mems-stereo {args.command}: interrupted; no partial output was kept",
              file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
