"""The per-detection part of :func:`~mems_stereo.pipeline.detections.detection_points`
in one compiled pass: the time-of-flight geometry of the five (L, θ) variants, the
fusion weight, the fused point's eight variants and the covariances, per detection,
from its run's stereo geometry (:func:`~mems_stereo.pipeline.detections._stereo_runs`).

The NumPy form evaluates each of these as whole-array expressions, about forty
(M,)- and (M, 3)-sized temporaries over the fusion's entries (352,000 on a dense
200,000-shot recording: 0.3 s).  :func:`_entries_py` does the same IEEE operations
in the same order per detection — so the same bits (tested against the NumPy form,
NaN rows included) — without them.  It runs compiled only where numba is loaded
already (a dense run's pass 1 loaded it, :func:`~mems_stereo.util.lazy_numba.compiled_if_loaded`).
"""

from __future__ import annotations

import math

import numpy as np

from mems_stereo.util.lazy_numba import compiled_if_loaded


def _entries_py(run, L, p, scal, S, var_st, ok_st, X0, C0, D, DB, full,
                x_st, c_st, x_tf, c_tf, x_f, c_f, w_out, ok, dxdL):
    """Per detection i of run ``r = run[i]``, written into the outputs (all (M, …)):

    run (M,) int64; L (M,) path length, m; p (3,) scanner position, m;
    scal (12,) ``[bb, Lc, hL, 2hu, 2hv, 2hL, 2ht, var_u, var_v, var_L, var_θ, σ_L²]``;
    S (7, R) the stereo ``s`` of the variants ``0, u+, u-, v+, v-, t+, t-``;
    var_st (R,); ok_st (R,) bool; X0 (R, 3) and C0 (R, 3, 3) the stereo point and its
    covariance (read only when ``full``); D (3, R, 3) the scan directions ``0, t+, t-``
    and DB (3, R) their d·p.  Outputs as ``_detection_result`` makes them: the fused
    point and covariance ``x_f, c_f`` and ``ok`` always; with ``full`` also ``x_st,
    c_st, x_tf, c_tf``, the weight ``w_out`` and ``dxdL``.
    """
    bb, Lc, hL = scal[0], scal[1], scal[2]
    h2u, h2v, h2L, h2t = scal[3], scal[4], scal[5], scal[6]
    var0, var1, var2, var3 = scal[7], scal[8], scal[9], scal[10]
    sigL2 = scal[11]
    xt = np.empty(3)
    f = np.empty((9, 3))  # fused variants 0, u+, u-, v+, v-, L+, L-, t+, t-
    J = np.empty((4, 3))
    var = np.empty(4)
    var[0], var[1], var[2], var[3] = var0, var1, var2, var3
    sv = np.empty(5)  # the ToF s of the variants 0, L+, L-, t+, t-
    for i in range(run.shape[0]):
        r = run[i]
        Li = L[i]
        for v in range(5):
            # tof_on_scanner_ray's s: the same operations in the same order
            Lv = Li + hL if v == 1 else (Li - hL if v == 2 else Li)
            db = DB[0, r] if v < 3 else DB[v - 2, r]
            if not math.isfinite(Lv):
                sv[v] = math.nan
                continue
            Le = Lv if Lv > Lc else Lc
            s = (Le * Le - bb) / (2.0 * (Le + db))
            if Lv < Lc:
                t = Lc + db
                slope = (Lc * Lc + 2.0 * Lc * db + bb) / (2.0 * (t * t))
                s = s + slope * (Lv - Lc)
            sv[v] = s
        s0, sLp, sLm, stp, stm = sv[0], sv[1], sv[2], sv[3], sv[4]
        dsdL = (sLp - sLm) / h2L
        var_tf = dsdL * dsdL * sigL2
        den = var_st[r] + var_tf
        w = var_tf / den if den > 0 else 0.5
        w1 = 1.0 - w
        fin = True
        for j in range(3):
            xt[j] = p[j] + s0 * D[0, r, j]
            if not math.isfinite(xt[j]):
                fin = False
        good = ok_st[r] and fin and math.isfinite(w)
        n3 = 0.0 if good else math.nan
        wt0 = w1 * s0
        # the fused s of each variant: w·s_stereo + (1 − w)·s_tof, as the NumPy form
        fs0 = w * S[0, r] + wt0
        fsu_p = w * S[1, r] + wt0
        fsu_m = w * S[2, r] + wt0
        fsv_p = w * S[3, r] + wt0
        fsv_m = w * S[4, r] + wt0
        fsL_p = w * S[0, r] + w1 * sLp
        fsL_m = w * S[0, r] + w1 * sLm
        fst_p = w * S[5, r] + w1 * stp
        fst_m = w * S[6, r] + w1 * stm
        for j in range(3):
            d0 = D[0, r, j]
            f[0, j] = p[j] + fs0 * d0
            f[1, j] = p[j] + fsu_p * d0
            f[2, j] = p[j] + fsu_m * d0
            f[3, j] = p[j] + fsv_p * d0
            f[4, j] = p[j] + fsv_m * d0
            f[5, j] = p[j] + fsL_p * d0
            f[6, j] = p[j] + fsL_m * d0
            f[7, j] = p[j] + fst_p * D[1, r, j]
            f[8, j] = p[j] + fst_m * D[2, r, j]
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
        if full:
            w_out[i] = w if good else math.nan
            for j in range(3):
                x_st[i, j] = X0[r, j] + n3
                x_tf[i, j] = xt[j] + n3
                dxdL[i, j] = D[0, r, j] * dsdL + n3
                # the ToF covariance's L and θ columns (its u, v columns are 0)
                J[0, j] = ((p[j] + sLp * D[0, r, j]) - (p[j] + sLm * D[0, r, j])) / h2L
                J[1, j] = ((p[j] + stp * D[1, r, j]) - (p[j] + stm * D[2, r, j])) / h2t
            for a in range(3):
                for b in range(3):
                    c_st[i, a, b] = C0[r, a, b] + n3
                    c_tf[i, a, b] = ((0.0 + (J[0, a] * var2) * J[0, b])
                                     + (J[1, a] * var3) * J[1, b]) + n3


def compiled_entries():
    """The numba form of :func:`_entries_py` where numba is imported already, else None."""
    return compiled_if_loaded(_entries_py)


#: the outputs of :func:`_entries_py`, in :class:`~mems_stereo.pipeline.detections.
#: DetectionPoints` order, with their shapes per detection (the first four, ``w`` and
#: ``dxdL`` have no rows unless ``full``)
_OUTPUTS = (("x_st", (3,), True), ("c_st", (3, 3), True), ("x_tf", (3,), True),
            ("c_tf", (3, 3), True), ("x_f", (3,), False), ("c_f", (3, 3), False),
            ("w", (), True), ("ok", (), False), ("dxdL", (3,), True))


def entries(run, L, p, scal, R: dict, full: bool, kernel=None):
    """Run :func:`_entries_py` (``kernel``, default its compiled form) over the
    detections; R the per-run stereo geometry of ``_stereo_runs`` (``c_st`` and ``x0``
    read only when ``full``).  Returns ``(x_st, c_st, x_tf, c_tf, x_f, c_f, w, ok,
    dxdL)`` (the fields of ``DetectionPoints``) with ``full``, else ``(x_f, c_f, ok)``."""
    kernel = compiled_entries() if kernel is None else kernel
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
    kernel(np.ascontiguousarray(run, dtype=np.int64), np.ascontiguousarray(L, np.float64),
           np.ascontiguousarray(p, np.float64), np.asarray(scal, np.float64), S,
           np.ascontiguousarray(R["var_st"], np.float64),
           np.ascontiguousarray(R["ok_st"], np.bool_), X0, C0, D, DB, bool(full), *out)
    return tuple(out) if full else (out[4], out[5], out[7])
