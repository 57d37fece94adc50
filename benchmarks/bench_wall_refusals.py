"""The ``--model ideal`` wall calibrations of bench_real_hardware's trials, alone.

    nice python benchmarks/bench_wall_refusals.py --seeds 1002,1011 [--hardware imperfect]

Per seed, the trial's walls (:func:`bench_real_hardware.simulate_walls` at
``--shot-scale``, the same seeds) by the ideal or the imperfect hardware (the latter
with the nominal system carrying the code-density test's code widths, as the trial),
then the steps of ``calibrate_system(model="ideal")``: :func:`fit_walls`, then
:func:`~mems_stereo.calib.goodness.judge` of a written result or
:func:`~mems_stereo.calib.goodness.name_failure` of a refused one.  Prints per seed the
verdict (written / refused naming an effect / refused without one), the reason, every
structure test's p-value and the CPU seconds of the fit (the cost the pose search
dominates), and writes the lines to ``--log``.  ``--cache DIR`` keeps each seed's
walls and fit (pickle) so that a rerun judges again without fitting.
"""

from __future__ import annotations

import argparse
import os
import pickle
import sys
import time
import warnings
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_real_hardware import (  # noqa: E402
    DARK_MIN_WIDTH,
    EFFECT_WORDS,
    dark_code_widths,
    draw_imperfections,
    simulate_walls,
)
from mems_stereo.calib.family import draw_case  # noqa: E402
from real_hardware_summary import cpu_model  # noqa: E402

from mems_stereo.model.system import burkard2022  # noqa: E402


def inputs(seed: int, hardware: str, shot_scale: float, dark: int):
    """(walls as WallData, nominal system, priors) of a trial's calibration."""
    from mems_stereo.calib.association import wall_data

    from mems_stereo.model.tdc import code_centres

    nom = burkard2022()
    case = draw_case(np.random.default_rng(seed), seed)
    true = case.true_system(nom)
    if hardware == "imperfect":
        imp = draw_imperfections(np.random.default_rng([seed, 30]))
        true = imp.apply(true, np.random.default_rng([seed, 31]))
        if dark > 0:
            est, _ = dark_code_widths(nom, true, seed, dark, DARK_MIN_WIDTH)
            nom = nom.replace(tdc=replace(nom.tdc, code_widths=est.width[0],
                                          code_widths_std=est.width_sigma[0]))
    wd = [wall_data(r) for r in simulate_walls(case, nom, true, shot_scale)]
    if nom.tdc.code_widths is not None:
        for w in wd:
            w.code_centres = code_centres(nom.tdc)
    priors = [(j, "axis", float(d), 2e-3) for j, d in enumerate(case.measured)]
    return wd, nom, priors


def one(seed: int, args) -> list:
    """The lines of one seed."""
    from mems_stereo.calib.fit import fit_walls
    from mems_stereo.calib.goodness import judge, name_failure

    cache = Path(args.cache) / f"{args.hardware}_{seed}.pkl" if args.cache else None
    if cache is not None and cache.exists() and not args.refit:
        wd, nom, priors, fit, cpu = pickle.loads(cache.read_bytes())
    else:
        wd, nom, priors = inputs(seed, args.hardware, args.shot_scale, args.dark_per_code)
        t0 = time.process_time()
        fit = fit_walls(wd, nom, priors=priors)
        cpu = time.process_time() - t0
        if cache is not None:
            cache.parent.mkdir(parents=True, exist_ok=True)
            cache.write_bytes(pickle.dumps((wd, nom, priors, fit, cpu)))
    t0 = time.process_time()
    out = judge(fit) if fit else name_failure(fit, wd, nom, priors)
    cpu_judge = time.process_time() - t0
    reps = (fit.extra.get("goodness") if fit else None) or ()
    if not out:
        reps = out.details.get("goodness") or ()
    named = [k for k, w in EFFECT_WORDS.items() if not out and w in out.reason]
    verdict = "written" if out else ("refused naming " + ",".join(named) if named
                                     else "refused without an effect")
    lines = [f"seed {seed} ({args.hardware}): {verdict}; fit CPU {cpu:.1f} s, tests "
             f"{cpu_judge:.1f} s"]
    if not out:
        lines.append(f"    reason: {out.reason[:400]}")
    for rep in reps:
        d = rep if isinstance(rep, dict) else rep.to_dict()
        lines.append("    tests: " + ", ".join(f"{t['name']} p={t['p']:.1e} eff={t['effect']:.3f}"
                                              for t in d["tests"]))
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", required=True, help="comma-separated seeds")
    ap.add_argument("--hardware", choices=["ideal", "imperfect"], default="imperfect")
    ap.add_argument("--shot-scale", type=float, default=8.0)
    ap.add_argument("--dark-per-code", type=int, default=1000)
    ap.add_argument("--cache", default=None, help="folder for each seed's walls and fit")
    ap.add_argument("--refit", action="store_true", help="fit again even when cached")
    ap.add_argument("--log", default=str(ROOT / "benchmarks" / "results" / "wall_refusals.log"))
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    lines = [f"bench_wall_refusals: {len(seeds)} seeds, {args.hardware} hardware, wall shots / "
             f"{args.shot_scale:g}, CPU {cpu_model()}"]
    print(lines[0], flush=True)
    counts: dict = {}
    for s in seeds:
        got = one(s, args)
        for x in got:
            print(x, flush=True)
        lines += got
        v = got[0].split(": ", 1)[1].split(";")[0]
        key = v.split(" ")[0] + (" naming" if "naming" in v else "")
        counts[key] = counts.get(key, 0) + 1
    lines.append(f"verdicts: {counts}")
    print(lines[-1])
    Path(args.log).parent.mkdir(parents=True, exist_ok=True)
    Path(args.log).write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
