"""Monte-Carlo benchmark of calibration over the family of flat-wall recordings.

    OMP_NUM_THREADS=1 python benchmarks/bench_calibrate_mc.py --trials 100
    python benchmarks/bench_calibrate_mc.py --fast            # 12 trials, shots / 8
    python benchmarks/bench_calibrate_mc.py --trials 100 --shot-scale 1 --jobs 16

Each trial draws a random member of the family documented in
docs/calibration.md (:mod:`mems_stereo.calib.family`: 2–6 walls at 0.6–6 m,
yaw and pitch ±15°, 0.03–3 detected photons per shot, 2k–50k shots per wall,
10 kHz–6 MHz background, reflectivity 0.1–0.9, a true system within ±10 mrad
θ0, ±10 mm baseline x/z, ±3 ns offset, ±1 % amplitude, ±30 mrad phase lag),
simulates its recordings (:func:`mems_stereo.sim.simulate`, seeds from the trial
number) and calibrates them without and with the measured distances
(true optical-axis distance + N(0, 2 mm), σ = 2 mm).  ``--shot-scale F``
divides every wall's shot count by F (the run says so; F = 1 is the family).

A trial succeeds when the calibration is written (truthy result) and every
free parameter lies within 4 reported σ of the truth, or when it is refused
and the Fisher information at the true system agrees that a parameter is not
observable (:func:`mems_stereo.calib.fit.fisher_std` at the true system and
walls gives a σ above the limit of :data:`DEFAULT_MAX_STD` for some parameter).  Printed:
success rates, refusal fractions, error quantiles, pulls (error / σ) per
parameter with their standard deviation, the CPU and wall time per
calibration, and the cause of each failed trial (written but wrong; refused as
not observable with the σ at the truth within 20 % of its limit; walls missed
by the association; not converged; implausible).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
import warnings
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
import mems_stereo  # noqa: E402

try:  # an editable install maps calib/ to mems_stereo.calib; a bare checkout does not
    import mems_stereo.calib  # noqa: F401
except ImportError:
    mems_stereo.__path__.append(str(ROOT))

from mems_stereo.calib.association import wall_data  # noqa: E402
from mems_stereo.calib.family import FAMILY, draw_case, simulate_case  # noqa: E402
from mems_stereo.calib.fit import fisher_std, fit_walls  # noqa: E402
from mems_stereo.calib.model import PARAM_UNIT  # noqa: E402
from mems_stereo.calib.observability import DEFAULT_MAX_STD  # noqa: E402

from mems_stereo.model.system import burkard2022  # noqa: E402

PARAMS = ("theta0", "theta_mech_max", "phase_offset", "tdc_offset", "baseline_x", "baseline_z")
PULL_LIMIT = 4.0


def true_walls(case, true_system):
    """(T, 5) α, β, D, log μ, log s of the case's walls in the fit's parametrisation
    (a line sensor sees each wall's trace in the scan plane y = 0)."""
    out = np.zeros((len(case.walls), 5))
    for j, w in enumerate(case.walls):
        n = w.normal
        k = math.hypot(n[0], n[2])
        alpha = math.atan2(-n[0], -n[2])
        D = -n[2] * w.distance / k
        out[j] = [alpha, 0.0, D, math.log(w.flux), math.log(0.3)]
    return out


def run_trial(args):
    seed, shot_scale, fisher = args
    warnings.simplefilter("ignore")
    nom = burkard2022()
    case = draw_case(np.random.default_rng(seed), seed)
    true = case.true_system(nom)
    recs = simulate_case(case, nom, shot_scale=shot_scale)
    walls = [wall_data(r) for r in recs]
    truth = {n: true.get_param(n) for n in PARAMS}
    out = {"seed": seed, "walls": [(w.distance, w.flux, w.shots, w.background_hz)
                                   for w in case.walls]}
    for mode, priors in (("free", []), ("dist", [(j, "axis", d, FAMILY["distance_std"])
                                                 for j, d in enumerate(case.measured)])):
        t0, c0 = time.perf_counter(), time.process_time()
        r = fit_walls(walls, nom, priors=priors)
        dt, dc = time.perf_counter() - t0, time.process_time() - c0
        left = sum(1 for w in r.warnings if w.startswith("left out"))
        rec = {"time": dt, "cpu": dc, "ok": bool(r), "left_out": left}
        if r:
            rec["err"] = {n: r.values[n] - truth[n] for n in r.names if n in truth}
            rec["std"] = {n: r.std[n] for n in r.names if n in truth}
            rec["iterations"] = r.iterations
        else:
            rec["reason"] = r.reason
            rec["kind"] = r.kind
            if fisher:  # does the Fisher information at the truth agree?
                vals = {n: true.get_param(n) for n in PARAMS}
                st = fisher_std(walls, nom, vals, true_walls(case, true), priors)
                rec["truth_std"] = {n: st[n] for n in PARAMS}
                rec["truth_ratio"] = max(st[n] / DEFAULT_MAX_STD[n] for n in PARAMS)
                rec["truth_observable"] = all(st[n] <= DEFAULT_MAX_STD[n] for n in PARAMS)
        out[mode] = rec
    return out


def summarise(results, mode):
    n = len(results)
    ok = [r[mode] for r in results if r[mode]["ok"]]
    refused = [r[mode] for r in results if not r[mode]["ok"]]
    wrong = [r for r in ok if any(abs(r["err"][p]) > PULL_LIMIT * r["std"][p] for p in r["err"])]
    ref_ok = [r for r in refused if r.get("truth_observable") is False]
    observable = n - len(ref_ok)
    success = len(ok) - len(wrong) + len(ref_ok)
    lines = [f"[{mode}] trials {n}: written {len(ok)}, refused {len(refused)} "
             f"({len(refused) / n:.0%}; Fisher at the truth agrees for {len(ref_ok)}), "
             f"written but wrong by > {PULL_LIMIT:g}σ: {len(wrong)}",
             f"[{mode}] success {success}/{n} = {success / n:.1%}; where observable "
             f"{success - len(ref_ok)}/{observable} = "
             f"{(success - len(ref_ok)) / max(observable, 1):.1%}"]
    if ok:
        lines.append(f"[{mode}] {'param':<15}{'median|err|':>12}{'p90|err|':>11}{'max|err|':>11}"
                     f"{'med σ':>10}{'pull std':>10}{'pull MAD':>10}  unit")
        for p in PARAMS:
            e = np.array([r["err"][p] for r in ok if p in r["err"]])
            s = np.array([r["std"][p] for r in ok if p in r["std"]])
            if e.size == 0:
                continue
            f, unit = PARAM_UNIT[p]
            pull = e / s
            lines.append(f"[{mode}] {p:<15}{np.median(np.abs(e)) * f:>12.4g}"
                         f"{np.quantile(np.abs(e), 0.9) * f:>11.4g}{np.max(np.abs(e)) * f:>11.4g}"
                         f"{np.median(s) * f:>10.3g}{np.std(pull):>10.2f}"
                         f"{1.4826 * np.median(np.abs(pull - np.median(pull))):>10.2f}  {unit}")
    t = np.array([r[mode]["time"] for r in results])
    c = np.array([r[mode].get("cpu", np.nan) for r in results])
    lines.append(f"[{mode}] time per calibration: CPU median {np.median(c):.1f} s, "
                 f"p90 {np.quantile(c, 0.9):.1f} s, max {c.max():.1f} s; wall median "
                 f"{np.median(t):.1f} s, max {t.max():.1f} s")
    causes = {}
    if wrong:
        causes["written, wrong by > 4σ"] = len(wrong)
    for r in refused:
        if r.get("truth_observable") is not False:
            k = failure_cause(r)
            causes[k] = causes.get(k, 0) + 1
    for k, v in sorted(causes.items(), key=lambda kv: -kv[1]):
        lines.append(f"[{mode}]   failure {v}×: {k}")
    reasons = {}
    for r in refused:
        key = r["reason"].split(":")[0][:60]
        reasons[key] = reasons.get(key, 0) + 1
    for k, v in sorted(reasons.items(), key=lambda kv: -kv[1])[:6]:
        lines.append(f"[{mode}]   refused {v}×: {k}")
    return lines


def failure_cause(r) -> str:
    """Why a refusal that the Fisher information at the truth does not back failed."""
    reason = r["reason"]
    if reason.startswith("not observable") and r.get("truth_ratio", 0.0) > 0.8:
        return "refused as not observable, σ at the truth within 20 % of the limit"
    if r.get("left_out", 0) or "usable wall return" in reason:
        return (f"walls missed by the association ({reason.split(':')[0][:50]})")
    return reason.split("(")[0].split(":")[0][:60]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=100)
    ap.add_argument("--seed", type=int, default=1000, help="first trial's seed")
    ap.add_argument("--seeds", type=str, default=None,
                    help="comma-separated trial seeds to run instead of a range "
                         "(e.g. the failing seeds of a logged run)")
    ap.add_argument("--shot-scale", type=float, default=None,
                    help="divide each wall's shot count by this (default 1; --fast: 8)")
    ap.add_argument("--fast", action="store_true", help="12 trials, shots / 8")
    ap.add_argument("--jobs", type=int, default=1, help="worker processes")
    ap.add_argument("--no-fisher", action="store_true",
                    help="skip the Fisher check at the truth for refusals")
    ap.add_argument("--verbose", action="store_true", help="one line per trial")
    ap.add_argument("--records", type=str, default=None,
                    help="append each finished trial as a JSON line to this file")
    ap.add_argument("--summarise", type=str, default=None, metavar="RECORDS",
                    help="print the summary of a records file (e.g. of a run cut short) "
                         "and exit")
    args = ap.parse_args(argv)
    if args.summarise:
        results = [json.loads(line) for line in Path(args.summarise).read_text().splitlines()
                   if line.strip()]
        results.sort(key=lambda r: r["seed"])
        print(f"summary of {len(results)} trial records from {args.summarise}, seeds "
              f"{results[0]['seed']}..{results[-1]['seed']}")
        for mode in ("free", "dist"):
            for line in summarise(results, mode):
                print(line)
        return 0
    trials = 12 if args.fast and args.trials == 100 else args.trials
    seeds = ([int(x) for x in args.seeds.split(",") if x.strip()] if args.seeds
             else list(range(args.seed, args.seed + trials)))
    trials = len(seeds)
    scale = args.shot_scale if args.shot_scale is not None else (8.0 if args.fast else 1.0)
    span = (f"seeds {seeds[0]}..{seeds[-1]}" if seeds == list(range(seeds[0], seeds[0] + trials))
            else "seeds " + ",".join(map(str, seeds)))
    print(f"calibration Monte-Carlo: {trials} trials, {span}"
          + (f", shot counts divided by {scale:g} (REDUCED family: {FAMILY['shots'][0] / scale:.0f}"
             f"–{FAMILY['shots'][1] / scale:.0f} shots per wall)" if scale != 1 else
             ", full family shot counts"), flush=True)
    jobs = [(s, scale, not args.no_fisher) for s in seeds]
    t0 = time.perf_counter()
    results = []

    def done(r):
        results.append(r)
        _trial_line(r, args.verbose)
        if args.records:
            with open(args.records, "a", encoding="utf-8") as f:
                f.write(json.dumps(r, default=float) + "\n")

    if args.jobs > 1:
        with ProcessPoolExecutor(args.jobs) as ex:
            for r in ex.map(run_trial, jobs):
                done(r)
    else:
        for j in jobs:
            done(run_trial(j))
    for mode in ("free", "dist"):
        for line in summarise(results, mode):
            print(line)
    print(f"wall time {time.perf_counter() - t0:.0f} s ({os.cpu_count()} CPUs, "
          f"{args.jobs} job(s))")
    return 0


def _trial_line(r, verbose):
    if not verbose:
        return
    parts = []
    for mode in ("free", "dist"):
        m = r[mode]
        if m["ok"]:
            worst = max(abs(m["err"][p] / m["std"][p]) for p in m["err"])
            parts.append(f"{mode}: ok {m.get('cpu', m['time']):.1f}s CPU, "
                         f"{m.get('iterations', 0)} it, "
                         f"θ0 {m['err']['theta0'] * 1e3:+.3f} mrad "
                         f"off {m['err']['tdc_offset'] * 1e9:+.3f} ns max|pull| {worst:.1f}")
        else:
            parts.append(f"{mode}: refused (truth observable {m.get('truth_observable')}, "
                         f"σ/limit {m.get('truth_ratio', float('nan')):.2f}, "
                         f"{m.get('left_out', 0)} left out) {m['reason'][:90]}")
    w = " ".join(f"{d:.1f}m/{f:.2f}/{s}/{b / 1e6:.2g}M" for d, f, s, b in r["walls"])
    print(f"seed {r['seed']} [{w}]\n   " + "\n   ".join(parts), flush=True)


if __name__ == "__main__":
    sys.exit(main())
