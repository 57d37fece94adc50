"""The summary of ``bench_real_hardware.py``: every criterion of issue 30 with its
measured value and verdict, the error distributions, pulls and refusals (from the
trials' records, plain dicts)."""

from __future__ import annotations

import math
import os

import numpy as np
from _machine import cpu_model  # noqa: F401 - bench_real_hardware imports it from here

BANDS = ((0.0, 2.0), (2.0, 4.0), (4.0, math.inf))
PULL_LIMIT = 4.0


def q(x, ps=(10, 50, 90)) -> str:
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    if not x.size:
        return "n/a"
    return " ".join(f"p{p} {v:.3g}" for p, v in zip(ps, np.percentile(x, ps)))


def ok_word(ok) -> str:
    """PASS, FAIL, or N/A (None: nothing to judge)."""
    return "N/A" if ok is None else "PASS" if ok else "FAIL"


def trial_line(r) -> str:
    """One line per trial: hardware drawn, movement, calibration outcomes, medians."""
    im = r["imp"]
    hs = ",".join(f"{k}:{a * 100:.2f}%" for k, a in im["harmonics"]) or "-"
    cal = " ".join(f"{k.split()[0][:5]}/{k.split()[-1]}:" + ("ok" if v["ok"] else (
        "GOF(" + ",".join(v["named"]) + ")" if v["goodness"] else "refused"))
        for k, v in r["cal"].items())
    fl = r["flows"]
    med = " ".join(f"{k.split(',')[0][:5]}/{k.split()[-1]} {fl[k]['median'] * 100:.2f}"
                   for k in ("ideal hw, calib", "imperfect, calib full") if k in fl)
    return (f"seed {r['seed']}: {len(r['walls'])} walls, harm [{hs}] edges "
            f"{im['edges'][0] * 1e9:.0f}/{im['edges'][1] * 1e9:.0f} ns tail "
            f"{im['tail'][0] * 100:.0f}%/{im['tail'][1] * 1e9:.1f}ns pix "
            f"{im['pixels'] * 1e12:.0f}ps DNL {im['dnl'][0]:.2f}/{im['dnl'][1]:.3f} | M "
            f"{r.get('movement_p90', math.nan):.2f} (median {r['movement']:.2f}) | {cal} | "
            f"median cm {med}")


def summarise_flows(results, log) -> dict:
    """Criteria on the processed rooms: error ratio, d/σ per band, false points."""
    verdicts = {}
    flows = ("ideal hw, calib", "imperfect, calib full", "imperfect, exact full",
             "imperfect, exact geometry")
    log("point errors |range − true| (cm) and false points, per workflow, over the trials:")
    for f in flows:
        rows = [r["flows"][f] for r in results if f in r["flows"]]
        e = np.abs(np.concatenate([row["e"] for row in rows] or [np.zeros(0)])) * 100
        n = sum(row["n"] for row in rows)
        fa = sum(row["false"] for row in rows)
        per = [row["false"] / max(row["n"], 1) * 100 for row in rows]
        log(f"  {f:26s} trials {len(rows):3d} points {n:6d} |e| {q(e, (50, 68, 90, 95, 99))}; "
            f"false {fa / max(n, 1) * 100:.2f} % pooled, per trial {q(per, (50, 90, 100))} %, "
            f"trials > 1 %: {sum(p > 1 for p in per)}")
    both = [r for r in results if {"ideal hw, calib", "imperfect, calib full"} <= set(r["flows"])]
    ratio = [r["flows"]["imperfect, calib full"]["median"] / r["flows"]["ideal hw, calib"]["median"]
             for r in both]
    med_ratio = float(np.median(ratio)) if ratio else math.nan
    verdicts["median point error ≤ 1.3× ideal hw"] = (
        f"median over {len(ratio)} trials of median(imperfect, calib full) / median(ideal hw, "
        f"calib) = {med_ratio:.3f} (ratio {q(ratio)})", med_ratio <= 1.3)
    log(f"  per-trial median-error ratio imperfect/ideal: {q(ratio, (10, 25, 50, 75, 90))}")
    log("RMS d/σ per true-range band (false points left out):")
    band_ok, band_v = True, []
    for f in flows:
        d = np.concatenate([r["flows"][f]["d"] for r in results if f in r["flows"]] or [[]])
        rr = np.concatenate([r["flows"][f]["r"] for r in results if f in r["flows"]] or [[]])
        parts = []
        for lo, hi in BANDS:
            m = (rr >= lo) & (rr < hi)
            v = float(np.sqrt(np.mean(d[m] ** 2))) if m.any() else math.nan
            parts.append(f"{lo:g}–{hi:g} m: {v:.2f} (n {int(m.sum())})")
            if f == "imperfect, calib full":
                band_ok &= 0.7 <= v <= 1.4
                band_v.append(f"{v:.2f}")
        log(f"  {f:26s} " + "; ".join(parts))
    verdicts["RMS d/σ 0.7–1.4 in every band"] = (
        "imperfect, calib full: " + " / ".join(band_v) + " (<2 / 2–4 / >4 m)", band_ok)
    rows = [r["flows"]["imperfect, calib full"] for r in results
            if "imperfect, calib full" in r["flows"]]
    n = sum(row["n"] for row in rows)
    fa = sum(row["false"] for row in rows)
    per = [row["false"] / max(row["n"], 1) for row in rows]
    verdicts["false points ≤ 1 %"] = (
        f"imperfect, calib full: {fa / max(n, 1) * 100:.2f} % pooled ({fa}/{n}); trials over "
        f"1 %: {sum(p > 0.01 for p in per)}/{len(per)} (per-trial median "
        f"{np.median(per) * 100 if per else math.nan:.2f} %)", fa <= 0.01 * n)
    return verdicts


def pull_table(results, key: str, log) -> tuple:
    """Pulls per parameter of the written calibrations in ``key``: (parameters whose pull
    std is outside 0.7–1.4 over at least 5 fits, [(seed, worst |pull|)] beyond 4σ, the
    number of parameters fitted at least 5 times)."""
    pulls: dict = {}
    wrong = []
    for r in results:
        worst = 0.0
        for n, p in r[key].items():
            p = np.atleast_1d(np.asarray(p, float))
            pulls.setdefault(n, []).append(p)
            worst = max(worst, float(np.abs(p).max()) if p.size else 0.0)
        if worst > PULL_LIMIT:
            wrong.append((r["seed"], round(worst, 1)))
    bad = []
    judged = sum(len(ps) >= 5 for ps in pulls.values())
    for n, ps in pulls.items():
        p = np.concatenate(ps)
        sd = float(p.std()) if p.size > 1 else math.nan
        good = 0.7 <= sd <= 1.4 if len(ps) >= 5 else True
        if not good:
            bad.append(f"{n} {sd:.2f}")
        log(f"  {n:20s} fits {len(ps):3d} values {p.size:6d} mean {p.mean():+.2f} std {sd:.2f}"
            f" max |pull| {np.abs(p).max():.2f} over 4σ {int((np.abs(p) > PULL_LIMIT).sum())}"
            + ("" if len(ps) >= 5 else "  (too few fits to judge)") + ("" if good else "  <--"))
    return bad, wrong, judged


def pull_comparison(recs, before, log) -> None:
    """Pulls of the imperfect hardware's ``--model full`` calibrations in ``recs`` (full
    or ``--pulls-only`` trials); where ``before`` (an earlier run's records) has the
    same seeds, each parameter's pull std there and here over those seeds."""
    recs = sorted(recs, key=lambda r: r["seed"])
    seeds = [r["seed"] for r in recs]
    written = [r for r in recs if r["cal"]["imperfect full"]["ok"]]
    log(f"--- imperfect --model full over {len(recs)} trials (seeds "
        f"{', '.join(map(str, seeds))}): written {len(written)}")
    for r in recs:
        p = {k: v for k, v in r["pulls1"].items() if k != "pixel offsets"}
        worst = max(p, key=lambda k: abs(p[k])) if p else None
        log(f"  seed {r['seed']}: " + (f"fitted {', '.join(r['fitted']) or 'none'}; largest "
                                       f"pull {worst} {p[worst]:+.2f}" if worst else
                                       r["cal"]["imperfect full"]["reason"][:100]))
    bad, wrong, judged = pull_table(written, "pulls1", log)
    log(f"  pull std outside 0.7–1.4 (parameters fitted ≥ 5 times: {judged}): "
        f"{', '.join(bad) or 'none'}; results beyond {PULL_LIMIT:g}σ: {wrong or 'none'}")
    old = {r["seed"]: r for r in before if "pulls1" in r}
    both = [r for r in written if r["seed"] in old and old[r["seed"]]["cal"][
        "imperfect full"]["ok"]]
    if not both:
        return
    log(f"  before ({len(both)} seeds written in both runs): pull std per parameter "
        "before → after (fits), largest |pull| before → after")
    for n in sorted({k for r in both for k in r["pulls1"] if k != "pixel offsets"}):
        a = [old[r["seed"]]["pulls1"][n] for r in both if n in old[r["seed"]]["pulls1"]]
        b = [r["pulls1"][n] for r in both if n in r["pulls1"]]
        if a and b:
            log(f"    {n:20s} {np.std(a):.2f} → {np.std(b):.2f} ({len(a)} → {len(b)}), "
                f"{np.max(np.abs(a)):.2f} → {np.max(np.abs(b)):.2f}")
    moved = [r["seed"] for r in both if r["fitted"] != old[r["seed"]]["fitted"]]
    log(f"  terms fitted differ before and after in seeds {moved or 'none'}")


def summarise_calibration(results, log) -> dict:
    """Calibration outcomes, pulls, goodness-of-fit refusals, pulse mean delay."""
    v = {}
    log("calibration outcomes (written / refused by the goodness-of-fit test / refused "
        "otherwise):")
    for k in ("ideal hw ideal", "ideal hw full", "imperfect ideal", "imperfect full"):
        c = [r["cal"][k] for r in results]
        gof = sum(x["goodness"] for x in c)
        other = [x["reason"].split(":")[0][:50] for x in c if not x["ok"] and not x["goodness"]]
        top = ", ".join(f"{other.count(s)}× {s}" for s in dict.fromkeys(other))
        log(f"  {k:16s} written {sum(x['ok'] for x in c):3d}/{len(c)}  goodness {gof:3d}  "
            f"other {len(other):3d}" + (f" ({top})" if top else ""))
    for key, what in (("fitted0", "ideal"), ("fitted", "imperfect")):
        if not any(key in r for r in results):
            continue
        sel: dict = {}
        for r in results:
            for n in r.get(key, []):
                n = n.replace("_cos", "").replace("_sin", "")
                sel[n] = sel.get(n, 0) + 1
        log(f"  terms --model full selected on {what} hardware (trials): "
            + (", ".join(f"{k} {v // (2 if k.startswith('harmonic') else 1)}"
                         for k, v in sorted(sel.items())) or "none"))
    for key, what in (("pulls0", "ideal hardware, --model full"),
                      ("pulls1", "imperfect hardware, --model full")):
        log(f"pulls (estimate − truth)/σ, {what}:")
        bad, wrong, judged = pull_table(results, key, log)
        n_w = sum(bool(r[key]) for r in results)
        log(f"  written results with a parameter beyond {PULL_LIMIT:g}σ: {len(wrong)}/{n_w} "
            f"{wrong}")
        if key == "pulls1":
            v["calibration pull std 0.7–1.4 per parameter"] = (
                "outside: " + (", ".join(bad) or "none") + f" ({judged} parameters fitted ≥ 5 "
                "times)", None if not judged else not bad)
            v["no written result beyond 4σ"] = (f"{len(wrong)} of {n_w} written", not wrong)
    v.update(summarise_refusals(results, log))
    v.update(summarise_pulse(results, log))
    return v


#: the movement that defines "imperfections move points by more than 2σ" (records'
#: keys: the 90th percentile, the median and the RMS of |Δrange|/σ_r over matched points)
MOVEMENT = ("movement_p90", "90th percentile")
OTHER_MOVEMENTS = (("movement", "median"), ("movement_rms", "RMS"))


def summarise_refusals(results, log) -> dict:
    """``--model ideal``'s goodness-of-fit refusals against the trial's movement M."""
    v = {}
    key, word = MOVEMENT
    m = [r.get(key, math.nan) for r in results]
    moved = [r for r, x in zip(results, m) if x > 2]
    ref = [r for r in moved if r["cal"]["imperfect ideal"]["goodness"]
           and r["cal"]["imperfect ideal"]["named"]]
    any_ref = [r for r in moved if not r["cal"]["imperfect ideal"]["ok"]]
    frac = len(ref) / len(moved) if moved else math.nan
    log(f"movement M ({word} of |Δrange|/σ_r over the room's points, true full system vs "
        f"true geometry under the ideal model): {q(m, (10, 25, 50, 75, 90))}; M > 2 in "
        f"{len(moved)}/{len(results)} trials")
    for lo, hi in ((0, 1), (1, 2), (2, 3), (3, 5), (5, math.inf)):
        s = [r for r, x in zip(results, m) if lo <= x < hi]
        n_g = sum(r["cal"]["imperfect ideal"]["goodness"] for r in s)
        n_a = sum(not r["cal"]["imperfect ideal"]["ok"] for r in s)
        log(f"  M {lo:g}–{hi:g}: {len(s):3d} trials, --model ideal refused by the goodness test "
            f"{n_g}, refused in all {n_a}")
    for k, w in OTHER_MOVEMENTS:
        s = [r for r in results if r.get(k, math.nan) > 2]
        n_g = sum(r["cal"]["imperfect ideal"]["goodness"] and bool(r["cal"]["imperfect ideal"][
            "named"]) for r in s)
        log(f"  other definitions: {w} of |Δrange|/σ_r > 2 in {len(s)} trials "
            f"({q([r.get(k, math.nan) for r in results], (50, 90))}), refused naming the "
            f"effect {n_g}")
    for r in moved:
        if r not in ref:
            c = r["cal"]["imperfect ideal"]
            log(f"  not refused naming an effect: seed {r['seed']} (M {r[key]:.2f}): "
                + ("written" if c["ok"] else c["reason"][:110]))
    named: dict = {}
    for r in results:
        for e in r["cal"]["imperfect ideal"]["named"]:
            named[e] = named.get(e, 0) + 1
    log(f"  effects named by the refusals (imperfect, --model ideal): {named}")
    # walls that calibrate ideal hardware: its --model ideal fit written or refused by
    # the goodness test (the test ran); others cannot calibrate any hardware
    usable = [r for r in moved if r["cal"]["ideal hw ideal"]["ok"]
              or r["cal"]["ideal hw ideal"]["goodness"]]
    ref_u = [r for r in ref if r in usable]
    frac_u = len(ref_u) / len(usable) if usable else math.nan
    rest = [r for r in moved if r not in usable]
    log(f"  M > 2 trials whose walls calibrate ideal hardware (its --model ideal fit written "
        f"or refused by the goodness test): {len(usable)}/{len(moved)}; the others (seeds "
        f"{[r['seed'] for r in rest]}: not observable or no usable wall return on ideal "
        f"hardware too) are refused naming the effect on the imperfect walls in "
        f"{sum(r in ref for r in rest)}")
    v["--model ideal refuses ≥ 95 % of M > 2 trials whose walls calibrate ideal hardware, "
      "naming the effect"] = (
        f"{len(ref_u)}/{len(usable)} = {frac_u:.1%} (of all M > 2 trials: {len(ref)}/"
        f"{len(moved)} = {frac:.1%}; refused for any reason: {len(any_ref)})",
        None if not usable else frac_u >= 0.95)
    gof0 = sum(r["cal"]["ideal hw ideal"]["goodness"] for r in results)
    n0 = len(results) - sum(not r["cal"]["ideal hw ideal"]["ok"] and not r["cal"][
        "ideal hw ideal"]["goodness"] for r in results)
    v["goodness test refuses ≤ 2 % on ideal hardware"] = (
        f"{gof0}/{len(results)} trials = {gof0 / len(results):.2%} ({n0} fits reached the "
        "test)", gof0 <= 0.02 * len(results))
    return v


def summarise_pulse(results, log) -> dict:
    """The pulse's mean delay from the walls against the truth."""
    v = {}
    pl = [r["pulse"] for r in results if "pulse" in r]
    err = np.array([p["mean_delay"] - p["true"] for p in pl]) * 1e12
    sd = np.array([p["std"] for p in pl]) * 1e12
    within = int(np.sum(np.abs(err) <= 50)) if pl else 0
    src = {k: sum(p["source"] == k for p in pl) for k in ("written", "shape fit", "none")}
    log(f"pulse mean delay from the walls (imperfect, --model full, {len(pl)} written "
        f"calibrations; source {src}): error ps {q(err, (5, 25, 50, 75, 95))}; RMS "
        f"{np.sqrt(np.mean(err ** 2)) if pl else math.nan:.0f} ps; σ ps {q(sd, (10, 50, 90))};"
        f" pull std {np.nanstd(err / sd) if pl else math.nan:.2f}; |error| ≤ 50 ps in "
        f"{within}/{len(pl)}")
    for k in src:
        e = [e_ for e_, p in zip(err, pl) if p["source"] == k]
        if e:
            log(f"  {k:9s}: {len(e)} fits, |error| ps {q(np.abs(e), (50, 90, 100))}, within "
                f"50 ps {sum(abs(x) <= 50 for x in e)}")
    v["pulse mean delay within 50 ps (family trials)"] = (
        f"{within}/{len(pl)} calibrations within 50 ps (bar: ≥ 95 %; σ above)",
        within >= 0.95 * max(len(pl), 1))
    return v


def summarise_code_density(cds, log) -> dict:
    v = {}
    log("code-density test (dark recordings, one pixel group of 192 pixels, 4096 codes):")
    for t in sorted({c["target"] for c in cds}):
        s = [c for c in cds if c["target"] == t]
        rms = np.array([c["rms"] for c in s])
        log(f"  ≥ {t:5d} expected per code and group: {len(s)} TDCs, {s[0]['shots']} shots, "
            f"min counts {min(c['min_counts'] for c in s)}, median counts "
            f"{np.median([c['median_counts'] for c in s]):.0f}; width RMS error % "
            f"{q(rms * 100, (0, 50, 100))} (Poisson σ "
            f"{np.median([c['poisson'] for c in s]) * 100:.2f} %, true RMS DNL "
            f"{q([c['true_rms_dnl'] * 100 for c in s], (0, 100))} %, pull std "
            f"{np.median([c['pull_std'] for c in s]):.2f}); CPU {s[0]['cpu']:.1f} s each")
        v[f"code widths within 2 % RMS, ≥ {t} per code and group"] = (
            f"worst RMS {rms.max() * 100:.2f} % over {len(s)} TDCs (min counts "
            f"{min(c['min_counts'] for c in s)})", bool(rms.max() <= 0.02))
    return v


def report(results, cds, pts, args, log, wall: float) -> None:
    """Every criterion with its measured value and verdict, then the tables."""
    results = sorted(results, key=lambda r: r["seed"])
    for r in results:
        log(trial_line(r))
    n = len(results)
    log(f"--- summary over {n} trials (seeds {results[0]['seed']}..{results[-1]['seed']}), "
        f"wall shots / {results[0].get('shot_scale', args.shot_scale):g}, room "
        f"{results[0].get('room_shots', args.room_shots)} shots")
    keys = sorted({k for r in results for k in r["times"]})
    log("CPU time per trial by stage (s): " + "; ".join(
        f"{k} {np.mean([r['times'].get(k, 0.0) for r in results]):.1f}" for k in keys)
        + f"; total {np.mean([sum(r['times'].values()) for r in results]):.1f}")
    v = summarise_flows(results, log)
    v.update(summarise_calibration(results, log))
    if cds:
        v.update(summarise_code_density(cds, log))
    if pts:
        v.update(summarise_pulse_check(pts, log))
    log("--- criteria (issue 30), measured value, verdict")
    for k, (what, ok) in v.items():
        log(f"  [{ok_word(ok)}] {k}: {what}")
    log(f"trials {n}; wall time {wall:.0f} s with {args.jobs} job(s) on {os.cpu_count()} CPUs "
        f"({cpu_model()})")


def summarise_pulse_check(pts, log) -> dict:
    """The dedicated pulse checks (``pulse_trial``): mean delay against the truth."""
    ok = [p for p in pts if p.get("pulse")]
    err = np.array([p["pulse"]["mean_delay"] - p["pulse"]["true"] for p in ok]) * 1e12
    sd = np.array([p["pulse"]["std"] for p in ok]) * 1e12
    log(f"pulse checks ({len(pts)} × 3 walls at 0.3 photons per shot, "
        f"{pts[0]['shots']} shots each; tail only; fit started at the truth): written "
        f"{len(ok)}; sources {[p['pulse']['source'] for p in ok]}")
    for p, e, s_ in zip(ok, err, sd):
        pl = " ".join(f"{k} {v:+.2f}" for k, v in p.get("pulls", {}).items())
        log(f"  seed {p['seed']}: tail {p['tail'][0] * 100:.0f} % / {p['tail'][1] * 1e9:.1f} ns, "
            f"mean delay {p['pulse']['mean_delay'] * 1e12:.0f} ps (true "
            f"{p['pulse']['true'] * 1e12:.0f}), error {e:+.0f} ± {s_:.0f} ps; pulls {pl}; "
            f"CPU {p['cpu']:.0f} s")
    worst = float(np.max(np.abs(err))) if ok else math.nan
    big = float(np.max(sd)) if ok else math.nan
    return {"pulse mean delay within 50 ps (dedicated walls)": (
        f"worst |error| {worst:.0f} ps, largest σ {big:.0f} ps over {len(ok)} of {len(pts)} "
        f"checks (bar: both ≤ 50 ps; σ 50 ps needs ≈ {(big / 50) ** 2:.1f}× these returns)",
        bool(ok and len(ok) == len(pts) and worst <= 50 and big <= 50))}

