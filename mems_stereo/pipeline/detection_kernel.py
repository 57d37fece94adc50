"""The per-detection part of :func:`~mems_stereo.pipeline.detections.detection_points`
in compiled passes: the time-of-flight geometry of the five (L, θ) variants and the
fusion weight (:func:`_tof_variants_py`), the fused point's eight variants and its
covariance (:func:`_fused_py`), the stereo and ToF points and covariances
(:func:`_full_py`), per detection, from its run's stereo geometry
(:func:`~mems_stereo.pipeline.detections._stereo_runs`).

The NumPy form evaluates each of these as whole-array expressions, about forty
(M,)- and (M, 3)-sized temporaries over the fusion's entries.  The kernels do the
same IEEE operations in the same order per detection — so the same bits (tested
against the NumPy form, NaN rows included) — without them.  They run compiled only
where numba is loaded already (a dense run's pass 1 loaded it,
:func:`~mems_stereo.util.lazy_numba.compiled_if_loaded`).
"""

from __future__ import annotations

import math

import numpy as np

from mems_stereo.util.lazy_numba import compiled_if_loaded


def _tof_variants_py(run, L, scal, var_st, DB, sv, dsdL, w):
    """The time-of-flight ``s`` of the five (L, θ) variants ``0, L+, L-, t+, t-`` of
    each detection i of run ``r = run[i]`` into ``sv`` (M, 5), ``∂s/∂L`` into ``dsdL``
    (M,) and the fusion weight into ``w`` (M,): :func:`~mems_stereo.pipeline.detections.
    tof_on_scanner_ray`'s operations in the same order.

    run (M,) int64; L (M,) path length, m; scal (12,) ``[bb, Lc, hL, 2hu, 2hv, 2hL,
    2ht, var_u, var_v, var_L, var_θ, σ_L²]``; var_st (R,) the stereo's along-ray
    variance; DB (3, R) the scan directions' d·p.
    """
    bb, Lc, hL = scal[0], scal[1], scal[2]
    h2L = scal[5]
    sigL2 = scal[11]
    for i in range(run.shape[0]):
        r = run[i]
        Li = L[i]
        for v in range(5):
            Lv = Li + hL if v == 1 else (Li - hL if v == 2 else Li)
            db = DB[0, r] if v < 3 else DB[v - 2, r]
            if not math.isfinite(Lv):
                sv[i, v] = math.nan
                continue
            Le = Lv if Lv > Lc else Lc
            s = (Le * Le - bb) / (2.0 * (Le + db))
            if Lv < Lc:
                t = Lc + db
                slope = (Lc * Lc + 2.0 * Lc * db + bb) / (2.0 * (t * t))
                s = s + slope * (Lv - Lc)
            sv[i, v] = s
        d = (sv[i, 1] - sv[i, 2]) / h2L
        dsdL[i] = d
        var_tf = d * d * sigL2
        den = var_st[r] + var_tf
        w[i] = var_tf / den if den > 0 else 0.5


def _fused_py(run, p, scal, S, ok_st, D, sv, w, x_f, c_f, ok):
    """The fused point ``x_f`` (M, 3), its covariance ``c_f`` (M, 3, 3) and ``ok`` (M,)
    of each detection from its ToF variants ``sv`` and weight ``w``
    (:func:`_tof_variants_py`): ``w·s_stereo + (1 − w)·s_tof`` of each of the eight
    variants, their central differences, ``Σ_k (J_k var_k) J_kᵀ`` in k order.

    S (7, R) the stereo ``s`` of the variants ``0, u+, u-, v+, v-, t+, t-``; ok_st (R,)
    bool; D (3, R, 3) the scan directions ``0, t+, t-``; other inputs as
    :func:`_tof_variants_py`.
    """
    h2u, h2v, h2L, h2t = scal[3], scal[4], scal[5], scal[6]
    f = np.empty((9, 3))  # fused variants 0, u+, u-, v+, v-, L+, L-, t+, t-
    J = np.empty((4, 3))
    var = np.empty(4)
    var[0], var[1], var[2], var[3] = scal[7], scal[8], scal[9], scal[10]
    fs = np.empty(9)  # the fused s of each variant
    for i in range(run.shape[0]):
        r = run[i]
        s0, sLp, sLm, stp, stm = sv[i, 0], sv[i, 1], sv[i, 2], sv[i, 3], sv[i, 4]
        wi = w[i]
        w1 = 1.0 - wi
        fin = True
        for j in range(3):
            if not math.isfinite(p[j] + s0 * D[0, r, j]):
                fin = False
        good = ok_st[r] and fin and math.isfinite(wi)
        n3 = 0.0 if good else math.nan
        wt0 = w1 * s0
        # the fused s of each variant: w·s_stereo + (1 − w)·s_tof, as the NumPy form
        for v in range(5):
            fs[v] = wi * S[v, r] + wt0
        fs[5] = wi * S[0, r] + w1 * sLp
        fs[6] = wi * S[0, r] + w1 * sLm
        fs[7] = wi * S[5, r] + w1 * stp
        fs[8] = wi * S[6, r] + w1 * stm
        for j in range(3):
            d0 = D[0, r, j]
            for v in range(7):
                f[v, j] = p[j] + fs[v] * d0
            f[7, j] = p[j] + fs[7] * D[1, r, j]
            f[8, j] = p[j] + fs[8] * D[2, r, j]
            J[0, j] = (f[1, j] - f[2, j]) / h2u
            J[1, j] = (f[3, j] - f[4, j]) / h2v
            J[2, j] = (f[5, j] - f[6, j]) / h2L
            J[3, j] = (f[7, j] - f[8, j]) / h2t
        for a in range(3):
            x_f[i, a] = f[0, a] + n3
            for b in range(3):
                acc = 0.0
                for k in range(4):
                    acc += (J[k, a] * var[k]) * J[k, b]
                c_f[i, a, b] = acc + n3
        ok[i] = good


def _full_py(run, p, scal, X0, C0, D, sv, dsdL, w, ok, x_st, c_st, x_tf, c_tf, w_out, dxdL):
    """The stereo and ToF points and covariances, the weight and ``∂x/∂L`` of each
    detection (the fields :func:`_fused_py` leaves), NaN where not ``ok``.

    X0 (R, 3) and C0 (R, 3, 3) the stereo point and its covariance; other inputs as
    :func:`_tof_variants_py` and :func:`_fused_py`.
    """
    h2L, h2t = scal[5], scal[6]
    var2, var3 = scal[9], scal[10]
    J = np.empty((2, 3))
    for i in range(run.shape[0]):
        r = run[i]
        s0, sLp, sLm, stp, stm = sv[i, 0], sv[i, 1], sv[i, 2], sv[i, 3], sv[i, 4]
        good = ok[i]
        n3 = 0.0 if good else math.nan
        w_out[i] = w[i] if good else math.nan
        for j in range(3):
            x_st[i, j] = X0[r, j] + n3
            x_tf[i, j] = (p[j] + s0 * D[0, r, j]) + n3
            dxdL[i, j] = D[0, r, j] * dsdL[i] + n3
            # the ToF covariance's L and θ columns (its u, v columns are 0)
            J[0, j] = ((p[j] + sLp * D[0, r, j]) - (p[j] + sLm * D[0, r, j])) / h2L
            J[1, j] = ((p[j] + stp * D[1, r, j]) - (p[j] + stm * D[2, r, j])) / h2t
        for a in range(3):
            for b in range(3):
                c_st[i, a, b] = C0[r, a, b] + n3
                c_tf[i, a, b] = ((0.0 + (J[0, a] * var2) * J[0, b])
                                 + (J[1, a] * var3) * J[1, b]) + n3


def compiled_entries():
    """The numba forms of :func:`_tof_variants_py`, :func:`_fused_py` and
    :func:`_full_py` where numba is imported already, else None."""
    kernels = tuple(compiled_if_loaded(k) for k in (_tof_variants_py, _fused_py, _full_py))
    return None if any(k is None for k in kernels) else kernels


#: the outputs of :func:`entries`, in :class:`~mems_stereo.pipeline.detections.
#: DetectionPoints` order, with their shapes per detection (the first four, ``w`` and
#: ``dxdL`` have no rows unless ``full``)
_OUTPUTS = (("x_st", (3,), True), ("c_st", (3, 3), True), ("x_tf", (3,), True),
            ("c_tf", (3, 3), True), ("x_f", (3,), False), ("c_f", (3, 3), False),
            ("w", (), True), ("ok", (), False), ("dxdL", (3,), True))


def entries(run, L, p, scal, R: dict, full: bool, kernels=None):
    """Run :func:`_tof_variants_py`, :func:`_fused_py` and (with ``full``)
    :func:`_full_py` (``kernels``, default their compiled forms) over the detections;
    R the per-run stereo geometry of ``_stereo_runs`` (``c_st`` and ``x0`` read only
    when ``full``).  Returns a list ``[x_st, c_st, x_tf, c_tf, x_f, c_f, w, ok, dxdL]``
    (the fields of ``DetectionPoints``, in their order) with ``full``, else the
    tuple ``(x_f, c_f, ok)``."""
    tof_variants, fused, rest = compiled_entries() if kernels is None else kernels
    M = run.shape[0]

    def stacked(keys):
        return np.ascontiguousarray(np.stack([R[k] for k in keys]), dtype=np.float64)

    S = stacked(["s" + k for k in ("0", "u+", "u-", "v+", "v-", "t+", "t-")])
    D = stacked(["d" + k for k in ("0", "t+", "t-")])
    DB = stacked(["db" + k for k in ("0", "t+", "t-")])
    X0 = np.ascontiguousarray(R["x0"] if full else np.zeros((0, 3)), dtype=np.float64)
    C0 = np.ascontiguousarray(R["c_st"] if full else np.zeros((0, 3, 3)), dtype=np.float64)
    out = [np.empty(((M if full or not only_full else 0),) + shape,
                    np.bool_ if name == "ok" else np.float64)
           for name, shape, only_full in _OUTPUTS]
    run = np.ascontiguousarray(run, dtype=np.int64)
    p = np.ascontiguousarray(p, np.float64)
    scal = np.asarray(scal, np.float64)
    sv, dsdL, w = np.empty((M, 5)), np.empty(M), np.empty(M)
    tof_variants(run, np.ascontiguousarray(L, np.float64), scal,
                 np.ascontiguousarray(R["var_st"], np.float64), DB, sv, dsdL, w)
    x_st, c_st, x_tf, c_tf, x_f, c_f, w_out, ok, dxdL = out
    fused(run, p, scal, S, np.ascontiguousarray(R["ok_st"], np.bool_), D, sv, w, x_f, c_f, ok)
    if not full:
        return x_f, c_f, ok
    rest(run, p, scal, X0, C0, D, sv, dsdL, w, ok, x_st, c_st, x_tf, c_tf, w_out, dxdL)
    return out
