"""3-D triangulation and uncertainty for a two-axis scanner and a 2-D SPAD array.

A detection of the two-axis system is measured as a pixel ``(u, v)``
(column, row; px), a path length ``L = c · t_TOF`` (m, mirror → target →
projection centre) and the shot's two mirror angles ``(θ1, θ2)`` (rad).  The
target lies on the ellipsoid ``|x − p| + |x| = L`` with foci at the mirror
``p`` and the projection centre (origin); two estimators use the closed forms
of :mod:`mems_stereo.geometry.triangulation` (which are general 3-D):

* :func:`pixel_point_2d` — the pixel ray ∩ ellipsoid (uses u, v, L): the
  point of a pixel's histogram peak;
* :func:`beam_point_2d` — the beam ray ``p + s·d(θ1, θ2)`` ∩ ellipsoid (uses
  θ1, θ2, L): the point of one shot.

Uncertainty: :func:`propagate_2d` maps the spreads of the five inputs
(:class:`Spreads2D`: the pixel's 2-D extent, the timing spread, both scan
angles) to a 3 × 3 covariance ``J Σ Jᵀ`` (central-difference Jacobian, first
order).  Points and covariances: metres, receiver camera frame (OpenCV).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mems_stereo.errors import GeometryError
from mems_stereo.geometry.triangulation import pixel_ray_point, scanner_ray_point
from mems_stereo.geometry.uncertainty import central_differences
from mems_stereo.model.camera import pixels_to_rays
from mems_stereo.model.scanner2d import scan_direction_2d
from mems_stereo.model.system import System
from mems_stereo.physics.pulse import FWHM_PER_SIGMA

INPUTS_2D = ("u", "v", "L", "theta1", "theta2")
_STEPS_2D = {"u": 1e-3, "v": 1e-3, "L": 1e-4, "theta1": 1e-7, "theta2": 1e-7}


@dataclass(frozen=True)
class Spreads2D:
    """1-σ spreads of a two-axis detection's inputs.

    sigma_u, sigma_v : px (pixel extent, e.g. 1/√12 for a uniformly lit pixel).
    sigma_L : m (c × the timing spread: pulse, jitter, TDC quantisation).
    sigma_theta1, sigma_theta2 : rad (mirror angles from the monitors).
    """

    sigma_u: float
    sigma_v: float
    sigma_L: float
    sigma_theta1: float
    sigma_theta2: float

    def variances(self) -> np.ndarray:
        """(5,) float64 in the order of ``INPUTS_2D``."""
        return np.array([self.sigma_u, self.sigma_v, self.sigma_L, self.sigma_theta1,
                         self.sigma_theta2], dtype=np.float64) ** 2


def timing_sigma(system: System, timing_jitter: float = 50e-12) -> float:
    """1-σ timing spread of one detection, s: pulse (Gaussian FWHM), jitter and
    TDC quantisation (bin/√12) in quadrature."""
    sp = system.laser.pulse_fwhm / FWHM_PER_SIGMA
    sq = system.tdc.bin_width / math.sqrt(12.0)
    return math.sqrt(sp * sp + timing_jitter ** 2 + sq * sq)


def spreads_2d(system: System, *, timing_jitter: float = 50e-12, sigma_theta: float = 5e-5,
               n_average: float = 1.0) -> Spreads2D:
    """Default spreads: uniform pixel (1/√12 px each axis), the timing of
    :func:`timing_sigma` averaged over ``n_average`` detections, σθ per axis."""
    sl = system.speed_of_light * timing_sigma(system, timing_jitter) / math.sqrt(n_average)
    s = 1.0 / math.sqrt(12.0)
    return Spreads2D(s, s, sl, float(sigma_theta), float(sigma_theta))


# --------------------------------------------------------------------------
# estimators: (system, u, v, L, theta1, theta2) -> (N, 3)


def pixel_point_2d(system: System, u, v, L, theta1=None, theta2=None) -> np.ndarray:
    """Pixel ray ∩ path-length ellipsoid, (N, 3) m (NaN: no solution / behind).

    u, v : (N,) px (column, row); L : (N,) m.  θ1, θ2 are not used.
    """
    rc = system.receiver
    u, v, L = np.broadcast_arrays(*(np.atleast_1d(np.asarray(a, float)) for a in (u, v, L)))
    rays = pixels_to_rays(np.stack([u, v], axis=1), rc.camera_matrix, rc.dist_coeffs)
    return pixel_ray_point(system.scanner.position, rays, L)[0]


def beam_point_2d(system: System, u=None, v=None, L=None, theta1=None, theta2=None) -> np.ndarray:
    """Beam ray ∩ path-length ellipsoid, (N, 3) m (NaN: no solution / behind).

    L : (N,) m; theta1, theta2 : (N,) rad.  u, v are not used.
    """
    L, t1, t2 = np.broadcast_arrays(*(np.atleast_1d(np.asarray(a, float))
                                      for a in (L, theta1, theta2)))
    d = scan_direction_2d(t1, t2, system.scanner)
    return scanner_ray_point(system.scanner.position, d, L)[0]


Estimator2D = Callable[..., np.ndarray]


def _inputs(u, v, L, theta1, theta2) -> dict:
    arrs = np.broadcast_arrays(*(np.atleast_1d(np.asarray(a, dtype=np.float64))
                                 for a in (u, v, L, theta1, theta2)))
    if arrs[0].ndim != 1:
        raise GeometryError(f"u, v, L, theta1, theta2: expected 1-D arrays, found shape "
                            f"{arrs[0].shape}")
    return dict(zip(INPUTS_2D, arrs))


def jacobian_2d(fn: Estimator2D, system: System, u, v, L, theta1, theta2):
    """Value (N, 3) and central-difference Jacobian (N, 3, 5) of an estimator,
    columns in the order of ``INPUTS_2D`` (per px, per m, per rad)."""
    return central_differences(fn, system, _inputs(u, v, L, theta1, theta2), _STEPS_2D,
                               INPUTS_2D)


def propagate_2d(fn: Estimator2D, system: System, u, v, L, theta1, theta2,
                 spreads: Spreads2D):
    """Point and 3 × 3 covariance of a two-axis estimator, first order.

    Inputs (N,) each (scalars broadcast): u, v px; L m; θ1, θ2 rad.
    Returns ``x (N, 3) m`` and ``cov (N, 3, 3) m²`` (receiver camera frame),
    ``cov = J diag(σ²) Jᵀ`` with the inputs independent.
    """
    x, J = jacobian_2d(fn, system, u, v, L, theta1, theta2)
    cov = np.einsum("nik,k,njk->nij", J, spreads.variances(), J)
    return x, cov
