"""Points of single detections: stereo, time of flight and their fusion per
(pixel, code, scan angle), with their propagated covariances (receiver camera frame,
metres).  Used by the fusion (:mod:`mems_stereo.pipeline.fusion`) for every distinct
(peak, step, code) entry and by the tests as the per-detection reference.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mems_stereo.errors import GeometryError
from mems_stereo.geometry.triangulation import (
    epipolar_stereo_point,
)
from mems_stereo.geometry.uncertainty import (
    DIFF_STEPS,
    INPUTS,
    Spreads,
    as_inputs,
    jacobian,
    pixel_rays,
    propagate,
    spreads_for,
    stereo_point_est,
)
from mems_stereo.model.scanner import scan_direction
from mems_stereo.model.system import System
from mems_stereo.model.tdc import detection_path_length
from mems_stereo.pipeline.classify_kernel import compiles
from mems_stereo.pipeline.detection_kernel import compiled_entries, entries
from mems_stereo.util.lazy_numba import compiled_if_loaded


@dataclass
class DetectionPoints:
    """Per-detection estimates, each (M, 3) m with covariance (M, 3, 3) m².

    stereo, cov_stereo : pixel ray ∩ scanner ray.
    tof, cov_tof : path length on the scanner ray.
    fused, cov_fused : inverse-variance combination along the scanner ray.
    weight_stereo : (M,) weight of the stereo estimate in the fusion (0..1).
    ok : (M,) bool, False where an estimate is degenerate (all NaN then).
    dtof_dL : (M, 3) m/m, derivative of the ToF point along the scanner ray
        with respect to the path length L (the fused point's is
        ``(1 − weight_stereo)`` times it), or None.
    """

    stereo: np.ndarray
    cov_stereo: np.ndarray
    tof: np.ndarray
    cov_tof: np.ndarray
    fused: np.ndarray
    cov_fused: np.ndarray
    weight_stereo: np.ndarray
    ok: np.ndarray
    dtof_dL: np.ndarray | None = None

    def subset(self, sel) -> DetectionPoints:
        """The entries ``sel`` (index or bool mask) of every field."""
        return DetectionPoints(*(None if v is None else v[sel] for v in (
            self.stereo, self.cov_stereo, self.tof, self.cov_tof, self.fused, self.cov_fused,
            self.weight_stereo, self.ok, self.dtof_dL)))


#: below ``TOF_LINEAR_BELOW`` × |b| of path length the time-of-flight point on the
#: scanner ray continues linearly (see :func:`tof_on_scanner_ray`)
TOF_LINEAR_BELOW = 2.0


def _dot3(d, p) -> np.ndarray:
    """(N,) d·p of (N, 3) rows and a (3,) vector, added left to right: the same bits as
    ``np.sum(d * p, axis=-1)`` (tested), without its slow reduction over 3 columns."""
    p = np.asarray(p, dtype=np.float64)
    return d[..., 0] * p[0] + d[..., 1] * p[1] + d[..., 2] * p[2]


def tof_on_scanner_ray(p, d, L, db=None):
    """Time-of-flight point at path length L on the scanner ray ``p + s·d``, for every L.

    The exact root ``s = (L² − |b|²) / (2 (L + d·b))`` (as
    :func:`~mems_stereo.geometry.triangulation.scanner_ray_point`) for
    ``L ≥ L_c = TOF_LINEAR_BELOW·|b|``, continued linearly below (value and
    slope of the root at L_c: C¹).  A near return's detections spread over
    ±c·σ_t ≈ ±1.9 m of path, and those at the TDC start are recorded at code 1
    (arrivals before it are clipped there): their path lengths fall below |b|,
    where the root does not exist.  Left out, they bias the peak's ToF mean
    late and take counts from its stereo mean; the first-photon model expects
    them (it knows the clipping), so each keeps its measured L on this
    continuation.  ``p`` (3,), ``d`` (N, 3) unit, ``L`` (N,); ``db`` (N,) ``d·p``
    when known (:func:`_dot3`).  Returns ``(points (N, 3), s (N,))``; NaN only for
    non-finite L.
    """
    p = np.asarray(p, dtype=np.float64)
    L = np.asarray(L, dtype=np.float64)
    bb = float(p @ p)
    if db is None:
        db = _dot3(np.asarray(d, dtype=np.float64), p)
    Lc = TOF_LINEAR_BELOW * math.sqrt(bb)
    Le = np.maximum(L, Lc)
    with np.errstate(invalid="ignore", divide="ignore"):
        s = (Le * Le - bb) / (2.0 * (Le + db))
        slope = (Lc * Lc + 2.0 * Lc * db + bb) / (2.0 * (Lc + db) ** 2)
        s = np.where(L < Lc, s + slope * (L - Lc), s)
    s = np.where(np.isfinite(L), s, np.nan)
    return p + s[..., None] * d, s


def _tof_point_ext(system: System, u, v, L, theta) -> np.ndarray:
    """:func:`tof_on_scanner_ray` as an estimator ``(system, u, v, L, θ) → (N, 3)``."""
    return tof_on_scanner_ray(system.scanner.position, scan_direction(theta, system.scanner),
                              L)[0]


def _s_stereo(system, u, v, L, theta):
    d = scan_direction(theta, system.scanner)
    s = epipolar_stereo_point(system.scanner.position, d, pixel_rays(system, u, v)).s
    return np.stack([s, np.zeros_like(s), np.zeros_like(s)], axis=1)


def _s_tof(system, u, v, L, theta):
    d = scan_direction(theta, system.scanner)
    s = tof_on_scanner_ray(system.scanner.position, d, L)[1]
    return np.stack([s, np.zeros_like(s), np.zeros_like(s)], axis=1)


def detection_points(system: System, shot_idx, rows, cols, codes, theta,
                     spreads: Spreads | None = None, fused_only: bool = False,
                     stereo_cache=None):
    """Stereo, time-of-flight and fused points of detections.

    The same numbers as :func:`_detection_points_reference` (the three
    estimators propagated one after the other), bit for bit, from one
    evaluation of the stereo geometry per (u, v, θ) variant of the central
    differences (7) and of the time-of-flight geometry per (L, θ) variant (5),
    instead of 35 evaluations: the stereo estimate ignores L, the ToF one u
    and v, so their other differences are ``(x0 − x0) / 2h`` = 0 (their terms
    of the covariances are left out: adding a zero changes no bit).  The
    stereo geometry (with its covariance) is evaluated once per run of
    consecutive detections with equal (u, v, θ) — the codes of one
    (peak, angle step) in the fusion's entries — and gathered: every value is
    a function of its own row, so this too changes no bit.  With a calibration
    covariance (``spreads.param_names``) it is the reference.

    Parameters
    ----------
    shot_idx, rows, cols, codes : (M,) integer arrays (codes 1..n_bins).
    theta : (K,) float64 scan angle of every shot, rad (indexed by shot_idx).
    spreads : :class:`~mems_stereo.geometry.uncertainty.Spreads` (default
        :func:`~mems_stereo.geometry.uncertainty.spreads_for`).
    fused_only : return only ``(fused (M, 3), cov_fused (M, 3, 3), ok (M,))``, the
        same bits as those fields of the full result, without the stereo and ToF
        covariances (the fusion's inlier margins need the fused range and its σ alone).
    stereo_cache : a :class:`StereoCache` for ``system`` and ``spreads`` (the
        fusion's accumulator keeps one: its sub-passes and inlier margins evaluate
        the same (pixel, angle step) runs several times), or None.
    """
    sp = spreads_for(system) if spreads is None else spreads
    if sp.param_names:
        dp = _detection_points_reference(system, shot_idx, rows, cols, codes, theta, sp)
        return (dp.fused, dp.cov_fused, dp.ok) if fused_only else dp
    inp = _detection_inputs(system, shot_idx, rows, cols, codes, theta)
    x_in = as_inputs(inp.u, inp.v, inp.L, inp.theta)
    p = np.asarray(system.scanner.position)
    U, V, Lx, TH = x_in["u"], x_in["v"], x_in["L"], x_in["theta"]
    hu, hv, hL, ht = (DIFF_STEPS[n] for n in INPUTS)
    sig = sp.input_sigmas(system)
    var_in = [sig[n] ** 2 for n in INPUTS]
    first, run = _runs(U, V, TH)
    Ur, Vr, Tr = U[first], V[first], TH[first]
    # per run of equal (u, v, θ): scan directions and the stereo geometry
    R = (_stereo_runs(system, sp, Ur, Vr, Tr, not fused_only) if stereo_cache is None
         else stereo_cache.get(system, sp, Ur, Vr, Tr))
    kernels = compiled_entries() if compiles(U.size, COMPILED_ROWS) else None
    if kernels is not None:  # the per-detection part in compiled passes (same bits)
        bb = float(p @ p)
        scal = [bb, TOF_LINEAR_BELOW * math.sqrt(bb), hL, 2.0 * hu, 2.0 * hv, 2.0 * hL,
                2.0 * ht, *var_in, sp.sigma_L(system) ** 2]
        out = entries(np.arange(U.size) if run is None else run, Lx, p, scal, R,
                      not fused_only, kernels)
        return out if fused_only else DetectionPoints(*out)
    return _entries_numpy(system, sp, R, run, Lx, fused_only)


def _entries_numpy(system: System, sp: Spreads, R: dict, run, Lx, fused_only: bool):
    """The per-detection part of :func:`detection_points` in NumPy, from the runs'
    stereo geometry ``R`` (:func:`_stereo_runs`), each detection's run ``run`` (M,)
    (None: every detection its own run) and path length ``Lx`` (M,) m."""
    p = np.asarray(system.scanner.position)
    hu, hv, hL, ht = (DIFF_STEPS[n] for n in INPUTS)
    sig = sp.input_sigmas(system)
    var_in = [sig[n] ** 2 for n in INPUTS]

    def gather(a):  # per run -> per detection
        return a if run is None else a[run]

    def diff(a, b, h):
        return (a - b) / (2.0 * h)

    c_st = None if fused_only else gather(R["c_st"])
    var_st = gather(R["var_st"])
    x_st = None if fused_only else gather(R["x0"])
    s_st = {k: gather(R["s" + k]) for k in ("0", "u+", "u-", "v+", "v-", "t+", "t-")}
    dirs = {k: gather(R["d" + k]) for k in ("0", "t+", "t-")}
    db = {k: gather(R["db" + k]) for k in ("0", "t+", "t-")}  # d·b, for the ToF
    # per detection: the time-of-flight geometry
    T = {"0": tof_on_scanner_ray(p, dirs["0"], Lx, db["0"]),
         "L+": tof_on_scanner_ray(p, dirs["0"], Lx + hL, db["0"]),
         "L-": tof_on_scanner_ray(p, dirs["0"], Lx - hL, db["0"]),
         "t+": tof_on_scanner_ray(p, dirs["t+"], Lx, db["t+"]),
         "t-": tof_on_scanner_ray(p, dirs["t-"], Lx, db["t-"])}
    x_tf = T["0"][0]
    # the u and v columns are 0 where x_tf is finite
    c_tf = None if fused_only else _cov([(diff(T["L+"][0], T["L-"][0], hL), var_in[2]),
                                         (diff(T["t+"][0], T["t-"][0], ht), var_in[3])],
                                        x_tf.shape[0])
    dsdL = diff(T["L+"][1], T["L-"][1], hL)
    var_tf = dsdL ** 2 * sp.sigma_L(system) ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        w = np.where(var_st + var_tf > 0, var_tf / (var_st + var_tf), 0.5)

    w1 = 1.0 - w
    ws, wt = {}, {}  # each product once: the same values as computing it per variant

    def fused(e, t, d):
        if e not in ws:
            ws[e] = w * s_st[e]
        if t not in wt:
            wt[t] = w1 * T[t][1]
        s = ws[e] + wt[t]
        return p + s[:, None] * dirs[d]

    x_f = fused("0", "0", "0")
    c_f = _cov([(diff(fused("u+", "0", "0"), fused("u-", "0", "0"), hu), var_in[0]),
                (diff(fused("v+", "0", "0"), fused("v-", "0", "0"), hv), var_in[1]),
                (diff(fused("0", "L+", "0"), fused("0", "L-", "0"), hL), var_in[2]),
                (diff(fused("t+", "t+", "t+"), fused("t-", "t-", "t-"), ht), var_in[3])],
               x_f.shape[0])
    ok_st = gather(R["ok_st"])
    ok = ok_st & np.all(np.isfinite(x_tf), 1) & np.isfinite(w)
    if fused_only:  # as _detection_result makes them
        nan3 = np.where(ok[:, None], 0.0, np.nan)
        return x_f + nan3, c_f + nan3[:, :, None], ok
    return _detection_result(x_st, c_st, x_tf, c_tf, x_f, c_f, w, dsdL[:, None, None],
                             dirs["0"], ok)


def _stereo_runs(system: System, sp: Spreads, Ur, Vr, Tr, want_cov: bool = True) -> dict:
    """The stereo geometry of :func:`detection_points` per run of equal (u, v, θ) (R,):
    scan directions ``d0, dt+, dt-`` (R, 3) and their ``d·b`` ``db0, dbt+, dbt-`` (R,),
    the stereo point ``x0`` (R, 3), its ``s`` of each variant ``s0, su+, …, st-`` (R,),
    covariance ``c_st`` (R, 3, 3) (None unless ``want_cov``), along-ray variance
    ``var_st`` (R,) and ``ok_st`` (R,).  Every value is a function of its own run."""
    hu, hv, _, ht = (DIFF_STEPS[n] for n in INPUTS)
    sig = sp.input_sigmas(system)
    var_in = [sig[n] ** 2 for n in INPUTS]
    p = np.asarray(system.scanner.position)
    # every variant's directions, rays and stereo in one call each, the variants laid
    # end to end (each row is computed from its own inputs: the same bits)
    R = Ur.size
    dr = dict(zip(("0", "t+", "t-"), np.split(scan_direction(
        np.concatenate([Tr, Tr + ht, Tr - ht]), system.scanner), 3)))
    rays = dict(zip(("0", "u+", "u-", "v+", "v-"), np.split(pixel_rays(
        system, np.concatenate([Ur, Ur + hu, Ur - hu, Ur, Ur]),
        np.concatenate([Vr, Vr, Vr, Vr + hv, Vr - hv])), 5)))
    keys = ("0", "u+", "u-", "v+", "v-", "t+", "t-")
    esp = epipolar_stereo_point(system.scanner.position,
                                np.concatenate([dr["0"]] * 5 + [dr["t+"], dr["t-"]]),
                                np.concatenate([rays[k] for k in keys[:5]] + [rays["0"]] * 2))
    E = {k: (esp.points[i * R:(i + 1) * R], esp.s[i * R:(i + 1) * R])
         for i, k in enumerate(keys)}  # (point (R, 3), s (R,)) of each variant

    def diff(a, b, h):
        return (a - b) / (2.0 * h)

    x_st0 = E["0"][0]
    out = {"x0": x_st0, "ok_st": np.all(np.isfinite(x_st0), 1)}
    # the L column is (x0 − x0)/2h = 0 where x0 is finite (NaN rows stay NaN below)
    out["c_st"] = (_cov([(diff(E["u+"][0], E["u-"][0], hu), var_in[0]),
                         (diff(E["v+"][0], E["v-"][0], hv), var_in[1]),
                         (diff(E["t+"][0], E["t-"][0], ht), var_in[3])], x_st0.shape[0])
                   if want_cov else None)
    # conditional (given θ) along-ray variance of the stereo: the s of the pixel variants
    ds_u = diff(E["u+"][1], E["u-"][1], hu)
    ds_v = diff(E["v+"][1], E["v-"][1], hv)
    out["var_st"] = ds_u ** 2 * sp.sigma_u ** 2 + ds_v ** 2 * sp.sigma_v ** 2
    for k in ("0", "u+", "u-", "v+", "v-", "t+", "t-"):
        out["s" + k] = E[k][1]
    for k, d in dr.items():
        out["d" + k] = d
        out["db" + k] = _dot3(d, p)
    return out


class StereoCache:
    """The per-run stereo geometry of :func:`detection_points` (:func:`_stereo_runs`)
    of one system and spreads, kept by exact (u, v, θ): a run met again is gathered,
    not computed (the same bits: each run's values are its own).  Runs with
    non-integer or large pixel coordinates or a non-finite angle are not kept."""

    #: pixel coordinates below this (integers) are kept: key ``u·2²⁰ + v + i·θ``
    SPAN = 1 << 20

    def __init__(self):
        self.keys = np.zeros(0, np.complex128)
        self.vals: dict | None = None

    def get(self, system: System, sp: Spreads, Ur, Vr, Tr) -> dict:
        """:func:`_stereo_runs` of the runs (R,), from the cache where it holds them."""
        ok = np.all(np.isfinite(Tr)) and all(
            np.all((x >= 0) & (x < self.SPAN) & (x == np.floor(x))) for x in (Ur, Vr))
        if not ok or Ur.size == 0:
            return _stereo_runs(system, sp, Ur, Vr, Tr)
        key = (Ur * self.SPAN + Vr) + 1j * Tr
        pos = np.searchsorted(self.keys, key)
        hit = self.keys[np.minimum(pos, max(self.keys.size - 1, 0))] == key if self.keys.size \
            else np.zeros(key.size, bool)
        if not np.all(hit):
            new_keys, first = np.unique(key[~hit], return_index=True)
            sel = np.flatnonzero(~hit)[first]
            new = _stereo_runs(system, sp, Ur[sel], Vr[sel], Tr[sel])
            keys = np.concatenate([self.keys, new_keys])
            order = np.argsort(keys, kind="stable")
            self.keys = keys[order]
            self.vals = {k: (v if self.vals is None else np.concatenate([self.vals[k], v]))[order]
                         for k, v in new.items()}
            pos = np.searchsorted(self.keys, key)
        return {k: v[pos] for k, v in self.vals.items()}


def _runs(u, v, th):
    """``(first (R,) index of each run of equal consecutive (u, v, θ), run (M,) its run
    per row)``; ``run`` None where every row is its own run."""
    M = u.size
    new = np.ones(M, bool)
    if M > 1:
        new[1:] = (u[1:] != u[:-1]) | (v[1:] != v[:-1]) | (th[1:] != th[:-1])
    first = np.flatnonzero(new)
    if first.size == M:
        return first, None
    return first, np.cumsum(new) - 1


def _cov(terms, n: int) -> np.ndarray:
    """Σ_k var_k·J_k J_kᵀ (n, 3, 3) of the columns ``terms`` = [(J_k (n, 3), var_k)], in
    the order given: as ``einsum("nik,k,njk->nij")`` over these columns, bit for bit
    (the same products ``(J_i·var)·J_j`` added one column after the other from 0).

    At least :data:`COMPILED_ROWS` rows where numba is loaded already (a dense
    run's pass 1 loaded it): one compiled pass (:func:`_cov_py`, the same IEEE
    operations in the same order, so the same bits; tested), without the (n, 3, 3)
    temporaries of each column; otherwise, and without numba, in NumPy."""
    kernel = _compiled_cov() if compiles(n, COMPILED_ROWS) else None
    if kernel is not None and terms:
        J = np.ascontiguousarray(np.stack([np.asarray(t[0], np.float64) for t in terms]))
        var = np.array([float(t[1]) for t in terms])
        C = np.empty((n, 3, 3))
        kernel(J, var, C)
        return C
    C = np.zeros((n, 3, 3))
    for J, var in terms:
        C += (J * var)[:, :, None] * J[:, None, :]
    return C


#: rows from which :func:`_cov` and the per-detection part of :func:`detection_points`
#: (:mod:`~mems_stereo.pipeline.detection_kernel`) run compiled (when numba is loaded
#: already)
COMPILED_ROWS = 4096


def _cov_py(J, var, C):
    """C[i, a, b] = Σ_k (J[k, i, a]·var[k])·J[k, i, b], added in k order from 0.0
    (J (K, n, 3), var (K,), C (n, 3, 3) written): the compiled form of :func:`_cov`."""
    K, n = J.shape[0], J.shape[1]
    for i in range(n):
        for a in range(3):
            for b in range(3):
                acc = 0.0
                for k in range(K):
                    acc += (J[k, i, a] * var[k]) * J[k, i, b]
                C[i, a, b] = acc


def _compiled_cov():
    """The numba form of :func:`_cov_py` where numba is imported already (dense runs:
    pass 1's kernels), else None: a small recording loads no compiled code."""
    return compiled_if_loaded(_cov_py)


@dataclass(frozen=True, slots=True)
class DetectionInputs:
    """The estimators' inputs of M detections, (M,) float64 each: pixel column ``u``
    and row ``v`` (px), path length ``L`` (m) and scan angle ``theta`` (rad)."""

    u: np.ndarray
    v: np.ndarray
    L: np.ndarray
    theta: np.ndarray


def _detection_inputs(system: System, shot_idx, rows, cols, codes, theta) -> DetectionInputs:
    shot_idx = np.asarray(shot_idx, dtype=np.int64).ravel()
    th_all = np.asarray(theta, dtype=np.float64).ravel()
    if shot_idx.size and (shot_idx.min() < 0 or shot_idx.max() >= th_all.size):
        raise GeometryError(f"shot_idx: expected indices in 0..{th_all.size - 1}")
    th = th_all[shot_idx]
    u = np.asarray(cols, dtype=np.float64).ravel()
    v = np.asarray(rows, dtype=np.float64).ravel()
    # the hardware model's code times (docs/hardware.md); ideal: the FORMAT v1 rule
    pixel = (None if system.tdc.pixel_offsets is None
             else np.rint(v).astype(np.int64) * system.receiver.width + np.rint(u).astype(np.int64))
    L = detection_path_length(np.asarray(codes).ravel(), system, pixel)
    if not (u.shape == v.shape == L.shape == th.shape):
        raise GeometryError(f"shot_idx, rows, cols, codes: expected equal shapes, found "
                            f"{shot_idx.shape}, {v.shape}, {u.shape}, {L.shape}")
    return DetectionInputs(u, v, L, th)


def _detection_result(x_st, c_st, x_tf, c_tf, x_f, c_f, w, J_tf, d, ok=None):
    if ok is None:
        ok = np.all(np.isfinite(x_st), 1) & np.all(np.isfinite(x_tf), 1) & np.isfinite(w)
    nan3 = np.where(ok[:, None], 0.0, np.nan)
    nan33 = nan3[:, :, None]
    dxdL = d * J_tf[:, 0, 0][:, None] + nan3
    return DetectionPoints(x_st + nan3, c_st + nan33, x_tf + nan3, c_tf + nan33,
                           x_f + nan3, c_f + nan33, np.where(ok, w, np.nan), ok, dxdL)


def _detection_points_reference(system: System, shot_idx, rows, cols, codes, theta,
                                spreads: Spreads | None = None) -> DetectionPoints:
    """:func:`detection_points` by propagating each estimator on its own (the
    reference it is tested against; used with a calibration covariance)."""
    sp = spreads_for(system) if spreads is None else spreads
    inp = _detection_inputs(system, shot_idx, rows, cols, codes, theta)
    u, v, L, th = inp.u, inp.v, inp.L, inp.theta
    x_st, c_st = propagate(stereo_point_est, system, u, v, L, th, sp)
    x_tf, c_tf = propagate(_tof_point_ext, system, u, v, L, th, sp)
    # conditional (given θ) along-ray variances: pixel for stereo, timing for ToF
    s_st, J_st = jacobian(_s_stereo, system, u, v, L, th, wrt=("u", "v"))
    s_tf, J_tf = jacobian(_s_tof, system, u, v, L, th, wrt=("L",))
    var_st = J_st[:, 0, 0] ** 2 * sp.sigma_u ** 2 + J_st[:, 0, 1] ** 2 * sp.sigma_v ** 2
    var_tf = J_tf[:, 0, 0] ** 2 * sp.sigma_L(system) ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        w = np.where(var_st + var_tf > 0, var_tf / (var_st + var_tf), 0.5)

    def fused(sys_, u, v, L, theta):
        d = scan_direction(theta, sys_.scanner)
        a = _s_stereo(sys_, u, v, L, theta)[:, 0]
        b = _s_tof(sys_, u, v, L, theta)[:, 0]
        s = w * a + (1.0 - w) * b
        return np.asarray(sys_.scanner.position) + s[:, None] * d

    x_f, c_f = propagate(fused, system, u, v, L, th, sp)
    return _detection_result(x_st, c_st, x_tf, c_tf, x_f, c_f, w, J_tf,
                             scan_direction(th, system.scanner))
