"""How well the calibration family's walls determine the pulse's mean delay (issue 30).

    nice python benchmarks/bench_pulse_delay_family.py --seeds 1000-1009 --shot-scale 1

Per seed s: the walls of ``draw_case(default_rng(s))`` (the family of
``bench_real_hardware.py``: 2–6 walls, 0.03–3 photons per shot, 2k–50k shots, every
wall's shots divided by ``--shot-scale``) recorded by hardware with the family's pulse
tail only (``draw_imperfections(default_rng([s, 30]))``: share 0–40 %, decay
0.5–8 ns); the geometry is **held at the truth** (an oracle: what the walls' pulse
information allows, no geometric error; ``tdc_offset`` and the walls' signal and spot
fitted), then the mean delay w·τ from

* ``shape 0.3``: the report's shape fit (``calib/pulse_returns.py``: cells of at most
  0.3 signal photons, core σ free);
* ``core 0.3`` / ``core 3``: the same with the core σ held at the calibration's (as the
  likelihood holds it), cells up to 0.3 / 3 photons;
* ``pooled``: the tail fitted in the first-photon likelihood over all cells of all walls
  with ``tdc_offset`` (``fit_walls`` with ``pulse_tail_fraction``,
  ``pulse_tail_decay`` free, started at the true tail), σ from the fit.

and the Cramér–Rao bound of the low-pile-up returns the walls give (one return's
information of (shift, w, τ) with the core σ known, no background, times n).
Prints one line per seed and the error / σ distributions.
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
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from bench_calibrate_mc import true_walls  # noqa: E402
from bench_real_hardware import draw_case, draw_imperfections, simulate_walls  # noqa: E402
from real_hardware_summary import cpu_model  # noqa: E402

from mems_stereo.model.system import burkard2022  # noqa: E402

MODES = ("shape 0.3", "core 0.3", "core 3", "pooled")


def crb_one_return(w: float, tau: float, sigma: float) -> float:
    """σ (s) of w·τ from one low-pile-up return: the ex-gaussian's Fisher information of
    (shift, w, τ) with the core σ known, no background (numerical integral)."""
    from mems_stereo.physics.pulse import emg_pdf

    x = np.linspace(-10 * sigma, 10 * sigma + 20 * tau, 40001)

    def f(mu, ww, tt):
        g = np.exp(-0.5 * ((x - mu) / sigma) ** 2) / (sigma * math.sqrt(2 * math.pi))
        return (1 - ww) * g + ww * emg_pdf(x - mu, sigma, tt)

    p, h = np.array([0.0, w, tau]), np.array([1e-12, 1e-5, tau * 1e-4])
    D = []
    for i in range(3):
        e = np.zeros(3)
        e[i] = h[i]
        D.append((f(*(p + e)) - f(*(p - e))) / (2 * h[i]))
    D = np.array(D)
    info = (D[:, None, :] * D[None, :, :] / np.maximum(f(*p), 1e-300)).sum(-1) * (x[1] - x[0])
    g = np.array([0.0, tau, w])
    return float(math.sqrt(g @ np.linalg.inv(info) @ g))


def shape_fits(prob, x) -> dict:
    """The mean delay of the low-pile-up shape fits (see the module): mode → dict."""
    from mems_stereo.calib.pulse_returns import fit_return_shape, wall_return_residuals

    out = {}
    for mode, ms, core in (("shape 0.3", 0.3, None), ("core 0.3", 0.3, prob.sigma),
                           ("core 3", 3.0, prob.sigma)):
        res, _ = wall_return_residuals(prob, x, max_signal=ms)
        r = {"n": int(res.residual.size)}
        try:
            pf = fit_return_shape(replace(res, core=core))
            r.update(est=pf.mean_delay, sd=pf.std["mean_delay"])
        except Exception as ex:  # noqa: BLE001 — a failed fit is a result here
            r["fail"] = str(ex)[:80]
        out[mode] = r
    return out


def trial(task) -> dict:
    from mems_stereo.calib.association import wall_data
    from mems_stereo.calib.fit import fit_walls
    from mems_stereo.calib.model import PULSE_PARAMS
    from mems_stereo.calib.solver import StartValues

    from mems_stereo.model.hardware import pulse_mean_delay
    from mems_stereo.sim.imperfections import Imperfections

    seed, sc = task
    warnings.simplefilter("ignore")
    t0 = time.process_time()
    nom = burkard2022()
    case = draw_case(np.random.default_rng(seed), seed)
    true0 = case.true_system(nom)
    imp = draw_imperfections(np.random.default_rng([seed, 30]))
    true1 = Imperfections(tail_fraction=imp.tail_fraction, tail_decay=imp.tail_decay).apply(
        true0, np.random.default_rng([seed, 31]))
    md = pulse_mean_delay(true1.laser)
    priors = [(j, "axis", float(d), 2e-3) for j, d in enumerate(case.measured)]
    wd = [wall_data(r) for r in simulate_walls(case, nom, true1, sc)]
    fit = fit_walls(wd, true0, free=["tdc_offset"], priors=priors, on_unobservable="warn",
                    initial=({"tdc_offset": true0.tdc.offset + md}, true_walls(case, true0)))
    out = {"seed": seed, "w": imp.tail_fraction, "tau": imp.tail_decay, "md": md,
           "ok": bool(fit)}
    if not fit:
        out["reason"] = fit.reason[:100]
    else:
        prob, x = fit.extra["problem"], fit.extra["x"]
        out["fired"] = int(sum(np.isfinite(c.t).sum() for c in prob.cells))
        out["cr1"] = crb_one_return(imp.tail_fraction, imp.tail_decay, prob.sigma)
        out.update(shape_fits(prob, x))
        vals, walls = prob.layout.unpack(x)
        start = StartValues({"tdc_offset": true0.tdc.offset,
                             "pulse_tail_fraction": max(imp.tail_fraction, 0.02),
                             "pulse_tail_decay": imp.tail_decay}, walls)
        r1 = fit_walls(wd, true0, free=["tdc_offset", *PULSE_PARAMS], priors=priors,
                       initial=start, on_unobservable="warn")
        if r1:
            i, k = r1.names.index(PULSE_PARAMS[0]), r1.names.index(PULSE_PARAMS[1])
            w, tau = r1.values[PULSE_PARAMS[0]], r1.values[PULSE_PARAMS[1]]
            C = np.asarray(r1.covariance)[np.ix_([i, k], [i, k])]
            g = np.array([tau, w])
            out["pooled"] = {"n": out["fired"], "est": w * tau,
                             "sd": math.sqrt(max(float(g @ C @ g), 0.0))}
        else:
            out["pooled"] = {"fail": r1.reason[:80]}
    out["cpu"] = time.process_time() - t0
    return out


def summary(rows: list) -> list:
    lines = []
    for r in sorted(rows, key=lambda r: r["seed"]):
        s = (f"seed {r['seed']}: tail {r['w'] * 100:.0f} % / {r['tau'] * 1e9:.1f} ns, mean "
             f"delay {r['md'] * 1e12:.0f} ps, fired cells {r.get('fired', 0)}")
        for m in MODES:
            q = r.get(m, {})
            s += (f" | {m}: n {q['n']} err {(q['est'] - r['md']) * 1e12:+.0f} σ "
                  f"{q['sd'] * 1e12:.0f}" if "est" in q else f" | {m}: {q.get('fail', '-')}")
        if "cr1" in r and r.get("shape 0.3", {}).get("n"):
            n = r["shape 0.3"]["n"]
            s += (f" | Cramér–Rao for {n} low-pile-up returns {r['cr1'] / math.sqrt(n) * 1e12:.0f}"
                  f" ps; 50 ps needs {(r['cr1'] / 50e-12) ** 2:.1e}; cpu {r['cpu']:.0f} s")
        lines.append(s if r["ok"] else s.split(", fired")[0] + ": fit failed: " + r["reason"])
    for m in MODES:
        q = [(r[m]["est"] - r["md"], r[m]["sd"]) for r in rows if "est" in r.get(m, {})]
        if not q:
            continue
        e, sd = np.array(q).T
        lines.append(
            f"{m:9s}: {e.size} fits; |error| ps p50 {np.median(abs(e)) * 1e12:.0f} max "
            f"{abs(e).max() * 1e12:.0f}; σ ps p50 {np.median(sd) * 1e12:.0f} min "
            f"{sd.min() * 1e12:.0f}; pull RMS {np.sqrt(np.mean((e / sd) ** 2)):.2f}; "
            f"|error| ≤ 50 ps {int(np.sum(abs(e) <= 50e-12))}/{e.size}; σ ≤ 50 ps "
            f"{int(np.sum(sd <= 50e-12))}/{e.size}")
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="1000-1009", help="first-last (inclusive)")
    ap.add_argument("--shot-scale", type=float, default=1.0)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--records", help="JSON lines, one per seed")
    a = ap.parse_args(argv)
    lo, hi = (int(v) for v in a.seeds.split("-"))
    tasks = [(s, a.shot_scale) for s in range(lo, hi + 1)]
    print(f"bench_pulse_delay_family: seeds {lo}-{hi}, wall shots / {a.shot_scale:g}, "
          f"geometry held at the truth; CPU {cpu_model()}", flush=True)
    rows = []
    with ProcessPoolExecutor(a.jobs) as ex:
        for r in ex.map(trial, tasks):
            rows.append(r)
            if a.records:
                with open(a.records, "a") as fh:
                    fh.write(json.dumps(r, default=float) + "\n")
    print("\n".join(summary(rows)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
