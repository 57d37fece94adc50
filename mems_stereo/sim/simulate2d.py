"""Simulate a two-axis MEMS scanner with a 2-D SPAD array, with epipolar readout gating.

The same physics as the one-axis simulator (:mod:`mems_stereo.sim.simulate`):
rays cast into the :class:`~mems_stereo.sim.scene.Scene`, the link budget
(:mod:`mems_stereo.physics.link_budget`), the imaged spot
(:class:`~mems_stereo.physics.spot.SpotModel`), first-photon sampling of the
laser return and of background + dark counts (:mod:`mems_stereo.sim.photons`).
What differs:

* the beam direction comes from both mirror axes (true trajectories: the fast
  axis as :class:`~mems_stereo.sim.trajectory.Trajectory`; axis 2 resonant
  (Lissajous, its own zero-crossing monitor) or a quasi-static triangle
  (raster, a sampled position channel with Gaussian noise));
* only the pixels of each shot's gate are read (:mod:`mems_stereo.geometry.gating`),
  computed, as hardware would, from the *nominal* system and the angles the
  monitors give; laser returns outside the gate are lost (counted in the truth);
  ``gate=None`` reads every pixel;
* the output is the event list of :mod:`mems_stereo.io.recording2d`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mems_stereo.errors import GeometryError, OptionError
from mems_stereo.geometry.gating import GateSpec, full_gate, gate_pixels
from mems_stereo.io.recording2d import Recording2D
from mems_stereo.model.presets import TWO_AXIS_LINK
from mems_stereo.model.scanner2d import (
    Axis2Monitor,
    require_two_axis,
    scan_angles_2d,
    scan_direction_2d,
    triangle_wave,
)
from mems_stereo.model.system import System
from mems_stereo.physics.link_budget import LinkBudget, emitted_photons
from mems_stereo.physics.pulse import PulseShape
from mems_stereo.physics.spot import SpotModel, spot_fractions
from mems_stereo.sim.photons import background_first_arrivals, first_signal_arrival
from mems_stereo.sim.scene import Scene
from mems_stereo.sim.simulate import beam_returns
from mems_stereo.sim.trajectory import Trajectory, monitor_zero_crossings

CHUNK_SHOTS = 8192
MIN_SLOT_PHOTONS = 1e-9


def default_link() -> LinkBudget:
    """The two-axis presets' link budget (:data:`mems_stereo.model.presets.TWO_AXIS_LINK`)."""
    return LinkBudget(**TWO_AXIS_LINK)


def default_gate_spec(system: System, r_min: float = 0.5, r_max: float = 8.0,
                      spot: SpotModel | None = None, link: LinkBudget | None = None) -> GateSpec:
    """Gate for the working range: half width from the largest imaged spot σ over
    [r_min, r_max] (:class:`SpotModel`) and :func:`~mems_stereo.geometry.gating.gate_half_width`."""
    from mems_stereo.geometry.gating import gate_half_width

    spot = SpotModel() if spot is None else spot
    link = default_link() if link is None else link
    r = np.geomspace(r_min, r_max, 64)
    sig = float(np.max(spot.sigma(r, r, link)))
    return GateSpec(r_min, r_max, gate_half_width(system, sig))


def _axis2_truth(system: System, n_shots: int, shot_time: np.ndarray, rng, phase2,
                 zc_jitter: float, position_rate: float, position_noise: float):
    """True θ2 per shot and the axis-2 monitor record."""
    a2 = require_two_axis(system)
    if a2.mode == "resonant":
        traj = Trajectory(a2.f_mech, float(phase2), 0.0, float(shot_time[0]), a2.theta0,
                          a2.theta_mech_max, a2.phase_offset)
        z2, r2 = monitor_zero_crossings(traj, shot_time, rng, zc_jitter)
        return traj.theta(shot_time), Axis2Monitor(zero_crossings=z2, rising=r2)

    def mech(t):
        return a2.theta_mech_max * triangle_wave(2 * np.pi * a2.f_mech * (t - shot_time[0])
                                                 + phase2 + a2.phase_offset)

    dt = 1.0 / position_rate
    pt = np.arange(shot_time[0] - 2 * dt, shot_time[-1] + 2 * dt, dt)
    pp = mech(pt) + rng.normal(0.0, position_noise, size=pt.shape)
    return a2.theta0 + mech(shot_time), Axis2Monitor(time=pt, position=pp)


def _check_args(system: System, ts: System, rng, n_shots, background_hz: float,
                dark_count_hz: float) -> int:
    """Validate :func:`simulate_2d`'s arguments; returns ``n_shots`` as int."""
    if not isinstance(rng, np.random.Generator):
        raise TypeError("rng: expected a numpy.random.Generator")
    n_shots = int(n_shots)
    if n_shots < 1:
        raise OptionError(f"n_shots: expected a positive integer, found {n_shots}")
    require_two_axis(system)
    require_two_axis(ts, "true_system")
    if tuple(ts.receiver.image_size) != tuple(system.receiver.image_size):
        raise GeometryError("true_system: expected the nominal system's image_size")
    if background_hz < 0 or dark_count_hz < 0:
        raise OptionError("background_hz, dark_count_hz: expected non-negative rates")
    return n_shots


def _signal_slots(ts: System, ret: dict, spot: SpotModel, pulse: PulseShape, rng):
    """First laser-return arrival per pixel-slot of one chunk of shots.

    ``ret`` : :func:`~mems_stereo.sim.simulate.beam_returns` of the chunk's k shots.
    Returns ``(slot, tau)``: chunk-local slot keys ``shot * H*W + row * W + col``
    (int64) and first-photon times (s after the trigger) of the slots that saw one.
    """
    w, h = ts.receiver.image_size
    tdc = ts.tdc
    rows, cols, frac = spot_fractions(ret["center"], ret["sigma_px"], (w, h), spot.radius)
    mu_slot = ret["mu"][:, None, None] * frac
    sel = mu_slot > MIN_SLOT_PHOTONS
    ks, ri, ci = np.nonzero(sel)
    slot = ks * (w * h) + rows[ks, ri] * w + cols[ks, ci]
    delay = ret["path_length"][ks] / ts.speed_of_light + tdc.offset
    tau, _ = first_signal_arrival(mu_slot[sel], delay, pulse, tdc.n_bins * tdc.bin_width, rng)
    has = np.isfinite(tau)
    return slot[has], tau[has]


def _in_gate(read_keys: np.ndarray, slot: np.ndarray) -> np.ndarray:
    """Which of the chunk-local ``slot`` keys are among the (sorted) ``read_keys``."""
    if not read_keys.size:
        return np.zeros(slot.shape, bool)
    pos = np.minimum(np.searchsorted(read_keys, slot), read_keys.size - 1)
    return read_keys[pos] == slot


def _first_events(b_key, b_tau, s_key, s_tau, tdc):
    """The earlier of signal and background per slot, as TDC events.

    Returns ``(key, code, label)``: slot keys (increasing), codes
    ``min(floor(τ / bin_width) + 1, n_bins)`` uint16 and labels (1 laser
    return, 2 background/dark) uint8.
    """
    keys = np.concatenate([b_key, s_key])
    taus = np.concatenate([b_tau.astype(np.float64), s_tau])
    labs = np.concatenate([np.full(b_key.size, 2, np.uint8), np.ones(s_key.size, np.uint8)])
    order = np.lexsort((taus, keys))
    keys, taus, labs = keys[order], taus[order], labs[order]
    first = np.ones(keys.size, bool)
    first[1:] = keys[1:] != keys[:-1]
    keys, taus, labs = keys[first], taus[first], labs[first]
    code = np.minimum(np.floor(taus / tdc.bin_width) + 1, tdc.n_bins).astype(np.uint16)
    return keys, code, labs


@dataclass(frozen=True, slots=True)
class Simulation2DOptions:
    """How :func:`simulate_2d` acquires: the mirror phases, the monitors, the optics.

    Attributes
    ----------
    phase, phase2 : rad, monitor phases of the axes at t = 0 (None: uniform from the rng).
    zc_jitter : s, zero-crossing monitor jitter (both resonant axes).
    timing_jitter : s, SPAD + TDC + trigger jitter.
    position_rate : Hz, sample rate of the quasistatic axis' position channel.
    position_noise : rad, Gaussian noise of the position channel.
    link : :class:`LinkBudget` (None: :func:`default_link`).
    spot : :class:`SpotModel` (None: the default).
    truth_per_shot : store θ1, θ2 (K,) and the hit point (K, 3) in the truth.
    """

    phase: float | None = None
    phase2: float | None = None
    zc_jitter: float = 20e-9
    timing_jitter: float = 50e-12
    position_rate: float = 20e3
    position_noise: float = 2e-5
    link: LinkBudget | None = None
    spot: SpotModel | None = None
    truth_per_shot: bool = True


@dataclass(frozen=True, slots=True)
class _ShotAngles:
    """The true angles of every shot and what the monitors record of them.

    shot_time : (K,) float64 s; zc, rising : (Z,) the fast axis' monitor;
    theta1, theta2 : (K,) float64 rad, true angles; mon2 : axis 2's monitor;
    phase, phase2 : rad, the monitors' phases at t = 0.
    """

    shot_time: np.ndarray
    zc: np.ndarray
    rising: np.ndarray
    theta1: np.ndarray
    theta2: np.ndarray
    mon2: Axis2Monitor
    phase: float
    phase2: float


def _shot_angles(ts: System, n_shots: int, rng, opt: Simulation2DOptions) -> _ShotAngles:
    """Draw the phases (when not given), the monitors and the true angles, in this order."""
    sc = ts.scanner
    phase, phase2 = opt.phase, opt.phase2
    if phase is None:
        phase = float(rng.uniform(0.0, 2 * math.pi))
    if phase2 is None:
        phase2 = float(rng.uniform(0.0, 2 * math.pi))
    shot_time = np.arange(n_shots, dtype=np.float64) / ts.laser.f_rep
    traj1 = Trajectory(sc.f_mech, phase, 0.0, 0.0, sc.theta0, sc.theta_mech_max,
                       sc.phase_offset, tuple(sc.harmonics), sc.monitor)
    zc, rising = monitor_zero_crossings(traj1, shot_time, rng, opt.zc_jitter)
    theta1 = traj1.theta(shot_time)
    theta2, mon2 = _axis2_truth(ts, n_shots, shot_time, rng, phase2, opt.zc_jitter,
                                opt.position_rate, opt.position_noise)
    return _ShotAngles(shot_time, zc, rising, theta1, theta2, mon2, phase, phase2)


def _chunk_gate(system: System, gate: GateSpec | None, npix: int, th1, th2, valid):
    """The readout gate of a chunk of shots from the nominal angles ``th1``, ``th2``
    (rad) of the monitors (unknown angle: nothing read); every pixel where ``gate``
    is None."""
    if gate is None:
        return full_gate(th1.size, npix)
    dn = scan_direction_2d(th1, th2, system.scanner)
    dn[~valid] = np.nan
    return gate_pixels(system, dn, gate)


def simulate_2d(system: System, scene: Scene, n_shots: int, *, rng: np.random.Generator,
                background_hz: float = 1e5, dark_count_hz: float = 1e3,
                true_system: System | None = None, gate: GateSpec | None | str = "auto",
                options: Simulation2DOptions | None = None, progress=None) -> Recording2D:
    """Simulate ``n_shots`` shots of a two-axis scanner and a 2-D SPAD array.

    Parameters
    ----------
    system : nominal two-axis System (written into the recording; the gate uses it).
    scene : the scene.
    n_shots : K >= 1; shots at 1 / f_rep from t = 0.
    rng : numpy.random.Generator (the only randomness).
    background_hz, dark_count_hz : per pixel, Hz (uniform over the array).
    true_system : the System that makes the photons (default ``system``).
    gate : a :class:`GateSpec`, "auto" (:func:`default_gate_spec`) or None (read all).
    options : :class:`Simulation2DOptions` (phases, jitters, position channel,
        link budget, spot, per-shot truth; None: the defaults).
    progress : called with the number of shots done after each chunk.

    Returns
    -------
    :class:`~mems_stereo.io.recording2d.Recording2D` with truth ``label`` (E,)
    uint8 (1 laser return, 2 background/dark) and the attributes
    ``signal_total`` (laser-return detections on the whole array, read or not)
    and ``signal_lost`` (those outside the gate).
    """
    opt = Simulation2DOptions() if options is None else options
    ts = system if true_system is None else true_system
    n_shots = _check_args(system, ts, rng, n_shots, background_hz, dark_count_hz)
    link = default_link() if opt.link is None else opt.link
    spot = SpotModel() if opt.spot is None else opt.spot
    gate = _resolve_gate(gate, system, spot, link)
    npix = system.receiver.width * system.receiver.height
    ang = _shot_angles(ts, n_shots, rng, opt)
    shot_time = ang.shot_time

    # what the hardware knows: the nominal system and the monitors' angles
    th1_n, th2_n, valid_n = scan_angles_2d(shot_time, ang.zc, ang.rising, ang.mon2,
                                           system.scanner)

    pulse = PulseShape.gaussian(ts.laser.pulse_fwhm, opt.timing_jitter)
    n_emit = emitted_photons(link, pulse, ts.laser.wavelength)
    window = ts.tdc.n_bins * ts.tdc.bin_width
    lam = float(background_hz + dark_count_hz)

    ev_key, ev_code, ev_label, counts = [], [], [], []
    point = np.full((n_shots, 3), np.nan)
    sig_total = 0
    sig_lost = 0
    for s0 in range(0, n_shots, CHUNK_SHOTS):
        s1 = min(n_shots, s0 + CHUNK_SHOTS)
        k = s1 - s0
        dirs = scan_direction_2d(ang.theta1[s0:s1], ang.theta2[s0:s1], ts.scanner)
        ret = beam_returns(ts, scene, dirs, link=link, spot=spot, n_emitted=n_emit)
        point[s0:s1] = np.where(ret["visible"][:, None], ret["point"], np.nan)
        g = _chunk_gate(system, gate, npix, th1_n[s0:s1], th2_n[s0:s1], valid_n[s0:s1])
        counts.append(g.counts())
        read_keys = g.keys()  # chunk-local slot keys, increasing

        slot_sig, tau_sig = _signal_slots(ts, ret, spot, pulse, rng)
        sig_total += int(slot_sig.size)
        # background + dark counts on the read slots only
        bidx, btau = background_first_arrivals(lam, read_keys.size, window, rng)
        in_gate = np.ones(slot_sig.shape, bool) if gate is None else _in_gate(read_keys,
                                                                              slot_sig)
        sig_lost += int(np.count_nonzero(~in_gate))
        keys, code, labs = _first_events(read_keys[bidx], btau, slot_sig[in_gate],
                                         tau_sig[in_gate], ts.tdc)
        ev_key.append(keys + s0 * npix)
        ev_code.append(code)
        ev_label.append(labs)
        if progress is not None:
            progress(k)

    key = np.concatenate(ev_key) if ev_key else np.zeros(0, np.int64)
    truth = {"label": np.concatenate(ev_label), "signal_total": np.int64(sig_total),
             "signal_lost": np.int64(sig_lost), "phase": np.float64(ang.phase),
             "phase2": np.float64(ang.phase2)}
    if opt.truth_per_shot:
        truth.update({"theta1": ang.theta1, "theta2": ang.theta2, "point": point})
    return Recording2D(system, shot_time, ang.zc, ang.rising.astype(np.uint8), ang.mon2,
                       _readout(gate), np.concatenate(counts), key // npix, key % npix,
                       np.concatenate(ev_code), truth, "<simulated>")


def _resolve_gate(gate: GateSpec | None | str, system: System, spot: SpotModel,
                  link: LinkBudget) -> GateSpec | None:
    """A :class:`GateSpec` or None from :func:`simulate_2d`'s ``gate`` argument."""
    if isinstance(gate, str):
        if gate != "auto":
            raise OptionError(f"gate: expected a GateSpec, 'auto' or None, found {gate!r}")
        gate = default_gate_spec(system, spot=spot, link=link)
    return gate


def _readout(gate: GateSpec | None) -> dict:
    """The recording's ``readout`` description of a gate (None: the full array)."""
    if gate is None:
        return {"mode": "full"}
    return {"mode": "gated", "r_min": gate.r_min, "r_max": gate.r_max,
            "half_width": gate.half_width}
