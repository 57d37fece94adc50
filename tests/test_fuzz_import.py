"""``mems-stereo import`` under hostile input (issue 15): PTU files cut short or with
flipped header bytes, channel maps with wrong types and values, Photon-HDF5 files
with wrong fields or unsafe links.  Every case: exit 2, one line naming the file,
no traceback, nothing created (the rules of tests/test_fuzz.py); flipped bytes in
the event records may also give a complete recording (exit 0).
"""

from __future__ import annotations

import json
import random
from pathlib import Path

import h5py
import numpy as np
import pytest
from fuzz_cases import external_link, rep
from test_fuzz import check_refused, run_cli

from mems_stereo.io.photon_hdf5 import write_photon_hdf5_events

SAMPLES = Path(__file__).resolve().parents[1] / "samples"
PTU = (SAMPLES / "room48.ptu").read_bytes()
MAP = json.loads((SAMPLES / "room48_map.json").read_text())
MAP["system"] = str(SAMPLES / "room48_system.json")
RNG = random.Random(48)
ARGV = ["import", "{d}/in.ptu", "--map", "{d}/map.json", "-o", "{d}/o.h5"]


def _flip(lo: int, hi: int, n: int) -> bytes:
    b = bytearray(PTU)
    for _ in range(n):
        j = RNG.randrange(lo, min(hi, len(b)))
        b[j] ^= 1 << RNG.randrange(8)
    return bytes(b)


PTU_CASES = [(f"cut-{c}", PTU[:c]) for c in (0, 8, 16, 100, 500, 1000, 3000, len(PTU) // 2)]
PTU_CASES += [(f"header-flip-{i}", _flip(0, 2000, RNG.randint(1, 6))) for i in range(12)]


def _map(fn):
    m = json.loads(json.dumps(MAP))
    fn(m)
    return m


MAP_CASES = [("list", [1, 2]),
             ("pixels-empty", _map(lambda m: m.__setitem__("pixels", []))),
             ("pixel-negative", _map(lambda m: m["pixels"].__setitem__(0, [0, -1, 0]))),
             ("pixel-outside", _map(lambda m: m["pixels"].__setitem__(0, [0, 9999, 0]))),
             ("pixel-twice", _map(lambda m: m["pixels"].__setitem__(1, m["pixels"][0]))),
             ("pixel-float", _map(lambda m: m["pixels"].__setitem__(0, [0.5, 0, 0]))),
             ("version-2", _map(lambda m: m.__setitem__("version", 2)))]
for key in ("shot_clock", "zero_crossings", "tdc", "shots", "photons", "time_origin"):
    for v in (-1, 1e300, "x", None, [1], True):
        if key == "time_origin" and v == -1:
            continue  # a valid shift of the time axis
        MAP_CASES.append((f"{key}={v!r}", _map(lambda m, k=key, v=v: m.__setitem__(k, v))))


def _write_ptu(data: bytes, m):
    def b(d: Path):
        (d / "in.ptu").write_bytes(data)
        (d / "map.json").write_text(json.dumps(m))
    return b


@pytest.mark.parametrize("name,data", PTU_CASES, ids=[c[0] for c in PTU_CASES])
def test_ptu_refused(name, data, tmp_path):
    _write_ptu(data, MAP)(tmp_path)
    rc, err, _ = run_cli([a.replace("{d}", str(tmp_path)) for a in ARGV])
    assert "Traceback" not in err and "internal error" not in err, err
    if rc == 0:  # the flips hit bytes that do not matter: a complete recording
        assert (tmp_path / "o.h5").is_file()
        return
    (tmp_path / "o.h5").unlink(missing_ok=True)
    check_refused(tmp_path, ARGV, "in.ptu")


@pytest.mark.parametrize("name,m", MAP_CASES, ids=[c[0] for c in MAP_CASES])
def test_map_refused(name, m, tmp_path):
    _write_ptu(PTU, m)(tmp_path)
    check_refused(tmp_path, ARGV, "map.json")


def _photon(d: Path, mutate=None):
    t = np.arange(0, 4000, 7, dtype=np.int64)
    write_photon_hdf5_events(d / "p.h5", t, (t % 5).astype(np.uint8), timestamps_unit=1e-9)
    (d / "map.json").write_text(json.dumps(MAP))
    if mutate is not None:
        with h5py.File(d / "p.h5", "r+") as f:
            mutate(f, d)


PH_CASES = [
    ("no-photon-data", lambda f, d: f.__delitem__("photon_data")),
    ("unit-string", rep("photon_data/timestamps_specs/timestamps_unit", "abc")),
    ("unit-nan", rep("photon_data/timestamps_specs/timestamps_unit", np.nan)),
    ("unit-zero", rep("photon_data/timestamps_specs/timestamps_unit", 0.0)),
    ("unit-array", rep("photon_data/timestamps_specs/timestamps_unit", np.ones(3))),
    ("timestamps-float", rep("photon_data/timestamps",
                              lambda f: f["photon_data/timestamps"][()].astype(float))),
    ("timestamps-2d", rep("photon_data/timestamps",
                           lambda f: f["photon_data/timestamps"][()][:570].reshape(57, 10))),
    ("detectors-short", rep("photon_data/detectors",
                             lambda f: f["photon_data/detectors"][()][:-1])),
    ("detectors-float", rep("photon_data/detectors",
                             lambda f: f["photon_data/detectors"][()].astype(float))),
    ("nanotimes-no-unit", lambda f, d: f.create_dataset(
        "photon_data/nanotimes", data=np.zeros(f["photon_data/timestamps"].shape, np.uint16))),
    ("timestamps-decreasing", rep("photon_data/timestamps",
                                   lambda f: f["photon_data/timestamps"][()][::-1].copy())),
    ("format-name", lambda f, d: f.attrs.__setitem__("format_name", "other")),
    ("external-link", external_link),
    ("soft-dangling", lambda f, d: f.__setitem__("y", h5py.SoftLink("/nowhere"))),
]


@pytest.mark.parametrize("name,mut", PH_CASES, ids=[c[0] for c in PH_CASES])
def test_photon_hdf5_refused(name, mut, tmp_path):
    _photon(tmp_path, mut)
    check_refused(tmp_path, ["import", "{d}/p.h5", "--map", "{d}/map.json", "-o", "{d}/o.h5"],
                  "p.h5")
