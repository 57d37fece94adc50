"""Robust start values that do not depend on the nominal system being close.

1. Per wall, the beam's track on the sensor: shots binned by the monitor phase
   (cos φ, each sweep direction apart), in each bin the (column, TDC time)
   histogram of the detections against the background that each pixel's
   measured rate predicts; the box of 3 columns × 2σ of the pulse with the
   largest significant excess (Poisson z > ``Z_TRACK``) is a track point
   (φ, column, median time).  Points off a smooth track are dropped
   (:func:`find_track`).  A wall too weak for it is searched over all its shots
   with the nominal system (:func:`find_wall`, the matched filter of
   :mod:`mems_stereo.calib.wall_search`), its track then collected around the
   pose found (:func:`track_from_pose`).  A wall without a track is left out,
   with a message; when no wall has one, the walls the pose search found start
   the likelihood fit from the nominal system.
2. A rough signal rate per wall (excess per shot) and the first-photon bias
   of the track times it implies.
3. Over all walls, a coarse grid of θ0 (±``THETA0_SPAN`` around the nominal
   value, step ``THETA0_STEP``): each start triangulates the track points,
   fits each wall's plane (robust line fit) and the TDC offset (median), then a
   robust least-squares refinement of the system and the planes on the track
   points; the start with the lowest cost wins.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from mems_stereo.calib.model import beam_hits, plane_normal
from mems_stereo.calib.problem import WallData, distance_model
from mems_stereo.calib.wall_search import search_pose
from scipy.optimize import least_squares

from mems_stereo.errors import NotObservableError
from mems_stereo.model.system import System
from mems_stereo.physics.first_photon import first_photon_timing

T_SEARCH = 200e-9  # s: returns are looked for before this TDC time (walls up to ~28 m)
Z_TRACK = 5.5  # significance of a track point (one phase bin, best of ~15,000 boxes)
THETA0_SPAN = 40e-3  # rad
THETA0_STEP = 5e-3  # rad
MIN_TRACK_POINTS = 4
N_REFINE = 4  # starts refined by least squares (the lowest start costs)


@dataclass
class Track:
    """Track points of one wall: phase (N,) rad, u (N,) px, t (N,) s, n (N,)
    excess counts; window (t0, t1) s; mu: mean signal photons per shot (rough);
    bias: first-photon bias of the median time, s; u_err (N,) px: σ of each
    point's column (a phase bin's return spreads over the columns it sweeps)."""

    phase: np.ndarray
    u: np.ndarray
    t: np.ndarray
    n: np.ndarray
    window: tuple
    mu: float
    bias: float
    z: float
    u_err: np.ndarray | None = None


def poisson_z(n, e):
    """Signed significance of ``n`` counts where ``e`` are expected (Poisson
    likelihood ratio, ``sign(n − e)·√(2(n ln(n/e) − n + e))``): right for the few
    counts of a weak wall at a low background, where ``(n − e)/√e`` is not."""
    n = np.asarray(n, dtype=np.float64)
    e = np.maximum(np.asarray(e, dtype=np.float64), 1e-12)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(n > 0, n * np.log(np.maximum(n, 1e-300) / e), 0.0) - n + e
    return np.sign(n - e) * np.sqrt(np.maximum(2.0 * t, 0.0))


def _early(w: WallData, t_search: float):
    k, r, c = np.nonzero((w.bins > 0) & (w.bins <= int(t_search / w.bin_width) + 1))
    t = (w.bins[k, r, c].astype(np.float64) - 0.5) * w.bin_width
    return k, r, c, t


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


def _track_at(w: WallData, k, c, t, sigma: float, n_half: int):
    """Track points with ``n_half`` phase bins per sweep (see :func:`find_track`)."""
    K, H, W = w.bins.shape
    dt = 2.5e-9
    ntb = int(T_SEARCH / dt)
    ph = w.phase
    sweep = (np.sin(ph) >= 0).astype(np.int64)
    b_shot = (np.minimum(((np.cos(ph) + 1.0) / 2.0 * n_half).astype(np.int64), n_half - 1)
              + n_half * sweep)
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
    # the beam crosses ~W columns per sweep: a phase bin spans ~W / n_half of them
    # (3 at 64 bins per sweep, 25 at 8), and the box collects the whole bin's return
    nc = max(3, int(W / n_half) | 1)
    hc = nc // 2
    ho = _box(_box(hist, 1, nc), 2, nt)
    he = _box(_box(expc, 1, nc), 2, nt)
    z = poisson_z(ho, he)
    flat = z.reshape(nbin, -1)
    best = np.argmax(flat, axis=1)
    zmax = flat[np.arange(nbin), best]
    pc, pt = np.divmod(best, ntb)
    P_phase, P_u, P_t, P_n, P_e, shots_used = [], [], [], [], [], 0.0
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
        P_u.append(float(np.sum(cols * ex) / ex.sum()))
        P_t.append(float(np.median(t[m])))
        P_phase.append(float(np.angle(np.mean(np.exp(1j * ph[k[m]])))))
        P_n.append(float(ex.sum()))
        # centroid of a return spread evenly over the nc columns the bin sweeps, and
        # (nc / 6) the box's placement and the track's curvature within the bin
        P_e.append(max(0.5, nc / 6.0, nc / math.sqrt(12.0 * max(ex.sum(), 1.0))))
        shots_used += n_shots_bin[b]
    return (np.array(P_phase), np.array(P_u), np.array(P_t), np.array(P_n),
            shots_used, float(zmax.max()) if zmax.size else 0.0, np.array(P_e))


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
    k, r, c, t = _early(w, T_SEARCH)
    lam_mean = float(np.mean(w.background))
    best = None
    for n_half in (64, 32, 16, 8, 4):
        res = _track_at(w, k, c, t, sigma, n_half)
        tr = _clean_track(Track(res[0], res[1], res[2], res[3], (0.0, T_SEARCH), 0.0, 0.0,
                                res[5], res[6]))
        if best is None or tr.u.size > best[0].u.size * 1.2:
            best = (tr, res[4])
    tr, shots_used = best
    if tr.u.size == 0:
        raise NotObservableError(
            f"{w.source}: no wall return found (largest excess over the background "
            f"{tr.z:.1f}σ in any phase bin, need {Z_TRACK:g}σ): record more shots or "
            f"check the recording")
    mu = max(float(tr.n.sum()) / max(shots_used, 1.0) / 0.8, 1e-3)
    mu = -math.log(max(1.0 - min(mu, 0.95), 1e-3))
    t_pk = float(np.median(tr.t))
    _, mean, _ = first_photon_timing(np.array([t_pk]), mu, sigma, lam_mean)
    tr.mu = mu
    tr.bias = float(mean[0]) if np.isfinite(mean[0]) else 0.0
    return tr


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


def _triangulate(system: System, values: dict, phase, u):
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


def _fit_line(P):
    """Plane (α, D) of points (N, 3) in x–z: z = a + b x by clipped least squares."""
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


def initialise(walls, system: System, names, sigma: float, priors=(), progress=None):
    """Start values: (values dict of ``names``, walls (T_used, 5): α, β, D, log μ, log s,
    used wall indices, messages on the walls left out, the used walls' :class:`Track`).

    A wall whose recording shows no return, or too few track points, is left
    out (its message says why).  Raises :class:`NotObservableError` when no
    wall is left.
    """
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
            pose = find_wall(w, system, _nominal_values(system), sigma)
            tr = None if pose is None else track_from_pose(w, system, sigma, pose=pose)
            if tr is None and pose is not None:
                posed[j] = pose
                why = (f"{w.source}: found by the pose search with the nominal system "
                       f"({pose[3]:.1f}σ) but too faint for a track")
        if tr is None:
            skipped.append(why)
            continue
        if progress and why:
            progress(f"{w.source}: track found by the pose search with the nominal system")
        tracks.append(tr)
        used.append(j)
    if not used and posed:
        # no wall bright enough for a track, but walls found by the matched filter
        # over all shots: the likelihood fit starts from the nominal system and the
        # poses found with it (the system's tolerances move a wall's image by a few
        # pixels, which its apparent pose absorbs); the checks judge the result
        used = sorted(posed)
        out_walls = np.array([[posed[j][0], 0.0, posed[j][1], math.log(max(posed[j][2], 1e-3)),
                               math.log(0.4)] for j in used])
        skipped = [m for m in skipped if not any(m.startswith(f"{walls[j].source}:")
                                                 for j in used)]
        if progress:
            progress(f"no track: {len(used)} wall(s) found by the pose search start the fit "
                     "from the nominal system")
        return ({n: system.get_param(n) for n in names}, out_walls, used, skipped,
                [None] * len(used))
    if not used:
        raise NotObservableError("no recording shows a usable wall return: "
                                 + "; ".join(skipped))
    T = len(used)
    priors = [(used.index(j), kind, d, sd) for j, kind, d, sd in priors if j in used]
    # stacked track points
    wj = np.concatenate([np.full(tr.u.size, j) for j, tr in enumerate(tracks)])
    ph = np.concatenate([tr.phase for tr in tracks])
    uu = np.concatenate([tr.u for tr in tracks])
    tt = np.concatenate([tr.t - tr.bias for tr in tracks])
    nn = np.concatenate([tr.n for tr in tracks])
    s_u = np.concatenate([tr.u_err for tr in tracks])
    s_t = np.maximum(sigma / np.sqrt(np.maximum(nn, 1.0)) * 1.5, 0.3e-9)
    free = [n for n in ("theta0", "theta_mech_max", "phase_offset", "tdc_offset",
                        "baseline_x", "baseline_z", "fx", "cx") if n in names]
    from mems_stereo.calib.model import PARAM_SCALE

    sc = np.array([PARAM_SCALE[n] for n in free] + [1e-3, 1e-3] * T)
    base = {n: system.get_param(n) for n in free}
    c_light = system.speed_of_light

    def unpack(z):
        v = dict(base)
        for i, n in enumerate(free):
            v[n] = base[n] + z[i] * sc[i]
        pl = (z[len(free):] * sc[len(free):]).reshape(T, 2)
        return v, pl

    def resid(z, pl0):
        v, dpl = unpack(z)
        pl = pl0 + dpl
        h = beam_hits(system, v, ph, plane_normal(pl[wj, 0]), pl[wj, 1])
        off = v.get("tdc_offset", system.tdc.offset)
        out_u = np.nan_to_num((uu - h.pixel[:, 0]) / s_u, nan=50.0)
        out_t = np.nan_to_num((tt - h.path / c_light - off) / s_t, nan=50.0)
        pr = [(distance_model([pl[j, 0], 0.0, pl[j, 1]], kind) - d) / max(sd, 3e-3)
              for j, kind, d, sd in priors]
        return np.concatenate([out_u, out_t, np.asarray(pr, dtype=np.float64)])

    def robust_cost(r):
        return float(np.sum(2.0 * 9.0 * (np.sqrt(1.0 + (r / 3.0) ** 2) - 1.0)))

    starts = []
    th_nom = system.get_param("theta0")
    grid = np.arange(-THETA0_SPAN, THETA0_SPAN + 1e-12, THETA0_STEP) if "theta0" in free \
        else np.array([0.0])
    for d_th in grid:
        v = dict(base)
        if "theta0" in free:
            v["theta0"] = th_nom + d_th
        P = _triangulate(system, v, ph, uu)
        pl0 = np.zeros((T, 2))
        for j in range(T):
            pl0[j] = _fit_line(P[wj == j])
        h = beam_hits(system, v, ph, plane_normal(pl0[wj, 0]), pl0[wj, 1])
        if "tdc_offset" in free:
            v["tdc_offset"] = float(np.nanmedian(tt - h.path / c_light))
        for j, kind, d, _ in priors:  # start on the measured distance
            pl0[j, 1] = d if kind == "normal" else d * math.cos(pl0[j, 0])
        z0 = np.array([(v[n] - base[n]) / sc[i] for i, n in enumerate(free)]
                      + [0.0] * (2 * T))
        if not np.all(np.isfinite(z0)) or not np.all(np.isfinite(pl0)):
            continue
        starts.append((robust_cost(resid(z0, pl0)), d_th, z0, pl0))
    starts.sort(key=lambda s_: s_[0])
    best = None
    for c0, d_th, z0, pl0 in starts[:N_REFINE]:
        try:
            sol = least_squares(resid, z0, args=(pl0,), loss="soft_l1", f_scale=3.0,
                                max_nfev=100, x_scale=1.0)
        except ValueError:
            continue
        if best is None or sol.cost < best[0]:
            best = (sol.cost, sol.x, pl0)
        if progress:
            progress(f"  start θ0 {d_th * 1e3:+.0f} mrad: cost {c0:.1f} → {sol.cost:.1f}")
    if best is None:
        raise NotObservableError("no start value of θ0 gave a consistent geometry")
    cost, z, pl0 = best
    v, dpl = unpack(z)
    pl = pl0 + dpl
    out_walls = np.zeros((T, 5))
    for j, tr in enumerate(tracks):
        out_walls[j] = [pl[j, 0], 0.0, pl[j, 1], math.log(max(tr.mu, 1e-3)), math.log(0.4)]
    values = {n: system.get_param(n) for n in names}
    values.update({n: v[n] for n in free})
    return values, out_walls, used, skipped, tracks


def find_wall(w: WallData, system: System, values: dict, sigma: float):
    """A wall's plane given the system: the matched-filter pose search of
    :func:`mems_stereo.calib.wall_search.search_pose` over every shot.

    Over tilts α (±40°, 2° steps) and inverse distances (0.4–15 m, steps of
    0.01/m ~ 0.25 px of parallax), the shots pooled by monitor phase: the
    detections at each phase's predicted column within ±2σ of the predicted
    return time, against the background each pixel's measured rate predicts.
    Returns (α, D, μ, z) or None when the best pose is not significant at the
    recording's false-alarm threshold (one-sided Gaussian quantile of
    ``FALSE_ALARM / n_poses``).
    """
    f = search_pose(w, system, values, sigma)
    if f is None or not f["z"] > f["z_needed"]:
        return None
    return f["alpha"], f["dist"], f["mu"], f["z"]


def _nominal_values(system: System) -> dict:
    return {n: system.get_param(n) for n in ("theta0", "theta_mech_max", "phase_offset",
                                             "tdc_offset", "baseline_x", "baseline_y",
                                             "baseline_z")}


def track_from_pose(w: WallData, system: System, sigma: float, pose=None) -> Track | None:
    """Track points of a wall too weak for the per-phase-bin search (:func:`find_track`).

    The pose search of :func:`find_wall` with the nominal system uses the whole
    recording coherently; the system's tolerances shift the beam's image by a
    few pixels and its returns by a few ns, which the pose (distance, tilt) and
    the pulse-wide time gate absorb.  Around the best pose's predicted image
    (±``POSE_COLUMNS`` columns, ±2σ of the pulse in time), the detections in
    each phase bin give a track point: the excess-weighted column centroid
    (measured, not the prediction's) and the median time.  Returns None when
    no pose is significant or fewer than ``MIN_TRACK_POINTS`` bins hold a return.
    ``pose``: the search's result (α, D, μ, z) when already done.
    """
    values = _nominal_values(system)
    f = find_wall(w, system, values, sigma) if pose is None else pose
    if f is None:
        return None
    a, d, mu, z = f
    K, H, W = w.bins.shape
    h = beam_hits(system, values, w.phase, plane_normal(a), d)
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
    excess = float(hit.sum() - pb.sum())
    n_half = int(np.clip(2 ** np.floor(np.log2(max(excess / 20.0, 1.0))), 4, 64))
    ph = w.phase[k]
    sweep = (np.sin(ph) >= 0).astype(np.int64)
    b = (np.minimum(((np.cos(ph) + 1.0) / 2.0 * n_half).astype(np.int64), n_half - 1)
         + n_half * sweep)
    P = [[], [], [], [], []]
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
        P[0].append(float(np.angle(np.mean(np.exp(1j * ph[m])))))
        P[1].append(float(np.mean(u_p[k[m]])) + du)
        P[2].append(float(np.median(t[m][hit[m]])))
        P[3].append(n_ex)
        P[4].append(max(0.5, 1.0 / math.sqrt(n_ex)) + 0.3 * W / n_half / 6.0)
    if len(P[0]) < MIN_TRACK_POINTS:
        return None
    tr = Track(np.array(P[0]), np.array(P[1]), np.array(P[2]), np.array(P[3]),
               (0.0, T_SEARCH), 0.0, 0.0, z, np.array(P[4]))
    tr = _clean_track(tr)
    if tr.u.size < MIN_TRACK_POINTS:
        return None
    tr.mu = mu
    _, mean, _ = first_photon_timing(np.array([float(np.median(tr.t))]), mu, sigma,
                                     float(np.mean(w.background)))
    tr.bias = float(mean[0]) if np.isfinite(mean[0]) else 0.0
    return tr


#: columns either side of the predicted image that a pose-found track collects
POSE_COLUMNS = 2
