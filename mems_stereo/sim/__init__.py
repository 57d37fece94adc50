"""The simulator: scenes, MEMS trajectory, photons, and simulated recordings.

Library code that tests and users call alike (``docs/simulator.md``)::

    from mems_stereo.sim import load_scene, simulate
    from mems_stereo.recording import write_recording
    rec = simulate(system, load_scene("samples/room_scene.json"), 800,
                   rng=np.random.default_rng(1))

Open3D is imported only when rays are cast or a mesh file is read.
"""

from .photons import (
    LinkBudget,
    PulseShape,
    SpotModel,
    background_first_arrivals,
    emitted_photons,
    expected_signal_photons,
    first_photon_cdf,
    first_photon_mean_delay,
    first_signal_arrival,
    spot_fractions,
)
from .scene import RayHits, Scene, SceneObject, load_scene, scene_from_dict
from .simulate import shot_returns, simulate, write_simulation
from .trajectory import Trajectory, monitor_zero_crossings

__all__ = [
    "LinkBudget", "PulseShape", "RayHits", "Scene", "SceneObject", "SpotModel", "Trajectory",
    "background_first_arrivals", "emitted_photons", "expected_signal_photons",
    "first_photon_cdf", "first_photon_mean_delay", "first_signal_arrival", "load_scene",
    "monitor_zero_crossings", "scene_from_dict",
    "shot_returns", "simulate", "spot_fractions", "write_simulation",
]
