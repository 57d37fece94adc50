"""Pulls of ``calibrate --model full`` on imperfect hardware, on chosen seeds.

    nice python benchmarks/pulls_full_model.py --seeds 1001,1019,1029 --cache /tmp/pfm

The calibration half of a :mod:`bench_real_hardware` trial on the imperfect hardware
only (same draws, seeds and steps: the dark code-density test, the ideal-model
:func:`~mems_stereo.calib.fit.fit_walls`, then :func:`~mems_stereo.calib.full_model.
add_hardware_terms` or :func:`~mems_stereo.calib.full_model.rescue`, then the
goodness test), no room.  ``--cache`` keeps each seed's ideal-model fit (pickled) so
that a change of the hardware-term steps is measured again in seconds.  Prints per
seed the pulls (estimate − truth)/σ in the conventions of
``bench_real_hardware.equivalent_truth``, then per parameter the pull std and max
|pull| over the seeds, and the written results beyond 4σ (``--before``: first those of
a ``bench_real_hardware.py --records`` file for the same seeds).  Log:
``benchmarks/results/pulls_full_model.log`` (``--log``).
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import sys
import time
import warnings
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import bench_real_hardware as brh  # noqa: E402
from _machine import cpu_model  # noqa: E402
from mems_stereo.calib.family import draw_case  # noqa: E402

from mems_stereo.model.system import burkard2022  # noqa: E402


def _ideal_fit(seed: int, shot_scale: float, dark: int, cache: Path | None):
    """(fit, walls data, nominal, priors, true system) of a seed's imperfect walls."""
    from dataclasses import replace

    from mems_stereo.calib.association import wall_data
    from mems_stereo.calib.fit import fit_walls

    from mems_stereo.model.tdc import code_centres

    nom = burkard2022()
    case = draw_case(np.random.default_rng(seed), seed)
    true0 = case.true_system(nom)
    imp = brh.draw_imperfections(np.random.default_rng([seed, 30]))
    true1 = imp.apply(true0, np.random.default_rng([seed, 31]))
    path = None if cache is None else cache / f"fit{seed}_{shot_scale:g}_{dark}.pkl"
    if path is not None and path.exists():
        with open(path, "rb") as f:
            fit, wd, nom1, priors = pickle.load(f)
        return fit, wd, nom1, priors, true1
    walls = brh.simulate_walls(case, nom, true1, shot_scale)
    nom1 = nom
    if dark > 0:
        est, _ = brh.dark_code_widths(nom, true1, seed, dark, brh.DARK_MIN_WIDTH)
        nom1 = nom.replace(tdc=replace(nom.tdc, code_widths=est.width[0],
                                       code_widths_std=est.width_sigma[0]))
    priors = [(j, "axis", float(d), 2e-3) for j, d in enumerate(case.measured)]
    wd = [wall_data(r) for r in walls]
    if nom1.tdc.code_widths is not None:
        for w in wd:
            w.code_centres = code_centres(nom1.tdc)
    fit = fit_walls(wd, nom1, priors=priors)
    if path is not None:
        with open(path, "wb") as f:
            pickle.dump((fit, wd, nom1, priors), f)
    return fit, wd, nom1, priors, true1


def run_seed(task) -> dict:
    """One seed: the full-model calibration's outcome and pulls (JSON-able)."""
    seed, opt = task
    warnings.simplefilter("ignore")
    from mems_stereo.calib import full_model
    from mems_stereo.calib.full_model import add_hardware_terms, rescue
    from mems_stereo.calib.goodness import judge

    full_model.NEWTON_START = not opt.get("zero_start", False)
    steps: list = []
    say = steps.append if opt.get("verbose") else None

    t0 = time.process_time()
    cache = Path(opt["cache"]) if opt["cache"] else None
    fit, wd, nom1, priors, true1 = _ideal_fit(seed, opt["shot_scale"], opt["dark"], cache)
    t1 = time.process_time()
    if fit:
        full = add_hardware_terms(fit, progress=say)
        full = judge(full) if (list(full.names) != list(fit.names)
                               or full.system.tdc.pixel_offsets is not None) else judge(fit)
    elif fit.kind == "estimate":
        full = rescue(fit, wd, nom1, priors, progress=say)
        if full:
            full = judge(add_hardware_terms(full, progress=say))
    else:
        full = fit
    out = {"seed": seed, "ok": bool(full), "reason": "" if full else full.reason[:200],
           "cpu_ideal": t1 - t0, "cpu_full": time.process_time() - t1, "steps": steps}
    if full:
        out["pulls"] = brh.pulls_of(full, true1)
        out["std"] = {n: float(full.std[n]) for n in full.names}
        out["warnings"] = [w[:160] for w in full.warnings]
        out["values"] = {n: float(full.values[n]) for n in full.names}
        out["terms"] = [n for n in full.names if n.startswith(("harmonic", "edge", "pulse"))]
        mon, sc = true1.scanner.monitor, true1.scanner
        out["truth"] = {n: float(brh.equivalent_truth(true1, n, full)) for n in full.names}
        if mon is not None:  # the phase offset with the mean of the two edge delays
            out["truth"]["phase_offset_mean"] = float(
                sc.phase_offset + np.pi * sc.f_mech * (mon.rising_delay + mon.falling_delay))
    return out


def summarise(recs: list, log) -> None:
    """Per parameter: fits, pull mean, std, max |pull|, count beyond 4σ."""
    by: dict = {}
    for r in recs:
        for n, v in r.get("pulls", {}).items():
            by.setdefault(n, []).extend(v if isinstance(v, list) else [v])
    for n, v in by.items():
        v = np.asarray(v, dtype=np.float64)
        log(f"  {n:20s} values {v.size:4d} mean {v.mean():+.2f} std {v.std():.2f} "
            f"max |pull| {np.abs(v).max():.2f} over 4σ {int((np.abs(v) > 4).sum())}")
    bad = [(r["seed"], round(max(abs(x) for k, x in r["pulls"].items()
                                 if not isinstance(x, list)), 1))
           for r in recs if r.get("pulls")]
    over = [b for b in bad if b[1] > 4]
    log(f"  written {len(bad)}/{len(recs)}; beyond 4σ (scalar parameters): {len(over)} {over}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", required=True, help="comma-separated seeds")
    ap.add_argument("--shot-scale", type=float, default=8.0)
    ap.add_argument("--dark-per-code", type=int, default=1000)
    ap.add_argument("--cache", default=None, help="folder for the ideal-model fits")
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--verbose", action="store_true",
                    help="log each seed's hardware-term steps (selection, start, outcome)")
    ap.add_argument("--zero-start", action="store_true",
                    help="start a newly selected hardware block at 0 (the former start) "
                         "instead of the score test's Newton step")
    ap.add_argument("--records", default=None, help="append each seed as a JSON line")
    ap.add_argument("--before", default=None, metavar="RECORDS",
                    help="a bench_real_hardware records file: print its pulls of the same "
                         "seeds first")
    ap.add_argument("--log", default=str(ROOT / "benchmarks" / "results" / "pulls_full_model.log"))
    args = ap.parse_args(argv)
    seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    if args.cache:
        Path(args.cache).mkdir(parents=True, exist_ok=True)
    opt = {"shot_scale": args.shot_scale, "dark": args.dark_per_code, "cache": args.cache,
           "zero_start": args.zero_start, "verbose": args.verbose}
    lines: list = []

    def log(s: str) -> None:
        print(s, flush=True)
        lines.append(s)

    log(f"pulls_full_model: seeds {seeds}, wall shots / {args.shot_scale:g}, new block start "
        f"{'0' if args.zero_start else 'Newton step'}, CPU {cpu_model()}")
    tasks = [(s, opt) for s in seeds]
    recs: list = []

    def keep(r: dict) -> None:
        recs.append(r)
        p = r.get("pulls", {})
        log(f"seed {r['seed']}: " + ("written " + " ".join(
            f"{k} {v:+.1f}" for k, v in p.items() if not isinstance(v, list))
            if r["ok"] else "refused: " + r["reason"][:120])
            + f" (CPU {r['cpu_ideal']:.0f} + {r['cpu_full']:.0f} s)"
            + "".join(f"\n    {m}" for m in r.get("steps", [])))
        if args.records:
            with open(args.records, "a", encoding="utf-8") as f:
                f.write(json.dumps(r, default=float) + "\n")

    if args.jobs > 1:  # each seed logged as it ends
        from concurrent.futures import ProcessPoolExecutor, as_completed

        with ProcessPoolExecutor(args.jobs) as ex:
            for fut in as_completed([ex.submit(run_seed, t) for t in tasks]):
                keep(fut.result())
    else:
        for t in tasks:
            keep(run_seed(t))
    recs.sort(key=lambda r: r["seed"])
    if args.before:  # the same seeds' pulls in a bench_real_hardware records file
        old = [json.loads(x) for x in Path(args.before).read_text().splitlines() if x.strip()]
        old = [{"seed": r["seed"], "pulls": r["pulls1"]} for r in old
               if r.get("seed") in seeds and r.get("pulls1") and "flows" in r]
        log(f"before ({args.before}, pulls1 of {len(old)} of these seeds):")
        summarise(sorted(old, key=lambda r: r["seed"]), log)
        log("after (this run):")
    summarise(recs, log)
    Path(args.log).parent.mkdir(parents=True, exist_ok=True)
    Path(args.log).write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
