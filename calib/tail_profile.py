"""The pulse tail's share in a full-model calibration: σ from its profile likelihood.

The family's pulse core is wide (σ ≈ 6.3 ns for ``pulse_fwhm`` 14.9 ns) against most
tail decays (0.5–8 ns): an ex-Gaussian tail of share w and decay τ then differs from
a shift of the core mostly by its skew, and the likelihood has a curved ridge along
which w·τ (the mean delay) and ``tdc_offset`` + w·τ stay nearly fixed.  The local
curvature at the maximum (the fit's information) is that of the steep side: the
likelihood falls fast towards w = 0 (a Gaussian pulse cannot hold the skew) and
slowly towards larger shares with shorter decays.  On imperfect walls of the
benchmark family (``bench_real_hardware.py`` seeds 1075 and 1091) the true share
lies 4–5 local σ above the estimate but 2.2 and 2.9 σ by the profile likelihood
(2·Δlog L 5.0 and 8.7).

:func:`share_profile` profiles ``pulse_tail_fraction`` (every other parameter,
the walls' too, refitted at each held share by
:func:`~mems_stereo.calib.solver.newton`, started on the ridge: the decay at
the same mean delay) and finds its interval at 2·Δlog L = :data:`LEVEL` (95 %);
the share's σ is the wider side over 2 (Wilks; Venzon & Moolgavkar 1988,
Appl. Stat. 37, 87 for the search).  :func:`widen_share` adds what this σ has
beyond the local one along the ridge — the fitted parameters' move per unit share
to the wide side's end, ``(σ_p² − σ_c²)·S Sᵀ`` (:func:`~mems_stereo.calib.nuisance.
add_held`) — so that the decay and ``tdc_offset`` widen with it; the estimates
are unchanged.  A share whose wide side does not close below :data:`MAX_SHARE` is
not determined by the walls: the warning says so and what to record.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from mems_stereo.calib import observability as obs
from mems_stereo.calib.nuisance import Held, add_held
from mems_stereo.calib.problem import Layout, Problem
from mems_stereo.calib.solver import FitState, newton

#: 2·Δlog L of the profile interval (95 %: χ²₁ at 0.05 ≈ 3.84, taken as 2²)
LEVEL = 4.0
#: largest share searched: a profile still open there leaves the share undetermined
MAX_SHARE = 0.95
#: step doublings per side of the interval search
MAX_STEPS = 6
SHARE, DECAY = "pulse_tail_fraction", "pulse_tail_decay"


@dataclass(frozen=True)
class ShareProfile:
    """The tail share's profile likelihood at a fit.

    share : the estimate ŵ; local_std : its σ from the fit's information;
    lower, upper : the ends of the interval at 2·Δlog L = :data:`LEVEL`
    (``lower`` 0 where w = 0 is inside it; ``upper`` :data:`MAX_SHARE` when
    ``closed`` is False); std : the wider side over √LEVEL; move : (P,) SI, the
    fitted parameters' move (the fit's layout, walls too; 1 for the share) per
    unit share to the wide side's end.
    """

    share: float
    local_std: float
    lower: float
    upper: float
    std: float
    move: np.ndarray
    closed: bool


class _Profile:
    """The fit ``prob`` at ``x`` with the share held: 2·Δlog L and the refitted
    parameters (the full layout's vector) at a held share."""

    def __init__(self, prob: Problem, x):
        lay = prob.layout
        self.names = list(lay.names)
        self.i = self.names.index(SHARE)
        rest = [n for n in self.names if n != SHARE]
        self.lay = Layout(rest, lay.T, lay.two_d)
        p = Problem(prob.walls, prob.system, self.lay, prob.sigma, prob.priors)
        p.cells, p.pixel_offsets, p.tail_decay = list(prob.cells), prob.pixel_offsets, \
            prob.tail_decay
        self.prob, self.x = p, np.asarray(x, dtype=np.float64)
        self.keep = np.array([k for k in range(lay.size) if k != self.i])
        self.ll = prob.loglik(self.x)

    def at(self, w: float):
        """(2·Δlog L, full parameter vector) with the share held at ``w``."""
        x, i, names = self.x, self.i, self.names
        xs = x[self.keep].copy()
        rest = self.lay.names
        if DECAY in names and w > 0:  # start on the ridge: the same mean delay w·τ
            mean = x[i] * x[names.index(DECAY)]
            tau = max(mean / w, 0.05 * self.prob.sigma)
            xs[rest.index(DECAY)] = tau
            if "tdc_offset" in rest:
                xs[rest.index("tdc_offset")] += mean - w * tau
        self.prob.pulse_fixed = (float(w), float(x[names.index(DECAY)]) if DECAY in names
                                 else self.prob.tail_decay)
        nr = newton(self.prob, xs, FitState(), max_iter=40)
        full = np.insert(nr.x, i, w)
        return 2.0 * (self.ll - nr.loglik), full


def interval_end(pf, sign: float, step: float, bound: float):
    """The interval's end on one side (``sign`` ±1) of the share ``pf.x[pf.i]``:
    steps of ``step`` doubled until ``pf.at(w)`` (a :class:`_Profile`: 2·Δlog L and
    the refitted vector) reaches :data:`LEVEL`, at most to ``bound``; the crossing
    interpolated in √(2·Δlog L) and refined once.  Returns (end, the refitted
    vector at the outer point or None, closed)."""
    w0 = float(pf.x[pf.i])
    inner, e_in, outer = w0, 0.0, None
    for _ in range(MAX_STEPS):
        w = w0 + sign * step
        if sign * (w - bound) >= 0:
            w = bound
        e, xf = pf.at(w)
        if not e < LEVEL:  # beyond the interval (or outside the model: inf)
            outer = (w, e, xf)
            break
        inner, e_in = w, max(e, 0.0)
        if w == bound:
            return bound, xf, False
        step *= 2.0
    if outer is None:
        return inner, None, False
    for _ in range(2):  # interpolate in √(2·Δlog L) (linear for a quadratic profile),
        w = _crossing(inner, e_in, outer[0], outer[1])  # then once more inside
        if w in (inner, outer[0]):
            break
        e, xf = pf.at(w)
        if e < LEVEL:
            inner, e_in = w, max(e, 0.0)
        else:
            outer = (w, e, xf)
    return _crossing(inner, e_in, outer[0], outer[1]), outer[2], True


def _crossing(w_in: float, e_in: float, w_out: float, e_out: float) -> float:
    """Where √(2·Δlog L) reaches √LEVEL between an inner and an outer point."""
    r_in = math.sqrt(e_in)
    r_out = math.sqrt(e_out) if math.isfinite(e_out) else math.inf
    frac = (math.sqrt(LEVEL) - r_in) / (r_out - r_in) if r_out > r_in else 1.0
    return w_in + (w_out - w_in) * min(max(frac, 0.0), 1.0)


def share_profile(prob: Problem, x, cov) -> ShareProfile | None:
    """The :class:`ShareProfile` of the fit ``prob`` at ``x`` (SI vector of its
    layout) with covariance ``cov`` (P, P) SI; None when the fit does not free the
    share or its local σ is not finite."""
    if SHARE not in prob.layout.names:
        return None
    pf = _Profile(prob, x)
    w0 = float(pf.x[pf.i])
    sc = float(math.sqrt(cov[pf.i, pf.i])) if np.isfinite(cov[pf.i, pf.i]) else math.inf
    if not (math.isfinite(sc) and sc > 0):
        return None
    lo, x_lo, closed_lo = interval_end(pf, -1.0, sc, 0.0)
    hi, x_hi, closed_hi = interval_end(pf, 1.0, sc, MAX_SHARE)
    lo = 0.0 if not closed_lo else lo  # w = 0 inside: the interval reaches the bound
    wide_hi = hi - w0 >= w0 - lo
    end = x_hi if wide_hi else x_lo
    half = max(hi - w0, w0 - lo) / math.sqrt(LEVEL)
    if end is None or end[pf.i] == w0:
        move = np.where(np.arange(pf.x.size) == pf.i, 1.0, 0.0)
    else:
        move = (end - pf.x) / (end[pf.i] - w0)
    return ShareProfile(w0, sc, lo, hi, half, move, closed_hi)


def widen_share(result):
    """``result`` (a full-model :class:`~mems_stereo.calib.result.CalibrationResult`
    with the pulse tail fitted) with the share's profile σ in its covariance along
    the ridge (see the module) where it exceeds the local σ; ``extra["share_profile"]``
    keeps the :class:`ShareProfile`.  ``result`` unchanged otherwise."""
    prob = result.extra.get("problem")
    if prob is None or SHARE not in result.names:
        return result
    C = result.extra.get("covariance_full")
    if C is None:
        C = obs.covariance(result.extra["information"], prob.layout.scales)[0]
    prof = share_profile(prob, result.extra["x"], C)
    if prof is None:
        return result
    result.extra["share_profile"] = prof
    if not prof.std > prof.local_std:
        return result
    spread = math.sqrt(prof.std ** 2 - prof.local_std ** 2)
    state = "" if prof.closed else f" (not closed below {MAX_SHARE:.2f}: the share is not " \
                                    "determined by these walls)"
    what = (f"the pulse tail's share lies on a curved ridge with its decay and tdc_offset: "
            f"its 95 % profile-likelihood interval is {prof.lower * 100:.0f}–"
            f"{prof.upper * 100:.0f} %{state}, σ from its wider side")
    return add_held(result, Held(prof.move, C, prof.share, prof.std), spread, "tail_profile",
                    what, "record the walls with more shots at low pile-up to narrow it")
