"""Importing a PTU file larger than memory: peak resident memory and throughput (issue 16).

Writes a Generic T2 PTU file of about --gigabytes GB block by block (a 48-pixel
line receiver at 20 kHz: one sync per shot, --photons photons per shot on
random pixels with random delays, the mirror monitor's edges on markers 1/2 at
2 × 1570 Hz), then imports it with ``mems-stereo import`` in a fresh
subprocess for each size in --sizes (fractions of the big file: the smaller
files are its first records), and prints wall time, records per second and
the peak resident memory (ru_maxrss) of the import.  Flat memory: the peak
does not grow with the file.  Also checks the imported recording against the
generator (shot count, first-photon codes of the first block).

Run:  .venv/bin/python benchmarks/bench_import.py [--gigabytes 2] [--dir /tmp]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from mems_stereo.io.ptu import MARKER, PHOTON, SYNC, encode_t2, ptu_header_bytes
from mems_stereo.model.system import burkard2022, save_system

W = 48
F_REP = 20000.0
TICKS_PER_BIN = 64


def system48():
    from dataclasses import replace

    s = burkard2022()
    K = np.array(s.receiver.camera_matrix, dtype=np.float64)
    K[0, 2] = (W - 1) / 2.0
    return s.replace(receiver=replace(s.receiver, image_size=(W, 1), camera_matrix=K))


def generate(path: Path, gigabytes: float, photons: int, seed: int = 16) -> dict:
    """Write the PTU file block by block; returns its facts (records, shots)."""
    s = system48()
    tick = s.tdc.bin_width / TICKS_PER_BIN
    period = int(round(1.0 / F_REP / tick))  # ticks per shot
    rng = np.random.default_rng(seed)
    target = int(gigabytes * 1e9 / 4)
    block_shots = 50_000
    n_rec = 0
    shot0 = 0
    prev_wrap = 0
    half_mech = 1.0 / (2 * s.scanner.f_mech) / tick
    with open(path, "wb") as f:
        f.write(ptu_header_bytes("T2", tick, tick, 0, F_REP))
        hdr_len = f.tell()
        while n_rec < target:
            k = np.arange(shot0, shot0 + block_shots, dtype=np.int64)
            st = k * period + 1000
            n_ph = rng.poisson(photons, block_shots)
            idx = np.repeat(np.arange(block_shots), n_ph)
            code = rng.integers(1, s.tdc.n_bins + 1, idx.size)
            pt = st[idx] + (code - 1) * TICKS_PER_BIN + rng.integers(0, TICKS_PER_BIN, idx.size)
            z0 = int(np.ceil(st[0] / half_mech))
            z1 = int(np.floor((st[-1] + period) / half_mech))
            zi = np.arange(z0, z1 + 1)
            zt = np.rint(zi * half_mech).astype(np.int64)
            zt = zt[(zt >= st[0]) & (zt < st[-1] + period)]
            t = np.concatenate([st, pt, zt])
            kind = np.concatenate([np.full(st.size, SYNC), np.full(pt.size, PHOTON),
                                   np.full(zt.size, MARKER)]).astype(np.int8)
            ch = np.concatenate([np.zeros(st.size, np.int64), rng.integers(0, W, pt.size),
                                 np.where(np.rint(zt / half_mech).astype(np.int64) % 2, 2, 1)])
            o = np.lexsort((kind != SYNC, t))
            rec = encode_t2(t[o], kind[o], ch[o], prev_wrap)
            prev_wrap = int(t[o][-1] // (1 << 25))
            f.write(rec.tobytes())
            n_rec += rec.size
            shot0 += block_shots
        f.seek(0)
        f.write(ptu_header_bytes("T2", tick, tick, n_rec, F_REP))
        assert f.tell() == hdr_len
    return {"records": n_rec, "shots": shot0, "bytes": path.stat().st_size}


def truncated(src: Path, dst: Path, n_records: int) -> None:
    """The first n_records records of src as a file of its own (header patched)."""
    import ptufile

    with ptufile.PtuFile(src) as p:
        tags = p.tags
        tick = float(tags["MeasDesc_GlobalResolution"])
    hdr = ptu_header_bytes("T2", tick, tick, n_records, F_REP)
    with open(src, "rb") as f, open(dst, "wb") as g:
        f.seek(len(hdr))
        g.write(hdr)
        left = n_records * 4
        while left:
            b = f.read(min(left, 1 << 26))
            g.write(b)
            left -= len(b)


CHILD = r"""
import json, resource, sys, time
from mems_stereo.cli import main
t0 = time.perf_counter()
rc = main(["import", sys.argv[1], "--map", sys.argv[2], "-o", sys.argv[3], "-q"])
dt = time.perf_counter() - t0
print(json.dumps({"rc": rc, "seconds": dt,
                  "maxrss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gigabytes", type=float, default=2.0)
    ap.add_argument("--sizes", type=float, nargs="+", default=[0.05, 0.25, 1.0],
                    help="fractions of the big file to import (default 0.05 0.25 1)")
    ap.add_argument("--photons", type=float, default=60.0, help="mean photons per shot")
    ap.add_argument("--dir", default="/tmp")
    ap.add_argument("--keep", action="store_true", help="keep the generated files")
    a = ap.parse_args(argv)
    d = Path(a.dir) / "mems_stereo_bench_import"
    d.mkdir(parents=True, exist_ok=True)
    big = d / "big.ptu"
    t0 = time.perf_counter()
    facts = generate(big, a.gigabytes, a.photons)
    print(f"generated {big}: {facts['bytes'] / 1e9:.2f} GB, {facts['records']} records, "
          f"{facts['shots']} shots in {time.perf_counter() - t0:.0f} s")
    s = system48()
    save_system(s, d / "system48.json")
    mp = {"format": "mems-stereo/tttr-map", "version": 1, "system": "system48.json",
          "pixels": [[i, i, 0] for i in range(W)],
          "zero_crossings": {"source": "marker", "rising_edge": 1, "falling_edge": 2},
          "tdc": {"binning": TICKS_PER_BIN}}
    (d / "map.json").write_text(json.dumps(mp))
    rows = []
    for frac in a.sizes:
        n = int(facts["records"] * frac)
        src = big if frac >= 1.0 else d / f"part_{frac:g}.ptu"
        if frac < 1.0:
            truncated(big, src, n)
        out = d / f"rec_{frac:g}.h5"
        r = subprocess.run([sys.executable, "-c", CHILD, str(src), str(d / "map.json"),
                            str(out)], capture_output=True, text=True)
        if r.returncode != 0:
            print(r.stdout, r.stderr)
            return 1
        res = json.loads(r.stdout.strip().splitlines()[-1])
        size_gb = src.stat().st_size / 1e9
        rows.append((size_gb, n, res["seconds"], res["maxrss_mb"]))
        print(f"import {size_gb:6.2f} GB ({n:>11d} records): {res['seconds']:7.1f} s, "
              f"{n / res['seconds'] / 1e6:6.2f} M records/s, peak RSS {res['maxrss_mb']:7.0f} MB")
        if frac < 1.0:
            src.unlink()
        if not a.keep:
            out.unlink(missing_ok=True)
    rss = [r[3] for r in rows]
    print(f"summary: file {rows[0][0]:.2f} → {rows[-1][0]:.2f} GB "
          f"({rows[-1][0] / rows[0][0]:.0f}×), peak RSS {min(rss):.0f} → {max(rss):.0f} MB "
          f"({max(rss) / min(rss):.2f}×): {'flat' if max(rss) < 1.3 * min(rss) else 'GROWS'}")
    if not a.keep:
        big.unlink()
    return 0


if __name__ == "__main__":
    sys.exit(main())
