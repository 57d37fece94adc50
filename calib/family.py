"""The family of flat-wall calibration recordings the calibration is proven on.

:func:`draw_case` draws one random member (walls, photon flux, background,
shot counts and a true system near the nominal one); :func:`simulate_case`
simulates its recordings with :func:`mems_stereo.sim.simulate`.  The Monte-Carlo
benchmark (``benchmarks/bench_calibrate_mc.py``) and the tests use it; the
family is documented in ``docs/calibration.md``.

Family, every draw independent and uniform unless said otherwise:

* 2–6 walls, one recording each; distance along the optical axis 0.6–6 m
  (log-uniform); yaw (about the camera's y axis) and pitch (about x) within ±15°;
  Lambertian reflectivity 0.1–0.9; 10 m × 3 m (the scan never leaves them);
* detected signal photons per shot at the wall centre (the whole spot) 0.03–3
  (log-uniform; the laser's peak power is scaled to give it);
* shots per wall 2,000–50,000 (log-uniform), divided by ``shot_scale`` where a
  caller asks for a reduced run (the benchmark says so when it does);
* background 10 kHz–6 MHz per pixel (log-uniform, one rate per wall);
* true system: nominal + θ0 ±10 mrad, baseline x and z ±10 mm, TDC offset ±3 ns,
  scan amplitude ±1 %, phase lag of the monitor ±30 mrad;
* measured distances (when used): the true optical-axis distance + N(0, 2 mm),
  given with σ = 2 mm.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from mems_stereo.model.system import System

FAMILY = {
    "n_walls": (2, 6),
    "distance_m": (0.6, 6.0),
    "yaw_deg": 15.0,
    "pitch_deg": 15.0,
    "reflectivity": (0.1, 0.9),
    "flux": (0.03, 3.0),
    "shots": (2000, 50000),
    "background_hz": (1e4, 6e6),
    "theta0": 10e-3,
    "baseline": 10e-3,
    "tdc_offset": 3e-9,
    "amplitude_rel": 0.01,
    "phase_offset": 30e-3,
    "distance_std": 2e-3,
}


@dataclass
class Wall:
    distance: float  # m along the optical axis
    yaw: float  # rad about y
    pitch: float  # rad about x
    reflectivity: float
    flux: float  # detected photons per shot at the wall centre
    shots: int
    background_hz: float

    @property
    def normal(self) -> np.ndarray:
        """Unit normal facing the camera, camera frame."""
        n = np.array([math.sin(self.yaw) * math.cos(self.pitch), math.sin(self.pitch),
                      -math.cos(self.yaw) * math.cos(self.pitch)])
        return n / np.linalg.norm(n)


@dataclass
class Case:
    walls: list
    true_offsets: dict
    seed: int
    measured: list = field(default_factory=list)  # measured axis distances, m

    def true_system(self, nominal: System) -> System:
        vals = {k: nominal.get_param(k) + v for k, v in self.true_offsets.items()
                if k != "theta_mech_max_rel"}
        vals["theta_mech_max"] = nominal.get_param("theta_mech_max") * (
            1.0 + self.true_offsets.get("theta_mech_max_rel", 0.0))
        return nominal.with_params(**vals)


def _logu(rng, lo, hi):
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def draw_case(rng: np.random.Generator, seed: int = 0, n_walls=None) -> Case:
    """One random member of :data:`FAMILY`."""
    F = FAMILY
    nw = int(rng.integers(F["n_walls"][0], F["n_walls"][1] + 1)) if n_walls is None \
        else int(n_walls)
    walls = []
    for _ in range(nw):
        walls.append(Wall(
            distance=_logu(rng, *F["distance_m"]),
            yaw=math.radians(rng.uniform(-F["yaw_deg"], F["yaw_deg"])),
            pitch=math.radians(rng.uniform(-F["pitch_deg"], F["pitch_deg"])),
            reflectivity=float(rng.uniform(*F["reflectivity"])),
            flux=_logu(rng, *F["flux"]),
            shots=int(round(_logu(rng, *F["shots"]))),
            background_hz=_logu(rng, *F["background_hz"])))
    off = {"theta0": rng.uniform(-1, 1) * F["theta0"],
           "baseline_x": rng.uniform(-1, 1) * F["baseline"],
           "baseline_z": rng.uniform(-1, 1) * F["baseline"],
           "tdc_offset": rng.uniform(-1, 1) * F["tdc_offset"],
           "theta_mech_max_rel": rng.uniform(-1, 1) * F["amplitude_rel"],
           "phase_offset": rng.uniform(-1, 1) * F["phase_offset"]}
    off = {k: float(v) for k, v in off.items()}
    measured = [w.distance + float(rng.normal(0.0, F["distance_std"])) for w in walls]
    return Case(walls, off, seed, measured)


class AnalyticWall:
    """A flat rectangular wall with :class:`~mems_stereo.sim.scene.Scene`'s ``cast``
    and ``reflectivity`` (exact ray–plane intersection in float64, no Open3D):
    what :func:`mems_stereo.sim.simulate` needs of a one-wall scene."""

    def __init__(self, center, normal, size, reflectivity: float, up=(0.0, -1.0, 0.0)):
        self.center = np.asarray(center, dtype=np.float64)
        n = np.asarray(normal, dtype=np.float64)
        self.normal = n / np.linalg.norm(n)
        up = np.asarray(up, dtype=np.float64)
        e1 = np.cross(up, self.normal)
        self.e1 = e1 / np.linalg.norm(e1)
        self.e2 = np.cross(self.normal, self.e1)
        self.half = 0.5 * np.asarray(size, dtype=np.float64)
        self._refl = float(reflectivity)
        self.objects = [self]
        self.name = "wall"
        self.params: dict = {}  # a scene object's parameters: no velocity, it stands still

    @property
    def reflectivity(self) -> np.ndarray:
        return np.array([self._refl])

    def cast(self, origins, directions):
        from mems_stereo.sim.scene import RayHits

        d = np.atleast_2d(np.asarray(directions, dtype=np.float64))
        o = np.broadcast_to(np.asarray(origins, dtype=np.float64), d.shape)
        nd = d @ self.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((self.center - o) @ self.normal) / nd
        p = o + t[:, None] * d
        q = p - self.center
        hit = (np.isfinite(t) & (t > 0) & (np.abs(q @ self.e1) <= self.half[0])
               & (np.abs(q @ self.e2) <= self.half[1]))
        t = np.where(hit, t, np.inf)
        pts = np.where(hit[:, None], p, np.nan)
        nrm = np.where(hit[:, None], np.where((nd > 0)[:, None], -self.normal, self.normal),
                       np.nan)
        return RayHits(t, pts, nrm, np.where(hit, 0, -1).astype(np.int64))


def wall_scene(wall: Wall, size=(10.0, 3.0)) -> AnalyticWall:
    """The scene of one wall (centre on the optical axis), :class:`AnalyticWall`."""
    return AnalyticWall([0.0, 0.0, wall.distance], wall.normal, size, wall.reflectivity)


def link_for_flux(system: System, wall: Wall):
    """A :class:`~mems_stereo.physics.link_budget.LinkBudget` whose peak power gives
    ``wall.flux`` detected photons per shot at the wall's centre."""
    from mems_stereo.physics.link_budget import (
        LinkBudget,
        emitted_photons,
        expected_signal_photons,
    )
    from mems_stereo.physics.pulse import PulseShape

    link = LinkBudget()
    pulse = PulseShape.gaussian(system.laser.pulse_fwhm, 50e-12)
    n_emit = emitted_photons(link, pulse, system.laser.wavelength)
    P = np.array([0.0, 0.0, wall.distance])
    p = np.asarray(system.scanner.position, dtype=np.float64)
    to_rx = -P / np.linalg.norm(P)
    n = wall.normal
    d_in = (P - p) / np.linalg.norm(P - p)
    cos_e = float(abs(n @ to_rx))
    del d_in
    mu0 = float(expected_signal_photons(n_emit, wall.reflectivity, cos_e, 1.0,
                                        wall.distance, link, system.receiver))
    from dataclasses import replace

    return replace(link, peak_power=link.peak_power * wall.flux / mu0)


def simulate_case(case: Case, nominal: System, shot_scale: float = 1.0):
    """The recordings of ``case`` (one per wall), nominal system inside, truth kept."""
    from mems_stereo.sim import SimulationOptions, simulate

    true = case.true_system(nominal)
    recs = []
    for i, w in enumerate(case.walls):
        n = max(200, int(round(w.shots / shot_scale)))
        rec = simulate(nominal, wall_scene(w), n,
                       rng=np.random.default_rng([case.seed, i]),
                       background_hz=w.background_hz, true_system=true,
                       options=SimulationOptions(link=link_for_flux(true, w)))
        rec.source = f"case{case.seed}_wall{i}"
        recs.append(rec)
    return recs
