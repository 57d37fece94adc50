"""``mems-stereo render``: draw a point cloud into a PNG offscreen (no GPU, no display)."""

from __future__ import annotations

import time

from mems_stereo.cli._common import Reporter, add_parents_argument, check_color_by
from mems_stereo.cli._writes import suffix_help
from mems_stereo.model.system import resolve_system
from mems_stereo.viz.colormap import ColorScale
from mems_stereo.viz.render import VIEWS, render_cloud
from mems_stereo.viz.render_decorations import Decorations

NAME = "render"
HELP = "render a point cloud offscreen to a PNG (Open3D + Mesa EGL; no display needed)"
EXAMPLE = ["mems-stereo samples -o samples room.h5",
           "mems-stereo process samples/room.h5 -o room.ply",
           "mems-stereo render room.ply -o room.png --color-by range --view oblique"]


def add_arguments(p):
    p.add_argument("cloud", help="point cloud (.ply, .pcd, .las)")
    p.add_argument("-o", "--output", required=True,
                   help=f"image to write ({suffix_help('render', 'output')})")
    add_parents_argument(p)
    p.add_argument("--color-by", default="range",
                   help="attribute (range, counts, sigma_r, sigma_phi, pixel, ...) or x/y/z "
                        "(default range)")
    p.add_argument("--view", default="oblique", choices=VIEWS,
                   help="oblique: from above and behind the sensor, shows a line sensor's "
                        "cloud (default); top: from above; side; camera: the receiver's own "
                        "viewpoint (a line sensor's cloud is then a single row of dots)")
    p.add_argument("--width", type=int, default=1280, help="pixels (default 1280)")
    p.add_argument("--height", type=int, default=960, help="pixels (default 960)")
    p.add_argument("--point-size", type=float, default=3.0, help="pixels (default 3)")
    p.add_argument("--cmap", default="turbo", choices=["turbo", "viridis"])
    p.add_argument("--vmin", type=float, default=None, help="value at the colormap's start")
    p.add_argument("--vmax", type=float, default=None, help="value at the colormap's end")
    p.add_argument("--decorate", action="store_true",
                   help="draw a ground grid with its scale and a colour bar")
    p.add_argument("--system", default=None,
                   help="system JSON or preset: draw the scanner and receiver at their poses "
                        "(implies --decorate)")
    p.add_argument("--ellipsoids", type=float, default=None, metavar="N_SIGMA",
                   help="draw N_SIGMA σ ellipsoids from sigma_r, sigma_phi (implies --decorate)")


def run(args) -> int:
    from mems_stereo.viz.export import read_cloud

    rep = Reporter(args)
    cloud = read_cloud(args.cloud)
    check_color_by(cloud, args.color_by, args.cloud)
    deco = None
    if args.decorate or args.system or args.ellipsoids:
        deco = Decorations(system=resolve_system(args.system) if args.system else None,
                           ellipsoids=bool(args.ellipsoids),
                           n_sigma=args.ellipsoids or 3.0)
    t0 = time.perf_counter()
    out = render_cloud(cloud, args.output, color_by=args.color_by, width=args.width,
                       height=args.height, view=args.view, point_size=args.point_size,
                       scale=ColorScale(args.cmap, args.vmin, args.vmax), decorations=deco)
    rep.info(f"{out}: {len(cloud)} points, {args.width} x {args.height} px, view {args.view}, "
             f"coloured by {args.color_by}")
    rep.detail(f"rendered in {time.perf_counter() - t0:.2f} s")
    return 0
