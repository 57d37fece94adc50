"""The README's sample figures of this package against another commit's, pixel by pixel.

    python benchmarks/readme_figures_vs.py --before a4f7623

The README quotes, per sample (room light, floodlight) and system (nominal,
calibrated), the median point error over *all* points and the coverage.  When
a change adds points — usually the weaker ones at the edges of the lit region
— that median can rise while no point already there got worse.  This script
separates the two: it runs ``scripts/doc_figures.py``'s chain (calibrate from
the three walls with the shipped distances, process both recordings with the
nominal and the calibrated system) once with the package of ``--before`` (its
``mems_stereo`` extracted by ``git archive``) and once with this one, on the
same bundled samples, and prints per (sample, system):

* the README figures of both (points, coverage, median error within 6 m);
* the median error over the pixels both have a point at (like for like), and
  how many of those pixels got better / worse by more than 5 mm;
* the pixels only one of them has, with their median error.

The default ``--before`` (a4f7623) is the first commit on the bundled samples
as they are now (they were last re-simulated in 362d757).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).parent))
from _dense import PACKAGE_PRELUDE  # noqa: E402

CHILD = PACKAGE_PRELUDE + r"""
import numpy as np
import mems_stereo as ms
from mems_stereo.calib.calibrate import calibrate_system, read_target_distances
from mems_stereo.pipeline import process_recording
from mems_stereo.sim import load_scene
from mems_stereo.sim.score import true_ranges
from pathlib import Path
smp = Path(sys.argv[2])
walls = [str(smp / f"calib_{d}m.h5") for d in ("1.5", "2.5", "4.0")]
d, sd, kind = read_target_distances(smp / "calib_distances.json", walls)
cal = calibrate_system(walls, target_distances=d, distance_std=sd, distance_kind=kind)
scene = load_scene(smp / "room_scene.json")
out = {}
for name in ("room", "floodlight"):
    rec = ms.read_recording(smp / f"{name}.h5")
    illum = np.any(np.asarray(rec.truth["label"]) == 1, axis=0)
    for label, system in (("nominal", rec.system), ("calibrated", cal.system)):
        c = process_recording(rec, system=system).cloud
        rt = true_ranges(scene, c.points)
        out[f"{name}/{label}"] = {"row": np.asarray(c["row"]).tolist(),
                                  "pixel": np.asarray(c["pixel"]).tolist(),
                                  "range": np.asarray(c["range"]).tolist(),
                                  "r_true": [float(x) for x in rt],
                                  "illuminated": np.argwhere(illum).tolist()}
json.dump({"package": ms.__file__, "runs": out}, open(sys.argv[1], "w"))
"""


def extract_commit(ref: str, d: Path) -> Path:
    """The package ``mems_stereo`` of git commit ``ref`` extracted under ``d``, with
    ``calib/`` and ``viz/`` placed as ``mems_stereo.calib`` and ``mems_stereo.viz`` (as
    pyproject.toml's package-dir installs them; the samples are this checkout's)."""
    out = d / f"src-{ref}"
    out.mkdir()
    tar = subprocess.run(["git", "archive", ref, "mems_stereo", "calib", "viz"], cwd=ROOT,
                         check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(out)], input=tar, check=True)
    for sub in ("calib", "viz"):
        (out / sub).rename(out / "mems_stereo" / sub)
    return out


def run_package(src: Path | None, d: Path, tag: str) -> dict:
    """The child's per-point table for one package (``src`` None: this checkout's)."""
    env = dict(os.environ)
    if src is not None:
        env["BENCH_PACKAGE_SRC"] = str(src)
    out = d / f"{tag}.json"
    subprocess.run([sys.executable, "-c", CHILD, str(out), str(ROOT / "samples")], env=env,
                   check=True, cwd=d)
    return json.loads(out.read_text())


def per_pixel(run: dict, max_range: float = 6.0) -> tuple[dict, int, int, int]:
    """{(row, pixel): |error| m} over points whose true surface is within ``max_range``
    (a pixel with several points keeps the largest error), the number of points, of
    illuminated pixels with a point and of illuminated pixels."""
    illum = {tuple(p) for p in run["illuminated"]}
    err, covered = {}, set()
    for r, p, rng, rt in zip(run["row"], run["pixel"], run["range"], run["r_true"]):
        if (r, p) in illum:
            covered.add((r, p))
        if np.isfinite(rt) and rt <= max_range:
            err[(r, p)] = max(err.get((r, p), 0.0), abs(rng - rt))
    return err, len(run["row"]), len(covered), len(illum)


def med_cm(v) -> str:
    return f"{100 * np.median(v):.2f} cm" if len(v) else "—"


def compare(before: dict, after: dict, before_tag: str) -> list[str]:
    lines = []
    for key in after["runs"]:
        eb, nb, cb, ill = per_pixel(before["runs"][key])
        ea, na, ca, _ = per_pixel(after["runs"][key])
        common = sorted(set(eb) & set(ea))
        db = np.array([eb[k] for k in common])
        da = np.array([ea[k] for k in common])
        better = int(np.sum(da < db - 0.005))
        worse = int(np.sum(da > db + 0.005))
        only_b = [eb[k] for k in set(eb) - set(ea)]
        only_a = [ea[k] for k in set(ea) - set(eb)]  # (pixels listed below: column, |error|)
        lines += [
            f"{key}:",
            f"  README figures: {before_tag} {nb} points, coverage {cb}/{ill}, median "
            f"{med_cm(list(eb.values()))}  ->  this {na} points, coverage {ca}/{ill}, "
            f"median {med_cm(list(ea.values()))}",
            f"  like for like ({len(common)} pixels with a point in both): median "
            f"{med_cm(db)} -> {med_cm(da)}; better by > 5 mm at {better}, worse by > 5 mm "
            f"at {worse}",
            f"  only {before_tag}: {len(only_b)} pixels (median {med_cm(only_b)}); only this: "
            f"{len(only_a)} pixels (median {med_cm(only_a)})"]
        for tag, e, other in ((before_tag, eb, ea), ("this", ea, eb)):
            only = sorted(set(e) - set(other))
            if only:
                lines.append(f"    only {tag}: " + ", ".join(
                    f"{c} ({100 * e[(r, c)]:.1f} cm)" for r, c in only[:12]))
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--before", default="a4f7623", metavar="COMMIT")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        before = run_package(extract_commit(args.before, d), d, "before")
        after = run_package(None, d, "after")
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT,
                          capture_output=True, text=True).stdout.strip()
    print(f"# README sample figures: {args.before} ({before['package']}) vs this checkout "
          f"({head}, {after['package']})")
    print("\n".join(compare(before, after, args.before)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
