"""Digest of the package's outputs, to show that a change keeps them bit for bit.

Runs the command line (so it survives any change of the Python API) on the
bundled samples and a few generated cases, and hashes every array written:

* calibration of the bundled line-sensor walls (with the shipped distances);
* ``process`` of room.h5 and floodlight.h5 with the nominal and the calibrated
  system: cloud (PLY bytes), labels and histograms (every HDF5 dataset);
* the two-axis samples: calibration of the lissajous64 walls, ``process`` of
  lissajous64.h5 and raster128x96.h5 with their systems;
* a dense 6 MHz floodlight recording (``benchmarks/_dense.py``) of 30,000 shots:
  the recording and its cloud, in one process and split over 2 Dask workers;
* the scenario sweep's per-point dump (``benchmarks/bench_scenarios.py --dump``)
  over a few small cases.

``python scripts/output_digest.py -o digest.json`` writes the digest;
``--compare OLD.json`` prints every entry that differs and exits 1 if any does.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import h5py
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-c", "import sys; from mems_stereo.cli import main; sys.exit(main())"]
#: JSON keys whose values change from run to run (times, dates, versions, paths)
VOLATILE = ("time", "date", "elapsed", "version", "seconds", "created", "path", "file",
            "host", "machine", "source")


def _run(args, cwd):
    proc = subprocess.run(args, cwd=cwd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"failed ({proc.returncode}): {' '.join(map(str, args))}\n"
                         f"{proc.stderr[-2000:]}")
    return proc.stdout


def _hash_h5(path: Path) -> dict[str, str]:
    out = {}
    with h5py.File(path, "r") as f:
        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                a = np.asarray(obj[()])
                out[name] = hashlib.sha256(
                    str(a.dtype).encode() + str(a.shape).encode() + a.tobytes()).hexdigest()[:16]
        f.visititems(visit)
    return out


def _strip(obj):
    if isinstance(obj, dict):
        return {k: _strip(v) for k, v in obj.items()
                if not any(w in k.lower() for w in VOLATILE)}
    if isinstance(obj, list):
        return [_strip(v) for v in obj]
    return obj


def _hash_file(path: Path):
    if path.suffix in (".h5", ".hdf5"):
        return _hash_h5(path)
    if path.suffix == ".json":
        text = json.dumps(_strip(json.loads(path.read_text())), sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]
    return hashlib.sha256(path.read_bytes()).hexdigest()[:16]


def _samples(work: Path, digest: dict) -> None:
    s = work / "samples"
    _run([*CLI, "samples", "-o", str(s)], work)
    _run([*CLI, "calibrate", *(str(s / f"calib_{d}m.h5") for d in ("1.5", "2.5", "4.0")),
          "--target-distances-file", str(s / "calib_distances.json"),
          "-o", str(work / "cal.json")], work)
    digest["calibrated_system"] = _hash_file(work / "cal.json")
    for rec in ("room", "floodlight"):
        for tag, system in (("nominal", []), ("calibrated", ["--system", str(work / "cal.json")])):
            stem = work / f"{rec}_{tag}"
            _run([*CLI, "process", str(s / f"{rec}.h5"), *system, "-o", f"{stem}.ply",
                  "--labels", f"{stem}_labels.h5", "--histograms", f"{stem}_hist.h5"], work)
            for suffix in (".ply", "_labels.h5", "_hist.h5"):
                digest[f"{rec}_{tag}{suffix}"] = _hash_file(Path(f"{stem}{suffix}"))
    _run([*CLI, "calibrate", *(str(s / f"lissajous64_calib_{d}m.h5")
                               for d in ("1.5", "2.5", "4.0")),
          "-o", str(work / "cal2d.json")], work)
    digest["lissajous64_calibrated_system"] = _hash_file(work / "cal2d.json")
    for rec in ("lissajous64", "raster128x96"):
        out = work / f"{rec}.ply"
        _run([*CLI, "process", str(s / f"{rec}.h5"), "--system",
              str(s / f"{rec}_system.json"), "-o", str(out)], work)
        digest[f"{rec}.ply"] = _hash_file(out)


def _dense(work: Path, digest: dict, shots: int) -> None:
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from _dense import make_dense_recording

    rec = work / "dense.h5"
    make_dense_recording(rec, shots, seed=14)
    digest["dense_recording"] = _hash_h5(rec)
    _run([*CLI, "process", str(rec), "-o", str(work / "dense.ply")], work)
    digest["dense.ply"] = _hash_file(work / "dense.ply")
    code = ("import sys, numpy as np, hashlib\n"
            "from mems_stereo.pipeline.distributed import process_split\n"
            "import mems_stereo as ms\n"
            "r = process_split(sys.argv[1], scheduler='local', n_workers=2)\n"
            "print(hashlib.sha256(r.cloud.to_structured().tobytes()).hexdigest()[:16])\n"
            "r1 = ms.process_recording(sys.argv[1])\n"
            "print(hashlib.sha256(r1.cloud.to_structured().tobytes()).hexdigest()[:16])\n")
    lines = _run([sys.executable, "-c", code, str(rec)], work).split()
    digest["dense_split_2_workers"] = lines[-2]
    digest["dense_one_process"] = lines[-1]


def _sweep(work: Path, digest: dict, cases: int) -> None:
    dump = work / "sweep.npz"
    _run([sys.executable, str(ROOT / "benchmarks" / "bench_scenarios.py"), "--cases",
          str(cases), "--seed", "30000", "--scale", "0.1", "--ladder", "0",
          "--dump", str(dump)], work)
    with np.load(dump) as z:
        digest["sweep"] = {k: hashlib.sha256(z[k].tobytes()).hexdigest()[:16]
                           for k in sorted(z.files)}


def _flatten(d, prefix=""):
    for k, v in d.items():
        if isinstance(v, dict):
            yield from _flatten(v, f"{prefix}{k}/")
        else:
            yield f"{prefix}{k}", v


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-o", "--output", type=Path, help="write the digest here (JSON)")
    ap.add_argument("--compare", type=Path, help="a digest to compare with")
    ap.add_argument("--dense-shots", type=int, default=30_000)
    ap.add_argument("--sweep-cases", type=int, default=4)
    ap.add_argument("--only", nargs="+", choices=["samples", "dense", "sweep"],
                    default=["samples", "dense", "sweep"])
    args = ap.parse_args(argv)
    digest: dict = {}
    with tempfile.TemporaryDirectory() as td:
        work = Path(td)
        if "samples" in args.only:
            _samples(work, digest)
        if "dense" in args.only:
            _dense(work, digest, args.dense_shots)
        if "sweep" in args.only:
            _sweep(work, digest, args.sweep_cases)
    if args.output:
        args.output.write_text(json.dumps(digest, indent=1, sort_keys=True) + "\n")
    if args.compare:
        old = dict(_flatten(json.loads(args.compare.read_text())))
        new = dict(_flatten(digest))
        bad = [k for k in new if k in old and old[k] != new[k]]
        missing = [k for k in old if k not in new and k.split("/")[0] in
                   {n.split("/")[0] for n in new}]
        for k in bad:
            print(f"DIFFERS: {k}")
        for k in missing:
            print(f"MISSING: {k}")
        print(f"{len(new) - len(bad)} of {len(new)} entries identical")
        return 1 if bad or missing else 0
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
