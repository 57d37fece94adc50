"""What the data determine: covariance from the information matrix, the
observability verdict, and the consistency checks of a fitted calibration.

* :func:`covariance` — pseudo-inverse of the information (scaled), with the
  relative singular values (exact null directions show as ~0);
* :func:`weak_parameters` — free system parameters whose σ exceeds the limit
  (:data:`DEFAULT_MAX_STD`), with the parameters they trade off with;
* :func:`consistency_scores` — score tests of a flat wall: per wall and per
  quarter of the sensor, a TDC-time shift and a column shift the model does not
  have.  Neyman's C(α) form (the shifts' score less what the wall's nuisance
  score explains: the system parameters are shared with the other walls, so
  this wall's score of them is not zero at the joint fit), with the expected
  information of :mod:`mems_stereo.calib.expected_info`.  Under the model each
  statistic is χ² with up to 8 degrees of freedom; a recording that is not a
  flat wall, or a fit that locked onto the wrong geometry, fails it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from mems_stereo.calib.model import PARAM_UNIT
from scipy.stats import chi2, norm

#: a free parameter with a σ above this is "not observable" (SI units)
#: (a σ this large means the data add nothing to a mechanical tolerance of that size)
DEFAULT_MAX_STD = {"theta0": 10e-3, "theta_mech_max": 10e-3, "phase_offset": 20e-3,
                   "tdc_offset": 3e-9, "baseline_x": 20e-3, "baseline_y": 20e-3,
                   "baseline_z": 20e-3, "fx": 5.0, "cx": 2.0}
CORRELATION_REPORT = 0.9
#: consistency: a wall fails when its score statistic's one-sided p-value is
#: below this AND the implied shift is larger than the sizes below
P_INCONSISTENT = 1e-12
SHIFT_TIME = 1e-9
SHIFT_PIXEL = 0.3
#: ... and at least this share of the pulse σ: the first-photon time model holds to a
#: fraction of the pulse width (a strong, piled-up wall's leading edge), not to 1 ns
SHIFT_TIME_PULSE = 0.5
#: ... and a shift that large counts only where it is itself this significant
#: (shift / its σ): an allowance for the model's approximations (Gaussian pulse,
#: background measured, not fitted); a genuine non-flat wall or a wrong geometry
#: shows shifts at tens of σ
SHIFT_Z = 8.0


def big_shift(dt_q: np.ndarray, du_q: np.ndarray, z: np.ndarray, sigma: float) -> bool:
    """A quarter of the sensor whose returns sit off the model by more than
    max(``SHIFT_TIME``, ``SHIFT_TIME_PULSE`` × the pulse σ ``sigma``) or
    ``SHIFT_PIXEL``, at a significance above ``SHIFT_Z``."""
    size = np.concatenate([np.abs(dt_q) > max(SHIFT_TIME, SHIFT_TIME_PULSE * sigma),
                           np.abs(du_q) > SHIFT_PIXEL])
    return bool(np.any(size & (np.abs(z) > SHIFT_Z)))


def covariance(H: np.ndarray, scales: np.ndarray):
    """(cov SI (P, P), relative singular values (P,), Vt) from the information ``H`` (SI)."""
    Hs = H * scales[:, None] * scales[None, :]
    d = np.sqrt(np.maximum(np.diag(Hs), 1e-200))
    Hn = Hs / d[:, None] / d[None, :]
    U, s, Vt = np.linalg.svd(Hn)
    tol = max(s[0] * 1e-12, 1e-300)
    inv = (Vt.T * (1.0 / np.maximum(s, tol)) * (s > tol)) @ U.T
    cov_s = inv / d[:, None] / d[None, :]
    # directions the data cannot see get an infinite σ
    null = s <= tol
    if null.any():
        bad = np.any(np.abs(Vt[null]) > 0.3, axis=0)
        cov_s[bad, :] = np.where(np.eye(len(s), dtype=bool)[bad, :], np.inf, 0.0)
        cov_s[:, bad] = np.where(np.eye(len(s), dtype=bool)[:, bad], np.inf, 0.0)
    return cov_s * scales[:, None] * scales[None, :], s / s[0], Vt


def fmt(name: str, v: float) -> str:
    f, unit = PARAM_UNIT[name.split("[")[0]]
    return f"{v * f:.3g} {unit}"


def tradeoffs(cov: np.ndarray, labels: list, n_sys: int):
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / sd[:, None] / sd[None, :]
    out = []
    for i in range(n_sys):
        for k in range(i + 1, len(labels)):
            if abs(corr[i, k]) > CORRELATION_REPORT:
                out.append((labels[i], labels[k], float(corr[i, k])))
    return corr, out


def weak_parameters(std: dict, limits: dict, trade: list) -> tuple[list, str]:
    """(names, message) of free system parameters with σ above their limit."""
    weak = [n for n, s in std.items() if not s <= limits.get(n, math.inf)]
    if not weak:
        return [], ""
    parts = []
    for n in weak:
        partners = [(b if a == n else a, r) for a, b, r in trade if n in (a, b)]
        parts.append(f"{n} σ = {fmt(n, std[n])} > {fmt(n, limits[n])}"
                     + (" (trades off with " + ", ".join(f"{p} ρ={r:+.3f}" for p, r in
                                                         partners[:3]) + ")"
                        if partners else ""))
    return weak, "; ".join(parts)


@dataclass(frozen=True, slots=True)
class ConsistencyTest:
    """The flat-wall score test of one wall (:func:`consistency_scores`).

    p_value : one-sided p-value of the χ² statistic (1.0 where nothing is tested).
    time_shifts : (4,) float64 s, the TDC-time shift per quarter of the sensor the
        data ask for beyond the fitted model.
    column_shifts : (4,) float64 px, the column shift per quarter.
    z : (8,) float64, each shift over its σ, time shifts first.
    """

    p_value: float
    time_shifts: np.ndarray
    column_shifts: np.ndarray
    z: np.ndarray


def _quarter_shift_scores(d_cells, col, width, info):
    """The cells' scores of the 8 shifts (time per quarter of the sensor, then column
    per quarter), (N, m) for the m shifts any cell (and ``info``) informs, and the
    (8,) bool of those."""
    q = np.clip((col / width * 4).astype(np.int64), 0, 3)
    E = np.zeros((col.size, 8))
    for i in range(4):
        m = q == i
        E[m, i] = d_cells[m, 0]
        E[m, 4 + i] = d_cells[m, 1]
    used = np.any(E != 0, axis=0)
    if info is not None:
        used &= np.diag(info)[:8] > 0
    return E[:, used], used


def consistency_scores(d_cells: np.ndarray, S_cells: np.ndarray, col: np.ndarray,
                       H_inv_block: np.ndarray | None = None, width: int = 192,
                       info: np.ndarray | None = None) -> ConsistencyTest:
    """Score test of per-quarter time and column shifts of one wall.

    d_cells : (N, 2) ∂ℓ/∂τ and ∂ℓ/∂u of each cell at the fit.
    S_cells : (N, P) the cells' scores of the fitted parameters (the nuisance).
    col : (N,) column of each cell (the quarter of the sensor it belongs to).
    info : None — the information is the outer product of the observed scores;
        or the (8 + P, 8 + P) expected information of [the 8 shifts (time per
        quarter, then column per quarter), the P nuisance parameters]
        (:mod:`mems_stereo.calib.expected_info`): the test then uses it (the
        outer product of a weak wall's few signal cells is too noisy for the
        small information left to a shift once the nuisance is fitted).

    Returns a :class:`ConsistencyTest`: the shifts the data ask for, each beyond
    the fitted model, and their significance.
    """
    none = ConsistencyTest(1.0, np.zeros(4), np.zeros(4), np.zeros(8))
    E, used = _quarter_shift_scores(d_cells, col, width, info)
    if E.shape[1] == 0:
        return none
    if info is None:
        unit = np.sqrt(np.maximum(np.einsum("ij,ij->j", E, E), 1e-300))
        E = E / unit  # columns in units of their own σ
        S_cells = S_cells / np.sqrt(np.maximum(np.einsum("ij,ij->j", S_cells, S_cells),
                                               1e-300))
        g = E.sum(axis=0)
        g_s = S_cells.sum(axis=0)
        Iee = E.T @ E
        Ies = E.T @ S_cells
        Iss = S_cells.T @ S_cells
    else:
        sel = np.concatenate([np.flatnonzero(used), 8 + np.arange(info.shape[0] - 8)])
        Ii = info[np.ix_(sel, sel)]
        dd = np.sqrt(np.maximum(np.diag(Ii), 1e-300))
        Ii = Ii / dd[:, None] / dd[None, :]
        ne = E.shape[1]
        unit = dd[:ne]
        g = E.sum(axis=0) / unit
        g_s = S_cells.sum(axis=0) / dd[ne:]
        Iee, Ies, Iss = Ii[:ne, :ne], Ii[:ne, ne:], Ii[ne:, ne:]
    try:
        Iss_inv = np.linalg.pinv(Iss, rcond=1e-10, hermitian=True)
        adj = Iee - Ies @ Iss_inv @ Ies.T
        # Neyman's C(α) effective score: the shifts' score less what the nuisance's
        # own score explains.  The system parameters are fitted to all walls, so one
        # wall's score of them is not zero at the fit (it pulls against the others);
        # without this a shift nearly collinear with the nuisance (a time trend
        # across the sensor vs the wall's yaw and the baseline) inherits that pull
        # divided by its small residual information
        g = g - Ies @ Iss_inv @ g_s
        ev, V = np.linalg.eigh(0.5 * (adj + adj.T))
    except np.linalg.LinAlgError:
        return none
    # directions the fitted parameters already span (e.g. the sum of the quarter
    # time shifts is the TDC offset) carry no test: keep the well-conditioned rest
    keep = ev > 1e-6
    if not keep.any():
        return none
    proj = V[:, keep].T @ g
    stat = float(np.sum(proj * proj / ev[keep]))
    p = float(chi2.sf(stat, int(keep.sum())))
    shift = V[:, keep] @ (proj / ev[keep]) / unit
    # σ of each shift (in its own units): the diagonal of the adjusted inverse
    var = np.einsum("ik,k,ik->i", V[:, keep], 1.0 / ev[keep], V[:, keep]) / unit ** 2
    full = np.zeros(8)
    full[used] = shift
    z = np.zeros(8)
    z[used] = shift / np.sqrt(np.maximum(var, 1e-300))
    return ConsistencyTest(p, full[:4], full[4:], z)


def sigma_of_p(p: float) -> float:
    """The one-sided normal quantile of a p-value (for messages)."""
    return float(norm.isf(max(p, 1e-300)))
