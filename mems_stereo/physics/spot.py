"""The imaged laser spot: its size on the sensor and its share on each pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr

from mems_stereo.model.scanner import scan_direction
from mems_stereo.model.system import System
from mems_stereo.physics.link_budget import LinkBudget

#: default 1-σ of the imaged laser spot on the sensor, metres (lens PSF + beam + defocus)
DEFAULT_SPOT_SIGMA = 10e-6


def spot_fraction(system: System, rows, cols, theta, rng, spot_sigma: float | None = None,
                  model: SpotModel | None = None, link: LinkBudget | None = None, cuts=None,
                  directions=None):
    """Share of the imaged laser spot on a pixel when the beam lights a target at range ``rng``.

    The target point is on the scanner ray at angle ``theta`` (rad) at distance
    ``rng`` (m) from the projection centre; its image (``project_points``)
    is the centre of a Gaussian spot whose σ (m on the sensor) is
    ``spot_sigma`` or, by default, the simulator's :class:`SpotModel` at that
    point (beam size, defocus and lens blur: wider near the sensor than at
    the focus distance); the share on pixel (row, col) is the product of the
    per-axis Gaussian integrals over the pixel (as :func:`spot_fractions`).
    Arguments broadcast; returns float64 of the broadcast shape (0 where the
    ray misses that range).  ``cuts`` (K + 1,) int or None: boundaries of segments of
    the flattened entries whose products ``d·p`` are computed apart
    (:func:`segment_dot`), the same bits as one call per segment.  ``directions``
    (N, 3) or None: the scan directions at ``theta`` (flattened) where known
    (:func:`step_directions`: the same bits).
    """
    from mems_stereo.model.camera import project_points

    rows, cols, th, r = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64)
                                              for a in (rows, cols, theta, rng)))
    p = np.asarray(system.scanner.position, dtype=np.float64)
    d = scan_direction(th.ravel(), system.scanner) if directions is None else directions
    pd = segment_dot(d, p, cuts)
    with np.errstate(invalid="ignore"):
        s = -pd + np.sqrt(pd * pd - p @ p + r.ravel() ** 2)
    x = p + s[:, None] * d
    uv = project_points(x, system.receiver.camera_matrix, system.receiver.dist_coeffs)
    pitch = np.asarray(system.receiver.pixel_pitch, dtype=np.float64)
    if spot_sigma is None:
        sm = SpotModel() if model is None else model
        lb = LinkBudget() if link is None else link
        with np.errstate(invalid="ignore"):
            sig = sm.sigma(np.nan_to_num(s, nan=1.0), np.nan_to_num(x[:, 2], nan=1.0), lb)
        sig = sig.reshape(th.shape)
    else:
        sig = float(spot_sigma)
    sc, sr = sig / pitch[0], sig / pitch[1]
    u, v = uv[:, 0].reshape(th.shape), uv[:, 1].reshape(th.shape)
    fc = ndtr((cols + 0.5 - u) / sc) - ndtr((cols - 0.5 - u) / sc)
    fr = ndtr((rows + 0.5 - v) / sr) - ndtr((rows - 0.5 - v) / sr)
    return np.nan_to_num(fc * fr, nan=0.0)


def step_directions(scanner, t0: float, dt: float, steps) -> np.ndarray:
    """(N, 3) float64: ``scan_direction(t0 + steps·dt)`` of integer angle steps ``steps``
    (N,) (an interval table's grid: ``t0``, ``dt`` rad), the same bits, from a table of
    every step kept per (scanner, grid) for the process (a frame's fusion reads the same
    steps many times; the scanner is frozen)."""
    steps = np.asarray(steps, np.int64)
    if steps.size == 0:
        return np.zeros((0, 3))
    lo, hi = int(steps.min()), int(steps.max())
    key = (id(scanner), float(t0), float(dt))
    hit = _STEP_DIRECTIONS.get(key)
    if hit is None or hit[0] is not scanner or lo < hit[1] or hi >= hit[1] + len(hit[2]):
        if hit is not None and hit[0] is scanner:  # widen the steps it holds
            lo, hi = min(lo, hit[1]), max(hi, hit[1] + len(hit[2]) - 1)
        if len(_STEP_DIRECTIONS) >= 8:
            _STEP_DIRECTIONS.clear()
        all_steps = np.arange(lo, hi + 1, dtype=np.int64)
        hit = (scanner, lo, scan_direction(float(t0) + all_steps * float(dt), scanner))
        _STEP_DIRECTIONS[key] = hit
    return hit[2][steps - hit[1]]


#: :func:`step_directions` by (id of the scanner, t0, dt): (scanner, first step, (n, 3))
_STEP_DIRECTIONS: dict = {}


def segment_dot(d, p, cuts=None) -> np.ndarray:
    """(N,) ``d @ p`` of rows d (N, 3) and a vector p (3,); with ``cuts`` (K + 1,) int
    (0 … N, increasing) one product per segment ``d[cuts[i]:cuts[i + 1]]``: BLAS's
    matrix-vector product may round a row differently by its place in the call, so a
    batch of entries that separate calls used to evaluate keeps their bits this way."""
    if cuts is None:
        return d @ p
    out = np.empty(d.shape[0])
    for a, b in zip(cuts[:-1], cuts[1:]):
        if b > a:
            out[a:b] = d[a:b] @ p
    return out


# --------------------------------------------------------------------------
# returned spot on the sensor


@dataclass(frozen=True)
class SpotModel:
    """Size of the imaged laser spot (Gaussian), from beam, defocus and optics.

    beam_diameter : m, beam Ø leaving the mirror (3.3 mm, the mirror aperture).
    beam_divergence : rad, full angle (1 mrad).
    focus_distance : m, where the receiver lens is focused (2.5 m).
    psf_sigma : m on the sensor, the lens's own blur (8 µm).
    radius : pixels considered on each side of the spot centre (2).

    σ² = (D_beam(R_tx) · f / z / 4)² + (c / 4)² + psf², with
    D_beam = beam_diameter + beam_divergence · R_tx and the defocus blur
    circle ``c = A · f · |1/z − 1/z_focus|`` (A = aperture Ø, z the depth).
    """

    beam_diameter: float = 3.3e-3
    beam_divergence: float = 1e-3
    focus_distance: float = 2.5
    psf_sigma: float = 8e-6
    radius: int = 2

    def sigma(self, range_tx, depth, budget: LinkBudget) -> np.ndarray:
        """(N,) float64, metres on the sensor."""
        f = budget.focal_length
        z = np.maximum(np.asarray(depth, float), 1e-6)
        d_beam = self.beam_diameter + self.beam_divergence * np.asarray(range_tx, float)
        aperture = f / budget.f_number
        blur = aperture * f * np.abs(1.0 / z - 1.0 / self.focus_distance)
        return np.sqrt((d_beam * f / z / 4.0) ** 2 + (blur / 4.0) ** 2 + self.psf_sigma ** 2)


def spot_fractions(center, sigma_px, image_size, radius: int = 2):
    """Share of a Gaussian spot falling on each nearby pixel.

    center : (N, 2) float64 pixel (column, row) of the spot centre (NaN: off).
    sigma_px : (N, 2) float64 spot σ in pixels (column, row direction).
    image_size : (W, H).
    Returns ``rows (N, nr) int64, cols (N, nc) int64, frac (N, nr, nc) float64``;
    pixels outside the sensor get row/col −1 and fraction 0.
    """
    w, h = int(image_size[0]), int(image_size[1])
    c = np.asarray(center, float)
    s = np.asarray(sigma_px, float)
    ok = np.all(np.isfinite(c), axis=1)
    c = np.where(ok[:, None], c, -1e6)

    def axis(u, su, n, r):
        if n <= 2 * r + 1:
            idx = np.broadcast_to(np.arange(n), (u.size, n)).copy()
        else:
            idx = np.rint(u)[:, None].astype(np.int64) + np.arange(-r, r + 1)
        frac = (ndtr((idx + 0.5 - u[:, None]) / su[:, None])
                - ndtr((idx - 0.5 - u[:, None]) / su[:, None]))
        bad = (idx < 0) | (idx >= n)
        frac[bad] = 0.0
        idx[bad] = -1
        return idx, frac

    cols, fc = axis(c[:, 0], s[:, 0], w, radius)
    rows, fr = axis(c[:, 1], s[:, 1], h, radius)
    frac = fr[:, :, None] * fc[:, None, :]
    frac[~ok] = 0.0
    return rows, cols, frac
