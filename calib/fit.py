"""The robust joint fit of system parameters and target poses, with its uncertainty.

:func:`fit_detections` estimates the free system parameters (θ0, amplitude,
phase offset, TDC offset, baseline x/y/z, optionally fx/cx) jointly with each
target's plane (tilt α, distance D; tilt β too for 2-D arrays) from signal
detections, by ``scipy.optimize.least_squares`` with a robust loss on the
residuals of :mod:`mems_stereo.calib.model`.  Uncertainties come from the Jacobian at the
solution: ``cov = (Σ_b J_bᵀ J_b / s_b²)⁻¹`` with ``s_b²`` the variance of the
(normalised, inlier) residuals of block b (pixel, time).

Observability is read from that same Jacobian: a parameter whose column
alone cannot pin it to better than ``max_std`` (baseline_y with a line
sensor: its column is zero) is fixed at its nominal value and reported as
unobservable (a warning); a parameter whose covariance-based σ exceeds
``max_std`` because it trades off with others (baseline_z and tdc_offset
with one target distance) raises :class:`~mems_stereo.errors.NotObservableError`
naming it (or warns, ``on_unobservable="warn"``); pairs with |correlation|
above 0.9 are reported.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np
from mems_stereo.calib.model import (
    DEFAULT_FREE,
    PARAM_SCALE,
    PARAM_UNIT,
    SYSTEM_PARAMS,
    beam_hits,
    code_time,
    plane_normal,
)
from scipy.optimize import least_squares

from mems_stereo.errors import NotObservableError
from mems_stereo.model.scanner import scan_angle_from_phase
from mems_stereo.model.system import System
from mems_stereo.physics.first_photon_timing import FirstPhotonTable, background_rate
from mems_stereo.physics.pulse import pulse_sigma

#: a parameter known worse than this is "not observable" (SI units)
DEFAULT_MAX_STD = {"theta0": 0.01, "theta_mech_max": 0.01, "phase_offset": 0.02,
                   "tdc_offset": 1e-9, "baseline_x": 0.02, "baseline_y": 0.02,
                   "baseline_z": 0.02, "fx": 5.0, "cx": 2.0}
SIGMA_PIXEL = 1.0 / math.sqrt(12.0)  # px: uniform over the pixel's extent
MIN_DETECTIONS_PER_TARGET = 30
CORRELATION_REPORT = 0.9
#: restart when θ0 or the baseline moved more than this many mm / mrad from the start
RESTART_MOVE = 8.0


class ObservabilityWarning(UserWarning):
    """A parameter was fixed or is poorly determined because the data cannot observe it."""


@dataclass
class CalibrationResult:
    """Outcome of a calibration fit (OpenCV-style: values, σ, RMS, flag).

    Attributes
    ----------
    system : the calibrated System (with its ``calibration`` block).
    names : free system parameters, order of ``covariance``.
    values, std, initial : dict name → SI value, its σ, and the start value.
    covariance : (n, n) SI units, over ``names``.
    correlation : (n, n).
    rms : {"pixel": px, "time": s} RMS of the inlier residuals.
    n_detections : signal detections used (inliers of the final fit).
    fixed : parameters held at their given value; unobservable : parameters
        the data cannot determine (fixed or flagged).
    tradeoffs : [(a, b, correlation)] for |correlation| > 0.9.
    planes : (T, 3) α (rad), β (rad), D (m) of each target; planes_std : (T, 3).
    converged : the solver converged and the residuals look like the model.
    message : why not, when not.
    report : human-readable text.
    """

    system: System
    names: list
    values: dict
    std: dict
    initial: dict
    covariance: np.ndarray
    correlation: np.ndarray
    rms: dict
    n_detections: int
    fixed: list
    unobservable: list
    tradeoffs: list
    planes: np.ndarray
    planes_std: np.ndarray
    converged: bool
    message: str = ""
    report: str = ""
    iterations: int = 0
    extra: dict = field(default_factory=dict)

    @property
    def rms_pixel(self) -> float:
        return float(self.rms["pixel"])

    @property
    def rms_time(self) -> float:
        return float(self.rms["time"])

    def calibration_dict(self) -> dict:
        """The ``calibration`` object written into the system JSON."""
        params = {n: {"value": self.values[n],
                      "std": self.std[n] if math.isfinite(self.std[n]) else None,
                      "initial": self.initial[n]} for n in self.names}
        corr = {f"{a}/{b}": round(float(r), 6) for a, b, r in self.tradeoffs}
        z = self.extra.get("axis_distance", [math.nan] * len(self.planes))
        zs = self.extra.get("axis_distance_std", [math.nan] * len(self.planes))
        return {"parameters": params, "rms_pixel": self.rms_pixel, "rms_time": self.rms_time,
                "n_detections": int(self.n_detections), "fixed": list(self.fixed),
                "unobservable": list(self.unobservable), "correlations": corr,
                "converged": bool(self.converged),
                "targets": [{"alpha": float(p[0]), "beta": float(p[1]), "distance": float(p[2]),
                             "std": [float(s) for s in ps], "distance_axis": float(za),
                             "distance_axis_std": float(zsa)}
                            for p, ps, za, zsa in zip(self.planes, self.planes_std, z, zs)]}


# --------------------------------------------------------------------------
# the problem: parameter vector <-> values, residuals


_TABLES: dict = {}


def _table(sigma: float, lam: float, bin_width: float, rel: float = 0.05) -> FirstPhotonTable:
    """Cached first-photon table: one already built for a background rate within
    ``rel`` (5 %) of ``lam`` is reused (the rate enters the timing model only
    through the rare background photon ahead of the pulse; the reclassification
    rounds change the estimated rate by well under 1 %)."""
    base = (round(sigma, 15), bin_width)
    for (b, lam_t), table in _TABLES.items():
        if b == base and abs(lam_t - lam) <= rel * max(lam, 1e-300):
            return table
    key = (base, float(f"{lam:.3g}"))
    _TABLES[key] = FirstPhotonTable(sigma, key[1], bin_width)
    return _TABLES[key]


class _Problem:
    """Per-shot observations, the parameter layout and the residual function.

    Detections are aggregated per shot: the pixel observation is the mean
    position of the shot's signal detections (the spot may light two
    pixels), the time observation the earliest of their TDC times, which is
    the first photon of the whole returned spot whatever its split over
    pixels.  Each target has a nuisance log μ_j (mean signal photons of a
    shot at the target's mean geometry; shot k has μ_j·g_k/ḡ with g the
    Lambertian factor cos θ_e·cos θ_r/R²), constrained by the share of shots
    with a detection and by the first-photon bias itself.
    """

    def __init__(self, targets, system, names, two_d, known, known_std, jitter,
                 distance_kind="axis"):
        self.targets = targets
        self.system = system
        self.names = list(names)
        self.two_d = two_d
        self.T = len(targets)
        self.known = known
        self.known_std = known_std
        self.distance_kind = distance_kind
        self.ref = {n: system.get_param(n) for n in SYSTEM_PARAMS}
        self.plane_names = (["alpha", "beta", "dist", "logmu"] if two_d
                            else ["alpha", "dist", "logmu"])
        self.plane_cols = [0, 1, 2, 3] if two_d else [0, 2, 3]
        bw = system.tdc.bin_width
        # per detection (fixed), aggregated per shot by update()
        self.d_tgt = np.concatenate([np.full(t.n_detections, j) for j, t in enumerate(targets)])
        self.d_shot = np.concatenate([t.shot for t in targets])
        self.d_col = np.concatenate([t.column for t in targets])
        self.d_row = np.concatenate([t.row for t in targets])
        self.d_t = code_time(np.concatenate([t.code for t in targets]), bw)
        self._aggregate([np.ones(t.n_detections, dtype=bool) for t in targets])
        self.sigma_p = pulse_sigma(system.laser.pulse_fwhm, jitter)
        self.window = system.tdc.n_bins * system.tdc.bin_width
        self.tables = [_table(self.sigma_p, background_rate(t.noise_fraction, self.window), bw)
                       for t in targets]
        self.plane_ref = np.zeros((self.T, 4))
        self.sigma_t = np.full(self.M, self.sigma_p)
        self.on_sets = [np.zeros(t.phase.size, dtype=bool) for t in targets]

    def _aggregate(self, keep):
        """Per-shot observations from the kept detections of each target.

        ``keep`` : list of (M_j,) bool.  Sets tgt, phase, col, row, t_meas,
        n_pix (one entry per shot with a kept detection), ``has_signal`` per
        target (shots with a kept detection) and resets the weights.
        """
        tg, ph, col, row, tt, npx, has = [], [], [], [], [], [], []
        start = 0
        for j, t in enumerate(self.targets):
            sl = slice(start, start + t.n_detections)
            start += t.n_detections
            k = keep[j]
            shot = self.d_shot[sl][k]
            shots, inv = np.unique(shot, return_inverse=True)
            cnt = np.bincount(inv, minlength=shots.size)
            tmin = np.full(shots.size, np.inf)
            np.minimum.at(tmin, inv, self.d_t[sl][k])
            tg.append(np.full(shots.size, j))
            ph.append(t.phase[shots])
            col.append(np.bincount(inv, self.d_col[sl][k], shots.size) / np.maximum(cnt, 1))
            row.append(np.bincount(inv, self.d_row[sl][k], shots.size) / np.maximum(cnt, 1))
            tt.append(tmin)
            npx.append(cnt)
            hs = np.zeros(t.phase.size, dtype=bool)
            hs[shots] = True
            has.append(hs)
        self.tgt = np.concatenate(tg)
        self.phase = np.concatenate(ph)
        self.col = np.concatenate(col)
        self.row = np.concatenate(row)
        self.t_meas = np.concatenate(tt)
        self.n_pix = np.concatenate(npx)
        self.has_signal = has
        self.M = self.tgt.size
        self.weights = np.ones(self.M)
        self.rows = [np.flatnonzero(self.tgt == j) for j in range(self.T)]

    @property
    def labels(self):
        out = list(self.names)
        for j in range(self.T):
            out += [f"{p}[{j}]" for p in self.plane_names]
        return out

    @property
    def scales(self):
        sc = dict(PARAM_SCALE, logmu=0.01)
        s = [sc[n] for n in self.names]
        s += [sc[p] for _ in range(self.T) for p in self.plane_names]
        return np.array(s)

    def unpack(self, x):
        x = np.asarray(x, dtype=np.float64) * self.scales
        n = len(self.names)
        values = {name: self.ref[name] + x[i] for i, name in enumerate(self.names)}
        planes = self.plane_ref.copy()
        planes[:, self.plane_cols] += x[n:].reshape(self.T, len(self.plane_cols))
        return values, planes

    def hits(self, values, planes, j, phase):
        """Beam hits of shots with monitor ``phase`` on target j's plane."""
        normal = plane_normal(planes[j, 0], planes[j, 1])
        return beam_hits(self.system, values, phase, normal, planes[j, 2]), normal

    def tau0(self, values, hits):
        off = values.get("tdc_offset", self.ref["tdc_offset"])
        return hits.path / self.system.speed_of_light + off

    @staticmethod
    def lambert(hits, normal):
        """Relative signal g = cos θ_e · cos θ_r / R² of each hit (Lambertian target)."""
        P = hits.point
        r = np.sqrt(np.einsum("ij,ij->i", P, P))
        with np.errstate(invalid="ignore", divide="ignore"):
            g = np.abs(P @ normal) * P[:, 2] / (r * r * r * r)
        return np.where(hits.ok, g, np.nan)

    def _logmu(self, j, planes, hits, normal):
        g = self.lambert(hits, normal) / self.g_ref[j]
        return planes[j, 3] + np.log(np.where(np.isfinite(g) & (g > 0), g, 1.0))

    def update(self, values, planes, gate=None, margin=1.0, max_fraction_shots=1000):
        """Refresh what is held fixed within one solver run.

        With ``gate`` (pixels), keep only detections within ``gate`` of the
        beam's predicted image (false "signal" detections elsewhere on the
        epipolar line are left out) and aggregate them per shot; then σ_t,
        the on-sensor shots of each target (a subsample for the
        detection-share residual) and each target's mean Lambertian factor.
        """
        w = self.system.receiver.width
        h_ = self.system.receiver.height
        if gate is not None:
            keep = []
            start = 0
            for j, t in enumerate(self.targets):
                sl = slice(start, start + t.n_detections)
                start += t.n_detections
                hh, _ = self.hits(values, planes, j, t.phase)
                pred = hh.pixel[self.d_shot[sl]]
                with np.errstate(invalid="ignore"):
                    k = np.abs(self.d_col[sl] - pred[:, 0]) <= gate
                    if self.two_d:
                        k &= np.abs(self.d_row[sl] - pred[:, 1]) <= gate
                keep.append(k)
            self._aggregate(keep)
        self.g_ref = np.ones(self.T)
        self.frac_data = []
        for j, t in enumerate(self.targets):
            hh, nn = self.hits(values, planes, j, t.phase)
            col, row = hh.pixel[:, 0], hh.pixel[:, 1]
            on = hh.ok & (col > margin - 0.5) & (col < w - 0.5 - margin)
            if self.two_d:
                on &= (row > margin - 0.5) & (row < h_ - 0.5 - margin)
            g = self.lambert(hh, nn)
            self.g_ref[j] = float(np.nanmean(g[on])) if on.any() else 1.0
            idx = np.flatnonzero(on)
            n_on, n_hit = idx.size, int(np.count_nonzero(self.has_signal[j][idx]))
            sub = idx[np.linspace(0, idx.size - 1, min(idx.size, max_fraction_shots)).astype(int)] \
                if idx.size else idx
            self.frac_data.append((t.phase[sub], n_on, n_hit))
        sig = np.full(self.M, self.sigma_p)
        for j in range(self.T):
            rows = self.rows[j]
            hh, nn = self.hits(values, planes, j, self.phase[rows])
            s = self.tables[j].std(self.tau0(values, hh), self._logmu(j, planes, hh, nn))
            sig[rows] = np.where(np.isfinite(s), s, self.sigma_p)
        self.sigma_t = sig

    def segment(self, x, j):
        """Residual blocks of target j: pixel (, row), time (one per shot), fraction (1)."""
        values, planes = self.unpack(x)
        rows = self.rows[j]
        h, nn = self.hits(values, planes, j, self.phase[rows])
        ok = h.ok & np.all(np.isfinite(h.pixel), axis=1)
        w = self.weights[rows] * ok
        out = {"pixel": np.where(ok, (self.col[rows] - h.pixel[:, 0]) / SIGMA_PIXEL, 0.0) * w}
        if self.two_d:
            out["row"] = np.where(ok, (self.row[rows] - h.pixel[:, 1]) / SIGMA_PIXEL, 0.0) * w
        tau = np.where(ok, self.tau0(values, h), 0.0)
        logmu = np.where(ok, self._logmu(j, planes, h, nn), 0.0)
        t_pred = self.tables[j].mean_time(tau, logmu)
        out["time"] = np.where(ok, (self.t_meas[rows] - t_pred) / self.sigma_t[rows], 0.0) * w
        ph, n_on, n_hit = self.frac_data[j]
        fr = 0.0
        if n_on:
            hh, nj = self.hits(values, planes, j, ph)
            pj = self.tables[j].probability(self.tau0(values, hh), self._logmu(j, planes, hh, nj))
            p = min(max(float(np.nanmean(pj)), 0.0), 1.0)
            fr = (n_hit - n_on * p) / math.sqrt(n_on * p * (1 - p) + 1.0)
        out["fraction"] = np.array([fr])
        return out

    def prior(self, x):
        """Residuals of the known target distances (σ units), one per known target."""
        if self.known is None:
            return np.zeros(0)
        _, planes = self.unpack(x)
        return np.array([(known_distance_model(planes[j], self.distance_kind) - d) / sd
                         for j, (d, sd) in enumerate(zip(self.known, self.known_std))
                         if d is not None])

    def residual_blocks(self, x):
        """Residuals gathered by kind: pixel, (row,) time, fraction, prior."""
        segs = [self.segment(x, j) for j in range(self.T)]
        out = {k: np.concatenate([s[k] for s in segs]) for k in segs[0]}
        out["prior"] = self.prior(x)
        return out

    def residuals(self, x):
        """All residuals, target by target (then the priors), in σ units."""
        parts = []
        for j in range(self.T):
            parts += list(self.segment(x, j).values())
        parts.append(self.prior(x))
        return np.concatenate(parts)

    def block_index(self):
        """Row indices of each kind of residual inside :meth:`residuals`."""
        idx = {}
        pos = 0
        for j in range(self.T):
            for k, v in self.segment(np.zeros(len(self.labels)), j).items():
                idx.setdefault(k, []).append(np.arange(pos, pos + v.size))
                pos += v.size
        idx = {k: np.concatenate(v) for k, v in idx.items()}
        idx["prior"] = np.arange(pos, pos + self.prior(np.zeros(len(self.labels))).size)
        return idx

    def jacobian(self, x, step=1e-2, central=True):
        """Finite differences in scaled units (step 0.01 of PARAM_SCALE), central
        or forward; a target's own parameters change only its segment (and the
        priors)."""
        segs0 = [np.concatenate(list(self.segment(x, j).values())) for j in range(self.T)]
        starts = np.concatenate([[0], np.cumsum([s.size for s in segs0])])
        p0 = self.prior(x)
        r0 = np.concatenate(segs0 + [p0])
        J = np.zeros((r0.size, x.size))
        n = len(self.names)
        h = 2 * step if central else step
        for i in range(x.size):
            xp, xm = x.copy(), x.copy()
            xp[i] += step
            xm[i] -= step
            if i < n:
                J[:, i] = (self.residuals(xp) - (self.residuals(xm) if central else r0)) / h
                continue
            j = (i - n) // len(self.plane_names)
            rp = np.concatenate(list(self.segment(xp, j).values()))
            rm = np.concatenate(list(self.segment(xm, j).values())) if central else segs0[j]
            J[starts[j]:starts[j + 1], i] = (rp - rm) / h
            if p0.size:
                J[starts[-1]:, i] = (self.prior(xp) - (self.prior(xm) if central else p0)) / h
        return J


DISTANCE_KINDS = ("axis", "normal")


def known_distance_model(plane, kind: str = "axis") -> float:
    """The target distance a user measures, from a fitted plane (α, β, D, ...).

    ``kind="axis"``: from the receiver's projection centre to the target
    along the optical axis (camera z): ``D / n_z`` with
    ``n = plane_normal(α, β)``.  For a line sensor, whose fit sees only the
    plane's trace ``sin α·x + cos α·z = D`` in the scan plane, this is
    ``D / cos α`` whatever the target's pitch, so it is exactly what the fit
    determines.  ``kind="normal"``: the fit's own D (perpendicular distance
    of the plane (2-D arrays) or of its trace in the scan plane (line
    sensors) from the projection centre).  Metres.
    """
    if kind == "normal":
        return float(plane[2])
    return float(plane[2] / plane_normal(plane[0], plane[1])[2])


def _track_keep(prob: _Problem, values: dict, gate: float, n_bins: int = 100) -> list:
    """Detections near the beam's track on the sensor, found without a plane.

    For a fixed target the beam's image column is a smooth function of the
    scan angle θ; true returns pile up on it while false "signal"
    detections spread over the sensor.  Per θ bin (start values) the most
    frequent column marks the track; detections within ``gate`` pixels of it
    (interpolated in θ) are kept.  Returns a list of (M_j,) bool.
    """
    sysv = prob.system.with_params(**values)
    w = sysv.receiver.width
    keep = []
    start = 0
    for t in prob.targets:
        sl = slice(start, start + t.n_detections)
        start += t.n_detections
        th = scan_angle_from_phase(t.phase[prob.d_shot[sl]], sysv.scanner)
        col = prob.d_col[sl]
        edges = np.linspace(th.min(), th.max() + 1e-12, n_bins + 1)
        b = np.clip(np.searchsorted(edges, th, side="right") - 1, 0, n_bins - 1)
        ci = np.clip(np.rint(col).astype(np.int64), 0, w - 1)
        counts = np.zeros((n_bins, w))
        np.add.at(counts, (b, ci), 1.0)
        # smooth over ±1 pixel so a spot split over two pixels still wins
        sm = counts + 0.5 * (np.roll(counts, 1, axis=1) + np.roll(counts, -1, axis=1))
        mode = np.argmax(sm, axis=1).astype(np.float64)
        filled = counts.sum(axis=1) >= 3
        centres = 0.5 * (edges[1:] + edges[:-1])
        if filled.sum() < 2:
            keep.append(np.ones(t.n_detections, dtype=bool))
            continue
        track = np.interp(th, centres[filled], mode[filled])
        keep.append(np.abs(col - track) <= gate)
    return keep


def _initial_planes(prob: _Problem, values: dict) -> np.ndarray:
    """Planes from the ToF range along each pixel's ray (robust line fit in x–z).

    Uses the nominal (or given) system; the TDC time is taken at face value
    (no first-photon correction): good to a few decimetres, which the joint
    fit then refines.
    """
    sysv = prob.system.with_params(**values)
    K = sysv.receiver.camera_matrix
    c = sysv.speed_of_light
    b = sysv.baseline
    planes = np.zeros((prob.T, 4))
    for j in range(prob.T):
        sel = prob.tgt == j
        xn = (prob.col[sel] - K[0, 2]) / K[0, 0]
        yn = (prob.row[sel] - K[1, 2]) / K[1, 1] if prob.two_d else np.zeros(xn.size)
        r = np.stack([xn, yn, np.ones_like(xn)], axis=1)
        r /= np.linalg.norm(r, axis=1, keepdims=True)
        # undo the first-photon bias roughly (μ from the share of shots with a return)
        frac = min(max(float(np.mean(prob.has_signal[j])), 1e-3), 0.999)
        tau = prob.t_meas[sel]
        bias = prob.tables[j].mean_time(tau, math.log(-math.log1p(-frac))) - tau
        L = c * (tau - bias - sysv.tdc.offset)
        with np.errstate(divide="ignore", invalid="ignore"):
            rho = (L * L - b @ b) / (2.0 * (L - r @ b))
        P = rho[:, None] * r
        good = np.isfinite(rho) & (rho > 0)
        P = P[good]
        if P.shape[0] < 3:
            planes[j] = [0.0, 0.0, 1.0, 0.0]
            continue
        # z = a0 + a1 x (+ a2 y) by least squares with 3-MAD clipping
        keep = np.ones(P.shape[0], dtype=bool)
        A = np.column_stack([np.ones(P.shape[0]), P[:, 0]] + ([P[:, 1]] if prob.two_d else []))
        for _ in range(5):
            coef, *_ = np.linalg.lstsq(A[keep], P[keep, 2], rcond=None)
            res = P[:, 2] - A @ coef
            mad = 1.4826 * np.median(np.abs(res[keep] - np.median(res[keep]))) + 1e-9
            keep = np.abs(res - np.median(res[keep])) < 3 * mad
        nvec = np.array([-coef[1], -coef[2] if prob.two_d else 0.0, 1.0])
        nvec /= np.linalg.norm(nvec)
        alpha = math.atan2(nvec[0], nvec[2])
        beta = math.asin(np.clip(nvec[1], -1, 1))
        planes[j] = [alpha, beta, coef[0] * nvec[2], math.log(-math.log1p(-frac))]
    return planes


# --------------------------------------------------------------------------
# covariance and observability


def _covariance(prob: _Problem, x):
    """Scaled-unit information matrix, Jacobian, per-kind RMS (σ units), inlier counts."""
    J = prob.jacobian(x)
    r = prob.residuals(x)
    H = np.zeros((x.size, x.size))
    rms, n_in = {}, {}
    for name, idx in prob.block_index().items():
        Jb, rb = J[idx], r[idx]
        if name in ("prior", "fraction"):
            H += Jb.T @ Jb
            continue
        inl = (np.abs(rb) < 4.0) & (rb != 0.0)
        s2 = float(np.mean(rb[inl] ** 2)) if inl.any() else 1.0
        rms[name] = math.sqrt(s2)
        n_in[name] = int(inl.sum())
        H += Jb[inl].T @ Jb[inl] / s2
    return H, J, rms, n_in


def _inverse(H):
    """Pseudo-inverse by SVD with the singular values (relative to the largest)."""
    d = np.sqrt(np.maximum(np.diag(H), 1e-200))
    Hn = H / d[:, None] / d[None, :]
    U, s, Vt = np.linalg.svd(Hn)
    tol = max(s[0] * 1e-14, 1e-300)
    inv = (Vt.T * (1.0 / np.maximum(s, tol)) * (s > tol)) @ U.T
    return inv / d[:, None] / d[None, :], s / s[0], Vt


def _weak_column_text(name, col_std):
    if not col_std < 1e6 * PARAM_SCALE[name]:
        return f"{name} (its column of the Jacobian is zero: the data do not depend on it)"
    return f"{name} (even alone it would be known only to ±{_fmt(name, col_std)})"


def _fmt(name, v):
    f, unit = PARAM_UNIT[name.split("[")[0]]
    return f"{v * f:.4g} {unit}"


# --------------------------------------------------------------------------
# public


def fit_detections(targets, system: System, *, free=None, fix=(), known_distances=None,
                   distance_std=1e-3, distance_kind: str = "axis", loss: str = "soft_l1",
                   f_scale: float = 2.0,
                   jitter: float = 0.0, n_outer: int = 3, on_unobservable: str = "raise",
                   max_std: dict | None = None, initial_values: dict | None = None,
                   max_nfev: int = 100, gate: float = 1.5, gate_first: float = 2.5,
                   restarts: int = 1, _quiet_structural: bool = False) -> CalibrationResult:
    """Joint robust fit of system parameters and target planes.

    Parameters
    ----------
    targets : list of :class:`~mems_stereo.calib.detections.TargetDetections`, one per
        target pose (recording).
    system : the nominal system: start values and everything not fitted.
    free : system parameters to estimate (default: :data:`mems_stereo.calib.model.DEFAULT_FREE`;
        add ``"fx"``, ``"cx"`` to refine the receiver).
    fix : names held at their value in ``system``.
    known_distances : per target, its measured distance in m (see
        ``distance_kind``), or None where unknown; enters as a prior of σ
        ``distance_std`` (m; a scalar or one per target).  Breaks the scale
        (baseline × distance) / TDC offset trade-off.
    distance_kind : "axis" (default): from the receiver's projection centre
        to the target along the optical axis, what a rangefinder aligned
        with the receiver measures; "normal": the plane's perpendicular
        distance D of the fit (:func:`known_distance_model`).
    loss, f_scale : robust loss of ``least_squares`` (residuals are in σ units).
    jitter : SPAD timing jitter σ, s, added to the pulse's.
    n_outer : re-estimations of the signal rates and inlier weights.
    on_unobservable : "raise" (:class:`NotObservableError`) or "warn".
    max_std : dict of σ limits (SI) above which a parameter is unobservable.
    initial_values : start values overriding ``system``'s.
    gate, gate_first : pixels: detections farther than this from the beam's
        predicted image are not the target's (first round: from the start values).
    restarts : when θ0 or the baseline moved more than 8 mrad / 8 mm from the
        start, fit again from the solution (fresh plane start values and
        association), this many times.

    Returns
    -------
    :class:`CalibrationResult`.

    Raises
    ------
    NotObservableError : too few detections, or a free parameter the data
        cannot determine (named in the message).
    """
    if on_unobservable not in ("raise", "warn"):
        raise ValueError(f"on_unobservable: expected 'raise' or 'warn', found {on_unobservable!r}")
    limits = dict(DEFAULT_MAX_STD, **(max_std or {}))
    targets = list(targets)
    free = list(DEFAULT_FREE if free is None else free)
    for n in list(free) + list(fix):
        if n not in SYSTEM_PARAMS:
            raise KeyError(f"unknown calibration parameter {n!r}; known: {list(SYSTEM_PARAMS)}")
    names = [n for n in SYSTEM_PARAMS if n in free and n not in fix]
    fixed = [n for n in SYSTEM_PARAMS if n not in names]
    if not targets:
        raise NotObservableError("no recordings/targets given: nothing to calibrate")
    if known_distances is not None and len(known_distances) != len(targets):
        raise ValueError(f"known_distances: expected {len(targets)} entries (one per target), "
                         f"found {len(known_distances)}")
    if distance_kind not in DISTANCE_KINDS:
        raise ValueError(f"distance_kind: expected one of {DISTANCE_KINDS}, "
                         f"found {distance_kind!r}")
    dist_std = np.broadcast_to(np.asarray(distance_std, dtype=np.float64),
                               (len(targets),)).copy()
    if not np.all(dist_std > 0):
        raise ValueError(f"distance_std: expected positive σ (m), found {distance_std!r}")
    if known_distances is not None:
        known_distances = [None if d is None or not math.isfinite(d) else float(d)
                           for d in known_distances]
        if all(d is None for d in known_distances):
            known_distances = None
    for j, t in enumerate(targets):
        if t.n_detections < MIN_DETECTIONS_PER_TARGET:
            raise NotObservableError(
                f"too few signal detections in target {j} ({t.source}): {t.n_detections}, "
                f"need at least {MIN_DETECTIONS_PER_TARGET} to determine its plane (and with "
                f"it {', '.join(names)}); record more shots or check the classification")
    n_total = sum(t.n_detections for t in targets)
    two_d = system.receiver.height > 1
    if initial_values:
        system = system.with_params(**initial_values)
    prob = _Problem(targets, system, names, two_d, known_distances, dist_std, jitter,
                    distance_kind)
    initial = {n: system.get_param(n) for n in SYSTEM_PARAMS}
    prob._aggregate(_track_keep(prob, {}, gate_first))
    prob.plane_ref = _initial_planes(prob, {})
    if known_distances is not None:
        for j, d in enumerate(known_distances):
            if d is not None:  # start on the measured distance, keeping the start tilt
                prob.plane_ref[j, 2] = d * (1.0 if distance_kind == "normal" else
                                            plane_normal(*prob.plane_ref[j, :2])[2])
    x = np.zeros(len(prob.labels))
    values, planes = prob.unpack(x)
    prob.update(values, planes)

    # structural observability at the start: a column too weak on its own
    unobservable = []
    H0, _, _, _ = _covariance(prob, x)
    col_std = 1.0 / np.sqrt(np.maximum(np.diag(H0), 1e-300)) * prob.scales
    for i, n in enumerate(list(prob.names)):
        if col_std[i] > limits[n]:
            unobservable.append(n)
    if unobservable and not _quiet_structural:
        warnings.warn(
            "not observable from these data, held at the nominal value: "
            + ", ".join(_weak_column_text(n, col_std[prob.names.index(n)]) for n in unobservable),
            ObservabilityWarning, stacklevel=2)
    if unobservable:
        keep = [n for n in prob.names if n not in unobservable]
        prob.names = keep
        names = keep
        fixed = [n for n in SYSTEM_PARAMS if n not in names]
        x = np.zeros(len(prob.labels))
        prob.update(*prob.unpack(x))

    res = None
    nfev = 0
    for it in range(n_outer):
        values, planes = prob.unpack(x)
        # round 1 keeps the plane-free track association; later rounds gate on the model
        prob.update(values, planes, gate=None if it == 0 else gate)
        # gross time outliers (> 5σ at the current estimate) out of this round
        r_t = prob.residual_blocks(x)["time"]
        prob.weights[np.abs(r_t) > 5.0] = 0.0
        res = least_squares(prob.residuals, x, jac=lambda z: prob.jacobian(z, central=False),
                            loss=loss,
                            f_scale=f_scale, method="trf", x_scale=1.0, max_nfev=max_nfev,
                            xtol=1e-8, ftol=1e-8, gtol=1e-8)
        nfev += res.nfev
        x = res.x
    for j in range(prob.T):
        n_used = int(np.count_nonzero(prob.weights[prob.rows[j]]))
        if n_used < MIN_DETECTIONS_PER_TARGET:
            raise NotObservableError(
                f"target {j} ({targets[j].source}): only {n_used} shots with detections near "
                f"the fitted beam's image remain (need {MIN_DETECTIONS_PER_TARGET}); the fit "
                f"lost the target, so {', '.join(names)} cannot be estimated from these data")
    H, J, rms_blocks, n_in = _covariance(prob, x)
    cov_s, sv, Vt = _inverse(H)
    if restarts > 0:
        # a start far from the solution leaves the plane start values and the
        # association of detections behind: redo both from the solution
        vals, _ = prob.unpack(x)
        moved = max((abs(x[i]) for i, nm in enumerate(names)
                     if nm in ("theta0", "baseline_x", "baseline_z")), default=0.0)
        if moved > RESTART_MOVE:
            again = fit_detections(
                targets, system, free=free, fix=fix, known_distances=known_distances,
                distance_std=dist_std, distance_kind=distance_kind, loss=loss,
                f_scale=f_scale, jitter=jitter,
                n_outer=n_outer, on_unobservable=on_unobservable, max_std=max_std,
                initial_values={nm: float(vals[nm]) for nm in names}, max_nfev=max_nfev,
                gate=gate, gate_first=gate_first, restarts=restarts - 1,
                _quiet_structural=True)
            again.initial = {nm: initial[nm] for nm in again.names}
            again.unobservable = sorted(set(again.unobservable) | set(unobservable))
            again.system = again.system.replace(calibration=again.calibration_dict())
            again.report = format_report(again)
            return again
    cov_full = cov_s * prob.scales[:, None] * prob.scales[None, :]
    std_full = np.sqrt(np.maximum(np.diag(cov_full), 0.0))
    n = len(names)
    cov = cov_full[:n, :n]
    std = {nm: float(std_full[i]) for i, nm in enumerate(names)}
    with np.errstate(invalid="ignore", divide="ignore"):
        corr_full = cov_full / std_full[:, None] / std_full[None, :]
    corr = corr_full[:n, :n]
    labels = prob.labels
    tradeoffs = []
    for i in range(len(labels)):
        for k in range(i + 1, len(labels)):
            if i < n and abs(corr_full[i, k]) > CORRELATION_REPORT:
                tradeoffs.append((labels[i], labels[k], float(corr_full[i, k])))

    # too weak after the fit (trade-offs): raise or warn, naming the parameters
    weak = [nm for nm in names if not std[nm] <= limits[nm]]
    # exact null directions of the normalised information matrix
    null_names = set()
    for s_rel, v in zip(sv, Vt):
        if s_rel < 1e-10:
            null_names.update(labels[i] for i in np.flatnonzero(np.abs(v) > 0.3) if i < n)
    weak += [nm for nm in sorted(null_names) if nm not in weak]
    if weak:
        partners = {nm: [(b if a == nm else a, r) for a, b, r in tradeoffs if nm in (a, b)]
                    for nm in weak}
        msg = "; ".join(
            f"{nm}: σ = {_fmt(nm, std[nm])} > {_fmt(nm, limits[nm])}"
            + (" (trades off with " + ", ".join(f"{p} ρ={r:+.4f}" for p, r in partners[nm])
               + ")" if partners[nm] else "")
            for nm in weak)
        text = (f"not observable from these data: {msg}. Record the target at more distances, "
                "give measured target distances (--target-distances-file, --target-distance) or "
                "fix the parameter (--fix NAME)")
        if on_unobservable == "raise":
            raise NotObservableError(text)
        warnings.warn(text, ObservabilityWarning, stacklevel=2)
        unobservable += [nm for nm in weak if nm not in unobservable]
        for nm in weak:  # never a confident number for what the data cannot tell
            std[nm] = math.inf

    rms = {"pixel": rms_blocks.get("pixel", float("nan")) * SIGMA_PIXEL,
           "time": float(np.sqrt(np.mean((prob.residual_blocks(x)["time"]
                                          * prob.sigma_t)[prob.weights > 0] ** 2)))}
    inlier_frac = float(np.mean(prob.weights))
    converged = bool(res.success) and inlier_frac > 0.5 and rms_blocks.get("pixel", 9) < 2.0 \
        and rms_blocks.get("time", 9) < 2.0
    message = "" if converged else (
        f"the fit did not converge to a consistent solution (solver: {res.message}; "
        f"{inlier_frac:.0%} inliers; normalised RMS pixel {rms_blocks.get('pixel', 0):.2f}, "
        f"time {rms_blocks.get('time', 0):.2f}; expected about 1)")
    values, planes = prob.unpack(x)
    out_values = {nm: float(values[nm]) for nm in names}
    planes_std = np.zeros_like(planes)
    planes_std[:, prob.plane_cols] = std_full[n:].reshape(prob.T, len(prob.plane_cols))
    # each target's distance along the optical axis (what a rangefinder on the
    # receiver measures) with its σ from the plane parameters' covariance
    z_axis, z_std = np.zeros(prob.T), np.zeros(prob.T)
    npp = len(prob.plane_names)
    for j in range(prob.T):
        a, b, D = planes[j, 0], planes[j, 1], planes[j, 2]
        ca, cb = math.cos(a), math.cos(b)
        z_axis[j] = D / (ca * cb)
        grad = {"alpha": D * math.sin(a) / (ca * ca * cb), "beta": D * math.sin(b) / (ca * cb * cb),
                "dist": 1.0 / (ca * cb), "logmu": 0.0}
        g = np.array([grad[pn] for pn in prob.plane_names])
        sl = slice(n + j * npp, n + (j + 1) * npp)
        z_std[j] = math.sqrt(max(float(g @ cov_full[sl, sl] @ g), 0.0))
    result = CalibrationResult(
        system=system.with_params(**out_values), names=names, values=out_values, std=std,
        initial={nm: initial[nm] for nm in names}, covariance=cov, correlation=corr, rms=rms,
        n_detections=int(np.count_nonzero(prob.weights)), fixed=fixed,
        unobservable=unobservable, tradeoffs=tradeoffs, planes=planes, planes_std=planes_std,
        converged=converged, message=message, iterations=nfev,
        extra={"n_total": n_total, "mu": np.exp(planes[:, 3]).tolist(),
               "normalised_rms": rms_blocks,
               "singular_values": sv.tolist(), "labels": labels,
               "axis_distance": z_axis.tolist(), "axis_distance_std": z_std.tolist(),
               "correlation_full": corr_full})
    result.system = result.system.replace(calibration=result.calibration_dict())
    result.report = format_report(result)
    if not converged:
        warnings.warn(message, RuntimeWarning, stacklevel=2)
    return result


def format_report(r: CalibrationResult) -> str:
    """Plain-text table of estimates, σ, RMS, trade-offs and unobservable parameters."""
    lines = [f"calibration: {'converged' if r.converged else 'NOT CONVERGED'}, "
             f"{r.n_detections} signal detections, {len(r.planes)} target(s)",
             f"  RMS residual: pixel {r.rms_pixel:.3f} px, time {r.rms_time * 1e9:.3f} ns",
             f"  {'parameter':<16}{'initial':>14}{'estimate':>14}{'σ':>12}  unit"]
    for n in r.names:
        f, unit = PARAM_UNIT[n]
        lines.append(f"  {n:<16}{r.initial[n] * f:>14.4f}{r.values[n] * f:>14.4f}"
                     f"{r.std[n] * f:>12.4f}  {unit}")
    z = r.extra.get("axis_distance", [math.nan] * len(r.planes))
    zs = r.extra.get("axis_distance_std", [math.nan] * len(r.planes))
    for j, (p, s) in enumerate(zip(r.planes, r.planes_std)):
        lines.append(f"  target {j}: distance along the optical axis {z[j]:.4f} m "
                     f"± {zs[j] * 1e3:.2f} mm (plane: D {p[2]:.4f} m ± {s[2] * 1e3:.2f} mm, "
                     f"tilt {p[0] * 1e3:.2f} ± {s[0] * 1e3:.2f} mrad)")
    if r.fixed:
        lines.append("  fixed: " + ", ".join(r.fixed))
    if r.unobservable:
        lines.append("  not observable from these data: " + ", ".join(r.unobservable))
    for a, b, c in r.tradeoffs:
        lines.append(f"  {a} and {b} trade off: correlation {c:+.4f}")
    if r.message:
        lines.append("  " + r.message)
    return "\n".join(lines)
