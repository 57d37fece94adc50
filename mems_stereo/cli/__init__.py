"""The ``mems-stereo`` command line: thin wrappers that parse, call the API, report.

Each command lives in its own module exposing ``NAME``, ``HELP``,
``EXAMPLE``, ``add_arguments(parser)`` and ``run(args) -> int``.  User
mistakes (:class:`~mems_stereo.errors.MemsStereoError`, missing files) are
printed on stderr as one line, with exit code 2 and no traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from mems_stereo.errors import MemsStereoError

COMMAND_MODULES = [
    "info", "simulate", "process", "calibrate", "export", "view", "render", "plot", "demo",
    "import_",
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
    parser = argparse.ArgumentParser(
        prog="mems-stereo",
        description="Calibrate a MEMS-scanner / SPAD-receiver pair, turn raw TDC frames "
                    "into classified detections and point clouds, and look at them.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version="mems-stereo 0.1.0")
    verb = parser.add_mutually_exclusive_group()
    verb.add_argument("-q", "--quiet", action="store_true", help="print only errors")
    verb.add_argument("-v", "--verbose", action="store_true", help="print more detail")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for mod in _load_commands():
        p = sub.add_parser(mod.NAME, help=mod.HELP, description=mod.HELP,
                           epilog="example:\n  " + mod.EXAMPLE,
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
        print(f"mems-stereo {args.command}: error: {e}", file=sys.stderr)
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
