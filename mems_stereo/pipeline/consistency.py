"""Signal/noise classification: the paper's consistency test (Sec. 3.2), vectorised.

A detection (shot k, pixel (col, row), code N) is SIGNAL when the scanner ray
at the shot's angle θ_k is consistent with it within the propagated bound,
else NOISE.  The test depends only on (θ, pixel, code), so per shot and pixel
the package predicts the path length at which the pixel's ray meets the
scanner ray, bounds it, and turns the bound into an accepted interval of TDC
codes ``[lo, hi]``:

* the pixel's centre is projected onto the epipolar line (normalised image
  coordinates); a pixel farther from that line than ``k·σ_perp`` accepts
  nothing (2-D arrays; a line sensor in the scan plane has no offset);
* along the line, the pixel's extent ``±k·σ_along`` maps to path lengths
  ``L(−)``, ``L(+)`` on either side of ``L_pred`` (exact, not linearised, so
  the vanishing point of the beam — where L grows without bound — is right);
  a side with no intersection in front of both rays is unbounded;
* the scan angle adds ``k·|∂L/∂θ|·σ_θ`` and the timing ``k·c·σ_t``
  (pulse, jitter, quantisation), combined in quadrature with the geometric
  half-widths (first-order, as the paper's Eqs. 16–17);
* ``k = Φ⁻¹((1 + confidence)/2)``: 2.97 for the default 0.997 (3σ).

A code N is accepted when its bin centre's path length lies in the bound.
``docs/pipeline.md`` gives the derivation and the measured figures.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import ndtri

from mems_stereo.errors import GeometryError, OptionError
from mems_stereo.geometry.triangulation import coplanar_ray_intersection, pixel_ray_point
from mems_stereo.geometry.uncertainty import Spreads, spreads_for
from mems_stereo.io.labels import LABEL_NOISE, LABEL_NONE, LABEL_SIGNAL
from mems_stereo.model.camera import normalized_coordinates, pixel_grid
from mems_stereo.model.scanner import scan_direction, scan_direction_derivative
from mems_stereo.model.system import System
from mems_stereo.model.tdc import detection_codes, detection_path_length

DEFAULT_CONFIDENCE = 0.997


def k_from_confidence(confidence: float) -> float:
    """Two-sided Gaussian multiplier k with P(|z| ≤ k) = confidence (0.997 → 2.968)."""
    if not 0.0 < confidence < 1.0:
        raise OptionError(f"confidence: expected a value in (0, 1), found {confidence!r}")
    return float(ndtri(0.5 * (1.0 + confidence)))


def _pixel_geometry(system: System):
    """Normalised coordinates (P, 2) of every pixel and their Jacobian (P, 2, 2) per px."""
    rc = system.receiver
    g = pixel_grid(rc.image_size)
    K, dist = rc.camera_matrix, rc.dist_coeffs
    q = normalized_coordinates(g, K, dist)
    h = 0.25
    ju = (normalized_coordinates(g + [h, 0], K, dist)
          - normalized_coordinates(g - [h, 0], K, dist)) / (2 * h)
    jv = (normalized_coordinates(g + [0, h], K, dist)
          - normalized_coordinates(g - [0, h], K, dist)) / (2 * h)
    return q, np.stack([ju, jv], axis=-1)


def _path_on_line(p, d, qx, qy):
    """Path length where the ray through normalised (qx, qy) meets the scanner ray; NaN if none.

    ``d`` : (K, 1, 3); ``qx, qy`` : (K, P).  Returns (K, P) float64, metres.
    """
    l = np.stack([qx, qy, np.ones_like(qx)], axis=-1)
    s, rho = coplanar_ray_intersection(p, d, l)
    ok = (s > 0) & (rho > 0)
    L = s + rho * np.linalg.norm(l, axis=-1)
    return np.where(ok, L, np.nan)


@dataclass
class PathBounds:
    """Per (shot, pixel) predicted path length and its accepted interval, metres.

    Attributes
    ----------
    L_pred : (K, H, W) float64, NaN where the pixel's centre ray misses the beam.
    L_lo, L_hi : (K, H, W) float64; L_hi = inf when unbounded; L_lo > L_hi
        (both NaN) where nothing is accepted.
    """

    L_pred: np.ndarray
    L_lo: np.ndarray
    L_hi: np.ndarray


def path_length_bounds(system: System, theta, confidence: float = DEFAULT_CONFIDENCE,
                       spreads: Spreads | None = None,
                       min_range: float | None = None) -> PathBounds:
    """Accepted path-length interval of every pixel for every shot.

    ``theta`` : (K,) rad (NaN allowed: nothing accepted).  ``min_range`` (m,
    optional prior, default none): no target is closer than this to the
    projection centre, so a pixel whose geometric interval lies entirely at
    path lengths below ``2·min_range − |b|`` accepts nothing (the timing
    spread still widens the others).  See the module docstring for the bound.  Memory is
    O(K·H·W); call per chunk of shots.
    """
    th = np.asarray(theta, dtype=np.float64).ravel()
    sp = spreads_for(system) if spreads is None else spreads
    k = k_from_confidence(confidence)
    rc = system.receiver
    H, W = rc.height, rc.width
    p = np.asarray(system.scanner.position, dtype=np.float64)
    q, Jq = _pixel_geometry(system)  # (P, 2), (P, 2, 2)
    Sq = np.einsum("pij,j,pkj->pik", Jq, np.array([sp.sigma_u ** 2, sp.sigma_v ** 2]), Jq)

    fin = np.isfinite(th)
    th0 = np.where(fin, th, system.scanner.theta0)
    d = scan_direction(th0, system.scanner)  # (K, 3)
    dd = scan_direction_derivative(th0, system.scanner)
    m = np.cross(p, d)  # epipolar plane normal (unnormalised), (K, 3)
    dm = np.cross(p, dd)
    ab = np.linalg.norm(m[:, :2], axis=1)  # (K,)
    if np.any(ab[fin] < 1e-15):
        raise GeometryError("scan direction parallel to the baseline: no epipolar line")
    n2 = m[:, :2] / ab[:, None]  # unit normal of the image line, (K, 2)
    t2 = np.stack([-n2[:, 1], n2[:, 0]], axis=1)
    qh = np.concatenate([q, np.ones((q.shape[0], 1))], axis=1)  # (P, 3)
    e = (m @ qh.T) / ab[:, None]  # signed distance to the line, normalised units, (K, P)
    de = (dm @ qh.T) / ab[:, None]
    s_perp = np.sqrt(np.einsum("ki,pij,kj->kp", n2, Sq, n2) + (de * sp.sigma_theta) ** 2)
    s_along = np.sqrt(np.einsum("ki,pij,kj->kp", t2, Sq, t2))
    on_line = np.abs(e) <= k * s_perp

    fx = q[None, :, 0] - e * n2[:, None, 0]
    fy = q[None, :, 1] - e * n2[:, None, 1]
    d3 = d[:, None, :]
    L0 = _path_on_line(p, d3, fx, fy)
    La = _path_on_line(p, d3, fx + k * s_along * t2[:, None, 0], fy + k * s_along * t2[:, None, 1])
    Lb = _path_on_line(p, d3, fx - k * s_along * t2[:, None, 0], fy - k * s_along * t2[:, None, 1])
    # scan-angle sensitivity of the predicted path length (central difference)
    h = 1e-6
    dp = scan_direction(th0 + h, system.scanner)[:, None, :]
    dmn = scan_direction(th0 - h, system.scanner)[:, None, :]
    dLdth = (_path_on_line(p, dp, fx, fy) - _path_on_line(p, dmn, fx, fy)) / (2 * h)
    s_th = np.abs(dLdth) * sp.sigma_theta
    s_th = np.where(np.isfinite(s_th), s_th, np.inf)

    fa, fb = np.isfinite(La), np.isfinite(Lb)
    lo_edge = np.fmin(La, Lb)
    hi_edge = np.where(fa & fb, np.fmax(La, Lb), np.inf)
    # centre ray misses the beam but an edge meets it: the pixel reaches infinity
    centre = np.where(np.isfinite(L0), L0, lo_edge)
    any_ok = np.isfinite(centre) & on_line & fin[:, None]
    sL = k * sp.sigma_L(system)
    with np.errstate(invalid="ignore"):
        half_lo = np.sqrt((centre - lo_edge) ** 2 + (k * s_th) ** 2 + sL * sL)
        half_hi = np.sqrt((hi_edge - centre) ** 2 + (k * s_th) ** 2 + sL * sL)
    if min_range is not None and min_range > 0:
        L_min = 2.0 * float(min_range) - float(np.linalg.norm(p))
        any_ok &= ~(hi_edge < L_min)
    lo = np.where(any_ok, centre - half_lo, np.nan)
    hi = np.where(any_ok, centre + half_hi, np.nan)
    K = th.shape[0]
    return PathBounds(np.where(any_ok, L0, np.nan).reshape(K, H, W), lo.reshape(K, H, W),
                      hi.reshape(K, H, W))


def accepted_code_intervals(system: System, theta, confidence: float = DEFAULT_CONFIDENCE,
                            spreads: Spreads | None = None, chunk_shots: int = 1024,
                            min_range: float | None = None):
    """Accepted TDC code interval per (shot, pixel).

    Parameters
    ----------
    system : the scanner–receiver pair.
    theta : (K,) float64 scan angles, rad (NaN: nothing accepted).
    confidence : two-sided coverage of the bound (default 0.997, i.e. 3σ).
    spreads : :class:`~mems_stereo.geometry.uncertainty.Spreads` (default
        :func:`~mems_stereo.geometry.uncertainty.spreads_for`).
    chunk_shots : shots per vectorised block (memory).
    min_range : optional prior, m (see :func:`path_length_bounds`).

    Returns
    -------
    lo, hi : (K, H, W) int32 each; code N (1..n_bins) is accepted iff
        lo <= N <= hi; lo > hi where nothing is accepted.
    """
    th = np.asarray(theta, dtype=np.float64).ravel()
    rc = system.receiver
    K = th.shape[0]
    lo = np.ones((K, rc.height, rc.width), dtype=np.int32)
    hi = np.zeros((K, rc.height, rc.width), dtype=np.int32)
    tdc = system.tdc
    pixel = np.arange(rc.height * rc.width).reshape(rc.height, rc.width)
    for a in range(0, K, max(1, int(chunk_shots))):
        b = min(K, a + chunk_shots)
        pb = path_length_bounds(system, th[a:b], confidence, spreads, min_range)
        with np.errstate(invalid="ignore"):
            # code N's bin centre: L_N = c·((N − ½)·bin − offset) (model.tdc; with the
            # hardware model the code centres, pixel offsets and pulse delay)
            nlo = np.ceil(detection_codes(pb.L_lo, system, pixel))
            nhi = np.floor(detection_codes(np.minimum(pb.L_hi, 1e12), system, pixel))
        ok = np.isfinite(nlo) & np.isfinite(nhi)
        nlo = np.clip(np.where(ok, nlo, 1), 1, tdc.n_bins)
        nhi = np.clip(np.where(ok, nhi, 0), 0, tdc.n_bins)
        lo[a:b] = nlo.astype(np.int32)
        hi[a:b] = nhi.astype(np.int32)
    return lo, hi


def _check_bins(system: System, bins, theta, valid):
    b = np.asarray(bins)
    rc = system.receiver
    th = np.asarray(theta, dtype=np.float64).ravel()
    if b.ndim != 3 or b.shape[1:] != (rc.height, rc.width):
        raise GeometryError(f"bins: expected shape (K, {rc.height}, {rc.width}), "
                            f"found {b.shape}")
    if th.shape != (b.shape[0],):
        raise GeometryError(f"theta: expected shape ({b.shape[0]},), found {th.shape}")
    v = np.ones(th.shape, bool) if valid is None else np.asarray(valid, dtype=bool).ravel()
    if v.shape != th.shape:
        raise GeometryError(f"valid: expected shape {th.shape}, found {v.shape}")
    return b, th, v & np.isfinite(th)


def classify_bins(system: System, bins, theta, valid=None,
                  confidence: float = DEFAULT_CONFIDENCE, spreads: Spreads | None = None,
                  chunk_shots: int = 1024, min_range: float | None = None) -> np.ndarray:
    """Label every detection of a block of shots.

    Parameters
    ----------
    bins : (K, H, W) uint16 TDC codes (0 = no detection).
    theta : (K,) float64 scan angle of each shot, rad.
    valid : (K,) bool, False where the angle is unknown (those shots get 0).
    confidence, spreads, chunk_shots, min_range : see :func:`accepted_code_intervals`.

    Returns
    -------
    labels : (K, H, W) uint8 — 0 no detection (or shot not valid), 1 signal, 2 noise.
    """
    b, th, v = _check_bins(system, bins, theta, valid)
    labels = np.zeros(b.shape, dtype=np.uint8)
    idx = np.flatnonzero(v)
    for a in range(0, idx.size, max(1, int(chunk_shots))):
        sel = idx[a:a + chunk_shots]
        lo, hi = accepted_code_intervals(system, th[sel], confidence, spreads, chunk_shots,
                                         min_range)
        bb = b[sel].astype(np.int32)
        labels[sel] = np.where(bb == 0, LABEL_NONE,
                               np.where((bb >= lo) & (bb <= hi), LABEL_SIGNAL, LABEL_NOISE))
    return labels


def classify_detections(system: System, shot_idx, rows, cols, codes, theta,
                        confidence: float = DEFAULT_CONFIDENCE,
                        spreads: Spreads | None = None) -> np.ndarray:
    """Per-detection reference form of the test, in object space (paper Sec. 3.2).

    The detection's point on its pixel ray at the measured path length is
    compared with the scanner ray at θ: its offset from the ray, in the
    epipolar plane and out of it, normalised by the offset's propagated
    spread (pixel extent, timing, scan angle; first order), must be within
    ``k`` in each of the two components (in-plane and out-of-plane).

    Parameters
    ----------
    shot_idx, rows, cols, codes : (M,) int arrays; theta : (K,) rad.

    Returns
    -------
    (M,) bool, True for signal.  It agrees with :func:`classify_bins` except
    where the first-order bound is poor (near the beam's vanishing point).
    """
    from mems_stereo.geometry.uncertainty import INPUTS, jacobian

    sp = spreads_for(system) if spreads is None else spreads
    k = k_from_confidence(confidence)
    th = np.asarray(theta, dtype=np.float64)[np.asarray(shot_idx)]
    u = np.asarray(cols, dtype=np.float64)
    v = np.asarray(rows, dtype=np.float64)
    pixel = np.asarray(rows, np.int64) * system.receiver.width + np.asarray(cols, np.int64)
    L = detection_path_length(codes, system, pixel)
    p = np.asarray(system.scanner.position, dtype=np.float64)

    def offsets(sys_, u, v, L, theta):
        rc = sys_.receiver
        from mems_stereo.model.camera import pixels_to_rays

        l = pixels_to_rays(np.stack([u, v], axis=1), rc.camera_matrix, rc.dist_coeffs)
        x = pixel_ray_point(p, l, L)[0]
        d = scan_direction(theta, sys_.scanner)
        nrm = np.cross(p, d)
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        perp = np.cross(nrm, d)  # in-plane, perpendicular to the beam
        r = x - p
        return np.stack([np.sum(r * perp, 1), np.sum(r * nrm, 1), np.zeros_like(u)], axis=1)

    off, J = jacobian(offsets, system, u, v, L, th)
    s = sp.input_sigmas(system)
    var = np.array([s[n] ** 2 for n in INPUTS])
    sig = np.sqrt(np.einsum("nik,k->ni", J ** 2, var))[:, :2]
    with np.errstate(invalid="ignore"):
        ok = np.all(np.abs(off[:, :2]) <= k * np.maximum(sig, 1e-12), axis=1)
    return ok & np.isfinite(off[:, 0])


def truth_suffix(truth: dict | None) -> str:
    """``", recall R, noise rejection N"`` of a result's truth scores ("" without truth)."""
    if not truth:
        return ""
    return (f", recall {truth['recall']:.4f}, noise rejection "
            f"{truth['noise_rejection']:.4f}")
