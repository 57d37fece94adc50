"""``mems-stereo info``: the system and its acquisition statistics."""

from __future__ import annotations

import math

from mems_stereo.cli._common import Reporter, add_parents_argument
from mems_stereo.cli._writes import suffix_help
from mems_stereo.errors import FormatError
from mems_stereo.model.acquisition import acquisition_statistics
from mems_stereo.model.presets import PRESETS
from mems_stereo.model.system import resolve_system

NAME = "info"
HELP = "print a system description and its acquisition statistics (paper Sec. 2.1)"
EXAMPLE = ["mems-stereo info --system burkard2022 --shots 400 --distance 2.5 --plot fig2.png",
           "mems-stereo samples -o samples calib_true_system.json",
           "mems-stereo info --system samples/calib_true_system.json"]


def add_acquisition_arguments(p):
    """The options of the acquisition statistics (shared with ``plot acquisition``)."""
    p.add_argument("--system", default="burkard2022",
                   help=f"system JSON file or preset ({', '.join(PRESETS)}; default: "
                        "burkard2022)")
    p.add_argument("--shots", type=int, default=400, help="number of laser shots (default 400)")
    p.add_argument("--distance", type=float, default=2.5,
                   help="distance of a flat target, m (default 2.5)")
    p.add_argument("--ratio", type=float, default=None,
                   help="f_mech/f_rep (default: from the system; the paper's Fig. 2 uses 0.0785)")


def check_tdc_reaches(system, distance: float, spec) -> None:
    """Refuse a system whose TDC window (``tdc.offset`` + ``n_bins`` × ``bin_width``)
    ends before the round trip to a target at ``distance`` m (its returns could not
    be recorded); ``spec`` is the ``--system`` value, named in the message."""
    t = system.tdc
    end = t.offset + t.n_bins * t.bin_width
    tof = 2.0 * distance / system.speed_of_light
    if tof > end:
        reach = 0.5 * end * system.speed_of_light
        raise FormatError(f"{t.n_bins} codes of {t.bin_width * 1e12:g} ps reach "
                          f"{reach:.3g} m; expected a TDC window that covers the target at "
                          f"--distance {distance:g} m ({tof * 1e9:.4g} ns round trip)",
                          source=str(spec), field="tdc.n_bins")


def add_arguments(p):
    add_acquisition_arguments(p)
    p.add_argument("--plot", default=None,
                   help=f"write the Fig. 2 plot here ({suffix_help('info', 'plot')})")
    add_parents_argument(p)


def run(args) -> int:
    rep = Reporter(args)
    system = resolve_system(args.system)
    check_tdc_reaches(system, args.distance, args.system)
    st = acquisition_statistics(system, args.shots, args.distance, frequency_ratio=args.ratio)
    s, r, la, t = system.scanner, system.receiver, system.laser, system.tdc
    rep.info(f"system: {args.system}")
    rep.info(f"  receiver   {r.width} x {r.height} px, fx = {r.camera_matrix[0, 0]:.4f} px, "
             f"cx = {r.camera_matrix[0, 2]:.2f} px")
    rep.info(f"  scanner    at {s.position.tolist()} m, theta0 = {s.theta0:.6f} rad "
             f"({math.degrees(s.theta0):.3f} deg), f_mech = {s.f_mech:g} Hz, "
             f"amplitude = {s.theta_mech_max:.6f} rad")
    rep.info(f"  laser      f_rep = {la.f_rep:g} Hz, pulse {la.pulse_fwhm * 1e9:.1f} ns FWHM")
    rep.info(f"  tdc        {t.n_bins} bins of {t.bin_width * 1e12:.1f} ps, offset "
             f"{t.offset * 1e9:.3f} ns")
    ratio = args.ratio if args.ratio is not None else s.f_mech / la.f_rep
    rep.info(f"acquisition: {args.shots} shots, f_mech/f_rep = {ratio:.4f}, "
             f"target at {args.distance:g} m")
    lit = int((st.pixel_counts > 0).sum())
    rep.info(f"  shots on the sensor          {st.fraction_on_sensor * 100:.1f} %")
    rep.info(f"  pixels hit                   {lit} of {r.width}")
    rep.info(f"  mean accumulations per pixel {st.mean_per_illuminated_pixel:.2f} "
             f"(count-weighted {st.mean_accumulations:.2f})")
    if args.plot:
        from mems_stereo.viz.plots import plot_acquisition

        out = plot_acquisition(st, args.plot, title=f"{args.shots} shots, "
                               f"f_mech/f_rep = {ratio:.4f}")
        rep.info(f"  Fig. 2 plot                  {out}")
    return 0
