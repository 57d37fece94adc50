"""Matched-filter search for a faint wall over every shot of its recording.

A wall too faint for one phase bin (a few hundred signal photons in the whole
recording) is still visible when all its shots are added up along the track
that a wall pose predicts.  For a given system, every pose (tilt α, plane
offset D) predicts, for each monitor phase, the column u(φ) of the beam's
image and the return time τ(φ).  The shots are pooled by monitor phase
(``N_PHASE`` bins over the period); per bin the detections are histogrammed
by (column, TDC time) once, and each pose's count is the sum over the phase
bins of the detections at the predicted column within ±``GATE``·σ of the
predicted time.  The expected background count of the same cells follows
exactly from each pixel's measured rate (first photon: the pixel has not
fired before the gate opens, then fires inside it).  The count against that
expectation gives the Poisson likelihood-ratio significance
``√(2(n ln(n/e) − n + e))`` of the pose (a one-sided matched filter: the
signal template is the track).

False alarms are controlled per recording: the threshold is the one-sided
Gaussian quantile of ``FALSE_ALARM / n_poses`` (a Bonferroni bound over the
poses tested), so a recording of pure background passes with probability
below ``FALSE_ALARM`` whatever its shot count and background; a measured
distance narrows the distances searched and with them the threshold.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from mems_stereo.calib.model import beam_rays, plane_normal
from mems_stereo.calib.problem import WallData
from scipy.special import ndtri

from mems_stereo.model.camera import project_points

#: phase bins over the monitor's period (the image moves ≤ ~0.6 px per bin)
N_PHASE = 1024
#: TDC time bins of the pooled histogram, s (a fraction of the pulse σ ≈ 6 ns)
DT = 2.0e-9
#: half-width of the time gate, in pulse σ
GATE = 2.0
#: probability that a recording without any wall return yields a "found" pose
FALSE_ALARM = 1e-4
#: tilts searched, rad (the scan's field is ±~30°: steeper walls are refused later)
ALPHAS = np.radians(np.arange(-40.0, 40.1, 2.0))
#: inverse distances searched, 1/m (steps of 0.01/m ~ 0.25 px of parallax)
INV_DIST_STEP = 0.01
DIST_RANGE = (0.4, 15.0)


def threshold(n_poses: int, false_alarm: float = FALSE_ALARM) -> float:
    """Significance a pose needs among ``n_poses`` tested (one-sided, Bonferroni)."""
    return float(-ndtri(false_alarm / max(int(n_poses), 1)))


def poisson_z(n, e):
    """Signed significance of ``n`` counts where ``e`` are expected (Poisson
    likelihood ratio, ``sign(n − e)·√(2(n ln(n/e) − n + e))``): right for the few
    counts of a weak wall at a low background, where ``(n − e)/√e`` is not."""
    n = np.asarray(n, dtype=np.float64)
    e = np.maximum(np.asarray(e, dtype=np.float64), 1e-12)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(n > 0, n * np.log(np.maximum(n, 1e-300) / e), 0.0) - n + e
    return np.sign(n - e) * np.sqrt(np.maximum(2.0 * t, 0.0))


class PooledRecording:
    """A recording's detections pooled by monitor phase: cumulative counts
    ``C[b, c, i]`` of codes in phase bin b, column c (rows summed) before
    ``i·DT``; the shots per bin and each column's background rate (Hz)."""

    def __init__(self, w: WallData, t_max: float):
        K, H, W = w.bins.shape
        self.W = W
        self.ntb = int(math.ceil(t_max / DT)) + 1
        ph = np.mod(w.phase + math.pi, 2.0 * math.pi)
        self.b_shot = np.minimum((ph / (2.0 * math.pi) * N_PHASE).astype(np.int64),
                                 N_PHASE - 1)
        self.n_shots = np.bincount(self.b_shot, minlength=N_PHASE).astype(np.float64)
        # each bin's mean phase (circular), empty bins at their centre
        z = np.bincount(self.b_shot, weights=np.cos(w.phase), minlength=N_PHASE) \
            + 1j * np.bincount(self.b_shot, weights=np.sin(w.phase), minlength=N_PHASE)
        centre = (np.arange(N_PHASE) + 0.5) / N_PHASE * 2.0 * math.pi - math.pi
        self.phase = np.where(self.n_shots > 0, np.angle(z), centre)
        code_max = int((self.ntb - 1) * DT / w.bin_width)
        k, r, c = np.nonzero((w.bins > 0) & (w.bins <= code_max))
        t = (w.bins[k, r, c].astype(np.float64) - 0.5) * w.bin_width
        tb = np.minimum((t / DT).astype(np.int64), self.ntb - 2)
        idx = (self.b_shot[k] * W + c) * self.ntb + tb + 1
        hist = np.bincount(idx, minlength=N_PHASE * W * self.ntb).astype(np.int32)
        self.C = np.cumsum(hist.reshape(N_PHASE, W, self.ntb), axis=2, dtype=np.int32)
        self.lam = w.background.sum(axis=0)
        self._before = self._inside = None  # per (column, DT step) tables of counts()

    def counts(self, u, tau, sigma):
        """Observed and expected background counts of the gates (N_PHASE, M):
        column ``u`` (rounded), time τ ± GATE·σ (on the DT grid)."""
        ok = np.isfinite(u) & np.isfinite(tau)
        ui = np.rint(np.where(ok, u, -1)).astype(np.int64)
        ok &= (ui >= 0) & (ui < self.W)
        ui = np.where(ok, ui, 0)
        lo = np.clip(np.floor((tau - GATE * sigma) / DT), 0, self.ntb - 1).astype(np.int64)
        hi = np.clip(np.ceil((tau + GATE * sigma) / DT), 0, self.ntb - 1).astype(np.int64)
        ok &= hi > lo
        row = (np.arange(N_PHASE)[:, None] * self.W + ui) * self.ntb
        flat = self.C.reshape(-1)
        n = np.where(ok, flat[row + hi] - flat[row + lo], 0)
        # exp(−λ lo DT)·(1 − exp(−λ (hi − lo) DT)) per column from tables: the same
        # products as evaluating them per gate, a gather instead of two transcendentals
        if self._before is None:
            steps = np.arange(self.ntb)
            self._before = np.exp(-self.lam[:, None] * steps * DT).reshape(-1)
            self._inside = (-np.expm1(-self.lam[:, None] * steps * DT)).reshape(-1)
        col = ui * self.ntb
        e = np.where(ok, self.n_shots[:, None] * self._before[col + lo]
                     * self._inside[col + (hi - lo)], 0.0)
        return n, e, ok


class PoseGrid:
    """The beam of each phase bin, once per search; :meth:`hits` its image column and
    path for every (phase bin, plane offset) of one tilt: the arithmetic of
    :func:`~mems_stereo.calib.model.beam_hits` on an outer grid, without repeating the
    per-phase trajectory N_D times."""

    def __init__(self, system, values: dict, phase):
        self.p, d = beam_rays(system, values, phase)
        self.d = [np.ascontiguousarray(d[:, k:k + 1]) for k in range(3)]
        self.dirs = d
        K = np.array(system.receiver.camera_matrix, dtype=np.float64)
        K[0, 0] = values.get("fx", system.get_param("fx"))
        K[0, 2] = values.get("cx", system.get_param("cx"))
        self.K = K
        self.dist_coeffs = np.asarray(system.receiver.dist_coeffs, dtype=np.float64)

    def hits(self, alpha: float, dists):
        """(column u, path s + |P| m), each (N_PHASE, len(dists)); u NaN where the
        beam misses the plane or P is behind the camera."""
        nrm = plane_normal(alpha)
        p, (dx, dy, dz), K = self.p, self.d, self.K
        nd = self.dirs @ nrm
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (dists[None, :] - nrm @ p) / nd[:, None]
        px, py, pz = p[0] + s * dx, p[1] + s * dy, p[2] + s * dz
        ok = np.isfinite(s) & (s > 0) & (pz > 0)
        path = s + np.sqrt(px * px + py * py + pz * pz)
        if not np.any(self.dist_coeffs):
            with np.errstate(divide="ignore", invalid="ignore"):
                u = K[0, 0] * (px / pz) + K[0, 1] * (py / pz) + K[0, 2]
        else:
            P = np.stack([px, py, pz], axis=-1).reshape(-1, 3)
            P = np.where(ok.reshape(-1, 1), P, [0.0, 0.0, 1.0])
            u = project_points(P, K, self.dist_coeffs)[:, 0].reshape(s.shape)
        return np.where(ok, u, np.nan), path


@dataclass(frozen=True, slots=True)
class PoseSearch:
    """The most significant pose of a wall (:func:`search_pose`).

    alpha : rad, the plane's tilt; dist : m, the plane offset D; mu : rough
    signal photons per shot; z : the pose's significance; z_needed : the
    recording's threshold (:func:`threshold` over ``n_poses`` poses tested);
    excess : counts over the background along the pose.
    """

    alpha: float
    dist: float
    mu: float
    z: float
    z_needed: float
    n_poses: int
    excess: float


def search_pose(w: WallData, system, values: dict, sigma: float, *, distance=None,
                distance_tol: float = 0.0, pooled: PooledRecording | None = None,
                false_alarm: float = FALSE_ALARM) -> PoseSearch | None:
    """The most significant pose of a wall over all its shots, given a system.

    Parameters
    ----------
    w : the wall's recording.  system, values : the system (values: SI
        parameters, missing ones from ``system``).  sigma : pulse σ, s.
    distance : optional measured distance of the plane along the optical axis,
        m, with ``distance_tol`` (m) the range around it that the system's
        tolerances can shift the apparent pose by: only those plane offsets
        (D = d·cos α ± tol) are searched (fewer poses, a lower threshold).

    Returns
    -------
    PoseSearch, or None when the recording has no detection early enough.
    """
    inv = np.arange(1.0 / DIST_RANGE[1], 1.0 / DIST_RANGE[0], INV_DIST_STEP)
    dists = 1.0 / inv
    c_light = system.speed_of_light
    off = values.get("tdc_offset", system.get_param("tdc_offset"))
    t_max = 2.2 * DIST_RANGE[1] / c_light + abs(off) + (GATE + 1.0) * sigma
    if distance is not None:  # only offsets D = d cos α ± tol (the axis distance d)
        lo_d = (distance - distance_tol) * math.cos(ALPHAS.max())
        hi_d = distance + distance_tol
        dists = dists[(dists >= lo_d) & (dists <= hi_d)]
        t_max = 2.2 * hi_d / c_light + abs(off) + (GATE + 1.0) * sigma
    if dists.size == 0:
        return None
    pr = pooled if pooled is not None and pooled.ntb * DT >= t_max else PooledRecording(w, t_max)
    grid = PoseGrid(system, values, pr.phase)
    best = None
    n_poses = 0
    for a in ALPHAS:
        cols = (np.abs(dists - distance * math.cos(a)) <= distance_tol if distance is not None
                else np.ones(dists.size, dtype=bool))
        if not cols.any():
            continue
        sel = np.flatnonzero(cols)
        u, path = grid.hits(a, dists[sel])
        n, e, ok = pr.counts(u, path / c_light + off, sigma)
        ns, es = n.sum(axis=0), e.sum(axis=0)
        n_poses += sel.size
        z = np.where(es > 0, poisson_z(ns, es), -np.inf)
        i = int(np.argmax(z))
        if best is None or z[i] > best["z"]:
            n_on = max(float(pr.n_shots[ok[:, i]].sum()), 1.0)
            best = {"alpha": float(a), "dist": float(dists[sel[i]]), "z": float(z[i]),
                    "excess": float(ns[i] - es[i]), "frac": float((ns[i] - es[i]) / n_on)}
    if best is None or not np.isfinite(best["z"]):
        return None
    frac = max(best["frac"], 1e-3)
    return PoseSearch(alpha=best["alpha"], dist=best["dist"],
                      mu=-math.log(max(1.0 - min(frac / 0.8, 0.95), 1e-3)), z=best["z"],
                      z_needed=threshold(n_poses, false_alarm), n_poses=n_poses,
                      excess=best["excess"])
