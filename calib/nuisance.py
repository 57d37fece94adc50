"""Held hardware terms in the covariance of a full-model calibration.

A term the fit holds at its nominal value (not selected, or not separable from the
fitted ones) still moves the estimates when the hardware has it: with the held
term's value ``η`` off by ``δ`` the fitted parameters move by ``S·δ``, the
sensitivity ``S = −I_xx⁻¹ I_xη`` of the conditional fit (the information of the
fitted parameters ``x`` and of the held direction ``η``: the cells' outer-product
information of :meth:`~mems_stereo.calib.problem.Problem.score` with ``η`` added).
Their covariance then is ``I_xx⁻¹ + σ_η² S Sᵀ`` (Gelman et al., *Bayesian Data
Analysis*, 3rd ed., §3.5: a nuisance held at a value rather than integrated out;
the same first-order form as the sandwich of a misspecified model, White 1982),
with ``σ_η`` the spread of the held term the user's hardware may have.

The held term here is the monitor's **edge-delay difference** (rising − falling):
its effect on the mirror's angle is even in the scan phase (a constant plus mostly
the 2nd and 4th cosine harmonics), so where harmonics are fitted it is absorbed into
``theta0`` and ``harmonic{2,4}_cos`` (the fit cannot tell it apart; the score test
does not select it), while the phase offset holds the mean of the two delays.  The
direction is symmetric — rising + δ/2, falling − δ/2, the mean kept — which in the
fit's parameters (falling held) is ``edge_rising_delay`` + δ, ``phase_offset``
− π·f_mech·δ.

The other is a **pulse tail** the Gaussian fit leaves out (not separable from
``tdc_offset``, or missed by the score test at share 0): the local sensitivity at
share 0 is far off for a tail of tens of %, so its share is fitted at a few held
decays (:func:`profile_tail`) and the measured move δ (the Gaussian fit less that
fit, ``tdc_offset`` compared at the pulse's mean delay) enters as
``(1 + (σ_w/w)²)·δ δᵀ`` (:func:`add_held_tail`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from mems_stereo.calib import observability as obs
from mems_stereo.calib.hardware_fit import TAIL_DECAYS, extended_problem
from mems_stereo.calib.solver import FitState, newton

#: s, σ of the monitor's edge-delay difference a calibration that holds it at the
#: nominal value allows for (comparator delays and hysteresis of the two edges: up to
#: a few hundred ns each, docs/hardware.md)
EDGE_DIFFERENCE_STD = 250e-9


@dataclass(frozen=True)
class Held:
    """A held direction η at a fit (:func:`held_sensitivity`).

    S : (P,) SI, the move of the fitted parameters (layout order, walls too) per unit
    of η; C : (P, P) SI, their covariance ``I_xx⁻¹``; value, std : the one-step
    estimate of η from the data (its score less what the fitted parameters explain,
    over its conditional information) and that estimate's σ.
    """

    S: np.ndarray
    C: np.ndarray
    value: float
    std: float


def held_sensitivity(prob, x, direction: dict, tail_decay: float | None = None) -> Held:
    """The :class:`Held` of the direction ``direction`` (dict parameter name →
    coefficient, SI per unit of η; names not in ``prob``'s layout are added at their
    nominal value, :func:`~mems_stereo.calib.hardware_fit.extended_problem`, with
    ``tail_decay`` s for a pulse tail's share) at the fitted ``x``."""
    lay = prob.layout
    extra = [n for n in direction if n not in lay.names]
    p2, x2 = extended_problem(prob, x, extra, tail_decay)
    _, g, H = p2.score(x2)
    names2 = p2.layout.names
    idx = [names2.index(n) for n in lay.names] + list(range(p2.layout.n_sys, p2.layout.size))
    v = np.zeros(p2.layout.size)
    for n, c in direction.items():
        v[names2.index(n)] = c
    h_xv = H[idx] @ v
    C, _, _ = obs.covariance(H[np.ix_(idx, idx)], lay.scales)
    Cf = np.where(np.isfinite(C), C, 0.0)
    S = -(Cf @ h_xv)
    info = float(v @ H @ v + h_xv @ S)  # I_vv − I_vx I_xx⁻¹ I_xv
    score = float(g @ v + g[idx] @ S)
    if not info > 0:
        return Held(S, C, 0.0, math.inf)
    return Held(S, C, score / info, 1.0 / math.sqrt(info))


def edge_direction(system) -> dict:
    """The symmetric edge-delay difference in the fit's parameters (see the module)."""
    return {"edge_rising_delay": 1.0, "phase_offset": -math.pi * system.scanner.f_mech}


def holds_edges(result) -> bool:
    """Whether ``result`` fits harmonics of the trajectory from monitor records but
    holds the edge-delay difference (the case :func:`add_held_edges` covers)."""
    prob = result.extra.get("problem")
    return (prob is not None and "edge_rising_delay" not in result.names
            and any(n.startswith("harmonic") for n in result.names)
            and all(w.shot_time is not None for w in prob.walls))


def add_held_edges(result, std: float = EDGE_DIFFERENCE_STD):
    """``result`` (a full-model :class:`~mems_stereo.calib.result.CalibrationResult`
    that :func:`holds_edges`) with the held edge-delay difference's share
    ``std² S Sᵀ`` in its covariance (see :func:`add_held`)."""
    prob = result.extra["problem"]
    held = held_sensitivity(prob, result.extra["x"], edge_direction(prob.system))
    return add_held(result, held, std, "held_edges",
                    f"the monitor's edge-delay difference is held equal (not separable from "
                    f"the fitted harmonics): σ include a difference of ±{std * 1e9:.0f} ns",
                    "record walls at two or more distances over the whole scan to fit it")


@dataclass(frozen=True)
class TailProfile:
    """A pulse tail's share fitted at a held decay (:func:`profile_tail`): ``decay``
    s, ``share`` and its σ ``share_std``, the fit's ``loglik``, and ``move`` (P,) SI:
    the Gaussian fit's parameters (its layout, walls too) less this fit's, its
    ``tdc_offset`` taken at the pulse's mean delay (core + share·decay)."""

    decay: float
    share: float
    share_std: float
    loglik: float
    move: np.ndarray


def profile_tail(prob, x, decays=TAIL_DECAYS) -> TailProfile | None:
    """The tail's share fitted with the other parameters at each held decay of
    ``decays`` (from ``x``, the Gaussian fit; the TDC offset kept at the pulse's mean
    delay at the start): the one of the largest likelihood among those that converge
    with a share in (0, 1) known to better than ±0.5, or None."""
    best = None
    lay = prob.layout
    for d in decays:
        p2, x2 = extended_problem(prob, x, ["pulse_tail_fraction"], d)
        i = p2.layout.names.index("pulse_tail_fraction")
        idx = ([p2.layout.names.index(n) for n in lay.names]
               + list(range(p2.layout.n_sys, p2.layout.size)))
        x2[i] = 0.1
        k = p2.layout.names.index("tdc_offset") if "tdc_offset" in lay.names else None
        if k is not None:
            x2[k] -= 0.1 * d
        st = FitState()
        nr = newton(p2, x2, st, max_iter=30)
        cov, _, _ = obs.covariance(nr.info, p2.layout.scales)
        w, sw = float(nr.x[i]), float(math.sqrt(max(cov[i, i], 0.0)))
        if st.converged and 0.0 < w < 1.0 and sw < 0.5 and (
                best is None or nr.loglik > best.loglik):
            xp = nr.x.copy()
            if k is not None:
                xp[k] += w * d
            best = TailProfile(d, w, sw, float(nr.loglik), np.asarray(x) - xp[idx])
    return best


def add_held_tail(result, profile: TailProfile):
    """``result`` (a Gaussian-pulse fit whose walls show a pulse tail) with the tail's
    share in its covariance: ``(1 + (σ_w/w)²)·δ δᵀ``, δ the ``profile``'s move (the
    Gaussian fit less the fit with the tail at its held decay, ``tdc_offset`` at the
    pulse's mean delay: the Gaussian fit's convention), w its share (see
    :func:`add_held`)."""
    w, sw = profile.share, profile.share_std
    held = Held(profile.move, _covariance(result), w, sw)
    return add_held(result, held, math.sqrt(1.0 + (sw / w) ** 2), "held_tail",
                    f"a pulse tail (share ≈ {w * 100:.0f} ± {sw * 100:.0f} % at "
                    f"{profile.decay * 1e9:.0f} ns) is left out of the Gaussian pulse: σ "
                    "include the move it makes", "record the walls with more shots at low "
                    "pile-up to fit the tail")


def _covariance(result) -> np.ndarray:
    """The covariance of all of ``result``'s fitted parameters (SI): that of its
    information."""
    prob = result.extra["problem"]
    return obs.covariance(result.extra["information"], prob.layout.scales)[0]


def add_held(result, held: Held, spread: float, key: str, what: str, advice: str):
    """``result`` with ``spread² S Sᵀ`` added to its covariance (σ, correlations,
    walls' σ and the system's calibration block follow) and a warning ``what``
    naming the two parameters it widens most, then ``advice``; the estimates are
    unchanged.  ``extra[key]`` keeps S (SI per unit of the held term) and ``spread``;
    ``extra["covariance_full"]`` the covariance of all the fit's parameters (a second
    held term adds to it)."""
    return add_covariance(result, held.C, spread * spread * np.outer(held.S, held.S), key,
                          {"sensitivity": held.S, "spread": float(spread),
                           "estimate": held.value, "estimate_std": held.std}, what, advice)


def add_covariance(result, base, extra, key: str, record: dict, what: str, advice: str):
    """``result`` with ``extra`` (P, P) SI added to its covariance over all the fit's
    parameters (``extra["covariance_full"]``, else ``base``): σ, correlations, walls'
    σ and the system's calibration block follow, a warning ``what`` names the two
    parameters it widens most, then ``advice``; ``extra[key]`` = ``record``."""
    prob = result.extra["problem"]
    lay = prob.layout
    C = result.extra.get("covariance_full", base) + extra
    result.extra["covariance_full"] = C
    n = lay.n_sys
    sd = np.sqrt(np.maximum(np.diag(C), 0.0))
    sd[~np.isfinite(np.diag(C))] = np.inf
    grow = [(sd[i] / result.std[nm], nm) for i, nm in enumerate(lay.names)
            if result.std[nm] > 0 and np.isfinite(sd[i])]
    result.covariance = C[:n, :n]
    result.std = {nm: float(sd[i]) for i, nm in enumerate(lay.names)}
    with np.errstate(invalid="ignore", divide="ignore"):
        result.correlation = C[:n, :n] / sd[:n, None] / sd[None, :n]
    for j in range(lay.T):
        ws = lay.wall_slice(j)
        for i, pn in enumerate(lay.wall_names):
            if pn in ("alpha", "beta", "dist"):
                result.planes_std[j, {"alpha": 0, "beta": 1, "dist": 2}[pn]] = sd[ws.start + i]
    top = sorted(grow, reverse=True)[:2]
    result.warnings.append(f"{what} ({', '.join(f'{nm} σ ×{k:.2f}' for k, nm in top)}); "
                           + advice)
    result.extra[key] = record
    result.system = result.system.replace(calibration=result.calibration_dict())
    return result
