"""Epipolar readout gating for 2-D SPAD arrays: which pixels to read for each shot.

For a shot with scan direction ``d`` (from the two mirror angles), a target at
range ``r ∈ [r_min, r_max]`` (the working range) lies on the beam segment
``p + s·d``; its image is the *epipolar segment* on the array.  The return
lands within the imaged spot of it, so only the pixels whose centre lies
within ``half_width`` pixels (Euclidean) of the segment need to be read and
processed: the gate.  ``half_width`` is the uncertainty band
(:func:`gate_half_width`): the pixel's half diagonal (a spot touching the
pixel's corner), k σ of the imaged spot, and the image shift of the beam's
angle uncertainty.

The gate is an API for hardware (:func:`gate_pixels` returns, per shot, the
flat indices ``row · W + column`` of the pixels to read, as CSR arrays) and
the pipeline's fast path (only gated detections exist, only they are
classified).  The segment is sampled at ``n_samples`` points spaced evenly in
inverse range and projected with the receiver's intrinsics (distortion
included), so the band follows a curved image of the beam.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from mems_stereo.errors import GeometryError
from mems_stereo.model.camera import project_points
from mems_stereo.model.system import System


@dataclass(frozen=True)
class GateSpec:
    """The gate's parameters: working range [r_min, r_max] (m, range from the
    projection centre) and band half width (px)."""

    r_min: float
    r_max: float
    half_width: float

    def __post_init__(self):
        if not (0 < self.r_min < self.r_max) or not math.isfinite(self.r_max):
            raise GeometryError(f"gate: expected 0 < r_min < r_max < inf, found "
                                f"r_min={self.r_min}, r_max={self.r_max}")
        if not (self.half_width > 0):
            raise GeometryError(f"gate: expected half_width > 0 px, found {self.half_width}")


@dataclass
class Gate:
    """Pixels read per shot, CSR.

    offsets : (K + 1,) int64; shot k reads ``pixels[offsets[k]:offsets[k + 1]]``.
    pixels : (R,) int32 flat pixel indices ``row · W + column``, increasing within a shot.
    n_pixels : H · W of the array.
    """

    offsets: np.ndarray
    pixels: np.ndarray
    n_pixels: int

    @property
    def n_shots(self) -> int:
        return int(self.offsets.size - 1)

    def counts(self) -> np.ndarray:
        """(K,) int64 pixels read per shot."""
        return np.diff(self.offsets)

    def read_fraction(self) -> float:
        """Mean share of the array read per shot."""
        return float(self.pixels.size) / max(1, self.n_shots * self.n_pixels)

    def exposure(self) -> np.ndarray:
        """(H·W,) int64: in how many shots each pixel was read."""
        return np.bincount(self.pixels, minlength=self.n_pixels).astype(np.int64)

    def keys(self) -> np.ndarray:
        """(R,) int64 slot keys ``shot · H·W + pixel``, increasing."""
        shot = np.repeat(np.arange(self.n_shots, dtype=np.int64), self.counts())
        return shot * self.n_pixels + self.pixels

    def contains(self, shot, pixel) -> np.ndarray:
        """(N,) bool: was ``pixel`` read in ``shot``?  (N,) int arrays."""
        keys = self.keys()
        q = np.asarray(shot, np.int64) * self.n_pixels + np.asarray(pixel, np.int64)
        if keys.size == 0:
            return np.zeros(q.shape, bool)
        pos = np.minimum(np.searchsorted(keys, q), keys.size - 1)
        return keys[pos] == q


def gate_half_width(system: System, spot_sigma_m: float = 12e-6, k: float = 3.0,
                    sigma_theta: float = 5e-5, margin_px: float = 0.25) -> float:
    """Band half width, px: ``√2/2 + k·√(σ_spot² + σ_beam²) + margin``.

    Parameters
    ----------
    spot_sigma_m : 1-σ of the imaged laser spot on the sensor (m), the largest
        over the working range (:class:`mems_stereo.physics.spot.SpotModel`).
    sigma_theta : rad, mirror angle uncertainty; the beam turns by 2θ, its
        image by ≈ 2σθ · f / pitch px.
    margin_px : allowance for calibration error of the system, px.
    """
    rc = system.receiver
    pitch = float(np.min(rc.pixel_pitch))
    f_px = float(max(rc.camera_matrix[0, 0], rc.camera_matrix[1, 1]))
    s_spot = spot_sigma_m / pitch
    s_beam = 2.0 * sigma_theta * f_px
    return math.sqrt(0.5) + k * math.hypot(s_spot, s_beam) + margin_px


def epipolar_polylines(system: System, d_scan, r_min: float, r_max: float,
                       n_samples: int = 24) -> np.ndarray:
    """Images of the beam segments for ranges in [r_min, r_max].

    d_scan : (K, 3) unit scan directions, camera frame.
    Returns (K, n_samples, 2) float64 pixel coordinates (column, row), evenly
    spaced in inverse range from r_min to r_max; NaN where there is no point
    at that range or it is behind the camera.
    """
    d = np.atleast_2d(np.asarray(d_scan, dtype=np.float64))
    if d.ndim != 2 or d.shape[1] != 3:
        raise GeometryError(f"d_scan: expected shape (K, 3), found {d.shape}")
    p = np.asarray(system.scanner.position, dtype=np.float64)
    inv = np.linspace(1.0 / r_min, 1.0 / r_max, int(n_samples))
    r = 1.0 / inv
    pd = d @ p
    disc = pd[:, None] ** 2 - float(p @ p) + r[None, :] ** 2
    with np.errstate(invalid="ignore"):
        s = np.where(disc >= 0, -pd[:, None] + np.sqrt(np.maximum(disc, 0.0)), np.nan)
    pts = p + s[..., None] * d[:, None, :]
    rc = system.receiver
    if np.any(rc.dist_coeffs):
        uv = project_points(pts.reshape(-1, 3), rc.camera_matrix, rc.dist_coeffs)
    else:
        K = rc.camera_matrix
        P = pts.reshape(-1, 3)
        with np.errstate(invalid="ignore", divide="ignore"):
            uv = np.stack([K[0, 0] * P[:, 0] / P[:, 2] + K[0, 2],
                           K[1, 1] * P[:, 1] / P[:, 2] + K[1, 2]], axis=1)
        uv[~(P[:, 2] > 0)] = np.nan
    return uv.reshape(d.shape[0], int(n_samples), 2)


@numba.njit(cache=True)
def _polyline_distance2(poly, k, c, r):
    """Squared distance (px²) of pixel (column c, row r) to shot k's polyline
    ``poly[k]`` (M, 2); NaN vertices are skipped, a NaN end falls back to its start."""
    m = poly.shape[1]
    best = 1e300
    for j in range(m - 1):
        ax = poly[k, j, 0]
        ay = poly[k, j, 1]
        bx = poly[k, j + 1, 0]
        by = poly[k, j + 1, 1]
        if not (ax == ax and ay == ay):
            continue
        if not (bx == bx and by == by):
            bx = ax
            by = ay
        ex = bx - ax
        ey = by - ay
        ll = ex * ex + ey * ey
        t = 0.0
        if ll > 0:
            t = ((c - ax) * ex + (r - ay) * ey) / ll
            t = min(1.0, max(0.0, t))
        dx = ax + t * ex - c
        dy = ay + t * ey - r
        d2 = dx * dx + dy * dy
        if d2 < best:
            best = d2
    if m == 1:
        dx = poly[k, 0, 0] - c
        dy = poly[k, 0, 1] - r
        best = dx * dx + dy * dy
    return best


@numba.njit(cache=True)
def _band_pass(poly, w, h, hw, offsets, out, fill):
    k_shots, m, _ = poly.shape
    hw2 = hw * hw
    n = 0
    for k in range(k_shots):
        if fill:
            n = offsets[k]
        cnt = 0
        umin, umax, vmin, vmax = 1e300, -1e300, 1e300, -1e300
        for j in range(m):
            u = poly[k, j, 0]
            v = poly[k, j, 1]
            if u == u and v == v:
                umin = min(umin, u)
                umax = max(umax, u)
                vmin = min(vmin, v)
                vmax = max(vmax, v)
        if umin > umax:
            if not fill:
                offsets[k + 1] = offsets[k]
            continue
        c0 = max(0, int(math.ceil(umin - hw)))
        c1 = min(w - 1, int(math.floor(umax + hw)))
        r0 = max(0, int(math.ceil(vmin - hw)))
        r1 = min(h - 1, int(math.floor(vmax + hw)))
        for r in range(r0, r1 + 1):
            for c in range(c0, c1 + 1):
                if _polyline_distance2(poly, k, c, r) <= hw2:
                    if fill:
                        out[n] = r * w + c
                        n += 1
                    cnt += 1
        if not fill:
            offsets[k + 1] = offsets[k] + cnt


def gate_pixels(system: System, d_scan, spec: GateSpec, n_samples: int = 24) -> Gate:
    """The pixels to read for each shot: the epipolar band of the working range.

    Parameters
    ----------
    system : the (nominal or calibrated) two-axis system.
    d_scan : (K, 3) unit scan directions of the shots, camera frame (NaN rows:
        shots of unknown angle, read nothing).
    spec : :class:`GateSpec` (working range, band half width in px).
    n_samples : samples of the segment (even in inverse range); the image of
        the segment is followed by straight pieces between them.

    Returns
    -------
    :class:`Gate` (CSR: offsets (K+1,), flat pixel indices (R,) int32).
    """
    poly = epipolar_polylines(system, d_scan, spec.r_min, spec.r_max, n_samples)
    w, h = system.receiver.image_size
    k = poly.shape[0]
    offsets = np.zeros(k + 1, dtype=np.int64)
    dummy = np.zeros(0, dtype=np.int32)
    _band_pass(poly, int(w), int(h), float(spec.half_width), offsets, dummy, False)
    out = np.empty(int(offsets[-1]), dtype=np.int32)
    _band_pass(poly, int(w), int(h), float(spec.half_width), offsets, out, True)
    return Gate(offsets, out, int(w) * int(h))


def full_gate(n_shots: int, n_pixels: int) -> Gate:
    """Every pixel in every shot (no gating), as a :class:`Gate`."""
    offsets = np.arange(n_shots + 1, dtype=np.int64) * n_pixels
    pixels = np.tile(np.arange(n_pixels, dtype=np.int32), n_shots)
    return Gate(offsets, pixels, n_pixels)
