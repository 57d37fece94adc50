"""Real hardware is not the ideal model: calibrate on walls, process a room, per workflow.

Each case draws imperfect hardware from a wide family (seeded): mirror harmonics of
orders 2–5 (each present with probability ½, amplitude up to 1 %), monitor edge delays
0–500 ns each, a pulse tail 0–40 % with decay 0.5–8 ns, per-pixel TDC offsets σ
0–300 ps, DNL with a periodic part up to ±0.3 LSB and a random part up to 0.05 LSB
(:class:`mems_stereo.sim.imperfections.Imperfections`), on top of the calibration
samples' true system.  The three calibration walls (1.5, 2.5, 4.0 m, measured
distances ±2 mm) and the room are simulated with the same seeds by ideal and by
imperfect hardware.  Workflows:

* ``ideal hw, exact``   — ideal hardware processed with the true system;
* ``ideal hw, calib``   — ideal hardware, calibrated (``--model full``: selects nothing);
* ``imperfect, exact geometry`` — imperfect hardware processed with the true geometry
  but the ideal hardware model;
* ``imperfect, calib ideal`` — calibrated with ``--model ideal`` (refused when the
  goodness-of-fit test fails: then ``--inflate-sigma``'s result is processed);
* ``imperfect, calib full`` — calibrated with ``--model full``;
* ``imperfect, exact full`` — processed with the true system with every member.

Printed and logged (``benchmarks/results/real_hardware.log``): per workflow the median
point error, RMS of (range − true)/σ_r, false points (farther than max(3σ_r, 10 cm)
from the true surface), coverage, calibration refusals; the hardware terms selected
and the pulls of the estimated parameters against the truth (edge delay compared as
the rising − falling difference, the phase offset with the falling delay's share,
the TDC offset with the pulse's mean delay).

Run: ``nice python benchmarks/bench_real_hardware.py --cases 3`` (about 3 min a case
on one core).
"""

from __future__ import annotations

import argparse
import math
import platform
import time
from pathlib import Path

import numpy as np
from mems_stereo.calib import calibrate_system

from mems_stereo.model.hardware import Harmonic
from mems_stereo.pipeline.run import process_recording
from mems_stereo.sim.imperfections import Imperfections
from mems_stereo.sim.scene import load_scene
from mems_stereo.sim.score import true_ranges
from mems_stereo.sim.simulate import simulate

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "samples"
WALLS = (("calib_1.5m_scene.json", 1.494), ("calib_2.5m_scene.json", 2.507),
         ("calib_4.0m_scene.json", 3.992))
FLOWS = ("ideal hw, exact", "ideal hw, calib", "imperfect, exact geometry",
         "imperfect, calib ideal", "imperfect, calib full", "imperfect, exact full")


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def draw(rng: np.random.Generator) -> Imperfections:
    """One imperfect hardware of the family (see the module)."""
    hs = tuple(Harmonic(k, float(rng.uniform(0.0, 0.01)), float(rng.uniform(-np.pi, np.pi)))
               for k in (2, 3, 4, 5) if rng.random() < 0.5)
    return Imperfections(hs, float(rng.uniform(0, 500e-9)), float(rng.uniform(0, 500e-9)),
                         float(rng.uniform(0, 0.4)), float(rng.uniform(0.5e-9, 8e-9)),
                         float(rng.uniform(0, 300e-12)), float(rng.uniform(0, 0.3)), 32,
                         float(rng.uniform(0, 0.05)))


def geometry_only(system):
    """``system`` without the hardware model's members (the ideal hardware model)."""
    from dataclasses import replace

    sc = replace(system.scanner, harmonics=(), monitor=None)
    return system.replace(scanner=sc, laser=replace(system.laser, pulse_shape=None),
                          tdc=replace(system.tdc, pixel_offsets=None, pixel_offsets_std=None,
                                      code_widths=None, code_widths_std=None))


def scores(res, scene) -> dict:
    """Median error, RMS error/σ_r, false points, coverage of a processed room."""
    c = res.cloud
    if not len(c):
        return {"median": math.nan, "rms_pull": math.nan, "false": math.nan, "coverage": 0.0}
    r_true = true_ranges(scene, c.points)
    e = c["range"] - r_true
    ok = np.isfinite(e)
    z = e[ok] / c["sigma_r"][ok]
    false = np.abs(e) > np.maximum(3 * c["sigma_r"], 0.1)
    good = ok & ~false
    return {"median": float(np.median(np.abs(e[ok]))),
            "rms_pull": float(np.sqrt(np.mean(z[~false[ok]] ** 2))) if good.any() else math.nan,
            "false": float(np.mean(false | ~ok)), "points": len(c)}


def simulate_all(true, nominal, seed: int, n_wall: int, n_room: int):
    walls = [simulate(nominal, load_scene(SAMPLES / s), n_wall,
                      rng=np.random.default_rng(seed * 10 + j), background_hz=1e5,
                      true_system=true) for j, (s, _) in enumerate(WALLS)]
    room = simulate(nominal, load_scene(SAMPLES / "room_scene.json"), n_room,
                    rng=np.random.default_rng(seed * 10 + 9), background_hz=1e5,
                    true_system=true)
    return walls, room


def equivalent_truth(true, name: str) -> float:
    """The true value of a fitted parameter in the fit's convention (falling delay held
    at 0: the rising − falling difference; the phase offset with the falling share; the
    TDC offset with the pulse's mean delay)."""
    mon = true.scanner.monitor
    if name == "edge_rising_delay":
        return 0.0 if mon is None else mon.rising_delay - mon.falling_delay
    if name == "tdc_offset":  # a Gaussian-pulse fit puts the pulse's mean delay there
        from mems_stereo.model.hardware import pulse_mean_delay

        return true.tdc.offset + pulse_mean_delay(true.laser)
    if name == "phase_offset" and mon is not None:
        return true.scanner.phase_offset + 2 * np.pi * true.scanner.f_mech * mon.falling_delay
    return true.get_param(name)


def calibrate(walls, nominal, model: str, inflate: bool = False):
    return calibrate_system(walls, nominal, target_distances=[d for _, d in WALLS],
                            distance_std=2e-3, model=model, inflate_sigma=inflate)


def run_case(i: int, seed: int, args, log) -> dict:
    from mems_stereo.model.system import load_system

    rng = np.random.default_rng(seed)
    nominal = load_system(SAMPLES / "nominal_system.json")
    true0 = load_system(SAMPLES / "calib_true_system.json")
    imp = draw(rng)
    true1 = imp.apply(true0, rng)
    room_scene = load_scene(SAMPLES / "room_scene.json")
    w0, room0 = simulate_all(true0, nominal, seed, args.wall_shots, args.room_shots)
    w1, room1 = simulate_all(true1, nominal, seed, args.wall_shots, args.room_shots)
    out, pulls = {}, []

    def proc(room, system):
        return scores(process_recording(room, system=system), room_scene)

    out["ideal hw, exact"] = proc(room0, true0)
    cal0 = calibrate(w0, nominal, "full")
    out["ideal hw, calib"] = proc(room0, cal0.system) if cal0 else {"refused": True}
    out["ideal hw, calib"]["refused"] = not cal0
    out["imperfect, exact geometry"] = proc(room1, geometry_only(true1))
    cal_i = calibrate(w1, nominal, "ideal")
    refused_ideal = not cal_i
    if refused_ideal:
        log(f"  ideal model refused: {cal_i.reason[:160]}")
        cal_i = calibrate(w1, nominal, "ideal", inflate=True)
    out["imperfect, calib ideal"] = proc(room1, cal_i.system) if cal_i else {}
    out["imperfect, calib ideal"]["refused"] = refused_ideal
    cal_f = calibrate(w1, nominal, "full")
    out["imperfect, calib full"] = proc(room1, cal_f.system) if cal_f else {"refused": True}
    out["imperfect, calib full"]["refused"] = not cal_f
    out["imperfect, exact full"] = proc(room1, true1)
    if cal_f:
        fitted = [n for n in cal_f.names if n.startswith(("harmonic", "edge"))]
        if cal_f.system.tdc.pixel_offsets is not None:
            fitted.append("pixel offsets")
        log(f"  full model fitted: {fitted or 'nothing'}")
        for n in cal_f.names:
            pulls.append((n, (cal_f.values[n] - equivalent_truth(true1, n)) / cal_f.std[n]))
    if not cal0:
        log(f"  ideal hardware refused: {cal0.reason[:160]}")
    log(f"case {i} seed {seed}: harmonics "
        f"{[(h.order, round(h.amplitude * 100, 2)) for h in imp.harmonics]} %, edges "
        f"{imp.rising_delay * 1e9:.0f}/{imp.falling_delay * 1e9:.0f} ns, tail "
        f"{imp.tail_fraction * 100:.0f} % {imp.tail_decay * 1e9:.1f} ns, pixels "
        f"{imp.pixel_offset_sigma * 1e12:.0f} ps, DNL {imp.dnl_periodic:.2f}/"
        f"{imp.dnl_random:.3f} LSB")
    for f in FLOWS:
        s = out[f]
        log(f"  {f:28s} median {s.get('median', math.nan) * 100:6.2f} cm  rms d/σ "
            f"{s.get('rms_pull', math.nan):5.2f}  false {s.get('false', math.nan) * 100:5.1f} %"
            f"  points {s.get('points', 0):4d}" + ("  REFUSED" if s.get("refused") else ""))
    return {"flows": out, "pulls": pulls}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=3)
    ap.add_argument("--seed", type=int, default=3000)
    ap.add_argument("--wall-shots", type=int, default=4000)
    ap.add_argument("--room-shots", type=int, default=800)
    ap.add_argument("--log", default=str(ROOT / "benchmarks" / "results" / "real_hardware.log"))
    args = ap.parse_args()
    lines: list[str] = []

    def log(s: str) -> None:
        print(s, flush=True)
        lines.append(s)

    log(f"bench_real_hardware: {args.cases} cases, seed {args.seed}, CPU {cpu_model()}")
    t0 = time.perf_counter()
    results = [run_case(i, args.seed + i, args, log) for i in range(args.cases)]
    log(f"--- summary over {args.cases} cases ({time.perf_counter() - t0:.0f} s)")
    for f in FLOWS:
        rows = [r["flows"][f] for r in results]
        med = np.array([r.get("median", math.nan) for r in rows])
        rp = np.array([r.get("rms_pull", math.nan) for r in rows])
        fa = np.array([r.get("false", math.nan) for r in rows])
        ref = sum(bool(r.get("refused")) for r in rows)
        log(f"{f:28s} median of medians {np.nanmedian(med) * 100:6.2f} cm, rms d/σ "
            f"{np.nanmedian(rp):5.2f}, false points {np.nanmedian(fa) * 100:5.1f} % "
            f"(worst {np.nanmax(fa) * 100:5.1f} %), refused {ref}/{len(rows)}")
    pulls: dict = {}
    for r in results:
        for n, p in r["pulls"]:
            pulls.setdefault(n, []).append(p)
    for n, ps in pulls.items():
        ps = np.array(ps)
        log(f"pull {n:20s} n {ps.size:3d}  mean {ps.mean():+.2f}  std "
            f"{ps.std() if ps.size > 1 else math.nan:.2f}  max |pull| {np.abs(ps).max():.2f}")
    Path(args.log).parent.mkdir(parents=True, exist_ok=True)
    Path(args.log).write_text("\n".join(lines) + "\n")
    print(f"wrote {args.log}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
