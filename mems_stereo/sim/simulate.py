"""Simulate a recording of the MEMS-scanning SPAD lidar (FORMAT v1 with /truth).

Per shot k at t_k = start_time + k / f_rep:

1. the true scan angle θ_k from the trajectory (:mod:`.trajectory`), the scan
   direction by the reflection law, a ray from the true mirror position cast
   into the scene (:mod:`.scene`);
2. the hit's visibility from the receiver (a second ray from the projection
   centre), the Lambertian link budget → μ_k mean detected signal photons,
   spread over nearby pixels by the imaged spot (:mod:`.photons`);
3. path length L = |x − x_mirror| + |x|, TDC time of the return
   τ = L / c + offset + pulse delay (+ timing jitter);
4. each pixel's first photon (signal or background/dark) in the TDC window;
   code N = floor(τ / bin_width) + 1, 0 when nothing arrives in the window;
5. optional optical crosstalk to a neighbouring pixel.

The true system's hardware model (``docs/hardware.md``: trajectory harmonics,
monitor edge delays, pulse shape, per-pixel TDC offsets, code widths) is
simulated where it is set (:mod:`.imperfections`; ideal hardware draws the
same numbers as without it).

Everything uses the *true* system; the recording carries the nominal one.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mems_stereo.errors import GeometryError, OptionError
from mems_stereo.io.recording import Recording
from mems_stereo.model.camera import project_points
from mems_stereo.model.scanner import scan_direction
from mems_stereo.model.system import System
from mems_stereo.physics.link_budget import LinkBudget, emitted_photons, expected_signal_photons
from mems_stereo.physics.pulse import PulseShape, pulse_shape_of
from mems_stereo.physics.spot import SpotModel, spot_fractions
from mems_stereo.sim.imperfections import pixel_delays, tdc_codes
from mems_stereo.sim.motion import as_moving, returns_over_time
from mems_stereo.sim.photons import (
    DENSE_BACKGROUND,
    background_first_arrivals,
    first_signal_arrival,
)
from mems_stereo.sim.scene import Scene
from mems_stereo.sim.trajectory import Trajectory, monitor_zero_crossings

CHUNK_SHOTS = 4096  # fixed: the random stream does not depend on progress reporting
MIN_SLOT_PHOTONS = 1e-9


@dataclass(frozen=True, slots=True)
class SimulationOptions:
    """How :func:`simulate` acquires: the mirror's motion, the jitters, the optics.

    Attributes
    ----------
    start_time : s, trigger time of shot 0; shots follow at 1 / f_rep.
    phase : rad, monitor phase φ_mon at ``start_time`` (None: uniform from the rng).
    drift : 1/s, relative linear drift of the mechanical frequency.
    amplitude : rad, true θ_mech,max (None: the true system's).
    zc_jitter : s, Gaussian timing jitter of the zero-crossing monitor.
    timing_jitter : s, Gaussian jitter of SPAD + TDC + laser trigger.
    pulse : None (Gaussian of the true system's pulse_fwhm), a
        :class:`PulseShape`, or ``(times, power)`` samples of any shape.
    link : :class:`LinkBudget` (None: the paper's system).
    spot : :class:`SpotModel` (None: the default).
    crosstalk : probability that a detection also fires a neighbouring pixel.
    """

    start_time: float = 0.0
    phase: float | None = None
    drift: float = 0.0
    amplitude: float | None = None
    zc_jitter: float = 20e-9
    timing_jitter: float = 50e-12
    pulse: PulseShape | tuple | None = None
    link: LinkBudget | None = None
    spot: SpotModel | None = None
    crosstalk: float = 0.0


def _pulse_for(true_system: System, pulse, timing_jitter: float) -> PulseShape:
    if pulse is None:  # the true laser's pulse model (the Gaussian without one)
        return pulse_shape_of(true_system.laser, timing_jitter)
    if isinstance(pulse, PulseShape):
        return pulse
    times, power = pulse
    return PulseShape.from_samples(times, power, timing_jitter)


def _rates(background_hz, dark_count_hz, shape) -> np.ndarray:
    bg = np.broadcast_to(np.asarray(background_hz, dtype=np.float64), shape)
    dk = np.broadcast_to(np.asarray(dark_count_hz, dtype=np.float64), shape)
    rate = bg + dk
    if not np.all(np.isfinite(rate)) or np.any(bg < 0) or np.any(dk < 0):
        raise OptionError("background_hz, dark_count_hz: expected non-negative finite rates")
    return rate


def _project(points: np.ndarray, receiver) -> np.ndarray:
    """Pixels (column, row) of points in front of the camera, (N, 2); pinhole in
    NumPy without distortion, ``cv2.projectPoints`` (via camera.project_points) with it."""
    if np.any(receiver.dist_coeffs):
        return project_points(points, receiver.camera_matrix, receiver.dist_coeffs)
    K = receiver.camera_matrix
    with np.errstate(divide="ignore", invalid="ignore"):
        xn = points[:, 0] / points[:, 2]
        yn = points[:, 1] / points[:, 2]
    out = np.stack([K[0, 0] * xn + K[0, 1] * yn + K[0, 2], K[1, 1] * yn + K[1, 2]], axis=1)
    out[points[:, 2] <= 0] = np.nan
    return out


def shot_returns(true_system: System, scene: Scene, theta, *, link: LinkBudget,
                 spot: SpotModel, n_emitted: float):
    """Geometry and mean signal of each shot.

    theta : (k,) rad, true scan angles.
    Returns a dict with ``point`` (k, 3) (NaN: no hit), ``object`` (k,) int64,
    ``path_length`` (k,) m (NaN: no hit), ``visible`` (k,) bool, ``mu`` (k,)
    mean detected signal photons of the whole spot, ``center`` (k, 2) pixel
    of the spot centre, ``sigma_px`` (k, 2).
    """
    dirs = scan_direction(np.asarray(theta, dtype=np.float64), true_system.scanner)
    return beam_returns(true_system, scene, dirs, link=link, spot=spot, n_emitted=n_emitted)


def beam_returns(true_system: System, scene: Scene, dirs: np.ndarray, *, link: LinkBudget,
                 spot: SpotModel, n_emitted: float):
    """:func:`shot_returns` for given beam directions ``dirs`` (k, 3), unit vectors in
    the receiver camera frame from the mirror (one- and two-axis scanners alike)."""
    sc, rc = true_system.scanner, true_system.receiver
    origin = np.asarray(sc.position, dtype=np.float64)
    hits = scene.cast(origin, dirs)
    x = hits.point
    hit = hits.hit
    r_rx = np.linalg.norm(x, axis=1)
    visible = np.zeros(hit.shape, dtype=bool)
    if np.any(hit):
        to_x = x[hit] / r_rx[hit, None]
        back = scene.cast(np.zeros(3), to_x)
        tol = 1e-4 + 1e-5 * r_rx[hit]
        visible[hit] = back.t >= r_rx[hit] - tol
    with np.errstate(invalid="ignore", divide="ignore"):
        cos_emit = -np.sum(hits.normal * x, axis=1) / r_rx
        cos_view = x[:, 2] / r_rx
    refl = np.zeros(hit.shape)
    refl[hit] = scene.reflectivity[hits.object_index[hit]]
    mu = expected_signal_photons(n_emitted, refl, np.where(visible, cos_emit, 0.0),
                                 np.where(visible, cos_view, 0.0), np.where(hit, r_rx, 1.0),
                                 link, rc)
    mu = np.where(visible, mu, 0.0)
    center = np.full((x.shape[0], 2), np.nan)
    if np.any(visible):
        center[visible] = _project(x[visible], rc)
    sig_m = spot.sigma(np.where(hit, hits.t, 1.0), np.where(hit, x[:, 2], 1.0), link)
    sigma_px = sig_m[:, None] / np.asarray(rc.pixel_pitch, dtype=np.float64)[None, :]
    path = np.where(hit, hits.t + r_rx, np.nan)
    return {"point": x, "object": hits.object_index, "path_length": path, "visible": visible,
            "mu": mu, "center": center, "sigma_px": sigma_px}


def _background_by_rate(uniq, inverse, k: int, npix: int, window: float,
                        rng: np.random.Generator):
    """First background and dark-count arrivals of ``k`` shots × ``npix`` pixels,
    grouped by rate (one group for a uniform rate): the slots (sorted) and their
    times (s), as :func:`background_first_arrivals` gives them."""
    bg_idx, bg_tau = [], []
    for g, lam in enumerate(uniq):
        pix = np.flatnonzero(inverse == g)
        idx, tau = background_first_arrivals(lam, k * pix.size, window, rng)
        if uniq.size > 1:
            shot, j = np.divmod(idx, pix.size)
            idx = shot * npix + pix[j]
        bg_idx.append(idx)
        bg_tau.append(tau)
    idx = np.concatenate(bg_idx)
    tau = np.concatenate(bg_tau)
    if uniq.size > 1:
        order = np.argsort(idx, kind="stable")
        idx, tau = idx[order], tau[order]
    return idx, tau


def _simulate_chunk(true_system: System, ret: dict, rates: np.ndarray, pulse: PulseShape,
                    spot: SpotModel, crosstalk: float, rng: np.random.Generator):
    """Codes and labels of one chunk of shots: (k, H, W) uint16 and uint8."""
    rc, tdc = true_system.receiver, true_system.tdc
    w, h = rc.image_size
    k = ret["mu"].shape[0]
    bw, window = tdc.bin_width, tdc.n_bins * tdc.bin_width
    npix = h * w
    n_slots = k * npix

    # laser return: slots near the spot centre
    rows, cols, frac = spot_fractions(ret["center"], ret["sigma_px"], (w, h), spot.radius)
    mu_slot = ret["mu"][:, None, None] * frac
    sel = mu_slot > MIN_SLOT_PHOTONS
    ks, ri, ci = np.nonzero(sel)
    slot_sig = ks * npix + rows[ks, ri] * w + cols[ks, ci]
    delay = ret["path_length"][ks] / true_system.speed_of_light + tdc.offset
    if tdc.pixel_offsets is not None:
        delay = delay + pixel_delays(tdc, slot_sig % npix)
    tau_sig, _ = first_signal_arrival(mu_slot[sel], delay, pulse, window, rng)

    flat_rate = rates.reshape(-1)
    uniq, inverse = np.unique(flat_rate, return_inverse=True)
    if uniq.size == 1 and -math.expm1(-float(uniq[0]) * window) > DENSE_BACKGROUND:
        # uniform, dense background (floodlight): the same draws as
        # background_first_arrivals, kept as whole arrays (no index scatter)
        bins, label, tau_bg_all = _dense_background(float(uniq[0]), n_slots, window, bw, rng)
        has_sig = np.isfinite(tau_sig)
        s_slot, s_tau = slot_sig[has_sig], tau_sig[has_sig]
        win = s_tau < tau_bg_all[s_slot]
        if tdc.code_widths is not None:
            bins = np.where(np.isfinite(tau_bg_all), tdc_codes(tau_bg_all, tdc), bins)
        code = tdc_codes(s_tau[win], tdc)
        bins[s_slot[win]] = code
        label[s_slot[win]] = 1
        return _finish_chunk(bins, label, mu_slot, k, h, w, crosstalk, rng)

    idx, tau = _background_by_rate(uniq, inverse, k, npix, window, rng)
    bins = np.zeros(n_slots, dtype=np.uint16)
    label = np.zeros(n_slots, dtype=np.uint8)
    code = tau * (1.0 / bw)  # non-negative: truncation is floor
    bins[idx] = code.astype(np.uint16) + 1 if tdc.code_widths is None else tdc_codes(tau, tdc)
    label[idx] = 2

    # the earlier of signal and background wins
    has_sig = np.isfinite(tau_sig)
    s_slot, s_tau = slot_sig[has_sig], tau_sig[has_sig]
    tau_bg = np.full(s_slot.shape, np.inf)
    if idx.size:
        pos = np.minimum(np.searchsorted(idx, s_slot), idx.size - 1)
        found = idx[pos] == s_slot
        tau_bg[found] = tau[pos[found]]
    win = s_tau < tau_bg
    code = tdc_codes(s_tau[win], tdc)
    bins[s_slot[win]] = code
    label[s_slot[win]] = 1

    return _finish_chunk(bins, label, mu_slot, k, h, w, crosstalk, rng)


def _finish_chunk(bins, label, mu_slot, k, h, w, crosstalk, rng):
    bins = bins.reshape(k, h, w)
    label = label.reshape(k, h, w)
    if crosstalk > 0:
        _crosstalk(bins, label, crosstalk, rng)
    mu_on = mu_slot.sum(axis=(1, 2))
    return bins, label, mu_on


def _dense_background(lam: float, n_slots: int, window: float, bw: float,
                      rng: np.random.Generator):
    """Codes, labels and first arrival (inf: none) of a dense uniform background.

    Draws exactly what :func:`~mems_stereo.sim.photons.background_first_arrivals`
    draws in its dense branch (one float32 uniform per slot) and applies the same
    arithmetic, on whole arrays: bit-identical results, without the index scatter.
    """
    p = -math.expm1(-lam * window)
    u = rng.random(n_slots, dtype=np.float32)
    fires = u < p
    tau = np.log1p(-u)
    tau *= np.float32(-1.0 / lam)
    np.minimum(tau, np.float32(window * (1 - 1e-6)), out=tau)
    code = tau * (1.0 / bw)
    bins = np.where(fires, code.astype(np.uint16) + np.uint16(1), np.uint16(0))
    label = np.where(fires, np.uint8(2), np.uint8(0))
    tau_all = np.where(fires, tau, np.float32(np.inf))
    return bins, label, tau_all


def _crosstalk(bins: np.ndarray, label: np.ndarray, p: float, rng: np.random.Generator):
    """Each detection fires one of its 4 neighbours (chosen at random) with
    probability p, in the same TDC code, unless that neighbour fired earlier.
    The neighbour inherits the label of its cause.  In place; one pass."""
    k, h, w = bins.shape
    ks, rs, cs = np.nonzero(bins)
    fire = rng.random(ks.size) < p
    d = rng.integers(0, 4, size=ks.size)
    dr = np.array([0, 0, -1, 1])[d]
    dc = np.array([-1, 1, 0, 0])[d]
    ks, rs, cs, dr, dc = ks[fire], rs[fire], cs[fire], dr[fire], dc[fire]
    src_code, src_label = bins[ks, rs, cs].copy(), label[ks, rs, cs].copy()
    rn, cn = rs + dr, cs + dc
    ok = (rn >= 0) & (rn < h) & (cn >= 0) & (cn < w)
    ks, rn, cn, src_code, src_label = ks[ok], rn[ok], cn[ok], src_code[ok], src_label[ok]
    cur = bins[ks, rn, cn]
    take = (cur == 0) | (src_code < cur)
    # several sources may hit one neighbour: keep the earliest
    order = np.argsort(src_code[take], kind="stable")[::-1]
    tk, tr, tc = ks[take][order], rn[take][order], cn[take][order]
    bins[tk, tr, tc] = src_code[take][order]
    label[tk, tr, tc] = src_label[take][order]


def simulate(system: System, scene: Scene, n_shots: int, *, rng: np.random.Generator,
             background_hz=1e5, dark_count_hz=1e3, true_system: System | None = None,
             options: SimulationOptions | None = None,
             progress: Callable[[int], object] | None = None) -> Recording:
    """Simulate ``n_shots`` laser shots of a MEMS-scanning SPAD lidar.

    Parameters
    ----------
    system : the nominal System written into the recording.
    scene : :class:`~mems_stereo.sim.scene.Scene` (objects with a ``velocity`` or an
        ``angular_rate`` move: :mod:`mems_stereo.sim.motion`).
    n_shots : K >= 1.
    rng : numpy.random.Generator (the only source of randomness).
    background_hz : ambient detections per second per pixel, scalar or (H, W)
        (paper: 1e5 room light, 6e6 floodlight).
    dark_count_hz : dark counts per second per pixel, scalar or (H, W).
    true_system : the System that generates the photons (default: ``system``).
    options : :class:`SimulationOptions` (start time, mirror phase and drift,
        jitters, pulse, link budget, spot, crosstalk; None: the defaults).
    progress : called with the number of shots done after each chunk.

    Returns
    -------
    Recording with ``system`` = nominal, ``bins`` (K, H, W) uint16, and truth
    ``label`` (K, H, W) uint8 (0 none, 1 laser return, 2 background/dark),
    ``theta`` (K,) rad, ``point`` (K, 3) m (NaN: no hit), ``object`` (K,)
    int64 (−1: no hit), ``path_length`` (K,) m, ``signal_mean`` (K,) mean
    detected signal photons on the sensor.
    """
    opt = SimulationOptions() if options is None else options
    if not isinstance(rng, np.random.Generator):
        raise TypeError("rng: expected a numpy.random.Generator")
    n_shots = int(n_shots)
    if n_shots < 1:
        raise OptionError(f"n_shots: expected a positive integer, found {n_shots}")
    ts = system if true_system is None else true_system
    if tuple(ts.receiver.image_size) != tuple(system.receiver.image_size):
        raise GeometryError(f"true_system: expected image_size {system.receiver.image_size} "
                            f"like the nominal system, found {ts.receiver.image_size}")
    crosstalk = opt.crosstalk
    if not 0.0 <= crosstalk <= 1.0:
        raise OptionError(f"crosstalk: expected a probability in [0, 1], found {crosstalk}")
    link = LinkBudget() if opt.link is None else opt.link
    scene = as_moving(scene)  # objects with a velocity: cast at each shot's time
    spot = SpotModel() if opt.spot is None else opt.spot
    w, h = system.receiver.image_size
    rates = _rates(background_hz, dark_count_hz, (h, w))

    phase = opt.phase
    if phase is None:
        phase = float(rng.uniform(0.0, 2.0 * math.pi))
    traj = Trajectory.from_scanner(ts.scanner, phase, opt.drift, opt.start_time, opt.amplitude)
    shot_time = opt.start_time + np.arange(n_shots, dtype=np.float64) / ts.laser.f_rep
    zc, rising = monitor_zero_crossings(traj, shot_time, rng, opt.zc_jitter)
    theta = traj.theta(shot_time)
    pulse_shape = _pulse_for(ts, opt.pulse, opt.timing_jitter)
    n_emit = emitted_photons(link, pulse_shape, ts.laser.wavelength)

    bins = np.zeros((n_shots, h, w), dtype=np.uint16)
    label = np.zeros((n_shots, h, w), dtype=np.uint8)
    point = np.full((n_shots, 3), np.nan)
    obj = np.full(n_shots, -1, dtype=np.int64)
    path = np.full(n_shots, np.nan)
    mu_on = np.zeros(n_shots)
    for s0 in range(0, n_shots, CHUNK_SHOTS):
        s1 = min(n_shots, s0 + CHUNK_SHOTS)
        ret = returns_over_time(  # a moving scene slice by slice (sim.motion)
            lambda sc, th: shot_returns(ts, sc, th, link=link, spot=spot, n_emitted=n_emit),
            scene, shot_time[s0:s1], theta[s0:s1])
        bins[s0:s1], label[s0:s1], mu_on[s0:s1] = _simulate_chunk(
            ts, ret, rates, pulse_shape, spot, crosstalk, rng)
        point[s0:s1], obj[s0:s1], path[s0:s1] = ret["point"], ret["object"], ret["path_length"]
        if progress is not None:
            progress(s1 - s0)
    truth = {"label": label, "theta": theta, "point": point, "object": obj,
             "path_length": path, "signal_mean": mu_on}
    return Recording(system, shot_time, bins, zc, rising.astype(np.uint8), truth,
                     source="<simulated>")


def write_simulation(path, recording: Recording):
    """Write a simulated :class:`Recording` (with its truth) atomically, gzip'd HDF5."""
    from mems_stereo.io.recording import write_recording

    return write_recording(path, recording.system, recording.shot_time, recording.bins,
                           recording.zero_crossings, recording.rising, truth=recording.truth)
