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

:func:`add_held_blocks` gives the fitted parameters the mean square error of
holding the blocks at 0: with the held terms' true values ``η`` the fitted
parameters are off by ``S·η`` beside the fit's own noise (``S = −I_xx⁻¹ I_xη``, the
move of the conditional fit per unit of ``η``; ``I`` the cells' information with the
held terms added at 0), so their covariance is ``I_xx⁻¹ + S E[η ηᵀ | data] Sᵀ``
(:mod:`~mems_stereo.calib.nuisance`; Gelman et al., *Bayesian Data Analysis*, 3rd
ed., §3.5).  The second moment is that of the posterior of ``η`` under the prior
the hardware has: each harmonic term (cos or sin) present with probability
:data:`PRESENT_PROB` (then Gaussian of σ :data:`HARMONIC_STD`/√:data:`PRESENT_PROB`,
so that the prior's RMS per term is :data:`HARMONIC_STD`) or absent (exactly 0), on
its own (:func:`held_groups`: a harmonic's phase may put one of its terms near 0,
so a small sin term bounds nothing of the cos term), the edge difference always
present (σ :data:`~mems_stereo.calib.nuisance.EDGE_DIFFERENCE_STD`); the data enter
through the held terms' efficient score ``u`` and conditional information ``J =
I_ηη − I_ηx I_xx⁻¹ I_xη`` (the linearised likelihood ``exp(uᵀη − ½ ηᵀJη)`` given
the fitted parameters at their optimum), and the posterior is exact over the 2ᴳ
subsets of present terms (:func:`held_moment`; a spike-and-slab prior: Mitchell &
Beauchamp, *JASA* 83, 1988; George & McCulloch, *JASA* 88, 1993).  A term the data
determine adds what they say: little when they show nothing (absent with
posterior probability near 1), its estimate's square and σ when they show it (a
present term the 10⁻³ selection missed, the bias of holding it at 0); a collinear
one, which the data cannot see, adds its prior's ``HARMONIC_STD²`` and widens the
parameters it trades with.  The estimates are unchanged (the held blocks
stay at 0).  The edge difference is left to
:func:`~mems_stereo.calib.nuisance.add_held_edges` where that already holds it.
A calibration that fits no hardware term (ideal hardware) is returned unchanged.
"""

from __future__ import annotations

import math

import numpy as np
from mems_stereo.calib import hardware_fit as hf
from mems_stereo.calib import observability as obs
from mems_stereo.calib.nuisance import EDGE_DIFFERENCE_STD, add_covariance, holds_edges

#: relative RMS of a held harmonic's cos and sin terms over hardware: the size
#: docs/hardware.md takes as typical (a 0.3 % third harmonic), about the RMS of the
#: benchmark family's draws (amplitudes uniform up to 1 %, each order present with
#: probability ½: 0.29 %)
HARMONIC_STD = 3e-3
#: prior probability that a harmonic term is present (the family's orders: ½)
PRESENT_PROB = 0.5


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


def prior_std(names) -> np.ndarray:
    """(k,) SI: the prior σ of each of ``names`` when present (see the module): a
    harmonic term's ``HARMONIC_STD / √PRESENT_PROB``, the edge difference's
    ``EDGE_DIFFERENCE_STD``."""
    return np.array([EDGE_DIFFERENCE_STD if n == "edge_rising_delay"
                     else HARMONIC_STD / math.sqrt(PRESENT_PROB) for n in names])


def held_groups(names) -> list:
    """Index lists into ``names``: one per harmonic term, each present or absent on its
    own (a harmonic's phase may put either of its cos and sin terms near 0, so what the
    walls say of one bounds nothing of the other), and last the edge difference's
    (always present) if held."""
    edge = [i for i, n in enumerate(names) if n == "edge_rising_delay"]
    return [[i] for i, n in enumerate(names) if n != "edge_rising_delay"] + (
        [edge] if edge else [])


def held_moment(J, u, std, groups, always: int = 0,
                present: float = PRESENT_PROB) -> np.ndarray:
    """(k, k) E[η ηᵀ | data] of held terms ``η`` (see the module).

    J : (k, k) the held terms' conditional information; u : (k,) their efficient
    score at η = 0 (the log-likelihood of η is ``uᵀη − ½ ηᵀJη`` + const); std : (k,)
    each term's prior σ when present; groups : index lists, each present (probability
    ``present``, its terms independent Gaussians of σ ``std``) or absent (0), the last
    ``always`` of them always present.  Exact over the 2ᴳ subsets of present groups:
    subset A has posterior precision ``Q = J_AA + diag(std_A⁻²)``, mean ``m = Q⁻¹u_A``
    and weight ∝ ``present^|A|·(1 − present)^(G − |A|)·exp(½ mᵀu_A)·det(Q diag(std_A²))^(−½)``
    (its marginal likelihood over that of η = 0); the moment is the weighted sum of
    ``Q⁻¹ + m mᵀ``.  Units: those of ``1/std`` for J, ``std`` squared for the result.
    """
    J, u, std = np.asarray(J, float), np.asarray(u, float), np.asarray(std, float)
    k, G = u.size, len(groups)
    Jt, ut = J * std[:, None] * std[None, :], u * std  # in units of each prior σ
    val, vec = np.linalg.eigh(0.5 * (Jt + Jt.T))
    Jt = (vec * np.maximum(val, 0.0)) @ vec.T  # an information: rounding cut to ≥ 0
    logw, moments = [], []
    for mask in range(1 << (G - always)):
        on = [g for b, g in enumerate(groups[:G - always]) if mask >> b & 1]
        a = np.array([i for g in on + groups[G - always:] for i in g], int)
        n_on = len(on)
        lw = n_on * math.log(present) + (G - always - n_on) * math.log1p(-present)
        M = np.zeros((k, k))
        if a.size:
            Q = Jt[np.ix_(a, a)] + np.eye(a.size)
            L = np.linalg.cholesky(0.5 * (Q + Q.T))
            Qi = np.linalg.inv(L).T @ np.linalg.inv(L)
            m = Qi @ ut[a]
            lw += 0.5 * float(m @ ut[a]) - float(np.sum(np.log(np.diag(L))))
            M[np.ix_(a, a)] = Qi + np.outer(m, m)
        logw.append(lw)
        moments.append(M)
    w = np.exp(np.array(logw) - max(logw))
    Mt = np.tensordot(w / w.sum(), np.array(moments), axes=1)
    return Mt * std[:, None] * std[None, :]


def held_covariance(prob, x, held: list) -> np.ndarray:
    """(P, P) SI, what holding the ``held`` parameters at nominal adds to the covariance
    of the fit ``prob`` at ``x`` (its layout's order, walls too): ``S E[η ηᵀ | data] Sᵀ``
    (see the module; :func:`held_moment` over :func:`held_groups`), symmetrised,
    negative eigenvalues (rounding) cut to 0."""
    p2, x2 = hf.extended_problem(prob, x, held)
    _, g, H = p2.score(x2)
    lay2 = p2.layout
    hi = [lay2.names.index(n) for n in held]
    idx = ([lay2.names.index(n) for n in prob.layout.names]
           + list(range(lay2.n_sys, lay2.size)))
    C = obs.covariance(H[np.ix_(idx, idx)], prob.layout.scales)[0]
    C = np.where(np.isfinite(C), C, 0.0)  # a direction the data cannot see: no move
    S = -(C @ H[np.ix_(idx, hi)])
    J = H[np.ix_(hi, hi)] + H[np.ix_(hi, idx)] @ S
    u = g[hi] + S.T @ g[idx]
    groups = held_groups(held)
    E = held_moment(J, u, prior_std(held), groups, always=int("edge_rising_delay" in held))
    D = S @ E @ S.T
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
            f"include them (harmonic terms present with probability {PRESENT_PROB:g} and "
            f"±{HARMONIC_STD * 100:.1f} % RMS, edge difference ±{EDGE_DIFFERENCE_STD * 1e9:.0f}"
            " ns, where the walls do not bound them)")
    return add_covariance(result, base, D, "held_blocks", {"names": held}, what,
                          "record walls at several distances over the whole scan to "
                          "fit or exclude them")
