"""Robust start values that do not depend on the nominal system being close.

1. Per wall, the beam's track on the sensor (:mod:`mems_stereo.calib.track`):
   track points (φ, column, median time) where the returns of a phase bin stand
   out of the background (:func:`~mems_stereo.calib.track.find_track`).  A wall
   too weak for it is searched over all its shots with the nominal system
   (:func:`~mems_stereo.calib.track.find_wall`, the matched filter of
   :mod:`mems_stereo.calib.wall_search`), its track then collected around the
   pose found (:func:`~mems_stereo.calib.track.track_from_pose`).  A wall
   without a track is left out, with a message; when no wall has one, the walls
   the pose search found start the likelihood fit from the nominal system.
2. A rough signal rate per wall (excess per shot) and the first-photon bias
   of the track times it implies.
3. Over all walls, a coarse grid of θ0 (±``THETA0_SPAN`` around the nominal
   value, step ``THETA0_STEP``): each start triangulates the track points,
   fits each wall's plane (robust line fit) and the TDC offset (median), then a
   robust least-squares refinement of the system and the planes on the track
   points; the start with the lowest cost wins.

Wall parameters are rows (α rad, β rad, D m, log μ, log s) — the plane's tilt
about y and x, its offset, the signal photons per shot and the spot σ (px) —
the layout of :class:`~mems_stereo.calib.problem.Layout`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from mems_stereo.calib.model import PARAM_SCALE, beam_hits, plane_normal
from mems_stereo.calib.problem import distance_model
from mems_stereo.calib.track import (
    MIN_TRACK_POINTS,
    Track,
    WallPose,
    find_track,
    find_wall,
    nominal_values,
    track_from_pose,
)
from scipy.optimize import least_squares

from mems_stereo.errors import NotObservableError
from mems_stereo.model.system import System

THETA0_SPAN = 40e-3  # rad
THETA0_STEP = 5e-3  # rad
N_REFINE = 4  # starts refined by least squares (the lowest start costs)
#: system parameters the track fit moves (those of them that are free)
TRACK_FIT_PARAMS = ("theta0", "theta_mech_max", "phase_offset", "tdc_offset", "baseline_x",
                    "baseline_z", "fx", "cx")
#: start spot σ, px, of a wall from its track (log s = log of it)
START_SPOT = 0.4
#: start spot σ, px, of a wall the pose search found with a fitted system
FOUND_SPOT = 0.3


@dataclass(frozen=True, slots=True)
class InitialGuess:
    """Start values of the likelihood fit (:func:`initialise`).

    values : dict name → SI value of every parameter asked for.
    walls : (T, 5) float64, one row per used wall: α (rad), β (rad, 0), D (m),
        log μ (μ: signal photons per shot), log s (s: spot σ, px).
    used : the indices (into the walls given) of the T walls kept.
    skipped : a message on each wall left out.
    tracks : per used wall its :class:`~mems_stereo.calib.track.Track`, or None
        where the pose search alone found it.
    """

    values: dict[str, float]
    walls: np.ndarray
    used: list[int]
    skipped: list[str]
    tracks: list[Track | None]


@dataclass(frozen=True, slots=True)
class TrackSearch:
    """Each wall's track, looked for (:func:`_search_tracks`): the ``tracks`` of the
    walls ``used`` (indices), a message on each wall ``skipped``, and the walls
    without a track that the pose search found (``posed``: index → pose)."""

    tracks: list[Track]
    used: list[int]
    skipped: list[str]
    posed: dict[int, WallPose]


@dataclass(frozen=True, slots=True)
class TrackStart:
    """One start of the track fit: its robust ``cost``, the θ0 step ``d_theta``
    (rad) from the nominal value, ``z0`` the scaled start vector and ``planes``
    (T, 2) α (rad), D (m) of each wall."""

    cost: float
    d_theta: float
    z0: np.ndarray
    planes: np.ndarray


def triangulate(system: System, values: dict, phase, u):
    """Points (N, 3) where the beam of each shot meets the camera ray of column u (x–z)."""
    hits0 = beam_hits(system, values, phase, np.array([0.0, 0.0, 1.0]), 1.0)
    p = np.array([values.get("baseline_x", system.get_param("baseline_x")), 0.0,
                  values.get("baseline_z", system.get_param("baseline_z"))])
    d = hits0.point - p  # direction scaled
    K = system.receiver.camera_matrix
    fx = values.get("fx", K[0, 0])
    cx = values.get("cx", K[0, 2])
    rx = (np.asarray(u) - cx) / fx
    # p + s d = ρ (rx, ·, 1) in x and z:  p_x + s d_x = ρ rx ; p_z + s d_z = ρ
    den = d[:, 0] - rx * d[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (rx * p[2] - p[0]) / den
    P = p + s[:, None] * d
    return P


def fit_line(P):
    """Plane (α rad, D m) of points (N, 3) in x–z: z = a + b x by clipped least squares
    ((0, 1) when fewer than two points are usable)."""
    ok = np.all(np.isfinite(P), axis=1) & (P[:, 2] > 0.05)
    P = P[ok]
    if P.shape[0] < 2:
        return 0.0, 1.0
    keep = np.ones(P.shape[0], dtype=bool)
    coef = np.array([np.median(P[:, 2]), 0.0])
    for _ in range(5):
        A = np.column_stack([np.ones(P.shape[0]), P[:, 0]])
        if keep.sum() >= 2:
            coef, *_ = np.linalg.lstsq(A[keep], P[keep, 2], rcond=None)
        res = P[:, 2] - A @ coef
        mad = 1.4826 * np.median(np.abs(res[keep])) + 1e-3
        keep = np.abs(res) < 3.0 * mad
    n = np.array([-coef[1], 1.0])
    n /= np.linalg.norm(n)
    alpha = math.atan2(n[0], n[1])
    return alpha, float(coef[0] * n[1])


def _search_tracks(walls, system: System, sigma: float, progress=None) -> TrackSearch:
    """Each wall's track (:func:`find_track`, else around the pose the nominal system
    finds); a wall without one is skipped with a message saying why."""
    tracks, used, skipped, posed = [], [], [], {}
    for j, w in enumerate(walls):
        try:
            tr = find_track(w, sigma)
            why = ""
        except NotObservableError as e:
            tr, why = None, str(e)
        if tr is not None and tr.u.size < MIN_TRACK_POINTS:
            why = (f"{w.source}: the beam's track on the sensor could not be followed "
                   f"({tr.u.size} phase bins with a significant return, need "
                   f"{MIN_TRACK_POINTS}): record more shots, or use a brighter wall")
            tr = None
        if tr is None:  # too weak for one phase bin: the whole recording at once
            pose = find_wall(w, system, nominal_values(system), sigma)
            tr = None if pose is None else track_from_pose(w, system, sigma, pose=pose)
            if tr is None and pose is not None:
                posed[j] = pose
                why = (f"{w.source}: found by the pose search with the nominal system "
                       f"({pose.z:.1f}σ) but too faint for a track")
        if tr is None:
            skipped.append(why)
            continue
        if progress and why:
            progress(f"{w.source}: track found by the pose search with the nominal system")
        tracks.append(tr)
        used.append(j)
    return TrackSearch(tracks, used, skipped, posed)


def _start_from_poses(walls, system: System, names, posed: dict[int, WallPose],
                      skipped: list, progress=None) -> InitialGuess:
    """Start values when no wall has a track but the pose search found some: the
    nominal system and the poses found with it."""
    used = sorted(posed)
    out_walls = np.array([[posed[j].alpha, 0.0, posed[j].dist,
                           math.log(max(posed[j].mu, 1e-3)), math.log(START_SPOT)]
                          for j in used])
    skipped = [m for m in skipped if not any(m.startswith(f"{walls[j].source}:")
                                             for j in used)]
    if progress:
        progress(f"no track: {len(used)} wall(s) found by the pose search start the fit "
                 "from the nominal system")
    return InitialGuess({n: system.get_param(n) for n in names}, out_walls, used, skipped,
                        [None] * len(used))


class TrackFit:
    """Least squares of the system and the walls' planes on the track points.

    The unknowns ``z`` are steps from the nominal values of the free parameters
    ``free`` (in units of :data:`~mems_stereo.calib.model.PARAM_SCALE`), then per
    wall (α, D) steps (1 mrad, 1 mm) from a start's planes.  Residuals: each
    point's column (px) and bias-corrected time (s) over their σ, and each
    measured distance over its σ (``priors``, wall indices among the tracks).
    """

    def __init__(self, system: System, names, tracks: list, sigma: float, priors):
        self.system = system
        self.T = T = len(tracks)
        self.priors = priors
        # stacked track points
        self.wj = np.concatenate([np.full(tr.u.size, j) for j, tr in enumerate(tracks)])
        self.ph = np.concatenate([tr.phase for tr in tracks])
        self.uu = np.concatenate([tr.u for tr in tracks])
        self.tt = np.concatenate([tr.t - tr.bias for tr in tracks])
        nn = np.concatenate([tr.n for tr in tracks])
        self.s_u = np.concatenate([tr.u_err for tr in tracks])
        self.s_t = np.maximum(sigma / np.sqrt(np.maximum(nn, 1.0)) * 1.5, 0.3e-9)
        self.free = [n for n in TRACK_FIT_PARAMS if n in names]
        self.sc = np.array([PARAM_SCALE[n] for n in self.free] + [1e-3, 1e-3] * T)
        self.base = {n: system.get_param(n) for n in self.free}
        self.c_light = system.speed_of_light

    def unpack(self, z):
        """System values (dict of the free ones) and plane steps (T, 2) of ``z``."""
        v = dict(self.base)
        for i, n in enumerate(self.free):
            v[n] = self.base[n] + z[i] * self.sc[i]
        pl = (z[len(self.free):] * self.sc[len(self.free):]).reshape(self.T, 2)
        return v, pl

    def resid(self, z, pl0):
        """Scaled residuals at ``z`` from the start planes ``pl0`` (T, 2)."""
        system, wj = self.system, self.wj
        v, dpl = self.unpack(z)
        pl = pl0 + dpl
        h = beam_hits(system, v, self.ph, plane_normal(pl[wj, 0]), pl[wj, 1])
        off = v.get("tdc_offset", system.tdc.offset)
        out_u = np.nan_to_num((self.uu - h.pixel[:, 0]) / self.s_u, nan=50.0)
        out_t = np.nan_to_num((self.tt - h.path / self.c_light - off) / self.s_t, nan=50.0)
        pr = [(distance_model([pl[j, 0], 0.0, pl[j, 1]], kind) - d) / max(sd, 3e-3)
              for j, kind, d, sd in self.priors]
        return np.concatenate([out_u, out_t, np.asarray(pr, dtype=np.float64)])

    @staticmethod
    def robust_cost(r) -> float:
        """The soft-ℓ1 cost (scale 3) of residuals ``r``."""
        return float(np.sum(2.0 * 9.0 * (np.sqrt(1.0 + (r / 3.0) ** 2) - 1.0)))

    def start(self, d_th: float) -> TrackStart | None:
        """The start at θ0 = nominal + ``d_th``: planes by triangulation and a line
        fit, the TDC offset by the median; None where it is not finite."""
        system, free, base, T = self.system, self.free, self.base, self.T
        v = dict(base)
        if "theta0" in free:
            v["theta0"] = system.get_param("theta0") + d_th
        P = triangulate(system, v, self.ph, self.uu)
        pl0 = np.zeros((T, 2))
        for j in range(T):
            pl0[j] = fit_line(P[self.wj == j])
        h = beam_hits(system, v, self.ph, plane_normal(pl0[self.wj, 0]), pl0[self.wj, 1])
        if "tdc_offset" in free:
            v["tdc_offset"] = float(np.nanmedian(self.tt - h.path / self.c_light))
        for j, kind, d, _ in self.priors:  # start on the measured distance
            pl0[j, 1] = d if kind == "normal" else d * math.cos(pl0[j, 0])
        z0 = np.array([(v[n] - base[n]) / self.sc[i] for i, n in enumerate(free)]
                      + [0.0] * (2 * T))
        if not np.all(np.isfinite(z0)) or not np.all(np.isfinite(pl0)):
            return None
        return TrackStart(self.robust_cost(self.resid(z0, pl0)), d_th, z0, pl0)


def _best_start(fit: TrackFit, progress=None):
    """The θ0 grid's starts, the ``N_REFINE`` cheapest refined: the best refinement's
    (z, start planes (T, 2))."""
    grid = np.arange(-THETA0_SPAN, THETA0_SPAN + 1e-12, THETA0_STEP) if "theta0" in fit.free \
        else np.array([0.0])
    starts = [s for s in (fit.start(d_th) for d_th in grid) if s is not None]
    starts.sort(key=lambda s_: s_.cost)
    best = None
    for s in starts[:N_REFINE]:
        try:
            sol = least_squares(fit.resid, s.z0, args=(s.planes,), loss="soft_l1", f_scale=3.0,
                                max_nfev=100, x_scale=1.0)
        except ValueError:
            continue
        if best is None or sol.cost < best[0]:
            best = (sol.cost, sol.x, s.planes)
        if progress:
            progress(f"  start θ0 {s.d_theta * 1e3:+.0f} mrad: cost {s.cost:.1f} → "
                     f"{sol.cost:.1f}")
    if best is None:
        raise NotObservableError("no start value of θ0 gave a consistent geometry")
    return best[1], best[2]


def initialise(walls, system: System, names, sigma: float, priors=(),
               progress=None) -> InitialGuess:
    """Start values of ``names`` and of the walls (an :class:`InitialGuess`).

    walls : the :class:`~mems_stereo.calib.problem.WallData`; sigma : s, pulse σ;
    priors : [(wall index, "axis" | "normal", distance m, σ m)] measured distances.
    A wall whose recording shows no return, or too few track points, is left
    out (its message says why).  Raises :class:`NotObservableError` when no
    wall is left.
    """
    found = _search_tracks(walls, system, sigma, progress)
    tracks, used, skipped = found.tracks, found.used, found.skipped
    if not used and found.posed:
        # no wall bright enough for a track, but walls found by the matched filter
        # over all shots: the likelihood fit starts from the nominal system and the
        # poses found with it (the system's tolerances move a wall's image by a few
        # pixels, which its apparent pose absorbs); the checks judge the result
        return _start_from_poses(walls, system, names, found.posed, skipped, progress)
    if not used:
        raise NotObservableError("no recording shows a usable wall return: "
                                 + "; ".join(skipped))
    T = len(used)
    priors = [(used.index(j), kind, d, sd) for j, kind, d, sd in priors if j in used]
    fit = TrackFit(system, names, tracks, sigma, priors)
    z, pl0 = _best_start(fit, progress)
    v, dpl = fit.unpack(z)
    pl = pl0 + dpl
    out_walls = np.zeros((T, 5))
    for j, tr in enumerate(tracks):
        out_walls[j] = [pl[j, 0], 0.0, pl[j, 1], math.log(max(tr.mu, 1e-3)),
                        math.log(START_SPOT)]
    values = {n: system.get_param(n) for n in names}
    values.update({n: v[n] for n in fit.free})
    return InitialGuess(values, out_walls, used, skipped, tracks)
