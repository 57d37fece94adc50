"""Epipolar geometry of the scanner–receiver pair and two-ray triangulation.

The scanner replaces one camera of a stereo pair (paper Sec. 2.3): its ray
``x = p + s·d_scan`` and a pixel's ray ``x = ρ·l`` (projection centre at the
origin) meet only if the epipolar constraint ``d_scan · (b × l) = 0`` holds,
with ``b = p`` the baseline (scanner position in the camera frame).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mems_stereo.errors import GeometryError
from mems_stereo.model.camera import pixels_to_rays, project_points
from mems_stereo.model.system import System
from mems_stereo.util.checks import check_shape


def epipolar_residual(d_scan, baseline, rays) -> np.ndarray:
    """Triple product d_scan · (b × l), broadcast over (..., 3).

    With unit ``d_scan`` and ``rays`` and ``baseline`` in metres the result is
    in metres: ``|b|`` times the sine of the angle between the ray and the plane
    spanned by ``b`` and ``d_scan``.  Zero for a consistent pair.

    Examples
    --------
    >>> system = ms.preset("burkard2022")
    >>> d = ms.scan_direction(system.scanner.theta0, system.scanner)
    >>> rays = np.array([[0.0, 0.0, 1.0], [0.0, 0.1, 0.995]])
    >>> np.round(ms.epipolar_residual(d, system.baseline, rays), 4)
    array([ 0.    , -0.0125])
    """
    d = check_shape(d_scan, ("...", 3), "d_scan")
    b = check_shape(baseline, ("...", 3), "baseline")
    l = check_shape(rays, ("...", 3), "rays")
    return np.sum(d * np.cross(b, l), axis=-1)


def epipolar_plane_normal(d_scan, baseline) -> np.ndarray:
    """Unit normal of the epipolar plane through the scanner ray and the origin.

    (..., 3) float64; NaN where ``d_scan`` is parallel to ``baseline``.
    """
    n = np.cross(check_shape(baseline, ("...", 3), "baseline"),
                 check_shape(d_scan, ("...", 3), "d_scan"))
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(norm > 1e-15, n / norm, np.nan)


def path_for_range(scanner_position, d_scan, ranges) -> np.ndarray:
    """Distance s along the scanner ray at which the point's range ‖x‖ equals r.

    ``x = p + s·d``, ``‖x‖ = r``  →  ``s = −p·d + sqrt((p·d)² − ‖p‖² + r²)``.
    ``ranges`` : (M,) metres.  Returns (M,) metres (NaN where r < distance of the
    ray from the origin, i.e. no such point).
    """
    p = check_shape(scanner_position, (3,), "scanner_position")
    d = check_shape(d_scan, (3,), "d_scan")
    r = np.asarray(ranges, dtype=np.float64)
    pd = float(p @ d)
    disc = pd * pd - float(p @ p) + r * r
    with np.errstate(invalid="ignore"):
        return np.where(disc >= 0, -pd + np.sqrt(np.maximum(disc, 0.0)), np.nan)


def epipolar_segment(system: System, d_scan, r_min: float, r_max: float,
                     n_samples: int = 64) -> np.ndarray:
    """Image of the scanner ray for target ranges in [r_min, r_max].

    Parameters
    ----------
    system : the pair.
    d_scan : (3,) unit scan direction, camera frame.
    r_min, r_max : range from the projection centre, metres, 0 < r_min < r_max.
    n_samples : points along the ray, spaced evenly in inverse range (the
        image of a ray is a straight line only without distortion).

    Returns
    -------
    (n_samples, 2) float64 pixel coordinates (column, row), from r_min to
    r_max; NaN for samples behind the camera or with no point at that range.

    Examples
    --------
    >>> system = ms.preset("burkard2022")
    >>> d = ms.scan_direction(system.scanner.theta0, system.scanner)
    >>> np.round(ms.epipolar_segment(system, d, 1.0, 5.0, n_samples=3), 2)
    array([[ 80.64,   0.  ],
           [ 90.56,   0.  ],
           [100.43,   0.  ]])
    """
    if not (0 < r_min < r_max):
        raise GeometryError(f"expected 0 < r_min < r_max, found r_min={r_min}, r_max={r_max}")
    inv = np.linspace(1.0 / r_min, 1.0 / r_max, int(n_samples))
    s = path_for_range(system.scanner.position, d_scan, 1.0 / inv)
    pts = np.asarray(system.scanner.position) + s[:, None] * np.asarray(d_scan)[None]
    return project_points(pts, system.receiver.camera_matrix, system.receiver.dist_coeffs)


def epipolar_pixels(system: System, d_scan, r_min: float, r_max: float,
                    half_width: float = 0.5, n_samples: int = 256) -> np.ndarray:
    """Pixels that can see the beam for ranges in [r_min, r_max] (readout gate).

    Returns (M, 2) int64 pixel indices (column, row) inside the image whose
    centre lies within ``half_width`` pixels (in each axis) of the projected
    scanner ray, sorted row-major and unique.  For a line sensor this is the
    column interval the beam can reach; for a 2-D array, the epipolar band.

    Examples
    --------
    >>> system = ms.preset("burkard2022")
    >>> d = ms.scan_direction(system.scanner.theta0, system.scanner)
    >>> pixels = ms.epipolar_pixels(system, d, 1.0, 5.0)
    >>> pixels.shape, pixels[0].tolist(), pixels[-1].tolist()
    ((20, 2), [81, 0], [100, 0])
    """
    seg = epipolar_segment(system, d_scan, r_min, r_max, n_samples)
    seg = seg[np.all(np.isfinite(seg), axis=1)]
    w, h = system.receiver.image_size
    if seg.shape[0] == 0:
        return np.zeros((0, 2), dtype=np.int64)
    # densify so consecutive samples are less than half a pixel apart
    steps = np.linalg.norm(np.diff(seg, axis=0), axis=1)
    n_sub = np.maximum(1, np.ceil(steps / 0.25).astype(int))
    pts = [seg[:1]]
    for a, b, n in zip(seg[:-1], seg[1:], n_sub):
        t = np.arange(1, n + 1)[:, None] / n
        pts.append(a + t * (b - a))
    pts = np.concatenate(pts)
    offs = np.arange(-np.ceil(half_width), np.ceil(half_width) + 1)
    cand = []
    for dc in offs:
        for dr in offs:
            c = np.rint(pts[:, 0] + dc)
            r = np.rint(pts[:, 1] + dr)
            ok = (np.abs(c - pts[:, 0]) <= half_width) & (np.abs(r - pts[:, 1]) <= half_width)
            cand.append(np.stack([c[ok], r[ok]], axis=1))
    px = np.concatenate(cand).astype(np.int64)
    inside = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
    px = np.unique(px[inside], axis=0)
    order = np.lexsort((px[:, 0], px[:, 1]))
    return px[order]


@dataclass(frozen=True, slots=True)
class Midpoints:
    """Two-ray midpoint triangulation of N ray pairs (:func:`triangulate_midpoint`).

    Attributes
    ----------
    points : (N, 3) float64, the midpoints of the common perpendiculars, in the
        unit and frame of the rays' origins (NaN where the rays are parallel).
    k : (N, 2) float64, the ray parameters k1, k2 of the perpendicular's feet
        ``o1 + k1·d1`` and ``o2 + k2·d2`` (in units of the directions' lengths).
    gap : (N,) float64, length of the common perpendicular (0 when the
        epipolar constraint holds), unit of the origins.
    ok : (N,) bool, False for parallel rays (no unique solution).
    """

    points: np.ndarray
    k: np.ndarray
    gap: np.ndarray
    ok: np.ndarray


def triangulate_midpoint(origin1, direction1, origin2, direction2) -> Midpoints:
    """Two-ray midpoint triangulation (paper Eqs. 2–4).

    Solves for k1, k2 such that the segment between ``o1 + k1·d1`` and
    ``o2 + k2·d2`` is perpendicular to both rays (Eq. 4), and returns its
    midpoint.

    Parameters
    ----------
    origin1, direction1, origin2, direction2 : (N, 3) or (3,) float64 (any
        consistent unit; directions need not be normalised).

    Returns
    -------
    Midpoints
        ``points`` (N, 3) midpoints (NaN where the rays are parallel), the ray
        parameters ``k`` (N, 2), the perpendicular's length ``gap`` (N,) and
        ``ok`` (N,) bool, False for parallel rays.

    Examples
    --------
    >>> m = ms.triangulate_midpoint(np.zeros(3), np.array([0.0, 0.0, 1.0]),
    ...                             np.array([-0.125, 0.0, 0.0]), np.array([0.125, 0.0, 2.0]))
    >>> m.points, m.gap
    (array([[0., 0., 2.]]), array([0.]))
    """
    o1, d1, o2, d2 = (np.atleast_2d(np.asarray(a, dtype=np.float64))
                      for a in (origin1, direction1, origin2, direction2))
    for name, a in (("origin1", o1), ("direction1", d1), ("origin2", o2), ("direction2", d2)):
        check_shape(a, ("N", 3), name)
    w0 = o1 - o2
    a = np.sum(d1 * d1, -1)
    b = np.sum(d1 * d2, -1)
    c = np.sum(d2 * d2, -1)
    d = np.sum(d1 * w0, -1)
    e = np.sum(d2 * w0, -1)
    den = a * c - b * b
    ok = den > 1e-12 * a * c
    with np.errstate(invalid="ignore", divide="ignore"):
        k1 = np.where(ok, (b * e - c * d) / den, np.nan)
        k2 = np.where(ok, (a * e - b * d) / den, np.nan)
    p1 = o1 + k1[:, None] * d1
    p2 = o2 + k2[:, None] * d2
    return Midpoints(0.5 * (p1 + p2), np.stack([k1, k2], axis=1),
                     np.linalg.norm(p1 - p2, axis=1), ok)


def pixel_rays_for(system: System, pixels) -> np.ndarray:
    """Unit rays of the given pixels of a system's receiver, (N, 3)."""
    r = system.receiver
    return pixels_to_rays(pixels, r.camera_matrix, r.dist_coeffs)
