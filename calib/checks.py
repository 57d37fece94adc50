"""Plausibility checks of a converged calibration fit.

:func:`check_walls` — per wall: the fitted beam follows the returns found on
the sensor, the distance and tilt are those of a calibration target, the fit
explains the excess over the background, the flat-wall consistency test
(:func:`mems_stereo.calib.observability.consistency_scores`), a spot not
collapsed onto its bound; and the fitted baseline's length.
:func:`check_distances` — each measured distance against a fit without it.
Both fill a :class:`Checks`: the per-wall ``targets`` of the report, the
``checks`` table, and ``bad`` (reasons) / ``bad_walls`` for a refusal.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from mems_stereo.calib import observability as obs
from mems_stereo.calib.expected_info import consistency_information
from mems_stereo.calib.model import PULSE_PARAMS, plane_normal
from mems_stereo.calib.problem import (
    SPOT_MIN,
    cell_terms,
    distance_model,
    shot_model,
    spot_px,
    spot_share,
)
from mems_stereo.calib.solver import FitSetup, Solution, leave_one_out
from numpy.polynomial.legendre import leggauss
from scipy.special import ndtr, ndtri

#: wall plausibility: incidence of the beam on a wall beyond this is not a calibration target
MAX_TILT = math.radians(60.0)
#: a wall closer than this (m) along the optical axis is a degenerate fit
MIN_DISTANCE = 0.2
#: share of the sensor's analysed cells the fitted signal must explain: at least
MIN_SIGNAL_SHARE = 0.5
#: a measured distance farther than this many σ from the data is named
DISTANCE_PULL = 5.0
#: the fitted track must pass within this many pixels (or 3σ of a point's column,
#: when larger) of this share of the track points
TRACK_GATE = 2.0
MIN_ON_TRACK = 0.6
#: Gauss–Legendre nodes and weights on [0, 1] of :func:`first_photon_mean`
_GL_X, _GL_W = leggauss(64)
_GL_X, _GL_W = 0.5 * (_GL_X + 1.0), 0.5 * _GL_W


def first_photon_mean(m, z0) -> np.ndarray:
    """Expected time of a pixel's first signal photon, in pulse σ from the pulse centre.

    m : (N,) mean signal photons the pixel receives in the shot (Poisson), the
    pulse Gaussian; z0 : (N,) where the gate opens, (0 − τ)/σ.  Given that at
    least one signal photon arrived after z0, the first one's density is
    ``m φ(z) exp(−m (Φ(z) − Φ(z0)))`` on [z0, ∞) (the model the fit's cell
    likelihood uses); its mean is ``∫₀¹ Φ⁻¹(Φ(z0) − ln(1 − W x) / m) dx`` with
    ``W = 1 − exp(−m (1 − Φ(z0)))``, here by 64-point Gauss–Legendre (within
    0.002 σ of a Monte Carlo for m in 0.01 … 50).  Returns (N,) float64, σ
    units: about −0.28 at m = 1, −1.50 at m = 10 (the first of many photons
    comes early), → the truncated normal's mean as m → 0.
    """
    m = np.maximum(np.asarray(m, dtype=np.float64), 1e-12)[..., None]
    u0 = ndtr(np.asarray(z0, dtype=np.float64))[..., None]
    w = -np.expm1(-m * (1.0 - u0))
    u = np.clip(u0 - np.log1p(-w * _GL_X) / m, 1e-300, 1.0 - 1e-16)
    return ndtri(u) @ _GL_W


@dataclass
class Checks:
    """What the checks found: per-wall report entries (``targets``), the checks
    table (name → (value, limit, passed)), the reasons to refuse (``bad``) and
    the walls they name, and the signal-weighted residual sums (pixel², s²,
    weight) with the expected signal count."""

    targets: list = field(default_factory=list)
    checks: dict = field(default_factory=dict)
    bad: list = field(default_factory=list)
    bad_walls: set = field(default_factory=set)
    rms_u: float = 0.0
    rms_t: float = 0.0
    wsum: float = 0.0
    n_sig: float = 0.0


@dataclass(frozen=True, slots=True)
class SignalFit:
    """How much of one wall's returns the fit explains, over its cells.

    spot_px : the fitted spot σ, px (clipped to its bounds); fired : cells that
    fired; background_expected, signal_expected : expected counts of background
    and of signal first photons; excess : fired less the background expected;
    share : ``signal_expected / excess`` (0 without an excess); rms_u (px²),
    rms_t (s²), wsum : the signal-weighted residual sums and their weight;
    mean_t : (s) the signal-weighted sum of the time residuals.  A time
    residual is the first detection's time less the model's expected first
    signal photon (pulse centre + σ · :func:`first_photon_mean`).
    """

    spot_px: float
    fired: int
    background_expected: float
    signal_expected: float
    excess: float
    share: float
    rms_u: float
    rms_t: float
    wsum: float
    mean_t: float


def _axis_distance(lay, j: int, wall: np.ndarray, cov: np.ndarray) -> tuple[float, float]:
    """The wall's distance along the optical axis (m) and its σ from ``cov``."""
    ws = lay.wall_slice(j)
    z_axis = wall[2] / plane_normal(wall[0], wall[1])[2]
    gz = np.zeros(lay.size)
    for i, pn in enumerate(lay.wall_names):
        if pn in ("alpha", "beta", "dist"):
            wp = wall.copy()
            col = {"alpha": 0, "beta": 1, "dist": 2}[pn]
            wp[col] += 1e-7
            gz[ws.start + i] = (distance_model(wp) - z_axis) / 1e-7
    z_std = math.sqrt(max(float(gz @ np.where(np.isfinite(cov), cov, 0.0) @ gz), 0.0))
    return z_axis, z_std


def _signal_fit(c, pred: np.ndarray, ok: np.ndarray, wall: np.ndarray,
                sigma: float) -> SignalFit:
    """Signal the fit explains vs the excess over the background in the cells ``c``;
    ``pred`` (N, 4) and ``ok`` (N,) per cell."""
    fired = np.isfinite(c.t)
    n_fired = int(np.count_nonzero(fired))
    exp_bg = float(np.sum(-np.expm1(-c.lam * c.t_max)))
    mu_k = np.exp(wall[3] + pred[:, 3] - c.log_gref)

    s_px = spot_px(wall[4])
    share = spot_share(c.col, pred[:, 1], s_px)[0]
    m = np.where(ok, mu_k * share, 0.0)
    zz = (c.t_max - pred[:, 0]) / sigma

    p_sig = np.where(ok, -np.expm1(-m * (ndtr(zz) - ndtr(-pred[:, 0] / sigma))), 0.0)
    exp_sig = float(p_sig.sum())
    excess = n_fired - exp_bg
    share_expl = exp_sig / excess if excess > 0 else 0.0
    # signal-weighted residuals
    wsig = np.where(fired, m * np.exp(-0.5 * ((c.t - pred[:, 0]) / sigma) ** 2)
                    / (sigma * math.sqrt(2 * math.pi)), 0.0)
    wsig = np.where(fired, wsig / (wsig + c.lam), 0.0)
    use = fired & (wsig > 0)
    res_t = np.zeros(c.t.size)
    res_t[use] = c.t[use] - pred[use, 0] - sigma * first_photon_mean(
        m[use], -pred[use, 0] / sigma)
    return SignalFit(s_px, n_fired, exp_bg, exp_sig, excess, share_expl,
                     float(np.sum(wsig * (c.col - pred[:, 1]) ** 2)),
                     float(np.sum(wsig * res_t ** 2)), float(np.sum(wsig)),
                     float(np.sum(wsig * res_t)))


def _check_track(chk: Checks, j: int, source: str, target: dict, track, system, values,
                 wall: np.ndarray) -> None:
    """The fitted beam must follow the wall's track points."""
    u_fit = shot_model(system.with_params(**values), values, wall, track.phase)[0][:, 1]
    gate = np.maximum(TRACK_GATE, 3.0 * track.u_err)
    on_track = float(np.mean(np.abs(u_fit - track.u) < gate))
    target["on_track"] = on_track
    chk.checks[f"wall {j} track points followed"] = (on_track, MIN_ON_TRACK,
                                                     on_track >= MIN_ON_TRACK)
    if on_track < MIN_ON_TRACK:
        chk.bad_walls.add(j)
        chk.bad.append(f"wall {j} ({source}): the fitted beam follows only "
                       f"{on_track:.0%} of the returns found on the sensor (need "
                       f"{MIN_ON_TRACK:.0%}): the fit converged to a wrong geometry")


def _judge_wall(chk: Checks, j: int, source: str, target: dict, big_shift: bool,
                warns: list) -> None:
    """Distance, spot, tilt, signal share and flat-wall consistency of one wall."""
    checks, bad = chk.checks, chk.bad
    z_axis, s_px, tilt = target["distance_axis"], target["spot_px"], target["tilt"]
    share_expl, p_cons = target["signal_share"], target["consistency_p"]
    checks[f"wall {j} distance"] = (z_axis, MIN_DISTANCE, z_axis >= MIN_DISTANCE)
    spot_ok = s_px > 1.05 * SPOT_MIN
    checks[f"wall {j} spot σ above its bound"] = (s_px, SPOT_MIN, spot_ok)
    if not spot_ok:  # pixel-share derivatives of a collapsed spot inflate the information
        warns.append(f"wall {j} ({source}): the fitted spot σ {s_px:.2f} px sits at "
                     f"its lower bound ({SPOT_MIN} px)")
    if z_axis < MIN_DISTANCE:
        chk.bad_walls.add(j)
        bad.append(f"wall {j} ({source}) fitted at {z_axis:.3f} m (closer than "
                   f"{MIN_DISTANCE} m): a degenerate geometry")
    checks[f"wall {j} tilt"] = (tilt, MAX_TILT, tilt <= MAX_TILT)
    checks[f"wall {j} signal explained"] = (share_expl, MIN_SIGNAL_SHARE,
                                            share_expl >= MIN_SIGNAL_SHARE)
    checks[f"wall {j} flat-wall consistency p"] = (
        p_cons, obs.P_INCONSISTENT, not (p_cons < obs.P_INCONSISTENT and big_shift))
    if tilt > MAX_TILT:
        chk.bad_walls.add(j)
        bad.append(f"wall {j} ({source}) fitted at {math.degrees(tilt):.0f}° to the "
                   f"optical axis (limit {math.degrees(MAX_TILT):.0f}°)")
    elif share_expl < MIN_SIGNAL_SHARE:
        chk.bad_walls.add(j)
        bad.append(f"wall {j} ({source}): the fit explains {share_expl:.0%} of the "
                   f"returns above the background (need {MIN_SIGNAL_SHARE:.0%})")
    elif p_cons < obs.P_INCONSISTENT and big_shift:
        dt_q, du_q = target["time_shifts"], target["column_shifts"]
        chk.bad_walls.add(j)
        bad.append(f"wall {j} ({source}) is not a flat wall seen by this model: returns "
                   f"shifted by up to {np.max(np.abs(dt_q)) * 1e9:.2f} ns / "
                   f"{np.max(np.abs(du_q)):.2f} px across the sensor "
                   f"({obs.sigma_of_p(p_cons):.0f}σ)")


def _check_baseline(chk: Checks, system, values: dict) -> None:
    """The fitted baseline's length within a factor of two of the nominal one."""
    b_fit = np.array([values.get(n, system.get_param(n))
                      for n in ("baseline_x", "baseline_y", "baseline_z")])
    ratio = float(np.linalg.norm(b_fit) / max(np.linalg.norm(system.baseline), 1e-9))
    chk.checks["baseline length / nominal"] = (ratio, (0.5, 2.0), 0.5 <= ratio <= 2.0)
    if not 0.5 <= ratio <= 2.0:
        chk.bad.append(f"fitted baseline {np.linalg.norm(b_fit) * 1e3:.1f} mm, nominal "
                       f"{np.linalg.norm(system.baseline) * 1e3:.1f} mm: a degenerate geometry")


def check_walls(sol: Solution, cov: np.ndarray, walls, tracks, setup: FitSetup, values: dict,
                warns: list) -> Checks:
    """The checks of each fitted wall and of the baseline (see the module).

    sol : the converged fit; cov : (P, P) SI covariance; walls : the fitted
    :class:`~mems_stereo.calib.problem.WallData`; tracks : each wall's
    :class:`~mems_stereo.calib.track.Track` or None (found by the pose search),
    or None for all; setup : the fit's nominal system, pulse σ and sensor kind;
    values : fitted system values.  A collapsed spot's warning goes to ``warns``.
    """
    prob, x = sol.problem, sol.x
    system, sigma, two_d = setup.system, setup.sigma, setup.two_d
    lay = prob.layout
    _, wall_p = lay.unpack(x)
    chk = Checks()
    for j, w in enumerate(walls):
        wall = wall_p[j]
        n_z = plane_normal(wall[0], wall[1])[2]
        z_axis, z_std = _axis_distance(lay, j, wall, cov)
        c = prob.cells[j]
        pred, ok, jac = prob.predictions(x, j, c.shots, steps=True)
        pos = np.searchsorted(c.shots, c.shot)
        pc = np.where(ok[pos, None], pred[pos], [0, -1e6, -1e6, 0])
        _, d_c = cell_terms(c, pc, wall[3], wall[4], sigma, two_d, prob.pitch_ratio,
                            prob.pulse(values))
        _, S, _ = prob.wall_terms(x, j, grad=True)
        info = consistency_information(c, pc, ok[pos], jac[0][pos], wall, sigma, two_d,
                                       prob.pitch_ratio, system.receiver.width,
                                       prob.pulse(values))
        # the pulse's tail moves no return across the sensor: not a nuisance of the test
        keep = [i for i in range(S.shape[1])
                if not (i < lay.n_sys and lay.names[i] in PULSE_PARAMS)]
        S = S[:, keep]
        info = info[np.ix_(list(range(8)) + [8 + i for i in keep],
                           list(range(8)) + [8 + i for i in keep])]
        test = obs.consistency_scores(d_c[:, :2], S, c.col, width=system.receiver.width,
                                      info=info)
        sig = _signal_fit(c, pred[pos], ok[pos], wall, sigma)
        chk.rms_u += sig.rms_u
        chk.rms_t += sig.rms_t
        chk.wsum += sig.wsum
        chk.n_sig += sig.signal_expected
        tilt = math.acos(min(1.0, abs(n_z)))
        big_shift = obs.big_shift(test.time_shifts, test.column_shifts, test.z, sigma)
        t = {"source": w.source, "distance_axis": z_axis, "distance_axis_std": z_std,
             "mu": float(math.exp(wall[3])), "spot_px": sig.spot_px, "tilt": tilt,
             "consistency_p": test.p_value, "time_shifts": test.time_shifts.tolist(),
             "column_shifts": test.column_shifts.tolist(),
             "signal_expected": sig.signal_expected, "signal_excess": sig.excess,
             "signal_share": sig.share, "cells": int(c.t.size), "fired": sig.fired,
             "background_expected": sig.background_expected,
             "time_residual_mean": sig.mean_t / max(sig.wsum, 1e-12),
             "time_residual_rms": math.sqrt(sig.rms_t / max(sig.wsum, 1e-12)),
             "pixel_residual_rms": math.sqrt(sig.rms_u / max(sig.wsum, 1e-12)),
             "log_gref": float(c.log_gref), "pulse_sigma": float(sigma)}
        chk.targets.append(t)
        if tracks is not None and tracks[j] is not None:  # beam must follow the track
            _check_track(chk, j, w.source, t, tracks[j], system, values, wall)
        _judge_wall(chk, j, w.source, t, big_shift, warns)
    _check_baseline(chk, system, values)
    return chk


def check_distances(sol: Solution, priors, walls, chk: Checks, warns: list) -> None:
    """Each measured distance against the data (linear pull first, then, when one
    is large, a fit without it): the pulls go to ``chk``; a distance off by more
    than ``DISTANCE_PULL`` σ is named in ``warns`` and heads ``chk.bad``.
    priors : [(wall index, kind, distance m, σ m)].  Every measured distance, its
    σ, its kind and the fitted distance of that kind go to the wall's target
    (``distance_measured``, ``distance_measured_std``, ``distance_kind``,
    ``distance_fitted``, m)."""
    prob, x = sol.problem, sol.x
    lay = prob.layout
    _, wall_p = lay.unpack(x)
    targets, checks, bad = chk.targets, chk.checks, chk.bad
    quick = []
    for j, kind, d, sd in priors:  # linear pull first: the refits only when needed
        var_fit = targets[j]["distance_axis_std"] ** 2
        fitted = float(distance_model(wall_p[j], kind))
        quick.append(abs(fitted - d) / math.sqrt(max(sd * sd - var_fit, 0.01 * sd * sd)))
        targets[j].update(distance_measured=float(d), distance_measured_std=float(sd),
                          distance_kind=str(kind), distance_fitted=fitted)
    if priors and max(quick) > 0.5 * DISTANCE_PULL:
        loo = leave_one_out(prob, x, lay)
        pulls = []
        for e in loo:
            sd, f_std = e.measured_std, e.fitted_std
            pull = (e.fitted - e.measured) / math.sqrt(sd * sd + f_std * f_std)
            pulls.append(pull)
            targets[e.wall]["distance_measured"] = e.measured
            targets[e.wall]["distance_pull"] = pull
            checks[f"wall {e.wall} measured distance pull"] = (pull, DISTANCE_PULL,
                                                               abs(pull) <= DISTANCE_PULL)
        if max(abs(p_) for p_ in pulls) > DISTANCE_PULL:
            # the culprit: the distance whose removal leaves the most consistent rest
            i = int(np.argmax([e.loglik if abs(p_) > DISTANCE_PULL else -np.inf
                               for e, p_ in zip(loo, pulls)]))
            e = loo[i]
            j = e.wall
            w_text = (f"the measured distance of wall {j} ({walls[j].source}), "
                      f"{e.measured:.4f} m ± {e.measured_std * 1e3:.1f} mm, contradicts the "
                      f"data by {abs(pulls[i]):.1f}σ (the data and the other distances put "
                      f"it at {e.fitted:.4f} m ± {e.fitted_std * 1e3:.1f} mm)")
            warns.append(w_text)
            bad.insert(0, w_text)
