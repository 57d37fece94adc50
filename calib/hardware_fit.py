"""The hardware model's terms in the wall calibration: tested, selected, estimated.

After the ideal-model fit (:func:`mems_stereo.calib.fit.fit_walls`):

1. **score tests** (Rao's LM test, with the fit's outer-product information): for each
   candidate block — the mirror's k-th harmonic (cos, sin; k in ``orders``), the
   monitor's rising-edge delay — ``LM = g_bᵀ [I⁻¹]_bb g_b`` at the fitted point, χ²
   with the block's size under the ideal model.  Only blocks with ``p < alpha`` are
   estimated: an ideal-hardware calibration gets no new term (at that rate) and keeps
   today's result;
2. the selected terms are **fitted** with the others, from the ideal fit's solution
   (:func:`refit`), with σ, correlations and the observability verdict of
   :mod:`mems_stereo.calib.observability`;
3. **per-pixel TDC offsets**: :mod:`mems_stereo.calib.pixel_offsets` (each cell's
   expected information, shrunk to the offsets' population).

Names follow :meth:`mems_stereo.model.hardware.System.with_params`; the falling
edge's delay is held at its nominal value (the mean of the two is the phase offset).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from mems_stereo.calib.model import HARDWARE_PARAMS, PULSE_PARAMS, harmonic_orders
from mems_stereo.calib.problem import Layout, Problem
from scipy import stats

#: significance of a score test that admits a term into the fit
ALPHA_SELECT = 1e-3
#: harmonic orders tested by default
DEFAULT_ORDERS = (2, 3, 4, 5)


@dataclass(frozen=True)
class TermTest:
    """A candidate block's score test: ``name`` ("harmonic 3", "edge delays",
    "pixel offsets"), its parameter ``names``, ``lm`` statistic, ``dof``,
    ``p_value``, and ``selected`` (p < alpha)."""

    name: str
    names: tuple
    lm: float
    dof: int
    p_value: float
    selected: bool


def candidate_blocks(orders=DEFAULT_ORDERS) -> dict:
    """Block name → parameter names: each harmonic order, and the edge delay."""
    out = {f"harmonic {k}": tuple(harmonic_orders((k,))) for k in orders}
    out["edge delays"] = ("edge_rising_delay",)
    return out


def extended_problem(prob: Problem, x, extra, tail_decay: float | None = None) -> tuple:
    """The problem ``prob`` with parameters ``extra`` (at their nominal values) added,
    on the same cells (``tail_decay``: s, the decay of a pulse tail whose share only
    is added): (problem, x)."""
    lay = prob.layout
    values, walls = lay.unpack(x)
    names = list(lay.names) + [n for n in extra if n not in lay.names]
    lay2 = Layout(names, lay.T, lay.two_d)
    p2 = Problem(prob.walls, prob.system, lay2, prob.sigma, prob.priors)
    p2.cells = list(prob.cells)
    p2.pixel_offsets = prob.pixel_offsets
    p2.tail_decay = prob.tail_decay if tail_decay is None else float(tail_decay)
    vals = {n: values.get(n, prob.system.get_param(n)) for n in lay2.names}
    return p2, lay2.pack(vals, walls)


def score_tests(prob: Problem, x, blocks: dict, alpha: float = ALPHA_SELECT,
                tail_decay: float | None = None) -> list:
    """One :class:`TermTest` per block, at the fitted ``x`` of ``prob``
    (``tail_decay``: see :func:`extended_problem`)."""
    extra = [n for b in blocks.values() for n in b]
    p2, x2 = extended_problem(prob, x, extra, tail_decay)
    _, g, H = p2.score(x2)
    sc = p2.layout.scales
    gs, Hs = g * sc, H * sc[:, None] * sc[None, :]
    # the fitted parameters where p2's layout put them (it orders the names: a harmonic
    # of a lower order goes before the fitted ones), and the walls'
    base = ([p2.layout.names.index(n) for n in prob.layout.names]
            + list(range(p2.layout.n_sys, p2.layout.size)))
    out = []
    for name, names in blocks.items():
        bi = [p2.layout.names.index(n) for n in names]
        idx = base + bi
        try:
            Hi = np.linalg.pinv(Hs[np.ix_(idx, idx)])
        except np.linalg.LinAlgError:
            continue
        gb = gs[idx]
        lm = float(gb @ Hi @ gb)
        p = float(stats.chi2.sf(lm, len(names)))
        if names == ("pulse_tail_fraction",):  # one-sided: a share w ≥ 0 (a tail delays)
            p = 0.5 * p if float((Hi @ gb)[-1]) > 0 else 1.0
        out.append(TermTest(name, tuple(names), lm, len(names), p, p < alpha))
    return out


def log_p_value(lm: float, dof: int) -> float:
    """ln of the χ² survival function of ``lm`` with ``dof`` degrees of freedom, finite
    where the p-value underflows to 0 (the leading term of the upper incomplete gamma
    function's expansion, Abramowitz & Stegun 6.5.32): forward selection ranks strong
    blocks by it (their p-values are all 0.0)."""
    v = float(stats.chi2.logsf(lm, dof))
    if math.isfinite(v):
        return v
    a, h = 0.5 * dof, 0.5 * lm
    return (a - 1.0) * math.log(h) - h - math.lgamma(a)


#: s, decays at which the pulse tail's share is tested (the decay is not defined at w = 0)
TAIL_DECAYS = (1e-9, 3e-9, 8e-9)


def tail_score_test(prob: Problem, x, alpha: float = ALPHA_SELECT) -> tuple:
    """Score test of a pulse tail (share w at 0) at each decay of :data:`TAIL_DECAYS`;
    Bonferroni over the decays.  Returns (:class:`TermTest` "pulse tail", the decay
    of the most significant test, s); the test is not selected where the system
    already has a pulse shape."""
    best, decay = None, TAIL_DECAYS[0]
    if prob.pulse_fixed is None:
        for d in TAIL_DECAYS:
            t = score_tests(prob, x, {"pulse tail": ("pulse_tail_fraction",)}, alpha, d)
            if t and (best is None or t[0].p_value < best.p_value):
                best, decay = t[0], d
    if best is None:
        return TermTest("pulse tail", ("pulse_tail_fraction",), 0.0, 1, 1.0, False), decay
    p = min(1.0, best.p_value * len(TAIL_DECAYS))
    return TermTest("pulse tail", PULSE_PARAMS, best.lm, 1, p, p < alpha), decay


def hardware_std(system, values: dict, std: dict, cov: np.ndarray, names: list):
    """``system`` with the σ of its fitted harmonics (amplitude, phase; delta method
    from the (cos, sin) covariance), edge delay and pulse tail (share, decay)."""
    sc = system.scanner
    hs = []
    for h in sc.harmonics:
        c, s = f"harmonic{h.order}_cos", f"harmonic{h.order}_sin"
        if c in names and s in names:
            i, k = names.index(c), names.index(s)
            C = cov[np.ix_([i, k], [i, k])]
            a = max(h.amplitude, 1e-300)
            ga = np.array([values[c], values[s]]) / a  # ∂A/∂(c, s)
            gp = np.array([values[s], -values[c]]) / (a * a)  # ∂ψ/∂(c, s), ψ = atan2(−s, c)
            h = replace(h, amplitude_std=math.sqrt(max(float(ga @ C @ ga), 0.0)),
                        phase_std=math.sqrt(max(float(gp @ C @ gp), 0.0)))
        hs.append(h)
    mon = sc.monitor
    if mon is not None and "edge_rising_delay" in names:
        mon = replace(mon, rising_delay_std=float(std["edge_rising_delay"]))
    laser = system.laser
    if laser.pulse_shape is not None and "pulse_tail_fraction" in names:
        laser = replace(laser, pulse_shape=replace(
            laser.pulse_shape, tail_fraction_std=float(std["pulse_tail_fraction"]),
            tail_decay_std=float(std.get("pulse_tail_decay", math.nan))))
    return system.replace(scanner=replace(sc, harmonics=tuple(hs), monitor=mon), laser=laser)


def is_hardware(name: str) -> bool:
    """Whether ``name`` is a hardware-model term of the fit."""
    return name in HARDWARE_PARAMS
