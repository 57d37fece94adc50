"""Calibration of a two-axis scanner with a 2-D SPAD array from flat-wall recordings.

What is estimated (``TWO_AXIS_PARAMS``): both rest angles (``theta0``,
``theta0_2``), both amplitudes (``theta_mech_max``, ``theta_mech_max_2``) and
both phase lags (``phase_offset``, ``phase_offset_2``) of a Lissajous mirror
(a raster mirror's slow axis has a position channel: only its rest angle),
the 3-D baseline (``baseline_x``, ``baseline_y``, ``baseline_z``: with a 2-D
array the image of the beam moves in both directions, so y is observable)
and the TDC offset.  The receiver's intrinsics are *inputs*: the camera matrix
and distortion from ChArUco views (:func:`mems_stereo.calib.intrinsics.calibrate_charuco`),
passed as ``intrinsics=``.

Observations: each shot with signal detections on a wall gives the centroid
``(u, v)`` of its detecting pixels and the mean raw path length
``c·(N − ½)·bin_width`` of its detections.  Forward model: the angles from the
monitors' phases (which do not depend on the parameters) →
``θ = θ0 + A cos(φ + δ)`` per axis → the gimbal's beam direction → the hit
point ``x`` on the wall plane ``n·x = dist`` (n(α, β) = (sin α cos β, sin β,
cos α cos β); α, β, dist per wall, free) → predicted pixel (OpenCV
projection) and raw path length ``|x − p| + |x| + c·offset``.  Residuals are
weighted by their σ (pixel: 1/√12 ⊕ spot; path: the timing σ per detection /
√n), solved by ``scipy.optimize.least_squares`` (soft-ℓ1 pass, then a plain
least-squares pass without the > 5σ outliers); the covariance is
``(JᵀJ)⁻¹ · χ²/dof``.  A fit that does not converge or whose normal matrix is
singular raises :class:`~mems_stereo.errors.NotObservableError` and writes
nothing.

The first-photon (pile-up) bias of each wall's detections is corrected from
the wall's detection rate (μ = −ln(1 − share of shots that detect);
:func:`mems_stereo.physics.first_photon.first_photon_mean_delay`); record the
walls at reduced laser power (μ ≲ 0.5) so this correction stays small.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import least_squares

from mems_stereo.errors import NotObservableError
from mems_stereo.geometry.twoaxis import timing_sigma
from mems_stereo.io.recording2d import Recording2D, read_recording_2d
from mems_stereo.io.recording_checks import check_codes_fit
from mems_stereo.model.scanner import phase_from_zero_crossings
from mems_stereo.model.scanner2d import require_two_axis, scan_direction_2d
from mems_stereo.model.system import System
from mems_stereo.pipeline.gate_check import check_gate
from mems_stereo.pipeline.twoaxis import Settings2D, classify_events, shot_directions

TWO_AXIS_PARAMS = ("theta0", "theta_mech_max", "phase_offset", "theta0_2", "theta_mech_max_2",
                   "phase_offset_2", "baseline_x", "baseline_y", "baseline_z", "tdc_offset")
_AXIS2_NAMES = {"theta0_2": "theta0", "theta_mech_max_2": "theta_mech_max",
                "phase_offset_2": "phase_offset"}


_K_INDEX = {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}


def get_param_2d(system: System, name: str) -> float:
    """A named scalar of a two-axis system (the one-axis names, ``*_2`` of axis 2,
    and the intrinsics ``fx``, ``fy``, ``cx``, ``cy`` in px)."""
    if name in _AXIS2_NAMES:
        return float(getattr(require_two_axis(system), _AXIS2_NAMES[name]))
    if name in _K_INDEX:
        return float(system.receiver.camera_matrix[_K_INDEX[name]])
    return system.get_param(name)


def with_params_2d(system: System, **params: float) -> System:
    """Copy with named scalars changed (names of :func:`get_param_2d`)."""
    a2 = {_AXIS2_NAMES[k]: float(v) for k, v in params.items() if k in _AXIS2_NAMES}
    kk = {k: float(v) for k, v in params.items() if k in _K_INDEX}
    rest = {k: v for k, v in params.items() if k not in _AXIS2_NAMES and k not in _K_INDEX}
    out = system.with_params(**rest) if rest else system
    if kk:
        K = np.array(out.receiver.camera_matrix, dtype=np.float64)
        for k, v in kk.items():
            K[_K_INDEX[k]] = v
        out = out.replace(receiver=replace(out.receiver, camera_matrix=K))
    if a2:
        sc = out.scanner
        out = out.replace(scanner=replace(sc, axis2=replace(require_two_axis(out), **a2)))
    return out


@dataclass(frozen=True, slots=True)
class WallObservations:
    """Per-shot observations of one wall recording.

    phase1, phase2 : (M,) rad, the monitors' phases at the shots (φ, before δ);
    theta2_mech : (M,) rad, the position channel (raster) or NaN (resonant);
    uv : (M, 2) px centroid of the shot's signal pixels; n : (M,) detections;
    L_raw : (M,) m, mean c·(N − ½)·bin_width (pile-up corrected);
    mu : the wall's mean return photons per shot (from the detection rate);
    source : the recording's name, for messages.
    """

    phase1: np.ndarray
    phase2: np.ndarray
    theta2_mech: np.ndarray
    uv: np.ndarray
    n: np.ndarray
    L_raw: np.ndarray
    mu: float
    source: str


def _plane_ransac(x: np.ndarray, sl: float):
    """A robust plane through the points ``x`` (N, 3) m: of 300 random triples (fixed
    seed), the plane with the most points within ``2·sl`` m.  Returns (unit normal
    (3,), offset m)."""
    rng = np.random.default_rng(0)
    best, best_in = None, -1
    for _ in range(300):
        a, b, e = x[rng.choice(x.shape[0], 3, replace=False)]
        nrm = np.cross(b - a, e - a)
        nn = np.linalg.norm(nrm)
        if nn < 1e-9:
            continue
        nrm /= nn
        n_in = int(np.count_nonzero(np.abs((x - a) @ nrm) < 2 * sl))
        if n_in > best_in:
            best, best_in = (nrm, float(nrm @ a)), n_in
    return best


def _wall_detections(rec: Recording2D, system: System, d: np.ndarray, margin_px: float,
                     timing_jitter: float) -> np.ndarray:
    """(E,) bool: the signal detections on the wall.  Classified with ``system``
    (beam directions ``d`` (M, 3) per shot, wide margin); then a robust plane
    through their beam points (RANSAC), and only detections within 5 timing σ of
    that plane's path length kept."""
    from mems_stereo.geometry.triangulation import scanner_ray_point

    st = Settings2D(margin_px=margin_px)
    r_min = rec.readout.get("r_min", 0.3)
    r_max = rec.readout.get("r_max", 30.0)
    lab = classify_events(system, d, rec.event_shot, rec.event_pixel, rec.event_code, r_min,
                          r_max, st)
    sig = lab == 1
    tdc = system.tdc
    c = system.speed_of_light
    L_all = c * ((rec.event_code.astype(float) - 0.5) * tdc.bin_width - tdc.offset)
    idx = np.flatnonzero(sig)
    x = scanner_ray_point(system.scanner.position, d[rec.event_shot[idx]], L_all[idx])[0]
    good = np.all(np.isfinite(x), axis=1)
    idx, x = idx[good], x[good]
    if idx.size < 10:
        raise NotObservableError(f"{rec.source}: fewer than 10 signal detections on the wall")
    sl = c * timing_sigma(system, timing_jitter)
    nrm, dist = _plane_ransac(x, sl)
    p = np.asarray(system.scanner.position, float)
    dd = d[rec.event_shot[idx]]
    with np.errstate(divide="ignore", invalid="ignore"):
        s_w = (dist - nrm @ p) / (dd @ nrm)
    xw = p + s_w[:, None] * dd
    L_pred = s_w + np.linalg.norm(xw, axis=1)
    keep = np.abs(L_all[idx] - L_pred) < 5 * sl
    sel = np.zeros(lab.shape, bool)
    sel[idx[keep]] = True
    return sel


def _shot_phases(rec: Recording2D, system: System, t: np.ndarray):
    """The monitors at the shot times ``t`` (M,) s: axis 1's phase (rad), axis 2's
    phase (rad, resonant; else NaN) and its position channel (rad, raster; else NaN)."""
    ph1, _ = phase_from_zero_crossings(t, rec.zero_crossings, rec.rising)
    a2 = require_two_axis(system)
    if a2.mode == "resonant":
        ph2, _ = phase_from_zero_crossings(t, rec.monitor2.zero_crossings, rec.monitor2.rising)
        th2m = np.full(t.shape, np.nan)
    else:
        ph2 = np.full(t.shape, np.nan)
        th2m = np.interp(t, rec.monitor2.time, rec.monitor2.position)
    return ph1, ph2, th2m


def wall_observations(rec: Recording2D, system: System, margin_px: float = 2.5,
                      timing_jitter: float = 50e-12) -> WallObservations:
    """Classify a wall recording with ``system`` (wide margin) and reduce it to shots."""
    from mems_stereo.physics.first_photon import first_photon_mean_delay
    from mems_stereo.physics.pulse import PulseShape

    sd = shot_directions(rec, system)
    d, valid = sd.direction, sd.valid
    sel = _wall_detections(rec, system, d, margin_px, timing_jitter)
    tdc = system.tdc
    c = system.speed_of_light
    es = rec.event_shot[sel]
    w = system.receiver.image_size[0]
    u = (rec.event_pixel[sel] % w).astype(float)
    v = (rec.event_pixel[sel] // w).astype(float)
    Lr = c * (rec.event_code[sel].astype(float) - 0.5) * tdc.bin_width
    shots, inv, n = np.unique(es, return_inverse=True, return_counts=True)
    uv = np.stack([np.bincount(inv, u), np.bincount(inv, v)], 1) / n[:, None]
    L = np.bincount(inv, Lr) / n
    # pile-up: the wall's mean photons per shot from the share of shots that detect
    p_det = shots.size / max(1, int(np.count_nonzero(valid)))
    mu = -math.log1p(-min(p_det, 0.95))
    pulse = PulseShape.gaussian(system.laser.pulse_fwhm, timing_jitter)
    bias = float(first_photon_mean_delay(np.array([mu]), pulse)[0]
                 - first_photon_mean_delay(np.array([1e-12]), pulse)[0])
    L = L - system.speed_of_light * bias
    ph1, ph2, th2m = _shot_phases(rec, system, rec.shot_time[shots])
    ok = np.isfinite(ph1) & (np.isfinite(ph2) | np.isfinite(th2m))
    return WallObservations(ph1[ok], ph2[ok], th2m[ok], uv[ok], n[ok], L[ok], mu, rec.source)


@dataclass(frozen=True, slots=True)
class TwoAxisCalibration:
    """Result of :func:`calibrate_two_axis`.

    system : the calibrated System (``calibration`` holds σ and RMS);
    names : estimated parameters; values, std : (P,); cov : (P, P);
    walls : (W, 3) α, β (rad), dist (m) per wall; rms_px, rms_L (m);
    n_obs : shots used; chi2_dof.
    """

    system: System
    names: tuple
    values: np.ndarray
    std: np.ndarray
    cov: np.ndarray
    walls: np.ndarray
    rms_px: float
    rms_L: float
    n_obs: int
    chi2_dof: float

    def report(self) -> str:
        lines = [f"{n:18s} {v: .6g} ± {s:.2g}" for n, v, s in zip(self.names, self.values,
                                                                   self.std)]
        lines.append(f"RMS {self.rms_px:.3f} px, {1e3 * self.rms_L:.1f} mm path; "
                     f"chi2/dof {self.chi2_dof:.2f}; {self.n_obs} shots")
        return "\n".join(lines)


def _plane_normal(alpha, beta):
    return np.array([math.sin(alpha) * math.cos(beta), math.sin(beta),
                     math.cos(alpha) * math.cos(beta)])


def predict_wall(system: System, obs: WallObservations, wall):
    sc = system.scanner
    a2 = sc.axis2
    th1 = sc.theta0 + sc.theta_mech_max * np.cos(obs.phase1 + sc.phase_offset)
    if a2.mode == "resonant":
        th2 = a2.theta0 + a2.theta_mech_max * np.cos(obs.phase2 + a2.phase_offset)
    else:
        th2 = a2.theta0 + obs.theta2_mech
    d = scan_direction_2d(th1, th2, sc)
    p = np.asarray(sc.position, float)
    nrm = _plane_normal(wall[0], wall[1])
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (wall[2] - nrm @ p) / (d @ nrm)
    x = p + s[:, None] * d
    rc = system.receiver
    K = rc.camera_matrix
    if np.any(rc.dist_coeffs):
        from mems_stereo.model.camera import project_points

        uv = project_points(x, K, rc.dist_coeffs)
    else:
        uv = np.stack([K[0, 0] * x[:, 0] / x[:, 2] + K[0, 2],
                       K[1, 1] * x[:, 1] / x[:, 2] + K[1, 2]], axis=1)
    L = s + np.linalg.norm(x, axis=1) + system.speed_of_light * system.tdc.offset
    return uv, L


def _initial_wall(system: System, obs: WallObservations):
    """Plane through the nominal beam points at the measured path lengths (SVD)."""
    from mems_stereo.geometry.triangulation import scanner_ray_point

    sc = system.scanner
    a2 = sc.axis2
    th1 = sc.theta0 + sc.theta_mech_max * np.cos(obs.phase1 + sc.phase_offset)
    th2 = (a2.theta0 + a2.theta_mech_max * np.cos(obs.phase2 + a2.phase_offset)
           if a2.mode == "resonant" else a2.theta0 + obs.theta2_mech)
    d = scan_direction_2d(th1, th2, sc)
    x = scanner_ray_point(sc.position, d, obs.L_raw - system.speed_of_light * system.tdc.offset)[0]
    x = x[np.all(np.isfinite(x), axis=1)]
    if x.shape[0] < 10:
        raise NotObservableError(f"{obs.source}: fewer than 10 shots with a wall point")
    c = np.median(x, axis=0)
    nrm = np.linalg.svd(x - c, full_matrices=False)[2][-1]
    if nrm[2] < 0:
        nrm = -nrm
    return np.array([math.atan2(nrm[0], nrm[2]), math.asin(np.clip(nrm[1], -1, 1)),
                     float(nrm @ c)])


@dataclass
class _Problem:
    """The least-squares problem: z = (scaled parameter steps, walls (α, β, dist))."""

    sys0: System
    free: tuple
    x0: np.ndarray
    scale: np.ndarray
    obs: list
    s_uv: float
    sl: float
    prior_index: np.ndarray = None  # indices into free of parameters with a prior
    prior_mean: np.ndarray = None
    prior_std: np.ndarray = None

    def unpack(self, z):
        k = len(self.free)
        vals = self.x0 + z[:k] * self.scale
        return (with_params_2d(self.sys0, **dict(zip(self.free, vals))),
                z[k:].reshape(len(self.obs), 3))

    def resid(self, z, keep=None):
        s_, walls = self.unpack(z)
        out = []
        for i, o in enumerate(self.obs):
            uv, L = predict_wall(s_, o, walls[i])
            out.append(np.concatenate([(o.uv - uv).ravel() / self.s_uv,
                                       (o.L_raw - L) * np.sqrt(o.n) / self.sl]))
        if self.prior_index is not None and self.prior_index.size:
            vals = self.x0 + z[:len(self.free)] * self.scale
            out.append((vals[self.prior_index] - self.prior_mean) / self.prior_std)
        r = np.nan_to_num(np.concatenate(out), nan=1e3)
        return r if keep is None else r[keep]


def _inputs(recordings, system: System | None, observations):
    """The recordings (read, their monitors and gate checked) and the starting system;
    no recordings where ``observations`` are given."""
    if observations is not None:  # already reduced (tests, custom front ends)
        recs = []
        if system is None or len(observations) < 2:
            raise NotObservableError("two-axis calibration from observations: expected a "
                                     "system and >= 2 walls")
    else:
        recs = [r if isinstance(r, Recording2D) else read_recording_2d(r, truth=False)
                for r in recordings]
        if len(recs) < 2:
            raise NotObservableError("two-axis calibration: expected walls at >= 2 distances, "
                                     f"found {len(recs)} recording(s)")
        for r in recs:  # monitors and gate must agree (a FormatError naming the field)
            check_gate(r)
    sys0 = recs[0].system if system is None else system
    for r in recs:  # every code within the TDC of the system used
        check_codes_fit(r.event_code, sys0.tdc.n_bins, r.source, "/events/code",
                        r.system.tdc.n_bins)
    return recs, sys0


def _intrinsics_prior(sys0: System, intrinsics) -> dict:
    """name → (mean, σ) px of the Gaussian prior on fx, fy, cx, cy from the ChArUco σ."""
    prior = {}
    std_i = np.asarray(intrinsics.std, float).ravel()
    std4 = np.zeros(4)
    std4[:min(4, std_i.size)] = std_i[:4]
    if std4[0] <= 0 < std4[1] or std4[1] <= 0 < std4[0]:
        std4[:2] = max(std4[0], std4[1])  # fixed aspect ratio: fx and fy move together
    for j, n in enumerate(("fx", "fy", "cx", "cy")):
        sd = float(std4[j]) if std4[j] > 0 else None
        if sd is not None:
            prior[n] = (get_param_2d(sys0, n), sd)
    return prior


def _solve(prob: _Problem, z0: np.ndarray):
    """Soft-ℓ1 least squares from ``z0``, then plain least squares without the > 5σ
    residuals (a ``scipy.optimize.OptimizeResult``)."""
    fit = least_squares(prob.resid, z0, loss="soft_l1", f_scale=3.0, x_scale="jac",
                        max_nfev=100)
    keep = np.abs(prob.resid(fit.x)) < 5.0
    fit = least_squares(prob.resid, fit.x, args=(keep,), x_scale="jac", max_nfev=100)
    if not fit.success:
        raise NotObservableError(f"two-axis calibration did not converge: {fit.message}")
    return fit


def _calibration(prob: _Problem, fit) -> TwoAxisCalibration:
    """Covariance ``(JᵀJ)⁻¹ · χ²/dof`` and RMS of the fit ``fit`` of ``prob``."""
    free, scale, obs = prob.free, prob.scale, prob.obs
    J = fit.jac
    dof = max(1, J.shape[0] - J.shape[1])
    chi2 = float(fit.fun @ fit.fun) / dof
    JTJ = J.T @ J
    if np.linalg.cond(JTJ) > 1e14:
        raise NotObservableError("two-axis calibration: singular normal matrix (walls too few "
                                 "or too alike to separate the parameters)")
    cov_z = np.linalg.inv(JTJ) * chi2
    npar = len(free)
    cov = cov_z[:npar, :npar] * np.outer(scale, scale)
    std = np.sqrt(np.diag(cov))
    est, walls = prob.unpack(fit.x)
    vals = np.array([get_param_2d(est, n) for n in free])
    # RMS of the kept residuals in their own units
    uv_res, L_res, n_obs = [], [], 0
    for i, o in enumerate(obs):
        uv, L = predict_wall(est, o, walls[i])
        uv_res.append(np.linalg.norm(o.uv - uv, axis=1))
        L_res.append(o.L_raw - L)
        n_obs += o.n.size
    uv_res, L_res = np.concatenate(uv_res), np.concatenate(L_res)
    ok = np.isfinite(uv_res) & (uv_res < 5) & np.isfinite(L_res)
    rms_px = float(np.sqrt(np.mean(uv_res[ok] ** 2)))
    rms_L = float(np.sqrt(np.mean(L_res[ok] ** 2)))
    calib = {"method": "two-axis walls", "std": dict(zip(free, std.tolist())),
             "rms_px": rms_px, "rms_path_m": rms_L, "chi2_dof": chi2, "n_shots": int(n_obs),
             "walls": walls.tolist()}
    est = est.replace(calibration=calib)
    return TwoAxisCalibration(est, free, vals, std, cov, walls, rms_px, rms_L, int(n_obs), chi2)


def calibrate_two_axis(recordings, system: System | None = None, *, intrinsics=None,
                       free=None, refine_intrinsics: bool = True,
                       timing_jitter: float = 50e-12, spot_sigma_px: float = 0.25,
                       observations=None) -> TwoAxisCalibration:
    """Estimate a two-axis system from recordings of flat walls (poses unknown).

    Parameters
    ----------
    recordings : paths or :class:`Recording2D` of walls at two or more distances.
    system : the starting (nominal) system; default the first recording's.
    intrinsics : optional :class:`mems_stereo.calib.intrinsics.IntrinsicsResult`
        (ChArUco): its camera matrix and distortion replace the system's; with
        ``refine_intrinsics`` fx, fy, cx, cy are refined in the joint fit with
        the ChArUco σ as a Gaussian prior.
    free : parameter names to estimate (default ``TWO_AXIS_PARAMS``; for a
        raster mirror without ``theta_mech_max_2`` and ``phase_offset_2``).
    refine_intrinsics : add fx, fy, cx, cy to the free parameters (needs ``intrinsics``).
    timing_jitter, spot_sigma_px : σ model of the residuals (s, px).
    observations : optional list of :class:`WallObservations` used instead of
        ``recordings`` (one fit, no reclassification; ``system`` required).

    Raises :class:`NotObservableError` when the fit fails (no result is made).
    """
    recs, sys0 = _inputs(recordings, system, observations)
    a2 = require_two_axis(sys0)
    if intrinsics is not None:
        sys0 = sys0.replace(receiver=replace(
            sys0.receiver, camera_matrix=np.asarray(intrinsics.camera_matrix, float),
            dist_coeffs=np.asarray(intrinsics.dist_coeffs, float).ravel()))
    if free is None:
        free = TWO_AXIS_PARAMS if a2.mode == "resonant" else tuple(
            n for n in TWO_AXIS_PARAMS if n not in ("theta_mech_max_2", "phase_offset_2"))
    free = tuple(free)
    prior = {}
    if intrinsics is not None and refine_intrinsics:
        prior = _intrinsics_prior(sys0, intrinsics)
        free = free + tuple(n for n in prior if n not in free)
    x0 = np.array([get_param_2d(sys0, n) for n in free])
    scale = np.array([1e-3 if "theta" in n or "phase" in n else
                      (1e-3 if "baseline" in n else (1.0 if n in _K_INDEX else 1e-9))
                      for n in free])
    p_idx = np.array([free.index(n) for n in prior], dtype=np.int64)
    p_mean = np.array([prior[n][0] for n in prior])
    p_std = np.array([prior[n][1] for n in prior])

    current = sys0
    for _ in range(1 if observations is not None else 2):  # classify, fit, reclassify, refit
        obs = (list(observations) if observations is not None
               else [wall_observations(r, current) for r in recs])
        walls0 = [_initial_wall(current, o) for o in obs]
        sl = current.speed_of_light * timing_sigma(current, timing_jitter)
        s_uv = math.sqrt(1.0 / 12.0 + spot_sigma_px ** 2)
        prob = _Problem(sys0, free, x0, scale, obs, s_uv, sl, p_idx, p_mean, p_std)
        z0 = np.concatenate([(np.array([get_param_2d(current, n) for n in free]) - x0) / scale,
                             np.concatenate(walls0)])
        fit = _solve(prob, z0)
        current = prob.unpack(fit.x)[0]
    return _calibration(prob, fit)
