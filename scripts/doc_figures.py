"""Regenerate the figures that README.md and docs/ quote, from the code and the bundled samples.

    python scripts/doc_figures.py            # rewrite the marked regions in place
    python scripts/doc_figures.py --check    # exit 1 if a region is out of date
    python scripts/doc_figures.py --print    # print the regions only

A region in a Markdown file is the text between ``<!-- figures: NAME -->`` and
``<!-- /figures -->``; this script owns it.  Everything is computed here, on
the bundled samples (:mod:`mems_stereo.data`): the calibration from the walls
(``calibrate_system`` with the shipped target distances), processing of the
room and floodlight recordings with the nominal system (the files' ``/system``)
and with the calibrated one, and the scores against the samples' truth
(:mod:`mems_stereo.sim.score`); the same for the two-axis ``lissajous64.h5``
with the system calibrated from its walls (docs/two_axis.md).  Run time is
measured on this machine.
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
REGION = re.compile(r"(<!-- figures: (\S+) -->\n)(.*?)(<!-- /figures -->)", re.S)


def _n(x: int) -> str:
    return f"{x:,}"


def _field(obj, name: str):
    """A field of a typed result (``Counts``, truth scores), or the item of a plain dict."""
    return obj[name] if isinstance(obj, dict) else getattr(obj, name)


def compute() -> dict:
    from mems_stereo.calib.calibrate import calibrate_system, read_target_distances

    import mems_stereo as ms
    from mems_stereo.cli.demo import calibration_gain
    from mems_stereo.pipeline import classify_recording, process_recording

    smp = ms.data.root()
    walls = [str(smp / f"calib_{d}m.h5") for d in ("1.5", "2.5", "4.0")]
    d, sd, kind = read_target_distances(smp / "calib_distances.json", walls)
    t0 = time.perf_counter()
    cal = calibrate_system(walls, target_distances=d, distance_std=sd, distance_kind=kind)
    t_cal = time.perf_counter() - t0
    true = ms.load_system(smp / "calib_true_system.json")
    out = {"t_cal": t_cal, "converged": cal.converged,
           "errors": {n: cal.system.get_param(n) - true.get_param(n)
                      for n in ("theta0", "baseline_x", "baseline_z", "tdc_offset",
                                "phase_offset")},
           "std": dict(zip(cal.names, cal.std)) if hasattr(cal, "names") else {},
           "gain": calibration_gain(smp, cal.system)}
    out["counts"] = {}
    for name in ("room", "floodlight"):
        rec = ms.read_recording(smp / f"{name}.h5")
        t = time.perf_counter()
        res = process_recording(rec, system=cal.system)
        t_proc = time.perf_counter() - t
        cl = classify_recording(rec, system=true)
        out["counts"][name] = {"process": res.counts, "truth": res.truth, "t": t_proc,
                               "classify_true": cl.counts, "classify_true_truth": cl.truth}
    out["gain2d"] = _two_axis_gain(smp)
    return out


def _two_axis_gain(smp: Path) -> list[dict]:
    """lissajous64.h5 with the nominal system and the one calibrated from its walls."""
    from mems_stereo.calib.twoaxis import calibrate_two_axis

    from mems_stereo.cli.demo import two_axis_calibration_gain

    cal = calibrate_two_axis([smp / f"lissajous64_calib_{d}m.h5" for d in ("1.5", "2.5", "4.0")])
    return two_axis_calibration_gain(smp, cal.system)[0]


def regions(f: dict) -> dict[str, str]:
    g = {(r["scene"], r["system"]): r for r in f["gain"]}
    c = f["counts"]
    lines = ["| | room light, nominal | room light, calibrated | floodlight, nominal | "
             "floodlight, calibrated |", "| --- | --- | --- | --- | --- |"]

    def row(title, fmt):
        cells = [fmt(g[s, k]) for s in ("room", "floodlight") for k in ("nominal", "calibrated")]
        lines.append(f"| {title} | " + " | ".join(cells) + " |")

    row("median point error, targets within 6 m", lambda r: f"{r['median_error'] * 100:.1f} cm")
    row("signal recall against the truth", lambda r: f"{r['recall']:.3f}")
    row("noise rejection against the truth", lambda r: f"{r['noise_rejection']:.3f}")
    row("illuminated pixels with a point (coverage)",
        lambda r: f"{r['coverage'] * 100:.0f} % ({r['covered']} / {r['illuminated']})")
    cr = {k: _field(c["room"]["process"], k) for k in ("raw", "signal", "shots")}
    cf = {k: _field(c["floodlight"]["process"], k) for k in ("raw", "signal", "shots")}
    e = f["errors"]
    headline = "\n".join(lines) + (
        f"\n\nRaw counts / classified signal / shots with the calibrated system: room "
        f"{_n(cr['raw'])} / {_n(cr['signal'])} / {_n(cr['shots'])}, floodlight "
        f"{_n(cf['raw'])} / {_n(cf['signal'])} / {_n(cf['shots'])}.  Calibration from the "
        f"three walls (with the shipped distances) took {f['t_cal']:.0f} s on this machine; "
        f"estimate − truth: θ0 {e['theta0'] * 1e3:+.3f} mrad, baseline x "
        f"{e['baseline_x'] * 1e3:+.2f} mm, baseline z {e['baseline_z'] * 1e3:+.2f} mm, TDC "
        f"offset {e['tdc_offset'] * 1e9:+.3f} ns, phase {e['phase_offset'] * 1e3:+.3f} mrad.\n")
    t = ["| sample | shots | raw detections | classified signal | recall | noise rejection |",
         "| --- | --- | --- | --- | --- | --- |"]
    for name, bg in (("room", "1e5 Hz/pixel"), ("floodlight", "6 MHz/pixel")):
        k, tr = c[name]["classify_true"], c[name]["classify_true_truth"]
        t.append(f"| {name} ({bg}) | {_n(_field(k, 'shots'))} | {_n(_field(k, 'raw'))} | "
                 f"{_n(_field(k, 'signal'))} | **{_field(tr, 'recall'):.4f}** | "
                 f"**{_field(tr, 'noise_rejection'):.4f}** |")
    classify = "\n".join(t) + "\n"
    cal_time = (f"The calibration of the bundled walls (3 × 4000 shots, with the shipped "
                f"distances) takes {f['t_cal']:.0f} s in one process on the machine that last "
                f"ran `scripts/doc_figures.py`.\n")
    return {"headline": headline, "classification": classify, "calibration-time": cal_time,
            "two-axis-gain": _two_axis_table(f["gain2d"])}


def _two_axis_table(gain: list[dict]) -> str:
    g = {r["system"]: r for r in gain}
    t = ["| `lissajous64.h5` | nominal system | calibrated from the walls |",
         "| --- | --- | --- |"]
    for title, fmt in (
            ("median point error, targets within 6 m",
             lambda r: f"{r['median_error'] * 100:.1f} cm"),
            ("signal recall against the truth", lambda r: f"{r['recall']:.3f}"),
            ("illuminated pixels with a point (coverage)",
             lambda r: f"{r['coverage'] * 100:.0f} % ({_n(r['covered'])} / "
                       f"{_n(r['illuminated'])})")):
        t.append(f"| {title} | {fmt(g['nominal'])} | {fmt(g['calibrated'])} |")
    return "\n".join(t) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    g = ap.add_mutually_exclusive_group()
    g.add_argument("--check", action="store_true", help="exit 1 if a region is out of date "
                   "(timings excepted)")
    g.add_argument("--print", action="store_true", help="print the regions, write nothing")
    args = ap.parse_args(argv)
    new = regions(compute())
    if args.print:
        for k, v in new.items():
            print(f"<!-- figures: {k} -->\n{v}<!-- /figures -->\n")
        return 0
    stale = []
    seen = set()
    for md in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        text = md.read_text()

        def repl(m, md=md):
            name = m.group(2)
            if name not in new:
                raise SystemExit(f"{md}: unknown figures region {name!r}")
            seen.add(name)
            if not _same(m.group(3), new[name]):
                stale.append(f"{md.relative_to(ROOT)}: {name}")
            return m.group(1) + new[name] + m.group(4)

        out = REGION.sub(repl, text)
        if not args.check and out != text:
            md.write_text(out)
    missing = set(new) - seen
    if missing:
        print(f"regions not found in any document: {sorted(missing)}", file=sys.stderr)
    if args.check:
        for s in stale:
            print(f"out of date: {s}")
        return 1 if stale or missing else 0
    print("updated: " + (", ".join(stale) if stale else "nothing (all current)"))
    return 0


def _same(a: str, b: str) -> bool:
    # timings differ from machine to machine: compare without the seconds
    strip = re.compile(r"\d+ s\b")
    return strip.sub("", a) == strip.sub("", b)


if __name__ == "__main__":
    sys.exit(main())
