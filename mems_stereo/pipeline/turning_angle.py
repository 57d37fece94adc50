"""The scan angle of a peak whose footprint the scan's turning point cuts.

A pixel's stereo is taken at the angle θ_c at which the spot is centred on it: the
detections' mean angle less its expected bias
(:func:`~mems_stereo.pipeline.first_photon_correction.mean_angle_bias`), the bias being
``em − tc`` with ``em = Σ N_s p_s θ_s / Σ N_s p_s`` the expected mean firing angle
(N_s the valid shots at step s, ``p_s = 1 − exp(−μ0 f_s)``, f_s the spot's share of
the pixel) and tc the centroid of the firing profile.  That subtraction assumes the
mean angle follows θ_c one to one, as it does where the sweep crosses the whole
footprint.  Where the scan turns inside the footprint (``Peaks.turning``) it does not:
the shots stop at the turning angle, so a footprint that lies further out moves the
mean angle much less than itself (a third as much at the paper's wall columns), and
the subtraction leaves most of the footprint's offset in the stereo (the earlier
model called it a systematic half pixel and let the time of flight carry the point).

Here the footprint's position is solved for instead.  The firing profile (the spot
share ``f_full`` about the peak's centre range, :func:`band_steps`) is shifted by δ
steps, ``f(s − δ)``, and the expected mean firing angle ``em(δ)`` over the frame's own
shots is matched to the observed mean angle: ``em(δ*) = θ̄``; the angle is the shifted
profile's centroid ``tc(δ*)``, and the bias removed ``θ̄ − tc(δ*)``.  Every error of
the mean angle (its scatter, the background's, the bias model's allowance) reaches
that angle divided by the slope ``s = dem/dδ`` at δ*: the stereo covariance is scaled
by ``1/s²``.  The mean angle's own spread is the firings' binomial variance given the
shots, ``Σ N p (1 − p)(s − em)² / (Σ N p)²`` at δ* (the shots' angles are known; which
of them fire is the randomness), not the footprint-wide spread of a full crossing: the
shots bunch at the turning angle.

Where the slope is below :data:`TURNING_MIN_SLOPE`, no shift matches, or the solved
angle lies beyond the angles the shots reached (a pixel lit by the spot's tail alone,
whose ray the beam's centre never crosses: the solution then rests on the tail's shape
alone) the angle is not solved, and the stereo keeps the mean angle less its expected
bias with a systematic σ of
:data:`~mems_stereo.pipeline.peak_estimates.TURNING_PIXEL_SIGMA` pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mems_stereo.pipeline.first_photon_correction import band_steps

#: smallest slope dem/dδ for which the turning peak's angle is solved (below: the
#: footprint hardly moves the mean angle; the stereo keeps the systematic pixel σ)
TURNING_MIN_SLOPE = 0.2
#: shifts δ tried, in steps: a grid of this spacing
SHIFT_STEP = 0.25


@dataclass(frozen=True, slots=True)
class TurningAngles:
    """The solved angles of Q peaks (:func:`turning_angles`).

    bias : (Q,) float64 rad, the mean angle less the solved angle ``θ̄ − tc(δ*)``
        (0 where not solved).
    slope : (Q,) float64, ``dem/dδ`` at the solution (1 where not solved).
    var_em : (Q,) float64 steps², the variance of the mean firing angle given the
        frame's shots, ``Σ N p (1 − p)(s − em)² / (Σ N p)²`` at the solution (binomial
        firings; NaN where not solved).
    solved : (Q,) bool, the peaks whose angle was solved (turning peaks whose slope
        is at least :data:`TURNING_MIN_SLOPE`, their solved angle among the scanned
        steps).
    """

    bias: np.ndarray
    slope: np.ndarray
    var_em: np.ndarray
    solved: np.ndarray


def turning_angles(acc, mu, theta_bar) -> TurningAngles:
    """The solved angle of each turning peak of the accumulator ``acc`` (a
    :class:`~mems_stereo.pipeline.peak_accumulator.PeakAccumulator` after both
    sub-passes, its first-photon correction applied: ``mu`` (Q,) the posterior
    signal photons per shot μ0, NaN where not corrected) from its mean angle
    ``theta_bar`` (Q,) rad (see the module)."""
    Q = acc.Q
    out = TurningAngles(np.zeros(Q), np.ones(Q), np.full(Q, np.nan), np.zeros(Q, bool))
    turning = np.asarray(getattr(acc, "turning", np.zeros(Q, bool)), bool)
    mu = np.asarray(mu, np.float64)
    ok = (turning & np.isfinite(mu) & (mu > 0) & np.isfinite(theta_bar)
          & (acc.band[1] >= acc.band[0]))
    q = np.flatnonzero(ok)
    if not q.size:
        return out
    t0, dt = acc.step_grid
    scanned = np.flatnonzero(acc.shots_per_step)
    em_obs = (np.asarray(theta_bar, np.float64)[q] - t0) / dt
    reach = 0.5 * (acc.band[1][q] - acc.band[0][q]) + 8.0
    for i in range(q.size):  # each peak alone (its own band width: the same bits in blocks)
        b = band_steps(acc, q[i:i + 1], full=True)
        sol = solve_shift(b.steps[0], b.shots[0], b.spot_full[0], mu[q[i]], em_obs[i],
                          float(reach[i]))
        if (sol is not None and sol[1] >= TURNING_MIN_SLOPE
                and scanned[0] <= sol[0] <= scanned[-1]):
            out.bias[q[i]] = (em_obs[i] - sol[0]) * dt
            out.slope[q[i]] = sol[1]
            out.var_em[q[i]] = sol[2]
            out.solved[q[i]] = True
    return out


def solve_shift(steps, shots, f_full, mu: float, em_obs: float, reach: float):
    """``(tc, slope, var_em)``: the centroid (steps) of the firing profile shifted so
    that the expected mean firing angle over ``shots`` is ``em_obs``, ``dem/dδ`` there
    and the mean firing angle's binomial variance (steps²) there; None where no shift
    within ±``reach`` steps matches.

    ``steps`` (B,) consecutive int steps, ``shots`` (B,) the valid shots counted at each
    (0: none, or outside the band), ``f_full`` (B,) the spot's share of the pixel at
    each (the profile, whatever the shots), ``mu`` the signal photons per shot with the
    spot centred.  The profile shifted by δ is ``f(s − δ)`` (linear between steps, 0
    beyond); ``em(δ) = Σ N p s / Σ N p``, ``p = 1 − exp(−μ f(s − δ))``; the match is the
    crossing of ``em(δ) − em_obs`` nearest δ = 0 (linear between grid shifts)."""
    s = np.asarray(steps, np.float64)
    n = np.asarray(shots, np.float64)
    delta = np.arange(-np.ceil(reach / SHIFT_STEP), np.ceil(reach / SHIFT_STEP) + 1) \
        * SHIFT_STEP
    f = np.interp((s[None, :] - delta[:, None]).ravel(), s, np.asarray(f_full, np.float64),
                  left=0.0, right=0.0).reshape(delta.size, s.size)
    p = -np.expm1(-mu * f)
    w = n[None, :] * p
    with np.errstate(invalid="ignore", divide="ignore"):
        em = (w @ s) / w.sum(axis=1)
        tc = (p @ s) / p.sum(axis=1)
    g = em - em_obs
    cross = np.flatnonzero(np.isfinite(g[:-1]) & np.isfinite(g[1:]) & np.isfinite(tc[:-1])
                           & np.isfinite(tc[1:]) & (g[:-1] * g[1:] <= 0) & (g[:-1] != g[1:]))
    if not cross.size:
        return None
    j = cross[np.argmin(np.abs(delta[cross] + 0.5 * SHIFT_STEP))]
    a = g[j] / (g[j] - g[j + 1])
    # dem/dδ over ±1 step about the crossing (a step's shift moves the linear
    # interpolation's kinks with the profile: a smooth difference)
    k = int(round(1.0 / SHIFT_STEP))
    lo, hi = max(j - k + 1, 0), min(j + k, delta.size - 1)
    slope = (em[hi] - em[lo]) / (delta[hi] - delta[lo])
    # the firings' binomial variance of the mean angle, at the solution
    f_sol = np.interp(s - (delta[j] + a * SHIFT_STEP), s, np.asarray(f_full, np.float64),
                      left=0.0, right=0.0)
    p_sol = -np.expm1(-mu * f_sol)
    w_sol = n * p_sol
    var = float(np.sum(w_sol * (1.0 - p_sol) * (s - em_obs) ** 2) / np.sum(w_sol) ** 2)
    return float(tc[j] + a * (tc[j + 1] - tc[j])), float(slope), var
