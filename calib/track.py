"""The beam's track on the sensor: per wall, the points (monitor phase, column,
TDC time) where its returns stand out of the background.

* :func:`find_track` — shots binned by the monitor phase (cos φ, each sweep
  direction apart), in each bin the (column, TDC time) histogram of the
  detections against the background that each pixel's measured rate predicts;
  the box with the largest significant excess (Poisson z > ``Z_TRACK``) is a
  track point.  Points off a smooth track are dropped.
* :func:`find_wall` — a wall too weak for that, searched over all its shots
  with a given system (the matched filter of :mod:`mems_stereo.calib.wall_search`);
* :func:`track_from_pose` — the track collected around the pose found.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from mems_stereo.calib.model import beam_hits, plane_normal
from mems_stereo.calib.problem import WallData
from mems_stereo.calib.wall_search import poisson_z, search_pose

from mems_stereo.errors import NotObservableError
from mems_stereo.model.system import System
from mems_stereo.physics.first_photon import first_photon_timing

T_SEARCH = 200e-9  # s: returns are looked for before this TDC time (walls up to ~28 m)
Z_TRACK = 5.5  # significance of a track point (one phase bin, best of ~15,000 boxes)
MIN_TRACK_POINTS = 4
#: columns either side of the predicted image that a pose-found track collects
POSE_COLUMNS = 2


@dataclass(frozen=True, slots=True)
class Track:
    """Track points of one wall, N of them.

    phase : (N,) float64 rad, mean monitor phase of the point's shots.
    u : (N,) float64 px, column of the beam's image.
    t : (N,) float64 s, median TDC time of the point's detections.
    n : (N,) float64, excess counts over the background.
    window : (t0, t1) s, the TDC times searched.
    mu : mean signal photons per shot (rough).
    bias : s, first-photon bias of the median time.
    z : the largest significance found (of any phase bin, or the pose's).
    u_err : (N,) float64 px, σ of each point's column (a phase bin's return
        spreads over the columns it sweeps).
    """

    phase: np.ndarray
    u: np.ndarray
    t: np.ndarray
    n: np.ndarray
    window: tuple[float, float]
    mu: float
    bias: float
    z: float
    u_err: np.ndarray | None = None


@dataclass(frozen=True, slots=True)
class BinnedTrack:
    """Track points at one phase binning (before cleaning): the ``track`` (``mu``
    and ``bias`` still 0) and ``shots_used``, the shots of the bins that gave a point."""

    track: Track
    shots_used: float


@dataclass(frozen=True, slots=True)
class WallPose:
    """A wall's plane found by the pose search (:func:`find_wall`): ``alpha`` rad,
    ``dist`` m (plane offset D), ``mu`` rough signal photons per shot, ``z`` the
    pose's significance."""

    alpha: float
    dist: float
    mu: float
    z: float


def _early(w: WallData, t_search: float):
    """Shot and column indices and TDC times (s) of the detections before ``t_search``."""
    k, r, c = np.nonzero((w.bins > 0) & (w.bins <= int(t_search / w.bin_width) + 1))
    t = (w.bins[k, r, c].astype(np.float64) - 0.5) * w.bin_width
    return k, c, t


def _box(a, axis, width):
    """Sum over a centred window of ``width`` cells along ``axis`` (zeros beyond)."""
    c = np.cumsum(a, axis=axis)
    pad = [(0, 0)] * a.ndim
    pad[axis] = (1, 0)
    c = np.pad(c, pad)
    n = a.shape[axis]
    hi = np.minimum(np.arange(n) + width // 2 + 1, n)
    lo = np.maximum(np.arange(n) - width // 2, 0)
    return np.take(c, hi, axis=axis) - np.take(c, lo, axis=axis)


def _phase_bins(ph: np.ndarray, n_half: int) -> np.ndarray:
    """Phase bin of each shot: ``n_half`` bins of cos φ per sweep direction."""
    sweep = (np.sin(ph) >= 0).astype(np.int64)
    return (np.minimum(((np.cos(ph) + 1.0) / 2.0 * n_half).astype(np.int64), n_half - 1)
            + n_half * sweep)


def _track_at(w: WallData, k, c, t, sigma: float, n_half: int) -> BinnedTrack:
    """Track points with ``n_half`` phase bins per sweep (see :func:`find_track`)."""
    K, H, W = w.bins.shape
    dt = 2.5e-9
    ntb = int(T_SEARCH / dt)
    ph = w.phase
    b_shot = _phase_bins(ph, n_half)
    nbin = 2 * n_half
    n_shots_bin = np.bincount(b_shot, minlength=nbin).astype(np.float64)
    tb = np.minimum((t / dt).astype(np.int64), ntb - 1)
    bk = b_shot[k]
    hist = np.bincount((bk * W + c) * ntb + tb, minlength=nbin * W * ntb).astype(
        np.float64).reshape(nbin, W, ntb)
    edges = np.arange(ntb + 1) * dt
    lam_c = w.background.sum(axis=0)  # rows of a column together
    pcell = np.exp(-lam_c[:, None] * edges[None, :-1]) * -np.expm1(-lam_c[:, None] * dt)
    expc = n_shots_bin[:, None, None] * pcell[None, :, :]
    nt = max(3, int(round(2.0 * sigma / dt)) | 1)
    # the beam crosses ~W columns per sweep: a phase bin spans ~W / n_half of them,
    # and the box collects the whole bin's return
    nc = max(3, int(W / n_half) | 1)
    hc = nc // 2
    ho = _box(_box(hist, 1, nc), 2, nt)
    he = _box(_box(expc, 1, nc), 2, nt)
    z = poisson_z(ho, he)
    flat = z.reshape(nbin, -1)
    best = np.argmax(flat, axis=1)
    zmax = flat[np.arange(nbin), best]
    pc, pt = np.divmod(best, ntb)
    phase, u, tt, n, u_err, shots_used = [], [], [], [], [], 0.0
    for b in np.flatnonzero(zmax > Z_TRACK):
        cc, t_pk = pc[b], (pt[b] + 0.5) * dt
        m = (bk == b) & (np.abs(c - cc) <= hc) & (np.abs(t - t_pk) < 2.0 * sigma)
        if np.count_nonzero(m) < 3:
            continue
        lo, hi = max(0, cc - hc), min(W, cc + hc + 1)
        cols = np.arange(lo, hi)
        ex = np.maximum(hist[b, lo:hi].sum(axis=1) - expc[b, lo:hi].sum(axis=1), 0.0)
        if ex.sum() <= 0:
            continue
        u.append(float(np.sum(cols * ex) / ex.sum()))
        tt.append(float(np.median(t[m])))
        phase.append(float(np.angle(np.mean(np.exp(1j * ph[k[m]])))))
        n.append(float(ex.sum()))
        # centroid of a return spread evenly over the nc columns the bin sweeps, and
        # (nc / 6) the box's placement and the track's curvature within the bin
        u_err.append(max(0.5, nc / 6.0, nc / math.sqrt(12.0 * max(ex.sum(), 1.0))))
        shots_used += n_shots_bin[b]
    track = Track(np.array(phase), np.array(u), np.array(tt), np.array(n), (0.0, T_SEARCH),
                  0.0, 0.0, float(zmax.max()) if zmax.size else 0.0, np.array(u_err))
    return BinnedTrack(track, shots_used)


def find_track(w: WallData, sigma: float) -> Track:
    """Track points of one wall.

    Shots are binned by the monitor phase (cos φ, each sweep direction apart;
    64, 32, ... 4 bins per sweep, the binning that yields the most points
    wins); in each bin the detections' (column, TDC time) histogram is
    compared with the background that each pixel's measured rate predicts
    (first-photon pile-up included), in boxes of 3 columns × 2σ of the pulse.
    The box of largest excess, when significant (z > ``Z_TRACK``), gives a
    track point: (mean phase, column centroid, median time of its detections).

    Raises :class:`NotObservableError` when the recording shows no wall return.
    """
    k, c, t = _early(w, T_SEARCH)
    lam_mean = float(np.mean(w.background))
    best = None
    for n_half in (64, 32, 16, 8, 4):
        res = _track_at(w, k, c, t, sigma, n_half)
        tr = _clean_track(res.track)
        if best is None or tr.u.size > best.track.u.size * 1.2:
            best = BinnedTrack(tr, res.shots_used)
    tr, shots_used = best.track, best.shots_used
    if tr.u.size == 0:
        raise NotObservableError(
            f"{w.source}: no wall return found (largest excess over the background "
            f"{tr.z:.1f}σ in any phase bin, need {Z_TRACK:g}σ): record more shots or "
            f"check the recording")
    mu = max(float(tr.n.sum()) / max(shots_used, 1.0) / 0.8, 1e-3)
    mu = -math.log(max(1.0 - min(mu, 0.95), 1e-3))
    t_pk = float(np.median(tr.t))
    _, mean, _ = first_photon_timing(np.array([t_pk]), mu, sigma, lam_mean)
    return replace(tr, mu=mu, bias=float(mean[0]) if np.isfinite(mean[0]) else 0.0)


def _clean_track(tr: Track) -> Track:
    """Drop track points off a smooth curve u(cos φ) of their sweep (robust quadratic)."""
    if tr.u.size < 4:
        return tr
    keep = np.ones(tr.u.size, dtype=bool)
    x = np.cos(tr.phase)
    sw = np.sin(tr.phase) >= 0
    for s in (True, False):
        m = np.flatnonzero(sw == s)
        if m.size < 5:
            continue
        k = np.ones(m.size, dtype=bool)
        for _ in range(4):
            A = np.column_stack([np.ones(m.size), x[m], x[m] ** 2])
            coef, *_ = np.linalg.lstsq(A[k], tr.u[m][k], rcond=None)
            res = tr.u[m] - A @ coef
            mad = 1.4826 * np.median(np.abs(res[k])) + 0.3
            k = np.abs(res) < np.maximum(max(3.0 * mad, 1.5), 3.0 * tr.u_err[m])
        keep[m] = k
    return Track(tr.phase[keep], tr.u[keep], tr.t[keep], tr.n[keep], tr.window, tr.mu,
                 tr.bias, tr.z, tr.u_err[keep])


def find_wall(w: WallData, system: System, values: dict, sigma: float) -> WallPose | None:
    """A wall's plane given the system: the matched-filter pose search of
    :func:`mems_stereo.calib.wall_search.search_pose` over every shot.

    Over tilts α (±40°, 2° steps) and inverse distances (0.4–15 m, steps of
    0.01/m ~ 0.25 px of parallax), the shots pooled by monitor phase: the
    detections at each phase's predicted column within ±2σ of the predicted
    return time, against the background each pixel's measured rate predicts.
    Returns None when the best pose is not significant at the recording's
    false-alarm threshold (one-sided Gaussian quantile of
    ``FALSE_ALARM / n_poses``).
    """
    f = search_pose(w, system, values, sigma)
    if f is None or not f.z > f.z_needed:
        return None
    return WallPose(f.alpha, f.dist, f.mu, f.z)


def nominal_values(system: System) -> dict:
    """The system's values of the parameters the pose search uses (SI)."""
    return {n: system.get_param(n) for n in ("theta0", "theta_mech_max", "phase_offset",
                                             "tdc_offset", "baseline_x", "baseline_y",
                                             "baseline_z")}


@dataclass(frozen=True, slots=True)
class PoseCells:
    """The cells around a pose's predicted image: M shots whose prediction falls on
    the sensor, C = 2·``POSE_COLUMNS`` + 1 columns each.

    shots : (M,) int64, indices of those shots; u_pred : (K,) float64 px, the
    predicted column of every shot; t : (M, C) float64 s, the TDC time of each
    cell's code; hit : (M, C) bool, a detection within ±2σ of the predicted
    return; background : (M, C) float64, the probability that background fires
    the cell first inside that gate.
    """

    shots: np.ndarray
    u_pred: np.ndarray
    t: np.ndarray
    hit: np.ndarray
    background: np.ndarray


def _pose_cells(w: WallData, system: System, values: dict, sigma: float,
                pose: WallPose) -> PoseCells:
    """The detections around ``pose``'s predicted image (``POSE_COLUMNS`` either side)."""
    K, H, W = w.bins.shape
    h = beam_hits(system, values, w.phase, plane_normal(pose.alpha), pose.dist)
    u_p = h.pixel[:, 0]
    tau = h.path / system.speed_of_light + values["tdc_offset"]
    good = h.ok & (u_p > -0.5) & (u_p < W - 0.5)
    lam = w.background.sum(axis=0)
    off = np.arange(-POSE_COLUMNS, POSE_COLUMNS + 1)
    k = np.flatnonzero(good)
    cols = np.rint(u_p[k])[:, None] + off[None, :]
    inside = (cols >= 0) & (cols < W)
    ci = np.clip(cols, 0, W - 1).astype(np.int64)
    code = w.bins[k[:, None], 0, ci]
    t = (code.astype(np.float64) - 0.5) * w.bin_width
    hit = inside & (code > 0) & (np.abs(t - tau[k, None]) < 2.0 * sigma)
    lo = np.maximum(tau[k, None] - 2.0 * sigma, 0.0)
    lu = lam[ci]
    pb = np.where(inside, np.exp(-lu * lo) * -np.expm1(-lu * (tau[k, None] + 2.0 * sigma - lo)),
                  0.0)
    return PoseCells(k, u_p, t, hit, pb)


def _pose_track(w: WallData, cells: PoseCells, z: float) -> Track | None:
    """Track points of the phase bins with a significant excess in ``cells``."""
    W = w.bins.shape[2]
    off = np.arange(-POSE_COLUMNS, POSE_COLUMNS + 1)
    k, u_p, t, hit, pb = cells.shots, cells.u_pred, cells.t, cells.hit, cells.background
    excess = float(hit.sum() - pb.sum())
    n_half = int(np.clip(2 ** np.floor(np.log2(max(excess / 20.0, 1.0))), 4, 64))
    ph = w.phase[k]
    b = _phase_bins(ph, n_half)
    phase, u, tt, n, u_err = [], [], [], [], []
    for i in range(2 * n_half):
        m = b == i
        if np.count_nonzero(m) < 3:
            continue
        ex_c = hit[m].sum(axis=0) - pb[m].sum(axis=0)  # excess per column offset
        n_ex = float(ex_c.sum())
        # a significant excess in this bin: at least 3 counts and 3σ over the background
        if n_ex < 3.0 or n_ex < 3.0 * math.sqrt(max(pb[m].sum(), 1.0)):
            continue
        wts = np.maximum(ex_c, 0.0)
        du = float(np.sum(off * wts) / max(wts.sum(), 1e-9))
        phase.append(float(np.angle(np.mean(np.exp(1j * ph[m])))))
        u.append(float(np.mean(u_p[k[m]])) + du)
        tt.append(float(np.median(t[m][hit[m]])))
        n.append(n_ex)
        u_err.append(max(0.5, 1.0 / math.sqrt(n_ex)) + 0.3 * W / n_half / 6.0)
    if len(phase) < MIN_TRACK_POINTS:
        return None
    return Track(np.array(phase), np.array(u), np.array(tt), np.array(n), (0.0, T_SEARCH),
                 0.0, 0.0, z, np.array(u_err))


def track_from_pose(w: WallData, system: System, sigma: float,
                    pose: WallPose | None = None) -> Track | None:
    """Track points of a wall too weak for the per-phase-bin search (:func:`find_track`).

    The pose search of :func:`find_wall` with the nominal system uses the whole
    recording coherently; the system's tolerances shift the beam's image by a
    few pixels and its returns by a few ns, which the pose (distance, tilt) and
    the pulse-wide time gate absorb.  Around the best pose's predicted image
    (±``POSE_COLUMNS`` columns, ±2σ of the pulse in time), the detections in
    each phase bin give a track point: the excess-weighted column centroid
    (measured, not the prediction's) and the median time.  Returns None when
    no pose is significant or fewer than ``MIN_TRACK_POINTS`` bins hold a return.
    ``pose``: the search's result when already done.
    """
    values = nominal_values(system)
    f = find_wall(w, system, values, sigma) if pose is None else pose
    if f is None:
        return None
    tr = _pose_track(w, _pose_cells(w, system, values, sigma, f), f.z)
    if tr is None:
        return None
    tr = _clean_track(tr)
    if tr.u.size < MIN_TRACK_POINTS:
        return None
    _, mean, _ = first_photon_timing(np.array([float(np.median(tr.t))]), f.mu, sigma,
                                     float(np.mean(w.background)))
    return replace(tr, mu=f.mu, bias=float(mean[0]) if np.isfinite(mean[0]) else 0.0)
