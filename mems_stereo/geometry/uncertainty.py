"""First-order propagation of a detection's spreads into points (paper Eqs. 10–17, generalised).

A detection is measured as pixel coordinates ``(u, v)`` (column, row; px),
a path length ``L = c·t_TOF`` (m) and the shot's scan angle ``θ`` (rad).
Their 1-σ spreads (:class:`Spreads`) come from

* the pixel extent: a photon lands uniformly over the photosensitive width
  of the pixel, σ² = extent²/12 (paper Eq. 11 with d_SPAD; here in pixel
  units, optionally widened by the image of the laser spot);
* the timing: TDC quantisation bin²/12 (paper Eq. 13), the laser pulse
  (Gaussian, σ = FWHM / 2.3548) and the trigger/SPAD jitter, added in
  quadrature (the paper keeps only the quantisation);
* the scan angle (zero-crossing interpolation, monitor noise);
* optionally the covariance of calibrated system parameters (names as in
  :meth:`mems_stereo.model.system.System.with_params`).

Every estimator maps ``(system, u, v, L, θ) -> (N, 3)`` points; its
covariance is ``J Σ Jᵀ`` with ``J`` from central differences (exact to first
order, like the paper's first-order second-moment method).  Points and
covariances are metres in the receiver camera frame; polar ``(r, φ)`` with
``r = |x|`` and ``φ = atan2(z, x)`` as the paper's Eqs. 14–15.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mems_stereo.errors import GeometryError, OptionError
from mems_stereo.geometry.triangulation import (
    epipolar_stereo_point,
    paper_eq8_z,
    paper_eq9_x,
    paper_mu_pix,
    pixel_ray_point,
    scanner_ray_point,
)
from mems_stereo.model.camera import pixels_to_rays
from mems_stereo.model.scanner import scan_direction
from mems_stereo.model.system import System
from mems_stereo.model.tdc import path_length_from_codes
from mems_stereo.physics.pulse import pulse_sigma_of
from mems_stereo.physics.spot import DEFAULT_SPOT_SIGMA

#: default 1-σ scan-angle uncertainty, rad (mirror angle; the beam turns by 2θ)
DEFAULT_SIGMA_THETA = 1e-4

INPUTS = ("u", "v", "L", "theta")
DIFF_STEPS = {"u": 1e-3, "v": 1e-3, "L": 1e-4, "theta": 1e-7}


@dataclass(frozen=True)
class Spreads:
    """1-σ spreads of a detection's measurements.

    Attributes
    ----------
    sigma_u, sigma_v : float, pixels (column, row) — pixel extent (+ spot image).
    sigma_t : float, s — total timing spread (quadrature sum of the parts below).
    sigma_theta : float, rad — scan (mirror) angle.
    sigma_t_pulse, sigma_t_jitter, sigma_t_quant : float, s — the timing parts.
    param_names : tuple of system parameter names with a covariance.
    param_cov : (P, P) float64 or None, covariance of those parameters (SI).
    """

    sigma_u: float
    sigma_v: float
    sigma_t: float
    sigma_theta: float
    sigma_t_pulse: float = 0.0
    sigma_t_jitter: float = 0.0
    sigma_t_quant: float = 0.0
    param_names: tuple = ()
    param_cov: np.ndarray | None = None

    def sigma_L(self, system: System) -> float:
        """1-σ spread of the path length, m (c · σ_t)."""
        return system.speed_of_light * self.sigma_t

    def input_sigmas(self, system: System) -> dict:
        return {"u": self.sigma_u, "v": self.sigma_v, "L": self.sigma_L(system),
                "theta": self.sigma_theta}


def pixel_extent_px(system: System, model: str = "pixel") -> tuple[float, float]:
    """Photosensitive extent of a pixel in pixel units, (along columns, along rows).

    ``model="pixel"`` (default): the whole pixel footprint, (1, 1) — a photon
    anywhere on the pixel counts (SPADs plus the optics' spread between them).
    ``model="spad"``: the paper's Eq. 11, the SPAD diameter horizontally
    (capped at the pitch) and the full pixel vertically (the SPADEye2 stacks
    4 SPADs over its 209.6 µm height).
    """
    if model == "pixel":
        return 1.0, 1.0
    if model != "spad":
        raise OptionError(f"pixel extent model: expected 'pixel' or 'spad', found {model!r}")
    rc = system.receiver
    ex = min(float(rc.spad_diameter), float(rc.pixel_pitch[0])) / float(rc.pixel_pitch[0])
    return ex, 1.0


def spreads_for(system: System, *, timing_jitter: float = 0.0,
                sigma_theta: float = DEFAULT_SIGMA_THETA, include_pulse: bool = True,
                spot_sigma: float = DEFAULT_SPOT_SIGMA, pixel_extent: str = "pixel",
                param_names=(), param_cov=None) -> Spreads:
    """The spreads of the system's detections (the package's default model).

    Parameters
    ----------
    timing_jitter : float, s, 1-σ trigger + SPAD jitter.
    sigma_theta : float, rad, 1-σ scan (mirror) angle.
    include_pulse : add the laser pulse (its σ, :func:`~mems_stereo.physics.pulse.pulse_sigma_of`:
        pulse_fwhm / 2.3548 for the Gaussian).
    spot_sigma : float, m on the sensor, 1-σ of the laser spot's image,
        added in quadrature to the pixel extent (converted with the pitch).
    pixel_extent : ``"pixel"`` or ``"spad"``, see :func:`pixel_extent_px`.
    param_names, param_cov : optional calibration covariance (P names, (P, P)).
    """
    ex, ey = pixel_extent_px(system, pixel_extent)
    pitch = np.asarray(system.receiver.pixel_pitch, dtype=np.float64)
    su = math.sqrt(ex * ex / 12.0 + (spot_sigma / pitch[0]) ** 2)
    sv = math.sqrt(ey * ey / 12.0 + (spot_sigma / pitch[1]) ** 2)
    sp = pulse_sigma_of(system.laser) if include_pulse else 0.0  # docs/hardware.md
    sq = system.tdc.bin_width / math.sqrt(12.0)
    st = math.sqrt(sp * sp + timing_jitter ** 2 + sq * sq)
    names = tuple(param_names)
    cov = None
    if names:
        cov = np.asarray(param_cov, dtype=np.float64)
        if cov.shape != (len(names), len(names)):
            raise GeometryError(f"param_cov: expected shape ({len(names)}, {len(names)}), "
                                f"found {cov.shape}")
    return Spreads(su, sv, st, float(sigma_theta), sp, float(timing_jitter), sq, names, cov)


def paper_spreads(system: System) -> Spreads:
    """The paper's model (Eqs. 11, 13): σ_pix = d_SPAD/√12, σ_TOF = t_bin/√12, nothing else."""
    su = system.receiver.spad_diameter / system.receiver.pixel_pitch[0] / math.sqrt(12.0)
    sq = system.tdc.bin_width / math.sqrt(12.0)
    return Spreads(float(su), 0.0, sq, 0.0, 0.0, 0.0, sq)


# --------------------------------------------------------------------------
# estimators: (system, u, v, L, theta) -> (N, 3) points


def pixel_rays(system: System, u, v) -> np.ndarray:
    """(N, 3) unit rays of the receiver's pixels at (u, v) (N,) each."""
    rc = system.receiver
    return pixels_to_rays(np.stack([u, v], axis=1), rc.camera_matrix, rc.dist_coeffs)


def tof_point(system: System, u, v, L, theta) -> np.ndarray:
    """Time-of-flight estimate: the point at path length L on the scanner ray (uses L, θ)."""
    d = scan_direction(theta, system.scanner)
    return scanner_ray_point(system.scanner.position, d, L)[0]


def tof_pixel_point(system: System, u, v, L, theta) -> np.ndarray:
    """Time-of-flight estimate on the pixel ray (uses u, v, L): a plain dtof camera's point."""
    return pixel_ray_point(system.scanner.position, pixel_rays(system, u, v), L)[0]


def stereo_point_est(system: System, u, v, L, theta) -> np.ndarray:
    """Stereo estimate: pixel ray ∩ scanner ray in the epipolar plane (uses u, v, θ; no time)."""
    d = scan_direction(theta, system.scanner)
    return epipolar_stereo_point(system.scanner.position, d, pixel_rays(system, u, v)).points


def paper_point(system: System, u, v, L, theta) -> np.ndarray:
    """The paper's 2-D point (Eqs. 8–9): Z from L and the beam angle, X from the pixel.

    y is 0.  Uses the pinhole focal length f = f_x · pitch_x and Eq. 10's μ_pix.
    """
    from mems_stereo.geometry.triangulation import beam_angle

    d = scan_direction(theta, system.scanner)
    Z = paper_eq8_z(L, beam_angle(d), float(system.scanner.position[0]))
    f = system.receiver.camera_matrix[0, 0] * system.receiver.pixel_pitch[0]
    X = paper_eq9_x(paper_mu_pix(u, system), Z, f)
    return np.stack([X, np.zeros_like(X), Z], axis=-1)


Estimator = Callable[..., np.ndarray]


def as_inputs(u, v, L, theta) -> dict:
    """The inputs as a mapping of broadcast 1-D float64 arrays keyed by :data:`INPUTS`."""
    arrs = np.broadcast_arrays(*(np.atleast_1d(np.asarray(a, dtype=np.float64))
                                 for a in (u, v, L, theta)))
    if arrs[0].ndim != 1:
        raise GeometryError(f"u, v, L, theta: expected 1-D arrays, found shape {arrs[0].shape}")
    return dict(zip(INPUTS, arrs))


def jacobian(fn: Estimator, system: System, u, v, L, theta, wrt=INPUTS,
             row_local: bool = False):
    """Value and central-difference Jacobian of an estimator.

    Returns ``(x (N, 3), J (N, 3, len(wrt)))``; derivatives per px, per m,
    per rad.  Rows where the estimator gives NaN stay NaN.  ``row_local``: see
    :func:`central_differences`.
    """
    return central_differences(fn, system, as_inputs(u, v, L, theta), DIFF_STEPS, wrt,
                               row_local)


def central_differences(fn: Estimator, system: System, inputs: dict, steps: dict, wrt,
                        row_local: bool = False):
    """``fn(system, **inputs)`` (N, 3) and its central-difference Jacobian (N, 3, len(wrt))
    with respect to the inputs named in ``wrt``, each with its step ``steps[name]``
    (one- and two-axis estimators alike).  ``row_local``: ``fn`` computes each row from
    that row's inputs alone (no reduction or matrix product across rows), so the
    1 + 2·len(wrt) variants are evaluated in one call on the inputs laid end to end,
    the same bits with one call's overhead."""
    variants = [inputs]
    for name in wrt:
        h = steps[name]
        plus, minus = dict(inputs), dict(inputs)
        plus[name] = inputs[name] + h
        minus[name] = inputs[name] - h
        variants += [plus, minus]
    if row_local:
        n = next(iter(inputs.values())).size
        x = fn(system, **{k: np.concatenate([v[k] for v in variants]) for k in inputs})
        xs = [x[i * n:(i + 1) * n] for i in range(len(variants))]
    else:
        xs = [fn(system, **v) for v in variants]
    cols = [(xs[1 + 2 * i] - xs[2 + 2 * i]) / (2.0 * steps[name]) for i, name in enumerate(wrt)]
    return xs[0], np.stack(cols, axis=-1)


def param_jacobian(fn: Estimator, system: System, u, v, L, theta, names, steps=None):
    """Jacobian of an estimator with respect to named system parameters, (N, 3, P)."""
    x_in = as_inputs(u, v, L, theta)
    cols = []
    for i, name in enumerate(names):
        v0 = system.get_param(name)
        h = (steps[i] if steps is not None else 1e-6 * max(1.0, abs(v0)))
        xp = fn(system.with_params(**{name: v0 + h}), **x_in)
        xm = fn(system.with_params(**{name: v0 - h}), **x_in)
        cols.append((xp - xm) / (2.0 * h))
    return np.stack(cols, axis=-1)


def propagate(fn: Estimator, system: System, u, v, L, theta, spreads: Spreads,
              row_local: bool = False):
    """Point and Cartesian covariance of an estimator, first order.

    Parameters
    ----------
    fn : an estimator ``(system, u, v, L, theta) -> (N, 3)`` (e.g. :func:`tof_point`).
    u, v : (N,) px; L : (N,) m; theta : (N,) rad (scalars broadcast).
    spreads : :class:`Spreads` (inputs independent; the calibration
        covariance, when given, is added through the parameter Jacobian).
    row_local : ``fn`` computes each row on its own (:func:`central_differences`).

    Returns
    -------
    x : (N, 3) float64, m, receiver camera frame (NaN where degenerate).
    cov : (N, 3, 3) float64, m².
    """
    x, J = jacobian(fn, system, u, v, L, theta, row_local=row_local)
    s = spreads.input_sigmas(system)
    var = np.array([s[n] ** 2 for n in INPUTS])
    cov = np.einsum("nik,k,njk->nij", J, var, J)
    if spreads.param_names:
        Jp = param_jacobian(fn, system, u, v, L, theta, spreads.param_names)
        cov = cov + np.einsum("nik,kl,njl->nij", Jp, spreads.param_cov, Jp)
    return x, cov


# --------------------------------------------------------------------------
# polar coordinates (paper Eqs. 14–17)


@dataclass(frozen=True, slots=True)
class Polar:
    """Points in the paper's polar coordinates of the x–z plane, with σ (Eqs. 14–17).

    Attributes
    ----------
    r : (N,) float64, range ‖x‖ from the projection centre, m.
    phi : (N,) float64, angle atan2(z, x) in the receiver frame, rad.
    sigma_r : (N,) float64, standard deviation of r, m (NaN without a covariance).
    sigma_phi : (N,) float64, standard deviation of φ, rad (NaN without a covariance).
    """

    r: np.ndarray
    phi: np.ndarray
    sigma_r: np.ndarray
    sigma_phi: np.ndarray


def polar_from_cartesian(points, cov=None) -> Polar:
    """Range r = ‖x‖ and angle φ = atan2(z, x) (x–z plane), with propagated σ.

    ``points`` : (N, 3) m; ``cov`` : (N, 3, 3) m² or None.
    Returns :class:`Polar` of (N,) arrays (σ NaN without cov).
    """
    x = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    r = np.linalg.norm(x, axis=1)
    phi = np.arctan2(x[:, 2], x[:, 0])
    if cov is None:
        nan = np.full(r.shape, np.nan)
        return Polar(r, phi, nan, nan)
    C = np.asarray(cov, dtype=np.float64).reshape(-1, 3, 3)
    with np.errstate(invalid="ignore", divide="ignore"):
        gr = x / r[:, None]
        rxz2 = x[:, 0] ** 2 + x[:, 2] ** 2
        gp = np.stack([-x[:, 2], np.zeros_like(r), x[:, 0]], axis=1) / rxz2[:, None]
    sr = np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", gr, C, gr), 0.0))
    sp = np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", gp, C, gp), 0.0))
    return Polar(r, phi, sr, sp)


def paper_polar_uncertainty(system: System, columns, codes, theta,
                            spreads: Spreads | None = None) -> Polar:
    """The paper's Eqs. 14–17 for 0-based columns, TDC codes and scan angles.

    The point is Eqs. 8–9 (:func:`paper_point`), the inputs the pixel
    position and the time of flight (and, unlike the paper, the scan angle
    when ``spreads.sigma_theta > 0``).  Defaults to :func:`paper_spreads`.
    Returns :class:`Polar`: μ_r, μ_φ (``r``, ``phi``) and σ_r, σ_φ, each (N,): m, rad.
    """
    sp = paper_spreads(system) if spreads is None else spreads
    L = path_length_from_codes(codes, system.tdc, system.speed_of_light)
    x, cov = propagate(paper_point, system, columns, 0.0, L, theta, sp)
    return polar_from_cartesian(x, cov)


def sigmas_xyz(cov) -> np.ndarray:
    """Standard deviations along x, y, z of covariances (N, 3, 3): (N, 3), m."""
    C = np.asarray(cov, dtype=np.float64)
    return np.sqrt(np.maximum(np.diagonal(C, axis1=-2, axis2=-1), 0.0))
