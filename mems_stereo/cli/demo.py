"""``mems-stereo demo``: the main job on the bundled samples, end to end."""

from __future__ import annotations

from pathlib import Path

from ..acquisition import acquisition_statistics
from ..system import preset
from ._common import Reporter

NAME = "demo"
HELP = "run the whole chain on the bundled samples and print where every output is"
EXAMPLE = "mems-stereo demo -o demo-output"


def add_arguments(p):
    p.add_argument("-o", "--output", default="demo-output",
                   help="directory for every output (default: demo-output)")


def run(args) -> int:
    rep = Reporter(args)
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    system = preset("burkard2022")
    rep.info("== mems-stereo demo ==")
    rep.info("system: burkard2022 (Burkard et al. 2022, Table 1)")
    st = acquisition_statistics(system, 400, 2.5, frequency_ratio=0.0785)
    rep.info(f"acquisition (Fig. 2 setting: 400 shots, f_mech/f_rep = 0.0785, wall at 2.5 m): "
             f"{int((st.pixel_counts > 0).sum())} pixels hit, mean "
             f"{st.mean_per_illuminated_pixel:.2f} accumulations per illuminated pixel")
    from viz.plots import plot_acquisition

    fig2 = plot_acquisition(st, out / "fig2_acquisition.png",
                            title="400 shots, f_mech/f_rep = 0.0785")
    rep.info(f"  wrote {fig2}")
    return 0
