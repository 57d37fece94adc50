"""Regenerate every sample recording of samples/ bit for bit from its seed.

    python samples/make_samples.py              # all samples, into samples/
    python samples/make_samples.py --only room  # one of: room floodlight calib
    python samples/make_samples.py --out /tmp/s # elsewhere (tests compare two runs)
    python samples/make_samples.py --hardware imperfect
                                                # the imperfect_* set (imperfect hardware)

Every recording is made by :func:`mems_stereo.sim.simulate` with a
``numpy.random.default_rng(seed)``; the seeds, shot counts and backgrounds
are listed in ``SAMPLES`` below and in samples/README.md.  All of them are
recorded by one true system (nominal + ``CALIB_OFFSETS``, written as
calib_true_system.json) and carry the nominal system in ``/system``.

``--hardware imperfect`` writes the separate imperfect-hardware set
(``IMPERFECT_SAMPLES``: imperfect_room.h5, imperfect_calib_<d>m.h5, the same
scenes and seeds): recorded with the hardware model of ``docs/hardware.md``
added to the same true system (:data:`HARDWARE_SEED`,
``mems_stereo.sim.Imperfections.typical()``: 0.3 % third harmonic, edge delays
300 / 100 ns, a 20 % tail of 2 ns, 100 ps per-pixel offsets, DNL), as a real
prototype records them.  Its true system, which carries those members, is
written as imperfect_true_system.json, and the walls' measured distances (those
of calib_distances.json: the same walls) as imperfect_calib_distances.json.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mems_stereo.model.system import System, burkard2022, save_system
from mems_stereo.sim import (
    Imperfections,
    SimulationOptions,
    load_scene,
    simulate,
    write_simulation,
)

HERE = Path(__file__).resolve().parent

# the samples' true system: nominal + these offsets (SI units)
CALIB_OFFSETS = {
    "baseline_x": +0.004,  # m: mirror 4 mm closer to the receiver than nominal (-0.121 m)
    "baseline_z": -0.003,  # m
    "theta0": +0.004,  # rad
    "tdc_offset": 1.0e-9,  # s
    "phase_offset": 0.012,  # rad
}


#: seed of the imperfections' random parts (per-pixel offsets, DNL) for --hardware imperfect
HARDWARE_SEED = 30


@dataclass(frozen=True)
class Sample:
    name: str  # output file stem
    scene: str  # scene JSON in samples/
    seed: int
    n_shots: int
    background_hz: float
    true_system: str  # "calib" (calib_true_system.json; every shipped sample) or "nominal"
    drift: float = 0.0  # 1/s


SAMPLES = [
    Sample("room", "room_scene.json", 1, 800, 1e5, "calib", 1e-3),
    Sample("floodlight", "room_scene.json", 2, 3200, 6e6, "calib", 1e-3),
    Sample("calib_1.5m", "calib_1.5m_scene.json", 11, 4000, 1e5, "calib", 2e-3),
    Sample("calib_2.5m", "calib_2.5m_scene.json", 12, 4000, 1e5, "calib", -1e-3),
    Sample("calib_4.0m", "calib_4.0m_scene.json", 13, 4000, 1e5, "calib", 1.5e-3),
]

# the imperfect-hardware set: same scenes, seeds and drifts; fewer wall shots (size, and the
# demo calibrates them twice), twice the room's shots (a steadier median point error)
IMPERFECT_SAMPLES = [
    Sample("imperfect_room", "room_scene.json", 1, 1600, 1e5, "calib", 1e-3),
    Sample("imperfect_calib_1.5m", "calib_1.5m_scene.json", 11, 800, 1e5, "calib", 2e-3),
    Sample("imperfect_calib_2.5m", "calib_2.5m_scene.json", 12, 800, 1e5, "calib", -1e-3),
    Sample("imperfect_calib_4.0m", "calib_4.0m_scene.json", 13, 800, 1e5, "calib", 1.5e-3),
]


def nominal_system() -> System:
    """The system written into every sample: the paper's preset (W = 2.5 m)."""
    return burkard2022()


def calib_true_system() -> System:
    """The true system of the calibration samples (nominal + CALIB_OFFSETS)."""
    nom = nominal_system()
    params = {k: nom.get_param(k) + v for k, v in CALIB_OFFSETS.items()}
    return nom.with_params(**params)


def with_hardware(system: System, hardware: str) -> System:
    """``system`` as recorded by ``"ideal"`` hardware (itself) or ``"imperfect"``
    (``Imperfections.typical()`` drawn with :data:`HARDWARE_SEED`)."""
    if hardware == "ideal":
        return system
    return Imperfections.typical().apply(system, np.random.default_rng(HARDWARE_SEED))


def make_sample(s: Sample, out: Path, hardware: str = "ideal") -> Path:
    nominal = nominal_system()
    true = with_hardware(calib_true_system() if s.true_system == "calib" else nominal,
                         hardware)
    rec = simulate(nominal, load_scene(HERE / s.scene), s.n_shots,
                   rng=np.random.default_rng(s.seed), background_hz=s.background_hz,
                   true_system=true, options=SimulationOptions(drift=s.drift))
    path = write_simulation(out / f"{s.name}.h5", rec)
    path.chmod(0o644)  # atomic_output's temporary file is created 0600
    return path


def imperfect_distances(out: Path) -> Path:
    """Write imperfect_calib_distances.json: calib_distances.json's measurements (the same
    walls), matched to the imperfect_calib_<d>m.h5 recordings."""
    doc = json.loads((HERE / "calib_distances.json").read_text())
    for t in doc["targets"]:
        t["recording"] = "imperfect_" + t["recording"]
    path = out / "imperfect_calib_distances.json"
    path.write_text(json.dumps(doc, indent=2) + "\n")
    return path


def make_set(out: Path, hardware: str, only: str | None = None) -> list[Path]:
    """Write one set into ``out``: ``"ideal"`` (the bundled samples and their systems) or
    ``"imperfect"`` (the imperfect_* set, its true system and distances); the paths."""
    if hardware == "ideal":
        samples, systems = SAMPLES, (("nominal_system", nominal_system()),
                                     ("calib_true_system", calib_true_system()))
    else:
        samples = IMPERFECT_SAMPLES
        systems = (("imperfect_true_system", with_hardware(calib_true_system(), hardware)),)
    written = [save_system(system, out / f"{name}.json") for name, system in systems]
    if hardware != "ideal":
        written.append(imperfect_distances(out))
    for p in written:
        p.chmod(0o644)
    for s in samples:
        if only and not s.name.removeprefix("imperfect_").startswith(only):
            continue
        p = make_sample(s, out, hardware)
        print(f"{p}  ({p.stat().st_size / 1e6:.2f} MB, seed {s.seed}, {s.n_shots} shots, "
              f"{s.background_hz:g} Hz)")
        written.append(p)
    return written


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(HERE), help="output folder (default: samples/)")
    ap.add_argument("--only", choices=["room", "floodlight", "calib"], default=None)
    ap.add_argument("--hardware", choices=["ideal", "imperfect"], default="ideal",
                    help="the ideal-hardware samples (default) or the imperfect_* set, "
                         "recorded with typical imperfections (docs/hardware.md)")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    make_set(out, args.hardware, args.only)
    return 0


if __name__ == "__main__":
    sys.exit(main())
