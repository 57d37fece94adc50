"""CPU cost of the wall pose search and of a calibration, against a reference commit.

    nice python benchmarks/bench_wall_search.py --seeds 1000,1001 --reference 3bc1661

Inputs: the wall recordings of ``bench_real_hardware.py``'s trials (seed s, ideal and
imperfect hardware, ``--shot-scale``), their nominal system and measured distances.
The reference is ``calib/wall_search.py`` as of ``--reference`` (read with ``git
show``, loaded as its own module).  Per seed, alternating the order of old and new:

* every wall's pose search with the nominal system (what the start search does for a
  weak wall, :func:`mems_stereo.calib.track.find_wall`): CPU s old / new, and whether
  the results (tilt, offset, μ, z, threshold, poses, excess) are identical;
* ``fit_walls`` of the walls (the ideal model, as ``calibrate --model ideal``) with
  the reference's search patched in and with today's: CPU s each, and whether the
  fitted values are identical.

Prints the CPU model, per seed and in total, and writes ``--log``.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import subprocess
import sys
import time
import warnings
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import mems_stereo.calib.track as track  # noqa: E402
from bench_wall_refusals import inputs  # noqa: E402
from mems_stereo.calib import wall_search  # noqa: E402
from mems_stereo.calib.fit import fit_walls  # noqa: E402
from mems_stereo.calib.track import nominal_values  # noqa: E402
from real_hardware_summary import cpu_model  # noqa: E402

from mems_stereo.physics.pulse import pulse_sigma  # noqa: E402


def reference_module(commit: str):
    """``calib/wall_search.py`` of ``commit``, loaded as the module ``ref_wall_search``."""
    src = subprocess.run(["git", "show", f"{commit}:calib/wall_search.py"], cwd=ROOT,
                         check=True, capture_output=True, text=True).stdout
    path = Path(os.environ.get("TMPDIR", "/tmp")) / f"ref_wall_search_{commit}.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location("ref_wall_search", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["ref_wall_search"] = mod
    spec.loader.exec_module(mod)
    return mod


def cpu(fn):
    t0 = time.process_time()
    out = fn()
    return out, time.process_time() - t0


def same_fit(a, b) -> bool:
    if bool(a) != bool(b):
        return False
    if not a:
        return a.reason == b.reason
    return a.values == b.values and np.array_equal(a.planes, b.planes)


def one(seed: int, hardware: str, ref, args, k: int) -> tuple:
    """(lines, [search old, search new, fit old, fit new] CPU s, all identical)."""
    wd, nom, priors = inputs(seed, hardware, args.shot_scale, args.dark_per_code)
    sigma = pulse_sigma(nom.laser.pulse_fwhm, 50e-12)
    vals = nominal_values(nom)
    t = np.zeros(4)
    same = True
    for w in wd:
        runs = [(0, ref.search_pose), (1, wall_search.search_pose)]
        got = {}
        for i, fn in (runs if k % 2 == 0 else runs[::-1]):
            got[i], dt = cpu(lambda fn=fn, w=w: fn(w, nom, vals, sigma))
            t[i] += dt
        a, b = got[0], got[1]
        same &= (a is None and b is None) or (a is not None and b is not None and all(
            getattr(a, f) == getattr(b, f) for f in ("alpha", "dist", "mu", "z", "z_needed",
                                                      "n_poses", "excess")))
    fits = {}
    order = (2, 3) if k % 2 == 0 else (3, 2)
    for i in order:
        track.search_pose = ref.search_pose if i == 2 else wall_search.search_pose
        fits[i], t[i] = cpu(lambda: fit_walls(wd, nom, priors=priors))
    track.search_pose = wall_search.search_pose
    same_f = same_fit(fits[2], fits[3])
    line = (f"seed {seed} {hardware:9s} {len(wd)} walls: pose search CPU {t[0]:6.1f} -> "
            f"{t[1]:5.1f} s (identical {same}); fit_walls CPU {t[2]:6.1f} -> {t[3]:6.1f} s "
            f"(identical {same_f}, {'written' if fits[3] else 'refused'})")
    return [line], t, same and same_f


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="1000,1001,1002,1003")
    ap.add_argument("--hardware", default="ideal,imperfect")
    ap.add_argument("--reference", default="3bc1661", help="commit of the old search")
    ap.add_argument("--shot-scale", type=float, default=8.0)
    ap.add_argument("--dark-per-code", type=int, default=1000)
    ap.add_argument("--log", default=str(ROOT / "benchmarks" / "results" / "wall_search.log"))
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    ref = reference_module(args.reference)
    lines = [f"bench_wall_search: reference calib/wall_search.py of {args.reference}, wall "
             f"shots / {args.shot_scale:g}, CPU {cpu_model()} (OMP_NUM_THREADS=1)"]
    print(lines[0], flush=True)
    total = np.zeros(4)
    all_same = True
    k = 0
    for s in (int(x) for x in args.seeds.split(",") if x.strip()):
        for hw in args.hardware.split(","):
            got, t, same = one(s, hw, ref, args, k)
            k += 1
            total += t
            all_same &= same
            for x in got:
                print(x, flush=True)
            lines += got
    lines.append(f"total over {k} calibrations: pose search CPU {total[0]:.1f} -> {total[1]:.1f} s"
                 f" ({total[0] / max(total[1], 1e-9):.1f}x); fit_walls CPU {total[2]:.1f} -> "
                 f"{total[3]:.1f} s ({total[2] / max(total[3], 1e-9):.2f}x, "
                 f"{total[2] / k:.1f} -> {total[3] / k:.1f} s per calibration); "
                 f"results identical: {all_same}")
    print(lines[-1])
    Path(args.log).parent.mkdir(parents=True, exist_ok=True)
    Path(args.log).write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
