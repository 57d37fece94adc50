"""``mems-stereo simulate``: a simulated recording of a scene (HDF5 with /truth)."""

from __future__ import annotations

import sys

import numpy as np

from mems_stereo.cli import _twoaxis
from mems_stereo.cli._common import Reporter, add_parents_argument
from mems_stereo.cli._writes import suffix_help
from mems_stereo.errors import FormatError
from mems_stereo.model.presets import PRESETS
from mems_stereo.model.scanner2d import is_two_axis
from mems_stereo.model.system import resolve_system

NAME = "simulate"
HELP = "simulate a recording of a scene (JSON of primitives/meshes) with ground truth"
EXAMPLE = ["mems-stereo samples -o samples room_scene.json calib_true_system.json",
           "mems-stereo simulate samples/room_scene.json -o room.h5 --shots 800 --seed 1 "
           "--true-system samples/calib_true_system.json"]


def add_arguments(p):
    p.add_argument("scene", help="scene JSON file (see docs/simulator.md)")
    p.add_argument("-o", "--output", required=True,
                   help=f"output recording ({suffix_help('simulate', 'output')})")
    add_parents_argument(p)
    p.add_argument("--shots", type=int, default=800, help="number of laser shots (default 800)")
    p.add_argument("--background", type=float, default=1e5,
                   help="ambient detections per pixel, Hz (default 1e5: room light; "
                        "6e6: the paper's floodlight)")
    p.add_argument("--dark", type=float, default=1e3,
                   help="dark counts per pixel, Hz (default 1e3)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--system", default="burkard2022",
                   help="nominal system written into the recording: JSON file or preset "
                        f"({', '.join(PRESETS)}; default burkard2022)")
    p.add_argument("--true-system", default=None,
                   help="system that generates the photons (default: --system)")
    p.add_argument("--drift", type=float, default=0.0,
                   help="relative drift of the mechanical frequency, 1/s (default 0)")
    p.add_argument("--crosstalk", type=float, default=0.0,
                   help="probability that a detection fires a neighbour pixel (default 0)")


def check_codes_written(system, true_system, args) -> None:
    """The recording's ``/system`` (``--system``) must take every code the photons get
    (from ``--true-system``'s TDC): else ``process`` would refuse the file written."""
    if true_system is not None and true_system.tdc.n_bins > system.tdc.n_bins:
        raise FormatError(f"{system.tdc.n_bins} codes, fewer than the "
                          f"{true_system.tdc.n_bins} of --true-system {args.true_system} that "
                          "generates the recording's codes; expected at least as many",
                          source=str(args.system), field="tdc.n_bins")


def run(args) -> int:
    rep = Reporter(args)
    if args.shots < 1:
        print(f"mems-stereo simulate: error: --shots: expected a positive integer, found "
              f"{args.shots}", file=sys.stderr)
        return 2
    from mems_stereo.sim import (  # not on other commands
        SimulationOptions,
        load_scene,
        simulate,
        write_simulation,
    )

    system = resolve_system(args.system)
    true_system = resolve_system(args.true_system) if args.true_system else None
    check_codes_written(system, true_system, args)
    scene = load_scene(args.scene)
    rep.detail(f"{scene!r}")
    if is_two_axis(system):  # two-axis scanner, 2-D array: cli/_twoaxis.py
        return _twoaxis.simulate(args, rep, system, true_system, scene)
    with rep.progress(args.shots, "simulating") as bar:
        rec = simulate(system, scene, args.shots, rng=np.random.default_rng(args.seed),
                       background_hz=args.background, dark_count_hz=args.dark,
                       true_system=true_system,
                       options=SimulationOptions(drift=args.drift, crosstalk=args.crosstalk),
                       progress=bar.update)
    out = write_simulation(args.output, rec)
    lab = rec.truth["label"]
    k = rec.n_shots
    rep.info(f"wrote {out}: {k} shots, {int((lab == 1).sum())} laser-return detections "
             f"({(lab == 1).sum() / k:.2f} per shot), {int((lab == 2).sum())} background "
             f"detections ({(lab == 2).sum() / k:.1f} per shot)")
    return 0
