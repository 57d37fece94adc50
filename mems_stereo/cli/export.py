"""``mems-stereo export``: convert a point cloud between PLY, PCD and LAS."""

from __future__ import annotations

from mems_stereo.cli._common import Reporter, add_parents_argument
from mems_stereo.cli._writes import suffix_help

NAME = "export"
HELP = "convert a point cloud (.ply, .pcd, .las) keeping every per-point attribute"
EXAMPLE = ["mems-stereo samples -o samples room.h5",
           "mems-stereo process samples/room.h5 -o room.ply",
           "mems-stereo export room.ply -o room.las"]


def add_arguments(p):
    p.add_argument("cloud", help="input point cloud (.ply, .pcd, .las)")
    p.add_argument("-o", "--output", required=True,
                   help="output file; the suffix picks the format "
                        f"({suffix_help('export', 'output')})")
    add_parents_argument(p)


def run(args) -> int:
    from mems_stereo.viz.export import read_cloud, write_cloud

    rep = Reporter(args)
    cloud = read_cloud(args.cloud)
    rep.detail(f"read {len(cloud)} points from {args.cloud}")
    out = write_cloud(args.output, cloud)
    rep.info(f"{out}: {len(cloud)} points, attributes {', '.join(cloud.attributes) or '-'}")
    missing = cloud.missing_required()
    if missing:
        rep.detail(f"note: the cloud lacks the FORMAT v1 attributes {', '.join(missing)}")
    return 0
