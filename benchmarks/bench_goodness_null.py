"""The goodness-of-fit tests' null distribution on ideal hardware (issue 30).

    nice python benchmarks/bench_goodness_null.py --seed 1000 --trials 60 --cache DIR

Each trial is the ideal-hardware half of ``benchmarks/bench_real_hardware.py``'s trial
of the same seed (the calibration family's case, walls simulated by the case's true
system with wall shots / ``--shot-scale``, measured distances σ 2 mm) calibrated with
``--model ideal``: :func:`~mems_stereo.calib.fit.fit_walls`, then the goodness tests
(:func:`~mems_stereo.calib.goodness.judge` on a written fit,
:func:`~mems_stereo.calib.goodness.name_failure` on a refused one).  Under a correct
null every test's p-value is uniform (or larger: conservative); printed per test: the
count, the Kolmogorov–Smirnov distance to the uniform and its p-value, quantiles, and
how many fall below the per-test level ``ALPHA_FAMILY / N_TESTS``; then the trials the
goodness verdict refuses.  A refused fit's hardware score tests (what
``name_failure`` falls back on) are listed the same way.

``--cache DIR`` keeps each trial's fitted problem and x (pickle), ``--reanalyse DIR``
recomputes the p-values from them with the current code (seconds per trial instead
of the fit's ~10 s); ``--replicas K`` adds, for each cached trial, K replicas of its
cells drawn from the model at the fit (:mod:`mems_stereo.calib.goodness_null`: the
tests' null on that design without the fit's projection).

Log: ``benchmarks/results/goodness_null.log`` (``--log``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pickle
import sys
import time
import warnings
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
import numpy as np  # noqa: E402
from scipy import stats  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from _machine import cpu_model  # noqa: E402
from bench_real_hardware import simulate_walls  # noqa: E402
from mems_stereo.calib.family import draw_case  # noqa: E402
from mems_stereo.calib.goodness import (  # noqa: E402
    ALPHA_FAMILY,
    N_TESTS,
    calibration_goodness,
    failed_problem,
    score_test_results,
)

from mems_stereo.model.system import burkard2022  # noqa: E402

LEVEL = ALPHA_FAMILY / N_TESTS


def fit_trial(seed: int, shot_scale: float, imperfect: bool = False):
    """The ``--model ideal`` fit of a seed's walls: dict with ``seed``, ``ok``,
    ``kind`` (the failure's), ``reason`` and ``problem``/``x`` (the fitted problem,
    or the refused fit's re-centred one; None where there is none).  ``imperfect``:
    the walls of the trial's imperfect hardware instead, the nominal system carrying
    the code widths of its dark recording (as ``bench_real_hardware.run_trial``)."""
    from dataclasses import replace

    from bench_real_hardware import DARK_MIN_WIDTH, dark_code_widths, draw_imperfections
    from mems_stereo.calib.association import wall_data
    from mems_stereo.calib.fit import fit_walls

    from mems_stereo.model.tdc import code_centres

    nom = burkard2022()
    case = draw_case(np.random.default_rng(seed), seed)
    true = case.true_system(nom)
    if imperfect:
        imp = draw_imperfections(np.random.default_rng([seed, 30]))
        true = imp.apply(true, np.random.default_rng([seed, 31]))
        est, _ = dark_code_widths(nom, true, seed, 1000, DARK_MIN_WIDTH)
        nom = nom.replace(tdc=replace(nom.tdc, code_widths=est.width[0],
                                      code_widths_std=est.width_sigma[0]))
    wd = [wall_data(r) for r in simulate_walls(case, burkard2022(), true, shot_scale)]
    if nom.tdc.code_widths is not None:
        for w in wd:
            w.code_centres = code_centres(nom.tdc)
    priors = [(j, "axis", float(d), 2e-3) for j, d in enumerate(case.measured)]
    fit = fit_walls(wd, nom, priors=priors)
    if fit:
        prob, x = fit.extra["problem"], fit.extra["x"]
        return {"seed": seed, "ok": True, "kind": "", "reason": "", "problem": prob, "x": x}
    got = failed_problem(fit, wd, nom, priors)
    return {"seed": seed, "ok": False, "kind": fit.kind, "reason": fit.reason[:200],
            "problem": None if got is None else got[0], "x": None if got is None else got[1]}


def analyse(tr: dict) -> dict:
    """The p-values of a fitted (or re-centred refused) trial: the seven structure
    tests ("time: …", "column: …") and, for a refused fit, the hardware score tests
    ("score: …"); ``refused`` names the tests that fail (the verdict's)."""
    out = {k: tr[k] for k in ("seed", "ok", "kind", "reason")}
    out["p"], out["refused"] = {}, []
    if tr["problem"] is None:
        return out
    prob, x = tr["problem"], tr["x"]
    for part, rep in zip(("time", "column"), calibration_goodness(prob, x)):
        for f in rep.findings:
            out["p"][f"{part}: {f.name}"] = f.p_value
            if not f.passed:
                out["refused"].append(f"{part}: {f.name}")
    if not tr["ok"]:
        for t in score_test_results(prob, x):
            out["p"][f"score: {t.name}"] = t.p_value
            if t.selected and not out["refused"]:
                out["refused"].append(f"score: {t.name}")
    return out


def replica_pvalues(tr: dict, k: int, seed: int) -> dict:
    """p-values on ``k`` replicas of a trial's cells drawn from the model at its fit:
    the calibration's tests ("time: …", "column: …") and, for comparison, the time
    tests as F tests over the cells' own mean square ("F test: …": ``weights`` an
    array: a pixel or code with the information of 5 average cells its own group)."""
    from mems_stereo.calib.goodness import calibration_goodness, cell_residuals
    from mems_stereo.calib.goodness_null import resampled

    from mems_stereo.pipeline.goodness import structure_tests

    if tr["problem"] is None or k <= 0:
        return {}
    rng = np.random.default_rng([seed, 77])
    out: dict = {}
    for _ in range(k):
        prob = resampled(tr["problem"], tr["x"], rng)
        for part, rep in zip(("time", "column"), calibration_goodness(prob, tr["x"])):
            for f in rep.findings:
                out.setdefault(f"{part}: {f.name}", []).append(f.p_value)
        r = cell_residuals(prob, tr["x"])
        for f in structure_tests(r.time, phase=r.phase, pixel=r.pixel, code=r.code,
                                 signal=r.signal, weights=r.time_info).findings:
            out.setdefault(f"F test: {f.name}", []).append(f.p_value)
    return out


def run_one(task) -> dict:
    seed, opt = task
    warnings.simplefilter("ignore")
    t0 = time.process_time()
    cache = opt["cache"]
    path = None if cache is None else Path(cache) / f"trial{seed}.pkl"
    if path is not None and path.exists():
        tr = pickle.loads(path.read_bytes())
    else:
        try:
            tr = fit_trial(seed, opt["shot_scale"], opt["imperfect"])
        except Exception as e:  # noqa: BLE001 - a trial the package raised on: listed
            return {"seed": seed, "crash": f"{type(e).__name__}: {e}"[:300]}
        if path is not None:
            path.write_bytes(pickle.dumps(tr))
    out = analyse(tr)
    out["replicas"] = replica_pvalues(tr, opt["replicas"], seed)
    out["cpu"] = time.process_time() - t0
    return out


def uniformity(p) -> str:
    """KS distance to U(0, 1), its p-value, quantiles and the count below LEVEL."""
    p = np.asarray(p, float)
    if not p.size:
        return "none"
    ks = stats.kstest(p, "uniform")
    qs = " ".join(f"q{int(q * 100)} {v:.3f}" for q, v in
                  zip((0.01, 0.05, 0.1, 0.5), np.quantile(p, (0.01, 0.05, 0.1, 0.5))))
    low = int(np.sum(p < LEVEL))
    return (f"n {p.size:4d}  KS D {ks.statistic:.3f} (p {ks.pvalue:.2g})  {qs}  "
            f"below {LEVEL:.2g}: {low} (expected {p.size * LEVEL:.2g}); below 0.01: "
            f"{int(np.sum(p < 0.01))} (expected {p.size * 0.01:.2g})")


def summary(recs: list, log, hw: str = "ideal") -> None:
    fitted = [r for r in recs if r["ok"]]
    refused = [r for r in recs if not r["ok"]]
    log(f"trials {len(recs)}: fits written {len(fitted)}, refused by another check "
        f"{len(refused)} ({sum(bool(r['p']) for r in refused)} with residuals to test)")
    names = sorted({k for r in recs for k in r["p"]})
    log(f"p-values of each test (uniform under a correct null; level {LEVEL:.3g} = "
        f"{ALPHA_FAMILY:g} / {N_TESTS}):")
    for n in names:
        log(f"  {n:28s} {uniformity([r['p'][n] for r in recs if n in r['p']])}")
    pooled = [v for r in recs for k, v in r["p"].items() if not k.startswith("score")]
    log(f"  {'pooled structure tests':28s} {uniformity(pooled)}")
    bad = [r for r in recs if r["refused"]]
    log(f"goodness verdict refusing {hw} hardware: {len(bad)} / {len(recs)} trials "
        f"({100.0 * len(bad) / max(len(recs), 1):.1f} %)"
        + "".join(f"; seed {r['seed']}: {', '.join(r['refused'])}" for r in bad))
    reps = {}
    for r in recs:
        for k, v in r.get("replicas", {}).items():
            reps.setdefault(k, []).extend(v)
    if reps:
        log("replicas drawn from the model at each fit (no refit):")
        for k in sorted(reps):
            log(f"  {k:28s} {uniformity(reps[k])}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1000)
    ap.add_argument("--trials", type=int, default=60)
    ap.add_argument("--seeds", default=None, help="comma-separated seeds instead")
    ap.add_argument("--shot-scale", type=float, default=8.0)
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--cache", default=None, help="folder of the fitted trials (pickles)")
    ap.add_argument("--reanalyse", default=None, metavar="DIR",
                    help="analyse every cached trial of DIR (no fit)")
    ap.add_argument("--replicas", type=int, default=0)
    ap.add_argument("--imperfect", action="store_true",
                    help="the trials' imperfect hardware instead (the tests' power)")
    ap.add_argument("--records", default=None, help="append each trial as a JSON line")
    ap.add_argument("--summarise", default=None, metavar="RECORDS",
                    help="print the summary of a records file (e.g. of another commit) and exit")
    ap.add_argument("--log", default=str(ROOT / "benchmarks" / "results" / "goodness_null.log"))
    ap.add_argument("--note", default="")
    args = ap.parse_args(argv)
    lines: list = []

    def log(s: str) -> None:
        print(s, flush=True)
        lines.append(s)

    t0 = time.perf_counter()
    if args.summarise:
        recs = [json.loads(x) for x in Path(args.summarise).read_text().splitlines() if x]
        log(f"bench_goodness_null: summary of {len(recs)} trial records of {args.summarise}")
        if args.note:
            log(args.note)
        summary(recs, log, "imperfect" if args.imperfect else "ideal")
        Path(args.log).write_text("\n".join(lines) + "\n")
        return 0
    if args.reanalyse:
        args.cache = args.reanalyse
        seeds = sorted(int(p.stem[5:]) for p in Path(args.reanalyse).glob("trial*.pkl"))
    else:
        seeds = ([int(s) for s in args.seeds.split(",")] if args.seeds
                 else list(range(args.seed, args.seed + args.trials)))
        if args.cache:
            Path(args.cache).mkdir(parents=True, exist_ok=True)
    hw = "imperfect" if args.imperfect else "ideal"
    log(f"bench_goodness_null: {len(seeds)} trials (seeds {seeds[0]}–{seeds[-1]}), {hw} "
        f"hardware, --model ideal, wall shots / {args.shot_scale:g}, {args.replicas} "
        f"replicas each, CPU {cpu_model()}")
    if args.note:
        log(args.note)
    opt = {"shot_scale": args.shot_scale, "cache": args.cache, "replicas": args.replicas,
           "imperfect": args.imperfect}
    recs, crashes = [], []
    tasks = [(s, opt) for s in seeds]
    if args.jobs > 1:
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(args.jobs) as ex:
            results = ex.map(run_one, tasks)
            for r in results:
                _keep(r, recs, crashes, args.records)
    else:
        for t in tasks:
            _keep(run_one(t), recs, crashes, args.records)
    summary(recs, log, hw)
    log(f"trials that raised: {len(crashes)}"
        + "".join(f"; seed {c['seed']}: {c['crash']}" for c in crashes))
    cpu = [r["cpu"] for r in recs]
    log(f"CPU s per trial: median {np.median(cpu) if cpu else math.nan:.1f}; wall "
        f"{time.perf_counter() - t0:.0f} s")
    Path(args.log).parent.mkdir(parents=True, exist_ok=True)
    Path(args.log).write_text("\n".join(lines) + "\n")
    print(f"wrote {args.log}")
    return 0


def _keep(r, recs, crashes, path) -> None:
    if "crash" in r:
        crashes.append(r)
        print(f"seed {r['seed']} RAISED {r['crash']}", flush=True)
        return
    recs.append(r)
    low = {k: f"{v:.2g}" for k, v in r["p"].items() if v < 0.01}
    print(f"seed {r['seed']}: ok {r['ok']} {r['kind']} refused {r['refused']} p<0.01 {low} "
          f"({r['cpu']:.0f} s)", flush=True)
    if path:
        with open(path, "a", encoding="utf-8") as f:
            f.write(json.dumps(r) + "\n")


if __name__ == "__main__":
    raise SystemExit(main())
