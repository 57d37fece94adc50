"""Calibration of the two-axis system from flat walls: errors, σ and pulls (issue 17).

Random cases, each with its own seed: the true system is the nominal
``lissajous64`` off by random offsets (rest angles ±4 mrad, amplitudes ±1 %,
phase lags ±0.02 rad, baseline ±5 mm per axis, TDC offset ±2 ns); three
walls at random poses (distances in 1.2-1.8, 2.2-3.0 and 3.5-5.0 m, yaw and
pitch within ±0.25 rad), 40000 shots each at reduced laser power (0.03 W),
100 kHz background.  :func:`mems_stereo.calib.twoaxis.calibrate_two_axis`
starts from the nominal system.  With ``--intrinsics-error E`` the receiver's
camera matrix handed to calibration is off by a factor (1 − E) in fx, fy and
by 1.5 px in cx, cy, as a ChArUco result (σ 4 px, 2 px) would be; fx, fy,
cx, cy are then refined in the joint fit with that prior.

Printed: per case and parameter the error and σ; the summary gives the
largest |error| per angle (mrad; target 0.3) and per baseline axis (mm;
target 2), and the pulls (error / σ: RMS and share within 3).

Run:  .venv/bin/python benchmarks/bench_calibrate_twoaxis.py [--cases 6] [--intrinsics-error 0.03]
"""

from __future__ import annotations

import argparse
import os
import sys
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("NUMBA_THREADING_LAYER", "omp")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "samples"))
from make_samples_2d import wall_scene  # noqa: E402
from mems_stereo.calib.intrinsics import IntrinsicsResult  # noqa: E402
from mems_stereo.calib.twoaxis import (  # noqa: E402
    TWO_AXIS_PARAMS,
    calibrate_two_axis,
    get_param_2d,
    with_params_2d,
)

from mems_stereo.errors import NotObservableError  # noqa: E402
from mems_stereo.model.presets import lissajous64  # noqa: E402
from mems_stereo.sim.simulate2d import (  # noqa: E402
    Simulation2DOptions,
    default_link,
    simulate_2d,
)

ANGLES = ("theta0", "theta_mech_max", "phase_offset", "theta0_2", "theta_mech_max_2",
          "phase_offset_2")
BASE = ("baseline_x", "baseline_y", "baseline_z")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=6)
    ap.add_argument("--shots", type=int, default=40000)
    ap.add_argument("--intrinsics-error", type=float, default=0.0)
    ap.add_argument("--seed", type=int, default=2718)
    args = ap.parse_args(argv)
    nom = lissajous64()
    link = replace(default_link(), peak_power=0.03)
    print(f"== {args.cases} random true systems and wall poses, {args.shots} shots per wall, "
          f"intrinsics error {args.intrinsics_error:g}, seed {args.seed}")
    errs, pulls, failed = [], [], 0
    for i, child in enumerate(np.random.SeedSequence(args.seed).spawn(args.cases)):
        rng = np.random.default_rng(child)
        off = {"theta0": rng.uniform(-4e-3, 4e-3), "theta0_2": rng.uniform(-4e-3, 4e-3),
               "theta_mech_max": nom.scanner.theta_mech_max * rng.uniform(-0.01, 0.01),
               "theta_mech_max_2": nom.scanner.axis2.theta_mech_max * rng.uniform(-0.01, 0.01),
               "phase_offset": rng.uniform(-0.02, 0.02),
               "phase_offset_2": rng.uniform(-0.02, 0.02),
               "baseline_x": rng.uniform(-5e-3, 5e-3), "baseline_y": rng.uniform(-5e-3, 5e-3),
               "baseline_z": rng.uniform(-5e-3, 5e-3), "tdc_offset": rng.uniform(-2e-9, 2e-9)}
        true = with_params_2d(nom, **{k: get_param_2d(nom, k) + v for k, v in off.items()})
        recs = []
        for lo, hi in ((1.2, 1.8), (2.2, 3.0), (3.5, 5.0)):
            scene = wall_scene(rng.uniform(lo, hi), rng.uniform(-0.25, 0.25),
                               rng.uniform(-0.25, 0.25))
            recs.append(simulate_2d(nom, scene, args.shots, rng=rng, true_system=true,
                                    options=Simulation2DOptions(link=link,
                                                                truth_per_shot=False)))
        intr = None
        if args.intrinsics_error:
            K = nom.receiver.camera_matrix.copy()
            K[0, 0] *= 1 - args.intrinsics_error
            K[1, 1] *= 1 - args.intrinsics_error
            K[0, 2] += 1.5
            K[1, 2] -= 1.5
            intr = IntrinsicsResult(0.4, K, np.zeros(5), np.array([4.0, 4.0, 2.0, 2.0]), 30)
        try:
            res = calibrate_two_axis(recs, nom, intrinsics=intr)
        except NotObservableError as e:
            failed += 1
            print(f"case {i}: failed: {e}")
            continue
        e = {n: v - get_param_2d(true, n) for n, v in zip(res.names, res.values)}
        s = dict(zip(res.names, res.std))
        errs.append(e)
        pulls.append({n: e[n] / s[n] for n in res.names})
        print(f"case {i}: chi2/dof {res.chi2_dof:.2f}, {res.n_obs} shots; "
              + ", ".join(f"{n} {1e3 * e[n]:+.3f}±{1e3 * s[n]:.3f}"
                          + ("mm" if n in BASE else "mrad" if n in ANGLES else "")
                          for n in TWO_AXIS_PARAMS if n in e and n != "tdc_offset")
              + f", tdc_offset {1e12 * e['tdc_offset']:+.0f}±{1e12 * s['tdc_offset']:.0f} ps")
    if not errs:
        print("summary: every case failed")
        return 1
    print(f"summary: {len(errs)} cases, {failed} failed")
    for group, unit in ((ANGLES, "mrad"), (BASE, "mm")):
        for n in group:
            v = np.abs([e[n] for e in errs]) * 1e3
            print(f"summary {n:18s} max |err| {v.max():.3f} {unit}, median {np.median(v):.3f}")
    allp = np.array([p[n] for p in pulls for n in p])
    print(f"summary pulls: RMS {np.sqrt(np.mean(allp ** 2)):.2f}, share within 3: "
          f"{np.mean(np.abs(allp) < 3):.3f} ({allp.size} estimates)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
