"""Code widths from the code-density test: the structured (empirical-Bayes) estimator
against the plain per-code one, over many TDCs of the issue-30 family.

    nice python benchmarks/bench_code_density.py --seeds 40 --targets 100,2500

Each seed s draws the family's DNL exactly as ``benchmarks/bench_real_hardware.py``'s
code-density check (periodic part up to ±0.3 LSB, period 32, random part up to
0.05 LSB; :class:`mems_stereo.sim.imperfections.Imperfections` from
``default_rng([s, 40])`` / ``default_rng([s, 41])``) on the 4096-code TDC of
:func:`mems_stereo.model.system.burkard2022`.  A dark recording of a pixel group is
drawn directly from its first-photon law: ``--pixels`` pixels (background rates 1/window
per pixel, ±20 % between pixels, one per LSB of mean width = 1/4096) fire at most once
per shot, so each pixel's first-photon codes are one multinomial over the codes and
"none" (probabilities ``exp(−r·e_{N−1}) − exp(−r·e_N)`` at the code edges ``e``), and its
armed shots follow from them.  The shot count is the smallest that gives every code at
least ``target`` detections in the group but by a 4σ chance (expectation λ with
λ − 4√λ = target in the narrowest late code).
``--simulate N`` also runs N seeds at the first target through the simulator (a dark
recording by :func:`mems_stereo.sim.simulate`, as ``bench_real_hardware.py`` makes it)
to check the direct draw.

Printed per target: width RMS error (structured / plain), its quantiles over seeds, the
share of TDCs within 2 % RMS, pull std of each estimator, the random part's τ against
its truth, and the Bayes bound ``τσ/√(τ² + σ²)`` (σ the Poisson RMS) that no
estimator using the codes' own counts beats for the random part.  Log:
``benchmarks/results/code_density.log``.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
import mems_stereo  # noqa: E402

try:  # an editable install maps calib/ to mems_stereo.calib; a bare checkout does not
    import mems_stereo.calib  # noqa: F401
except ImportError:
    mems_stereo.__path__.append(str(ROOT))

from _machine import cpu_model  # noqa: E402
from mems_stereo.calib.code_density import widths_from_tables  # noqa: E402

from mems_stereo.model.system import burkard2022  # noqa: E402
from mems_stereo.sim.imperfections import Imperfections  # noqa: E402


def family_tdc(seed: int):
    """(true widths (M,) mean 1, periodic amplitude, random amplitude) of seed's TDC."""
    from bench_real_hardware import draw_imperfections

    imp = draw_imperfections(np.random.default_rng([seed, 40]))
    true = Imperfections(dnl_periodic=imp.dnl_periodic, dnl_random=imp.dnl_random).apply(
        burkard2022(), np.random.default_rng([seed, 41]))
    w = np.asarray(true.tdc.code_widths, dtype=np.float64)
    return w / w.mean(), imp.dnl_periodic, imp.dnl_random


def dark_tables(widths, target: float, n_pix: int, rng):
    """Direct draw of a dark recording's first-photon tables (see the module):
    (events, at_risk) (P, M + 1), shots, expected counts per code (M,)."""
    M = widths.size
    rates = (1.0 / M) * rng.uniform(0.8, 1.2, n_pix)            # per LSB
    edges = np.concatenate([[0.0], np.cumsum(widths)])
    surv = np.exp(-rates[:, None] * edges[None, :])             # (P, M + 1)
    p = surv[:, :-1] - surv[:, 1:]                              # (P, M)
    lam = (2.0 + math.sqrt(4.0 + target)) ** 2     # λ − 4√λ = target
    shots = int(math.ceil(lam / p.sum(axis=0).min()))
    ev = np.zeros((n_pix, M + 1), dtype=np.int64)
    for i in range(n_pix):
        ev[i, 1:] = rng.multinomial(shots, np.append(p[i], surv[i, -1]))[:M]
    at_risk = np.zeros_like(ev)
    at_risk[:, 1:] = shots - np.cumsum(ev[:, :-1], axis=1)[:, :M]
    return ev, at_risk, shots, shots * p.sum(axis=0)


def simulated_tables(seed: int, target: float):
    """The bench's dark recording through the simulator: (events, at_risk), shots."""
    from bench_real_hardware import draw_imperfections
    from mems_stereo.calib.code_density import first_photon_tables
    from mems_stereo.calib.family import AnalyticWall

    from mems_stereo.sim import simulate

    nom = burkard2022()
    imp = draw_imperfections(np.random.default_rng([seed, 40]))
    true = Imperfections(dnl_periodic=imp.dnl_periodic, dnl_random=imp.dnl_random).apply(
        nom, np.random.default_rng([seed, 41]))
    w = np.asarray(true.tdc.code_widths, float)
    tdc = nom.tdc
    bg = 1.0 / (tdc.n_bins * tdc.bin_width)
    n_pix = nom.receiver.width * nom.receiver.height
    edges = np.concatenate([[0.0], np.cumsum(w / w.mean())]) / tdc.n_bins
    pmin = float(np.min(np.exp(-edges[:-1]) - np.exp(-edges[1:])))
    shots = int(math.ceil((2.0 + math.sqrt(4.0 + target)) ** 2 / (n_pix * pmin)))
    dark = AnalyticWall([0.0, 0.0, -10.0], [0.0, 0.0, 1.0], (0.1, 0.1), 0.5)
    rec = simulate(nom, dark, shots, rng=np.random.default_rng([seed, 42]), background_hz=bg,
                   true_system=true)
    codes = np.asarray(rec.bins).reshape(shots, -1)
    ev, ar = first_photon_tables(codes, tdc.n_bins)
    return ev, ar, shots


def score(ev, ar, w_true) -> dict:
    """Both estimators on one table: RMS errors, Poisson RMS σ, pull stds, τ."""
    out = {}
    for name, structured in (("structured", True), ("plain", False)):
        est = widths_from_tables(ev, ar, structured=structured)
        err = est.width[0] - w_true
        out[name] = float(np.sqrt(np.mean(err ** 2)))
        out[name + "_pull"] = float(np.std(err / est.width_sigma[0]))
        if structured:
            out["tau"] = float(est.random_rms[0])
        else:
            out["poisson"] = float(np.sqrt(np.mean(est.width_sigma[0] ** 2)))
            out["min_counts"] = int(est.counts.min())
            out["median_counts"] = float(np.median(est.counts))
    return out


def q(a, ps=(10, 50, 90)) -> str:
    return " ".join(f"p{p} {v:.2f}" for p, v in zip(ps, np.percentile(a, ps)))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=40)
    ap.add_argument("--seed", type=int, default=1000, help="first seed")
    ap.add_argument("--targets", default="100,2500",
                    help="fewest expected background detections per code and group")
    ap.add_argument("--pixels", type=int, default=192, help="pixels in the group")
    ap.add_argument("--simulate", type=int, default=2,
                    help="seeds also run through the simulator at the first target")
    ap.add_argument("--log", default=str(ROOT / "benchmarks" / "results" / "code_density.log"))
    args = ap.parse_args(argv)
    lines = []

    def log(s):
        print(s, flush=True)
        lines.append(s)

    log(f"code-density test, structured vs plain; seeds {args.seed}..{args.seed + args.seeds - 1}"
        f", {args.pixels} pixels in one group, 4096 codes; CPU {cpu_model()}")
    for target in [float(t) for t in args.targets.split(",")]:
        rows, t0 = [], time.process_time()
        for s in range(args.seed, args.seed + args.seeds):
            w, per, rnd = family_tdc(s)
            ev, ar, shots, _ = dark_tables(w, target, args.pixels, np.random.default_rng([s, 43]))
            r = score(ev, ar, w)
            r.update(seed=s, shots=shots, periodic=per, random=rnd)
            rows.append(r)
        cpu = (time.process_time() - t0) / len(rows)
        st = np.array([r["structured"] for r in rows]) * 100
        pl = np.array([r["plain"] for r in rows]) * 100
        sig = np.array([r["poisson"] for r in rows])
        rnd = np.array([r["random"] for r in rows])
        bound = rnd * sig / np.sqrt(rnd ** 2 + sig ** 2) * 100
        log(f"≥ {target:.0f} expected per code: shots {q([r['shots'] for r in rows], (0, 100))}"
            f", min counts {min(r['min_counts'] for r in rows)}, median counts "
            f"{np.median([r['median_counts'] for r in rows]):.0f}, Poisson σ "
            f"{np.median(sig) * 100:.2f} %")
        log(f"  width RMS error %  structured: {q(st, (0, 10, 50, 90, 100))}; within 2 %: "
            f"{int((st <= 2).sum())}/{len(st)}; pull std {q([r['structured_pull'] for r in rows])}")
        log(f"  width RMS error %  plain     : {q(pl, (0, 10, 50, 90, 100))}; within 2 %: "
            f"{int((pl <= 2).sum())}/{len(pl)}; pull std {q([r['plain_pull'] for r in rows])}")
        log(f"  structured / plain RMS: {q(st / pl)}; Bayes bound of the random part % "
            f"{q(bound, (0, 50, 100))}; structured − bound % {q(st - bound)}")
        tau = np.array([r["tau"] for r in rows])
        log(f"  τ estimated − true (random part RMS, LSB): {q((tau - rnd) * 100)} %; "
            f"CPU {cpu:.2f} s per TDC")
        for lo, hi in ((0.0, 0.02), (0.02, 0.035), (0.035, 0.06)):
            m = (rnd >= lo) & (rnd < hi)
            if m.any():
                log(f"    random part {lo * 100:.1f}–{hi * 100:.1f} %: {int(m.sum())} TDCs, "
                    f"structured RMS % {q(st[m], (50, 100))}, within 2 % {int((st[m] <= 2).sum())}"
                    f"/{int(m.sum())}, bound % {q(bound[m], (50, 100))}")
    first = float(args.targets.split(",")[0])
    for s in range(args.seed, args.seed + args.simulate):
        w, per, rnd = family_tdc(s)
        t0 = time.process_time()
        ev, ar, shots = simulated_tables(s, first)
        r = score(ev, ar, w)
        log(f"simulator, seed {s}, ≥ {first:.0f} per code ({shots} shots): RMS % structured "
            f"{r['structured'] * 100:.2f} (pull std {r['structured_pull']:.2f}), plain "
            f"{r['plain'] * 100:.2f} (pull std {r['plain_pull']:.2f}), min counts "
            f"{r['min_counts']}; CPU {time.process_time() - t0:.1f} s")
    Path(args.log).write_text("\n".join(lines) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
