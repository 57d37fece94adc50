"""dtof triangulation in 3-D: ray–ellipsoid closed forms and the stereo point.

A detection's path length ``L = c · t_TOF`` runs mirror → target → projection
centre (paper Eq. 7), so the target lies on the ellipsoid with foci at the
mirror ``p`` (the baseline ``b = p``, the projection centre being the world
origin) and at the origin: ``|x − p| + |x| = L``.  Derivation (ours, see
``docs/pipeline.md``):

* on the scanner ray ``x = p + s·d`` (``|d| = 1``): ``|x − p| = s`` and
  ``|p + s·d|² = (L − s)²`` give ``s = (L² − |b|²) / (2 (L + d·b))``;
* on the pixel ray ``x = ρ·l`` (``|l| = 1``): ``|x| = ρ`` and
  ``|ρ·l − b|² = (L − ρ)²`` give ``ρ = (L² − |b|²) / (2 (L − l·b))``.

Both rays start at a focus, i.e. inside the ellipsoid, so for ``L > |b|`` there
is exactly one positive root; ``L ≤ |b|`` has none.  The stereo point of a
pixel ray and a scanner ray (no time of flight) is their midpoint (paper
Eqs. 2–4).  Degenerate cases give NaN plus a flag (bit mask below), never a
number.  Frames and units: ``docs/conventions.md`` (metres, receiver camera
frame, origin at the projection centre).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mems_stereo.geometry.epipolar import triangulate_midpoint
from mems_stereo.model.system import System
from mems_stereo.util.checks import check_shape

FLAG_OK = 0
FLAG_NO_SOLUTION = 1  # L not finite or L <= |b|: no point on the ellipsoid
FLAG_BEHIND = 2  # the point is not in front of the receiver (z <= 0) or behind a ray origin
FLAG_GRAZING = 4  # (nearly) parallel rays or a vanishing denominator: ill-conditioned

#: stereo rays closer to parallel than this (rad) are flagged as grazing (≈ 12 km at 12.5 cm)
MIN_STEREO_ANGLE = 1e-5


def _vec3(a, name: str) -> np.ndarray:
    """(..., 3) float64 (declarative check: :func:`mems_stereo.util.checks.check_shape`)."""
    return check_shape(a, ("...", 3), name)


def cross3(a, b) -> np.ndarray:
    """``np.cross(a, b)`` of float64 (..., 3) vectors (broadcast): the same products and
    differences in the same order, so the same bits, without its per-call overhead
    (the stereo of every fusion entry calls it several times on small arrays)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out = np.empty(np.broadcast_shapes(np.shape(a), np.shape(b)))
    np.subtract(a1 * b2, a2 * b1, out=out[..., 0])
    np.subtract(a2 * b0, a0 * b2, out=out[..., 1])
    np.subtract(a0 * b1, a1 * b0, out=out[..., 2])
    return out


def path_length_of_point(points, scanner_position) -> np.ndarray:
    """L = ‖x − p‖ + ‖x‖ of points (..., 3), metres (paper Eq. 7)."""
    x = _vec3(points, "points")
    p = _vec3(scanner_position, "scanner_position")
    return np.linalg.norm(x - p, axis=-1) + np.linalg.norm(x, axis=-1)


# --------------------------------------------------------------------------
# ray–ellipsoid closed forms


def scanner_ray_point(scanner_position, d_scan, L):
    """Point at path length L on the scanner ray ``x = p + s·d``.

    Parameters
    ----------
    scanner_position : (3,) metres, world frame (the baseline b = p).
    d_scan : (..., 3) unit scan directions.
    L : (...) path lengths, metres (broadcast with ``d_scan[..., 0]``).

    Returns
    -------
    points : (..., 3) float64, metres; NaN where flagged.
    s : (...) float64, distance mirror → point, metres; NaN where flagged.
    flags : (...) uint8, FLAG_* bit mask (0 = ok).
    """
    p = check_shape(scanner_position, (3,), "scanner_position")
    d = _vec3(d_scan, "d_scan")
    L = np.asarray(L, dtype=np.float64)
    bb = float(p @ p)
    den = 2.0 * (L + np.sum(d * p, axis=-1))
    return _ellipsoid_root(L, bb, den, p, d, origin_is_p=True)


def pixel_ray_point(scanner_position, rays, L):
    """Point at path length L on the pixel ray ``x = ρ·l`` (origin = projection centre).

    ``rays`` : (..., 3) unit pixel rays; ``L`` : (...) metres.  Returns
    ``(points (..., 3), rho (...), flags (...) uint8)`` as
    :func:`scanner_ray_point` (ρ = ‖x‖, the range from the projection centre).
    """
    p = check_shape(scanner_position, (3,), "scanner_position")
    l = _vec3(rays, "rays")
    L = np.asarray(L, dtype=np.float64)
    bb = float(p @ p)
    den = 2.0 * (L - np.sum(l * p, axis=-1))
    return _ellipsoid_root(L, bb, den, p, l, origin_is_p=False)


def _ellipsoid_root(L, bb, den, p, d, origin_is_p: bool):
    L, den = np.broadcast_arrays(L, den)
    flags = np.zeros(L.shape, dtype=np.uint8)
    bad = ~np.isfinite(L) | (L <= np.sqrt(bb))
    flags[bad] |= FLAG_NO_SOLUTION
    # the denominator vanishes only for L -> |b| with the ray along ∓b: ill-conditioned
    graz = ~bad & (den <= 1e-9 * np.maximum(L, 1e-300))
    flags[graz] |= FLAG_GRAZING
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (L * L - bb) / den
    x = (p if origin_is_p else 0.0) + t[..., None] * d
    behind = ~bad & ~graz & ~(x[..., 2] > 0)
    flags[behind] |= FLAG_BEHIND
    ok = flags == 0
    t = np.where(ok, t, np.nan)
    x = np.where(ok[..., None], x, np.nan)
    return x, t, flags


# --------------------------------------------------------------------------
# stereo (pixel ray + scanner ray, no time of flight)


@dataclass(frozen=True, slots=True)
class StereoPoints:
    """Midpoint stereo points of N pixel rays and scanner rays (:func:`stereo_point`);
    receiver camera frame.

    Attributes
    ----------
    points : (N, 3) float64, metres (NaN where flagged).
    s : (N,) float64, distance along the scanner ray from the mirror to the foot
        of the common perpendicular, m.
    rho : (N,) float64, distance along the pixel ray from the projection centre, m.
    gap : (N,) float64, length of the common perpendicular (epipolar gap), m.
    flags : (N,) uint8, bit mask of ``FLAG_GRAZING`` and ``FLAG_BEHIND``.
    """

    points: np.ndarray
    s: np.ndarray
    rho: np.ndarray
    gap: np.ndarray
    flags: np.ndarray


@dataclass(frozen=True, slots=True)
class EpipolarStereoPoints:
    """Stereo points in the epipolar plane (:func:`epipolar_stereo_point`); receiver
    camera frame.

    Attributes
    ----------
    points : (N, 3) float64, metres (NaN where flagged).
    s : (N,) float64, distance along the scanner ray from the mirror, m.
    rho : (N,) float64, distance along the pixel ray from the projection centre, m.
    out_of_plane : (N,) float64, sine of the pixel ray's angle to the epipolar
        plane (NaN where flagged).
    flags : (N,) uint8, bit mask of ``FLAG_GRAZING`` and ``FLAG_BEHIND``.
    """

    points: np.ndarray
    s: np.ndarray
    rho: np.ndarray
    out_of_plane: np.ndarray
    flags: np.ndarray


def stereo_point(scanner_position, d_scan, rays,
                 min_angle: float = MIN_STEREO_ANGLE) -> StereoPoints:
    """Stereo point of pixel rays and scanner rays: midpoint of the common perpendicular.

    Parameters
    ----------
    scanner_position : (3,) metres.
    d_scan : (N, 3) unit scan directions; rays : (N, 3) unit pixel rays.
    min_angle : rays closer to parallel than this (rad) are flagged grazing.

    Returns
    -------
    StereoPoints
        ``points`` (N, 3) m (NaN where flagged); ``s`` (N,) the distance along
        the scanner ray to its foot of the perpendicular, m; ``rho`` (N,) along
        the pixel ray, m; ``gap`` (N,) the length of the common
        perpendicular (epipolar gap), m; ``flags`` (N,) uint8 (GRAZING for
        parallel rays, BEHIND for s <= 0, rho <= 0 or a point with z <= 0).
    """
    p = _vec3(scanner_position, "scanner_position")
    d = np.atleast_2d(_vec3(d_scan, "d_scan"))
    l = np.atleast_2d(_vec3(rays, "rays"))
    d, l = np.broadcast_arrays(d, l)
    o1 = np.broadcast_to(p, d.shape)
    o2 = np.zeros_like(l)
    mid = triangulate_midpoint(o1, d, o2, l)
    pts, k, gap, ok = mid.points, mid.k, mid.gap, mid.ok
    sin_ang = np.linalg.norm(np.cross(d, l), axis=-1) / (
        np.linalg.norm(d, axis=-1) * np.linalg.norm(l, axis=-1))
    flags = np.zeros(d.shape[0], dtype=np.uint8)
    graz = ~ok | ~(sin_ang >= np.sin(min_angle))
    flags[graz] |= FLAG_GRAZING
    behind = ~graz & ~((k[:, 0] > 0) & (k[:, 1] > 0) & (pts[:, 2] > 0))
    flags[behind] |= FLAG_BEHIND
    good = flags == 0
    s = np.where(good, k[:, 0] * np.linalg.norm(d, axis=-1), np.nan)
    rho = np.where(good, k[:, 1] * np.linalg.norm(l, axis=-1), np.nan)
    return StereoPoints(np.where(good[:, None], pts, np.nan), s, rho,
                        np.where(good, gap, np.nan), flags)


def epipolar_stereo_point(scanner_position, d_scan, rays,
                          min_angle: float = MIN_STEREO_ANGLE) -> EpipolarStereoPoints:
    """Stereo point in the epipolar plane: the pixel ray projected into the plane
    through the scanner ray and the origin, intersected with the scanner ray.

    For a line sensor whose row lies in the scan plane this ignores where on
    the pixel's height the photon landed (it does not move the beam), where
    the midpoint (:func:`stereo_point`) would shift with it to second order.
    Shapes as :func:`stereo_point`; returns :class:`EpipolarStereoPoints` whose
    ``out_of_plane`` is the sine of the pixel ray's angle to the plane (NaN where
    flagged).
    """
    p = _vec3(scanner_position, "scanner_position")
    d = np.atleast_2d(_vec3(d_scan, "d_scan"))
    l = np.atleast_2d(_vec3(rays, "rays"))
    d, l = np.broadcast_arrays(d, l)
    n = cross3(p, d)
    nn = np.linalg.norm(n, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = n / nn
        off = np.sum(l * n, axis=-1)
        lp = l - off[:, None] * n
        lp = lp / np.linalg.norm(lp, axis=-1, keepdims=True)
    s, rho = coplanar_ray_intersection(p, d, lp)
    sin_ang = np.linalg.norm(cross3(d, lp), axis=-1)
    flags = np.zeros(d.shape[0], dtype=np.uint8)
    graz = ~(nn[:, 0] > 1e-15) | ~(sin_ang >= np.sin(min_angle)) | ~np.isfinite(s)
    flags[graz] |= FLAG_GRAZING
    x = rho[:, None] * lp
    behind = ~graz & ~((s > 0) & (rho > 0) & (x[:, 2] > 0))
    flags[behind] |= FLAG_BEHIND
    good = flags == 0
    return EpipolarStereoPoints(np.where(good[:, None], x, np.nan), np.where(good, s, np.nan),
                                np.where(good, rho, np.nan), np.where(good, off, np.nan),
                                flags)


def coplanar_ray_intersection(scanner_position, d_scan, rays):
    """Exact intersection of coplanar scanner and pixel rays (closed form).

    ``p + s·d = ρ·l``: crossing with l and with d gives
    ``s = −(p×l)·(d×l) / |d×l|²`` and ``ρ = (p×d)·(l×d) / |l×d|²``.  For rays
    off the epipolar plane these are the least-squares parameters of the
    plane projection.  Shapes broadcast over (..., 3); returns (s, rho), each
    (...) float64 metres, NaN where the rays are parallel (‖d×l‖ < 1e-12).
    """
    p = _vec3(scanner_position, "scanner_position")
    d = _vec3(d_scan, "d_scan")
    l = _vec3(rays, "rays")
    dl = cross3(d, l)
    nn = np.sum(dl * dl, axis=-1)
    par = nn < 1e-24
    with np.errstate(invalid="ignore", divide="ignore"):
        s = -np.sum(cross3(p, l) * dl, axis=-1) / nn
        rho = -np.sum(cross3(p, d) * dl, axis=-1) / nn
    return np.where(par, np.nan, s), np.where(par, np.nan, rho)


# --------------------------------------------------------------------------
# the paper's 2-D form (cross-check)


def beam_angle(d_scan) -> np.ndarray:
    """Angle of the scan direction from the optical axis (z) toward +x, rad: atan2(d_x, d_z)."""
    d = _vec3(d_scan, "d_scan")
    return np.arctan2(d[..., 0], d[..., 2])


def paper_eq8_z(L, beam_angle_rad, x_m):
    """Paper Eq. 8 (restored from the garbled extraction): depth Z of the scanner-ray point.

    ``Z = (L² − x_M²)(L·sqrt(1 + tan²β) − x_M·tan β)(1 − sin²β) / (2 (L² − (x_M sin β)²))``

    with ``β`` the beam's angle from the optical axis toward +x
    (:func:`beam_angle`), ``x_M`` the mirror's x coordinate (metres) and
    ``L = c·t_TOF``.  It equals ``s·cos β`` of :func:`scanner_ray_point` for a
    scanner in the x–z plane (see docs/pipeline.md).  Z is measured from the
    projection centre, in metres.
    """
    L = np.asarray(L, dtype=np.float64)
    b = np.asarray(beam_angle_rad, dtype=np.float64)
    tb = np.tan(b)
    num = (L * L - x_m * x_m) * (L * np.sqrt(1.0 + tb * tb) - x_m * tb) * (1.0 - np.sin(b) ** 2)
    return num / (2.0 * (L * L - (x_m * np.sin(b)) ** 2))


def paper_eq9_x(mu_pix, Z, focal_length):
    """Paper Eq. 9 moved to the projection centre: ``X = −μ_pix · Z / f``.

    ``mu_pix`` : sensor coordinate of the pixel, metres, paper Eq. 10
    ``(96.5 − u)·w`` (u 1-based), which points opposite to the image x axis
    (the real image is inverted).  The paper's ``X = u(f − Z)/f`` has its
    origin on the sensor, a focal length behind the projection centre.
    """
    return -np.asarray(mu_pix, dtype=np.float64) * np.asarray(Z, dtype=np.float64) / focal_length


def paper_mu_pix(columns, system: System) -> np.ndarray:
    """Paper Eq. 10 for a 0-based column c: μ_pix = (c_x − c)·w, metres (c_x = 95.5 for u = c+1)."""
    K = system.receiver.camera_matrix
    w = float(system.receiver.pixel_pitch[0])
    return (K[0, 2] - np.asarray(columns, dtype=np.float64)) * w
