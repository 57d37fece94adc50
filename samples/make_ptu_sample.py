"""Make the PicoQuant PTU sample (room48.ptu) from a simulated recording, bit for bit.

    python samples/make_ptu_sample.py             # into samples/
    python samples/make_ptu_sample.py --out DIR   # elsewhere

A 48-pixel line receiver (the paper's optics, cropped so that every pixel
has an input of a 64-channel time tagger) looks at ``room_scene.json``;
4000 shots are simulated with ``default_rng(48)`` and encoded as Generic T2
records (:func:`mems_stereo.io.ptu.recording_to_ptu`): the laser sync as the
shot clock, pixel i on input channel i, the mirror monitor's rising and
falling edges on markers 1 and 2, time tags of bin_width / 64.  Written:
``room48.ptu``, ``room48_map.json`` (the mapping), ``room48_system.json``
(the nominal system); tests/test_io_ptu.py re-simulates the recording from
the seed and checks that the sample imports to it.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from mems_stereo.io.ptu import recording_to_ptu
from mems_stereo.model.system import System, burkard2022, save_system
from mems_stereo.sim import load_scene, simulate

HERE = Path(__file__).resolve().parent
SEED, N_SHOTS, WIDTH = 48, 4000, 48


def room48_system() -> System:
    """The paper's system with a 48-pixel receiver centred on the optical axis."""
    s = burkard2022()
    K = np.array(s.receiver.camera_matrix, dtype=np.float64)
    K[0, 2] = (WIDTH - 1) / 2.0
    return s.replace(receiver=replace(s.receiver, image_size=(WIDTH, 1), camera_matrix=K))


def room48_recording():
    """The simulated recording the sample encodes (with truth)."""
    return simulate(room48_system(), load_scene(HERE / "room_scene.json"), N_SHOTS,
                    rng=np.random.default_rng(SEED))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(HERE))
    a = ap.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    rec = room48_recording()
    mapping = recording_to_ptu(rec, out / "room48.ptu", mode="T2")
    mapping["system"] = "room48_system.json"
    save_system(rec.system, out / "room48_system.json")
    text = re.sub(r"\[\s+(\d+),\s+(\d+),\s+(\d+)\s+\]", r"[\1, \2, \3]",
                  json.dumps(mapping, indent=1))
    (out / "room48_map.json").write_text(text + "\n")
    for n in ("room48.ptu", "room48_map.json", "room48_system.json"):
        (out / n).chmod(0o644)
        print(out / n, (out / n).stat().st_size, "bytes")
    return 0


if __name__ == "__main__":
    sys.exit(main())
