"""The simulator: scenes, MEMS trajectory, photons, and simulated recordings.

Library code that tests and users call alike (``docs/simulator.md``)::

    from mems_stereo.sim import load_scene, simulate
    from mems_stereo.io.recording import write_recording
    rec = simulate(system, load_scene("samples/room_scene.json"), 800,
                   rng=np.random.default_rng(1))

Open3D is imported only when rays are cast or a mesh file is read.
"""

from mems_stereo.physics.first_photon import first_photon_cdf, first_photon_mean_delay
from mems_stereo.physics.link_budget import LinkBudget, emitted_photons, expected_signal_photons
from mems_stereo.physics.pulse import PulseShape
from mems_stereo.physics.spot import SpotModel, spot_fractions
from mems_stereo.sim.imperfections import Imperfections, imperfect_system
from mems_stereo.sim.photons import background_first_arrivals, first_signal_arrival
from mems_stereo.sim.scene import RayHits, Scene, SceneObject, load_scene, scene_from_dict
from mems_stereo.sim.simulate import (
    SimulationOptions,
    shot_returns,
    simulate,
    write_simulation,
)
from mems_stereo.sim.trajectory import Trajectory, monitor_zero_crossings

__all__ = [
    "LinkBudget", "PulseShape", "RayHits", "Scene", "SceneObject", "SimulationOptions",
    "SpotModel", "Trajectory",
    "background_first_arrivals", "emitted_photons", "expected_signal_photons",
    "first_photon_cdf", "first_photon_mean_delay", "first_signal_arrival", "load_scene",
    "monitor_zero_crossings", "scene_from_dict", "Imperfections", "imperfect_system",
    "shot_returns", "simulate", "spot_fractions", "write_simulation",
]
