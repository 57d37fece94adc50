"""Candidate hardware terms a full-model calibration holds at nominal, in its σ.

Forward selection (:mod:`mems_stereo.calib.full_model`) fits a candidate block —
a harmonic of the mirror's trajectory, the monitor's edge-delay difference — only
where its score test is significant at 10⁻³.  A block it leaves at 0 is not known
to be 0: its score says only that the walls do not show it beyond chance
*given the blocks fitted*.  Where a held block is nearly collinear with fitted
parameters, a small true value moves them by many of their σ: on imperfect walls
of the benchmark family a 0.31 % second harmonic left out beside a fitted edge
delay put ``theta0``, ``phase_offset`` and ``edge_rising_delay`` 5.9–6.5 σ off
(``bench_real_hardware.py`` seed 1071: the edge delay's effect is even in the scan
phase, a constant plus 2nd and 4th cosine harmonics), and a 0.17 % third harmonic
put ``theta_mech_max`` and ``baseline_z`` 7.7 σ off (seed 1085: cos 3φ =
4cos³φ − 3cos φ trades with the amplitude over the part of the scan the walls
see).

:func:`add_held_blocks` gives the fitted parameters the covariance of the fit with
the held blocks free as well, each with a Gaussian prior of σ :data:`HARMONIC_STD`
(harmonics) or :data:`~mems_stereo.calib.nuisance.EDGE_DIFFERENCE_STD` (the edge
difference) that bounds a block the walls cannot tell apart from the fitted
ones: the Schur complement ``[(I + P)⁻¹]_xx = I_xx⁻¹ + S Σ_η Sᵀ`` (``I`` the
cells' information with the held blocks added at 0, ``P`` the priors' precision;
Gelman et al., *Bayesian Data Analysis*, 3rd ed., §3.5, a nuisance integrated out
rather than held).  The estimates are unchanged (the held blocks stay at 0); a
block the data determine adds little, a collinear one widens the parameters it
trades with.  The edge difference is left to
:func:`~mems_stereo.calib.nuisance.add_held_edges` where that already holds it.
A calibration that fits no hardware term (ideal hardware) is returned unchanged.
"""

from __future__ import annotations

import numpy as np
from mems_stereo.calib import hardware_fit as hf
from mems_stereo.calib import observability as obs
from mems_stereo.calib.nuisance import EDGE_DIFFERENCE_STD, add_covariance, holds_edges

#: relative σ of a held harmonic's cos and sin terms: the size docs/hardware.md takes
#: as typical (a 0.3 % third harmonic), about the RMS of the benchmark family's draws
#: (amplitudes uniform up to 1 %, each order present with probability ½: 0.29 %)
HARMONIC_STD = 3e-3


def held_names(result, orders=hf.DEFAULT_ORDERS) -> list:
    """The candidate parameters ``result`` holds at nominal that :func:`add_held_blocks`
    integrates out: each harmonic of ``orders`` not fitted, and the edge delay unless
    it is fitted or :func:`~mems_stereo.calib.nuisance.holds_edges` covers it."""
    fitted = set(result.names)
    out = [n for b in hf.candidate_blocks(orders).values() for n in b if n not in fitted]
    prob = result.extra.get("problem")
    no_monitor = prob is None or any(w.shot_time is None for w in prob.walls)
    if holds_edges(result) or no_monitor:  # no monitor record: no edges to delay
        out = [n for n in out if n != "edge_rising_delay"]
    return out


def prior_precision(names) -> np.ndarray:
    """(k,) SI: 1/σ² of the priors of ``names`` (see the module)."""
    return np.array([1.0 / (EDGE_DIFFERENCE_STD if n == "edge_rising_delay"
                            else HARMONIC_STD) ** 2 for n in names])


def held_covariance(prob, x, held: list) -> np.ndarray:
    """(P, P) SI, what integrating out the ``held`` parameters (at nominal, with their
    priors) adds to the covariance of the fit ``prob`` at ``x`` (its layout's order,
    walls too): ``[(I + P)⁻¹]_xx − I_xx⁻¹``, symmetrised, negative eigenvalues
    (rounding) cut to 0."""
    p2, x2 = hf.extended_problem(prob, x, held)
    _, _, H = p2.score(x2)
    lay2 = p2.layout
    hi = [lay2.names.index(n) for n in held]
    P = np.zeros(lay2.size)
    P[hi] = prior_precision(held)
    idx = ([lay2.names.index(n) for n in prob.layout.names]
           + list(range(lay2.n_sys, lay2.size)))
    marg = obs.covariance(H + np.diag(P), lay2.scales)[0][np.ix_(idx, idx)]
    cond = obs.covariance(H[np.ix_(idx, idx)], prob.layout.scales)[0]
    ok = np.isfinite(marg) & np.isfinite(cond)
    D = np.where(ok, marg - cond, 0.0)
    D = 0.5 * (D + D.T)
    sc = prob.layout.scales
    val, vec = np.linalg.eigh(D / sc[:, None] / sc[None, :])
    D = (vec * np.maximum(val, 0.0)) @ vec.T
    return D * sc[:, None] * sc[None, :]


def add_held_blocks(result, orders=hf.DEFAULT_ORDERS):
    """``result`` (a full-model :class:`~mems_stereo.calib.result.CalibrationResult`)
    with the held candidate blocks integrated out of its covariance (see the module;
    ``extra["held_blocks"]`` names them); unchanged when it fits no hardware term or
    holds none."""
    if not any(hf.is_hardware(n) or n.startswith("pulse") for n in result.names):
        return result
    held = held_names(result, orders)
    if not held:
        return result
    prob = result.extra["problem"]
    base = obs.covariance(result.extra["information"], prob.layout.scales)[0]
    D = held_covariance(prob, result.extra["x"], held)
    blocks = sorted({n.split("_")[0] if n.startswith("harmonic") else "edge delay"
                     for n in held})
    what = (f"the hardware terms not selected ({', '.join(blocks)}) are held at 0: σ "
            f"include them (harmonics ±{HARMONIC_STD * 100:.1f} %, edge difference "
            f"±{EDGE_DIFFERENCE_STD * 1e9:.0f} ns where the walls do not bound them)")
    return add_covariance(result, base, D, "held_blocks", {"names": held}, what,
                          "record walls at several distances over the whole scan to "
                          "fit or exclude them")
