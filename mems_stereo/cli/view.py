"""``mems-stereo view``: interactive Open3D window (needs a display)."""

from __future__ import annotations

from mems_stereo.cli._common import Reporter, check_color_by

NAME = "view"
HELP = "show a point cloud in an interactive Open3D window, coloured by an attribute"
EXAMPLE = ["mems-stereo samples -o samples room.h5",
           "mems-stereo process samples/room.h5 -o room.ply",
           "mems-stereo view room.ply --color-by sigma_r    # opens a window: needs a display"]


def add_arguments(p):
    p.add_argument("cloud", help="point cloud (.ply, .pcd, .las)")
    p.add_argument("--color-by", default="range",
                   help="attribute (range, counts, sigma_r, sigma_phi, pixel, ...) or x/y/z "
                        "(default range)")
    p.add_argument("--cmap", default="turbo", choices=["turbo", "viridis"])
    p.add_argument("--point-size", type=float, default=2.0, help="pixels (default 2)")


def run(args) -> int:
    from mems_stereo.viz.export import read_cloud
    from mems_stereo.viz.view import view_cloud

    rep = Reporter(args)
    cloud = read_cloud(args.cloud)
    check_color_by(cloud, args.color_by, args.cloud)
    rep.detail(f"{args.cloud}: {len(cloud)} points; close the window to return")
    view_cloud(cloud, color_by=args.color_by, cmap=args.cmap, point_size=args.point_size,
               window_name=f"mems-stereo: {args.cloud}")
    return 0
