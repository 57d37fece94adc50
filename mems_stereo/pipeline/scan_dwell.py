"""The part of a point's error that every frame shares: the scan's dwell skew.

A pixel collects the laser's returns while the beam sweeps its footprint: the scan angles
θ at which the spot's image overlaps the pixel, a window of 1-σ width
``s_θ = σ_u·|∂r/∂u| / |∂r/∂θ|`` about the angle ``θ_c`` of the pixel's point (σ_u the
pixel extent and spot image in pixels, :func:`~mems_stereo.geometry.uncertainty.spreads_for`;
the derivatives of the stereo range at the point, so ``du/dθ`` at constant range).  The
shots are uniform in time, so their angles are dense where the mirror turns slowly:
``θ = θ0 + θ_max·cos φ`` with φ uniform gives the arcsine density, which rises steeply
toward the turning points.  The mean angle of a pixel's detections is therefore pulled
toward the nearer turning point by

    Δθ = Σ ρ(θ)·g(θ)·(θ − θ_c) / Σ ρ(θ)·g(θ),   g = N(θ_c, s_θ²)

(ρ the shots' angle density over one mechanical period, harmonics included), and the
stereo at the mean angle by ``∂x/∂θ · Δθ``: the same in every frame of a static pixel.
For the line sensor (burkard2022) it is below 1 mm over most of the field and grows to
about 7 cm at 6.6 m in the last columns (3·10⁻³ rad from a turning point), where one
frame's σ_r is 14 cm and twenty fused frames' 3 cm.
:class:`DwellSkew` gives that shift as a systematic σ of each point, weighted by the
stereo's share of the fused point (``weight_stereo``); the time-of-flight range hardly
depends on θ.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mems_stereo.geometry.uncertainty import spreads_for, stereo_point_est
from mems_stereo.model.scanner import (
    scan_angle_from_phase,
    scan_direction,
    scan_direction_derivative,
)

#: phase samples over one mechanical period (uniform in time, as the shots)
PHASE_SAMPLES = 1 << 20
#: bins of the shots' angle density over the scan's range
DENSITY_BINS = 1 << 15
#: the footprint's Gaussian is summed over ± this many σ
FOOTPRINT_SIGMAS = 4.0
#: scan-angle grid from which a point's angle is refined (:meth:`DwellSkew.angle_of`)
ANGLE_GRID = 257
#: Newton steps refining a point's angle from the grid
NEWTON_STEPS = 3
#: rad: central-difference steps of the stereo in θ and (px) in u
D_THETA, D_U = 1e-6, 1e-3


@dataclass(frozen=True, slots=True)
class Systematic:
    """The common part of N points' errors.

    sigma_r : (N,) float64 m, the range's systematic σ (0 where not defined).
    dx : (N, 3) float64 m, the systematic displacement's magnitude per axis (receiver
    camera frame; |∂x/∂θ·Δθ|·weight_stereo).
    """

    sigma_r: np.ndarray
    dx: np.ndarray


class DwellSkew:
    """The dwell skew of the mean scan angle of a system's pixels (see the module).

    ``system`` : a line-scan :class:`~mems_stereo.model.system.System`; ``spreads`` :
    the detection spreads (default :func:`spreads_for`).
    """

    def __init__(self, system, spreads=None):
        self.system = system
        sc = system.scanner
        phase = (np.arange(PHASE_SAMPLES) + 0.5) * (2.0 * np.pi / PHASE_SAMPLES)
        theta = np.asarray(scan_angle_from_phase(phase, sc), np.float64)
        lo, hi = float(theta.min()), float(theta.max())
        self.step = (hi - lo) / DENSITY_BINS
        counts = np.bincount(np.minimum(((theta - lo) / self.step).astype(np.int64),
                                        DENSITY_BINS - 1), minlength=DENSITY_BINS)
        self.lo = lo
        self.density = counts / counts.sum()
        self.sigma_u = float((spreads_for(system) if spreads is None else spreads).sigma_u)
        pad = 0.05 * (hi - lo)
        self.grid = np.linspace(lo - pad, hi + pad, ANGLE_GRID)
        self.grid_dir = scan_direction(self.grid, sc)

    def angle_of(self, points: np.ndarray) -> np.ndarray:
        """(N,) rad: the scan angle whose beam passes closest to each point (N, 3) m: the
        nearest of a coarse grid, then Newton steps on ∂(d(θ)·b)/∂θ = 0 (b the unit
        direction from the scanner to the point)."""
        sc = self.system.scanner
        b = np.asarray(points, np.float64) - np.asarray(sc.position)
        b = b / np.linalg.norm(b, axis=1, keepdims=True)
        th = self.grid[np.argmax(b @ self.grid_dir.T, axis=1)]
        h = 0.5 * (self.grid[1] - self.grid[0])
        for _ in range(NEWTON_STEPS):
            g = np.sum(scan_direction_derivative(th, sc) * b, axis=1)
            g2 = (np.sum((scan_direction_derivative(th + D_THETA, sc)
                          - scan_direction_derivative(th - D_THETA, sc)) * b, axis=1)
                  / (2 * D_THETA))
            with np.errstate(invalid="ignore", divide="ignore"):
                step = np.where(g2 < 0, -g / g2, 0.0)
            th = th + np.clip(step, -h, h)
            h = max(h * 1e-2, 1e-9)
        return th

    def mean_shift(self, theta_c: np.ndarray, s_theta: np.ndarray) -> np.ndarray:
        """(N,) rad: the mean of the shots' angles weighted by a Gaussian footprint
        N(θ_c, s_θ²), minus θ_c (0 where the footprint holds no shot or s_θ is 0)."""
        theta_c = np.asarray(theta_c, np.float64)
        s_theta = np.asarray(s_theta, np.float64)
        out = np.zeros(theta_c.size)
        ok = np.isfinite(theta_c) & np.isfinite(s_theta) & (s_theta > 0)
        if not np.any(ok):
            return out
        half = int(np.ceil(FOOTPRINT_SIGMAS * s_theta[ok].max() / self.step))
        centre = np.rint((theta_c[ok] - self.lo) / self.step - 0.5).astype(np.int64)
        idx = centre[:, None] + np.arange(-half, half + 1)[None, :]
        inside = (idx >= 0) & (idx < self.density.size)
        rho = np.where(inside, self.density[np.clip(idx, 0, self.density.size - 1)], 0.0)
        th = self.lo + (idx + 0.5) * self.step
        g = rho * np.exp(-0.5 * ((th - theta_c[ok, None]) / s_theta[ok, None]) ** 2)
        wsum = g.sum(axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = (g * (th - theta_c[ok, None])).sum(axis=1) / wsum
        out[ok] = np.where(wsum > 0, mean, 0.0)
        return out

    def systematic(self, cloud) -> Systematic:
        """The dwell skew of each point of ``cloud`` (attributes ``pixel``, ``row``
        optional, ``weight_stereo`` optional) as a :class:`Systematic`."""
        n = len(cloud)
        if n == 0:
            return Systematic(np.zeros(0), np.zeros((0, 3)))
        pts = np.asarray(cloud.points, np.float64)
        u = np.asarray(cloud["pixel"], np.float64)
        v = (np.asarray(cloud["row"], np.float64) if "row" in cloud.attributes
             else np.zeros(n))
        th = self.angle_of(pts)
        s = self.system
        # one call for the four central differences: θ ± D_THETA, u ± D_U
        x4 = stereo_point_est(s, np.concatenate([u, u, u + D_U, u - D_U]), np.tile(v, 4),
                              np.zeros(4 * n), np.concatenate([th + D_THETA, th - D_THETA,
                                                               th, th])).reshape(4, n, 3)
        r4 = np.linalg.norm(x4, axis=2)
        dx_dth = (x4[0] - x4[1]) / (2.0 * D_THETA)
        dr_dth = (r4[0] - r4[1]) / (2.0 * D_THETA)
        dr_du = (r4[2] - r4[3]) / (2.0 * D_U)
        with np.errstate(invalid="ignore", divide="ignore"):
            s_th = self.sigma_u * np.abs(dr_du / dr_dth)
        shift = self.mean_shift(th, np.nan_to_num(s_th, nan=0.0, posinf=0.0))
        w = (np.nan_to_num(np.asarray(cloud["weight_stereo"], np.float64), nan=1.0)
             if "weight_stereo" in cloud.attributes else np.ones(n))
        sig_r = np.nan_to_num(np.abs(dr_dth * shift) * w)
        dx = np.nan_to_num(np.abs(dx_dth * shift[:, None]) * w[:, None])
        return Systematic(sig_r, dx)
