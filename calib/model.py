"""Forward model of a flat-target calibration recording and its residuals.

For each signal detection (target j, shot with monitor phase φ):

* scan angle ``θ = θ0 + A·cos(φ + δ)`` (A = theta_mech_max, δ = phase_offset);
* scan direction ``d`` by the reflection law, from the scanner at ``p``
  (baseline_x, baseline_y, baseline_z);
* the beam meets target j's plane ``n_j·x = D_j`` at ``P = p + s·d``,
  ``s = (D_j − n_j·p) / (n_j·d)``; ``n_j = (sin α cos β, sin β, cos α cos β)``
  (β only for 2-D arrays; a line sensor sees the x–z plane only);
* pixel residual: measured column (and row) minus the projection of P,
  divided by σ_pix (the pixel's extent, pitch/√12 → 1/√12 px);
* time residual: measured TDC time ``(N − ½)·bin_width`` minus the expected
  first-photon time of a return centred at ``τ0 = (s + |P|)/c + offset``
  (:func:`mems_stereo.physics.first_photon.first_photon_timing`: truncation at the TDC
  start, first of several
  photons, background), divided by that distribution's σ.

All frames: receiver camera frame (OpenCV), metres, radians, seconds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mems_stereo.model.camera import project_points
from mems_stereo.model.system import System

#: system parameters the fit knows, in the order of the parameter vector
SYSTEM_PARAMS = ("theta0", "theta_mech_max", "phase_offset", "tdc_offset",
                 "baseline_x", "baseline_y", "baseline_z", "fx", "cx")
#: free by default
DEFAULT_FREE = ("theta0", "theta_mech_max", "phase_offset", "tdc_offset",
                "baseline_x", "baseline_y", "baseline_z")
#: the size of "one unit" of each parameter inside the solver (and in reports)
PARAM_SCALE = {"theta0": 1e-3, "theta_mech_max": 1e-3, "phase_offset": 1e-3,
               "tdc_offset": 1e-10, "baseline_x": 1e-3, "baseline_y": 1e-3,
               "baseline_z": 1e-3, "fx": 1.0, "cx": 0.1,
               "alpha": 1e-3, "beta": 1e-3, "dist": 1e-3}
#: the hardware model's terms the fit can estimate (docs/hardware.md): harmonics of the
#: mirror's trajectory (relative to theta_mech_max) and the monitor's rising-edge delay
#: (the falling edge's is held: their mean is the phase offset's)
MAX_HARMONIC = 8
HARDWARE_PARAMS = tuple(f"harmonic{k}_{p}" for k in range(2, MAX_HARMONIC + 1)
                        for p in ("cos", "sin")) + ("edge_rising_delay",)
PARAM_SCALE.update({n: 1e-4 for n in HARDWARE_PARAMS[:-1]})
PARAM_SCALE["edge_rising_delay"] = 1e-8
#: units for reports: (factor, unit)
PARAM_UNIT = {"theta0": (1e3, "mrad"), "theta_mech_max": (1e3, "mrad"),
              "phase_offset": (1e3, "mrad"), "tdc_offset": (1e9, "ns"),
              "baseline_x": (1e3, "mm"), "baseline_y": (1e3, "mm"), "baseline_z": (1e3, "mm"),
              "fx": (1.0, "px"), "cx": (1.0, "px"), "alpha": (1e3, "mrad"),
              "beta": (1e3, "mrad"), "dist": (1e3, "mm")}
PARAM_UNIT.update({n: (1e2, "%") for n in HARDWARE_PARAMS[:-1]})
PARAM_UNIT["edge_rising_delay"] = (1e9, "ns")
#: the pulse's ex-gaussian tail (share w, decay τ, s; ``docs/hardware.md``): fitted in
#: the time likelihood (:func:`mems_stereo.calib.problem.cell_terms`), not in the phase
PULSE_PARAMS = ("pulse_tail_fraction", "pulse_tail_decay")
PARAM_SCALE.update({"pulse_tail_fraction": 1e-2, "pulse_tail_decay": 1e-9})
PARAM_UNIT.update({"pulse_tail_fraction": (1e2, "%"), "pulse_tail_decay": (1e9, "ns")})


def harmonic_orders(orders=(2, 3, 4, 5)) -> list:
    """The fit's names of the harmonics of ``orders``: harmonic{k}_cos, harmonic{k}_sin."""
    return [f"harmonic{k}_{p}" for k in orders for p in ("cos", "sin")]


def trajectory(values: dict, phase) -> np.ndarray:
    """g(ψ) = cos ψ + Σ_k (c_k cos kψ + s_k sin kψ) of ψ = ``phase`` (+ offset), with the
    harmonic coefficients ``harmonic{k}_cos`` / ``_sin`` found in ``values``."""
    g = np.cos(phase)
    for name, v in values.items():
        if name.startswith("harmonic") and v != 0.0:
            k = int(name[8:name.index("_")])
            g = g + v * (np.cos(k * phase) if name.endswith("_cos") else np.sin(k * phase))
    return g


def plane_normal(alpha, beta=0.0) -> np.ndarray:
    """Unit normal (sin α cos β, sin β, cos α cos β), (..., 3): α tilts about y, β about x."""
    a = np.asarray(alpha, dtype=np.float64)
    b = np.asarray(beta, dtype=np.float64)
    a, b = np.broadcast_arrays(a, b)
    return np.stack([np.sin(a) * np.cos(b), np.sin(b), np.cos(a) * np.cos(b)], axis=-1)


@dataclass(frozen=True)
class BeamHits:
    """Where the beam of each shot meets its target plane.

    point : (N, 3) m, camera frame; path : (N,) m, mirror → P → projection
    centre (s + |P|); pixel : (N, 2) (column, row) of P; ok : (N,) bool (the
    beam meets the plane ahead of the mirror and P is in front of the camera).
    """

    point: np.ndarray
    path: np.ndarray
    pixel: np.ndarray
    ok: np.ndarray


def beam_rays(system: System, values: dict, phase) -> tuple[np.ndarray, np.ndarray]:
    """The beam of each shot (monitor ``phase`` (N,) rad; ``values`` as
    :func:`beam_hits`): (origin (3,) m, the mirror's centre in the camera frame;
    directions (N, 3) unit vectors, camera frame)."""
    def v(name):
        return values[name] if name in values else system.get_param(name)

    sc = system.scanner
    psi = np.asarray(phase) + v("phase_offset")
    if sc.harmonics or any(n.startswith("harmonic") for n in values):
        coef = {f"harmonic{h.order}_{p}": system.get_param(f"harmonic{h.order}_{p}")
                for h in sc.harmonics for p in ("cos", "sin")}
        coef.update({n: x for n, x in values.items() if n.startswith("harmonic")})
        th = v("theta0") + v("theta_mech_max") * trajectory(coef, psi)
    else:
        th = v("theta0") + v("theta_mech_max") * np.cos(psi)
    e1, e2 = np.asarray(sc.normal_basis, dtype=np.float64)
    dl = np.asarray(sc.laser_direction, dtype=np.float64)
    c, s_ = np.cos(th)[:, None], np.sin(th)[:, None]
    nm = c * e1 + s_ * e2
    d = dl - 2.0 * (nm @ dl)[:, None] * nm
    return np.array([v("baseline_x"), v("baseline_y"), v("baseline_z")]), d


def beam_hits(system: System, values: dict, phase, normals, dists) -> BeamHits:
    """Forward model of beam → plane → receiver for shots with monitor ``phase``.

    Parameters
    ----------
    system : provides the fixed parts (normal basis, laser direction, fy, cy,
        distortion).
    values : the scalar parameters (names of :data:`SYSTEM_PARAMS`) in SI
        units; missing names are taken from ``system``.
    phase : (N,) rad, monitor phase of each shot.
    normals : (N, 3) or (3,) unit plane normals; dists : (N,) or scalar, m,
        plane offsets D.
    """
    def v(name):
        return values[name] if name in values else system.get_param(name)

    p, d = beam_rays(system, values, phase)
    normals = np.asarray(normals, dtype=np.float64)
    nd = d @ normals if normals.ndim == 1 else np.sum(normals * d, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (dists - normals @ p) / nd
    P = p + s[:, None] * d
    ok = np.isfinite(s) & (s > 0) & (P[:, 2] > 0)
    path = s + np.sqrt(np.einsum('ij,ij->i', P, P))
    K = np.array(system.receiver.camera_matrix, dtype=np.float64)
    K[0, 0], K[0, 2] = v("fx"), v("cx")
    dist_coeffs = np.asarray(system.receiver.dist_coeffs, dtype=np.float64)
    if not np.any(dist_coeffs):
        with np.errstate(divide="ignore", invalid="ignore"):
            xn, yn = P[:, 0] / P[:, 2], P[:, 1] / P[:, 2]
        pix = np.stack([K[0, 0] * xn + K[0, 1] * yn + K[0, 2], K[1, 1] * yn + K[1, 2]], axis=1)
    else:
        Pq = np.where(ok[:, None], P, [0.0, 0.0, 1.0])
        pix = project_points(Pq, K, dist_coeffs)
    pix[~ok] = np.nan
    return BeamHits(P, path, pix, ok)


def code_time(code, bin_width: float) -> np.ndarray:
    """TDC time (N − ½)·bin_width of codes N, s (before the offset is removed)."""
    return (np.asarray(code, dtype=np.float64) - 0.5) * bin_width
