"""``mems-stereo plot``: the paper's figures as PNG (acquisition, histograms, cloud)."""

from __future__ import annotations

import argparse

from mems_stereo.cli._common import Reporter, add_parents_argument, check_color_by
from mems_stereo.cli._ux import epilog
from mems_stereo.cli._writes import suffix_help
from mems_stereo.cli.info import add_acquisition_arguments, check_tdc_reaches
from mems_stereo.io.histograms import read_histograms
from mems_stereo.model.acquisition import acquisition_statistics
from mems_stereo.model.system import resolve_system

NAME = "plot"
HELP = "write a figure: acquisition (Fig. 2), histograms (Figs. 8/9), cloud (top view)"
EXAMPLE = ["mems-stereo samples -o samples room.h5",
           "mems-stereo process samples/room.h5 -o room.ply --histograms room_hist.h5",
           "mems-stereo plot histograms room_hist.h5 -o fig8.png --max-code 256",
           "mems-stereo plot acquisition --shots 400 -o fig2.png",
           "mems-stereo plot cloud room.ply -o top.png"]
#: per figure: (description, example lines run after those of EXAMPLE that make their input)
FIGURES = {
    "acquisition": ("Fig. 2 of the paper: how many shots land on each pixel and scan angle, "
                    "for a system, a shot count and a target distance",
                    ["mems-stereo plot acquisition --shots 400 --ratio 0.0785 -o fig2.png"]),
    "histograms": ("Figs. 8/9 of the paper: the raw, signal and noise histograms (pixel x TDC "
                   "code) of a histogram file written by 'mems-stereo process --histograms'",
                   ["mems-stereo samples -o samples room.h5",
                    "mems-stereo process samples/room.h5 -o room.ply --histograms room_hist.h5",
                    "mems-stereo plot histograms room_hist.h5 -o fig8.png --max-code 256"]),
    "cloud": ("top view (x-z plane) of a point cloud, coloured by an attribute",
              ["mems-stereo samples -o samples room.h5",
               "mems-stereo process samples/room.h5 -o room.ply",
               "mems-stereo plot cloud room.ply -o top.png --color-by range"]),
}


def _out_help(figure: str) -> str:
    return f"figure to write ({suffix_help('plot ' + figure, 'output')})"


def add_arguments(p):
    sub = p.add_subparsers(dest="figure", metavar="FIGURE", required=True)

    def fig_parser(name, help_):
        desc, ex = FIGURES[name]
        return sub.add_parser(name, help=help_, description=desc, epilog=epilog(ex),
                              formatter_class=argparse.RawDescriptionHelpFormatter)

    a = fig_parser("acquisition", "Fig. 2: shots over scan angle and per pixel")
    add_acquisition_arguments(a)
    a.add_argument("-o", "--output", required=True, help=_out_help("acquisition"))
    h = fig_parser("histograms", "Figs. 8/9: raw, signal, noise histograms from a histogram file")
    h.add_argument("histograms", help="HDF5 histogram file (/raw /signal /noise)")
    h.add_argument("-o", "--output", required=True, help=_out_help("histograms"))
    h.add_argument("--max-code", type=int, default=None,
                   help="show TDC codes 1..N only (the paper shows 256)")
    h.add_argument("--row", type=int, default=None, help="sensor row (default: sum of rows)")
    h.add_argument("--linear", action="store_true", help="linear colour scale (default log)")
    c = fig_parser("cloud", "top view (x–z) of a point cloud")
    c.add_argument("cloud", help="point cloud (.ply, .pcd, .las)")
    c.add_argument("-o", "--output", required=True, help=_out_help("cloud"))
    c.add_argument("--color-by", default="range", help="attribute or x/y/z (default range)")
    for q in (a, h, c):
        add_parents_argument(q)
        q.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS,
                       help="print only errors")
        q.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS,
                       help="print more detail")


def run(args) -> int:
    from mems_stereo.viz import plots

    rep = Reporter(args)
    if args.figure == "acquisition":
        system = resolve_system(args.system)
        check_tdc_reaches(system, args.distance, args.system)
        st = acquisition_statistics(system, args.shots, args.distance,
                                    frequency_ratio=args.ratio)
        ratio = args.ratio if args.ratio is not None else system.scanner.f_mech / system.laser.f_rep
        out = plots.plot_acquisition(st, args.output,
                                     title=f"{args.shots} shots, f_mech/f_rep = {ratio:.4f}")
        rep.info(f"{out}: mean accumulations per lit pixel {st.mean_per_illuminated_pixel:.2f}")
    elif args.figure == "histograms":
        h = read_histograms(args.histograms)
        raw, sig, noise, attrs = h.raw, h.signal, h.noise, h.attrs
        out = plots.plot_histograms(raw, sig, noise, args.output, max_code=args.max_code,
                                    log=not args.linear, row=args.row,
                                    title=str(attrs.get("source", args.histograms)))
        rep.info(f"{out}: raw {int(raw.sum())}, signal {int(sig.sum())}, "
                 f"noise {int(noise.sum())} counts")
    else:
        from mems_stereo.viz.export import read_cloud

        cloud = read_cloud(args.cloud)
        check_color_by(cloud, args.color_by, args.cloud)
        out = plots.plot_cloud_topview(cloud, args.output, color_by=args.color_by)
        rep.info(f"{out}: {len(cloud)} points")
    return 0
