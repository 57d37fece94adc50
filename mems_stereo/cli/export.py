"""``mems-stereo export``: convert a point cloud between PLY, PCD, LAS/LAZ and ROS 2 bags.

A ROS 2 bag (``.mcap``, ``.db3``) is stamped with the cloud's time: a bag read
keeps its message's stamp; PLY, PCD and LAS carry no acquisition time, so
writing a bag from them needs ``--stamp`` (refused before any work without it).
"""

from __future__ import annotations

from pathlib import Path

from mems_stereo.cli._common import Reporter, add_parents_argument
from mems_stereo.cli._writes import suffix_help
from mems_stereo.errors import OptionError

NAME = "export"
HELP = "convert a point cloud (.ply, .pcd, .las) keeping every per-point attribute"
EXAMPLE = ["mems-stereo samples -o samples room.h5",
           "mems-stereo process samples/room.h5 -o room.ply",
           "mems-stereo export room.ply -o room.las",
           "mems-stereo export room.ply -o room.mcap --stamp 2026-11-27T08:00:00Z"]
_BAGS = (".mcap", ".db3")


def add_arguments(p):
    p.add_argument("cloud", help="input point cloud (.ply, .pcd, .las, .laz, .mcap, .db3)")
    p.add_argument("-o", "--output", required=True,
                   help="output file; the suffix picks the format "
                        f"({suffix_help('export', 'output')})")
    add_parents_argument(p)
    p.add_argument("--stamp", default=None, metavar="TIME",
                   help="the cloud's time for a ROS 2 bag (.mcap, .db3): ISO 8601 with a time "
                        "zone (2026-11-27T08:00:00Z), seconds since 1970-01-01 UTC, or 'now'; "
                        "default: a bag's own stamp (PLY, PCD and LAS carry none: required)")


def run(args) -> int:
    from mems_stereo.viz.export import read_cloud, write_cloud
    from mems_stereo.viz.export_ros2 import parse_stamp, read_ros2_stamp

    rep = Reporter(args)
    stamp = None
    if Path(args.output).suffix.lower() in _BAGS:
        if args.stamp is not None:
            stamp = parse_stamp(args.stamp)
        elif Path(args.cloud).suffix.lower() in _BAGS:
            stamp = read_ros2_stamp(args.cloud)
        if stamp is None:
            raise OptionError(f"{Path(args.cloud).name} carries no acquisition time: a ROS 2 "
                              "bag needs one (give --stamp: ISO 8601, seconds since the "
                              "epoch, or now)", field="--stamp")
    elif args.stamp is not None:
        raise OptionError("stamps a ROS 2 bag only (-o .mcap or .db3)", field="--stamp")
    cloud = read_cloud(args.cloud)
    rep.detail(f"read {len(cloud)} points from {args.cloud}")
    out = write_cloud(args.output, cloud, stamp_ns=stamp)
    rep.info(f"{out}: {len(cloud)} points, attributes {', '.join(cloud.attributes) or '-'}"
             + (f", stamp {stamp / 1e9:.9f} s" if stamp is not None else ""))
    missing = cloud.missing_required()
    if missing:
        rep.detail(f"note: the cloud lacks the FORMAT v1 attributes {', '.join(missing)}")
    return 0
