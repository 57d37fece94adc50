"""``mems-stereo samples``: list the bundled sample data or copy it into a folder."""

from __future__ import annotations

import shutil
from pathlib import Path

from mems_stereo import data
from mems_stereo.cli._common import Reporter, add_parents_argument
from mems_stereo.errors import FormatError

NAME = "samples"
HELP = ("list the bundled sample recordings, scenes and systems, or copy them into a folder "
        "(the --help examples of the other commands start from such a copy)")
EXAMPLE = ["mems-stereo samples --list", "mems-stereo samples -o samples"]


def add_arguments(p):
    p.add_argument("names", nargs="*", metavar="NAME",
                   help="samples to copy (default: all), e.g. room.h5 calib_true_system.json")
    p.add_argument("-o", "--output", default=None,
                   help="folder to copy them into (created if missing; its parent must "
                        "exist unless --parents)")
    add_parents_argument(p)
    p.add_argument("--list", action="store_true",
                   help="print the samples and where they are installed, copy nothing")


def run(args) -> int:
    rep = Reporter(args)
    names = args.names or data.list()
    paths = [data.path(n) for n in names]  # FormatError naming the samples for a typo
    if args.list or args.output is None:
        if args.output is None and not args.list:
            raise FormatError("nothing to do\ngive -o FOLDER to copy the samples, or --list",
                              field="-o")
        rep.info(f"{data.root()}:")
        for p in paths:
            rep.info(f"  {p.name:28s} {p.stat().st_size / 1e6:6.2f} MB")
        return 0
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    for p in paths:
        shutil.copyfile(p, out / p.name)
    rep.info(f"copied {len(paths)} sample file(s) from {data.root()} to {out}/")
    return 0
