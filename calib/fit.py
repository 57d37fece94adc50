"""The calibration fit: start values, the likelihood fit, checks, the outcome.

:func:`fit_walls` runs

1. :func:`mems_stereo.calib.initialisation.initialise` — start values from the
   beam's track on the sensor, a grid over θ0 (not the nominal system);
2. rounds of a damped Newton (BHHH) ascent of the exact first-photon
   likelihood of :mod:`mems_stereo.calib.problem` on the cells of
   :mod:`mems_stereo.calib.association`, the cells re-centred on the beam's image
   between rounds;
3. the covariance from the information matrix, the observability verdict
   and the consistency checks (:mod:`mems_stereo.calib.observability`);

and returns a :class:`~mems_stereo.calib.result.CalibrationResult` or, when any
step fails, a :class:`~mems_stereo.calib.result.CalibrationFailure` saying why
(it tests false and carries no system).
"""

from __future__ import annotations

import math
import time

import numpy as np
from mems_stereo.calib import observability as obs
from mems_stereo.calib.association import cells_near_track
from mems_stereo.calib.initialisation import _fit_line, _triangulate, find_wall, initialise
from mems_stereo.calib.model import DEFAULT_FREE, SYSTEM_PARAMS, plane_normal
from mems_stereo.calib.problem import (
    SPOT_MIN,
    Layout,
    Problem,
    cell_terms,
    distance_model,
    shot_model,
)
from mems_stereo.calib.result import CalibrationFailure, CalibrationResult, format_report

from mems_stereo.errors import NotObservableError
from mems_stereo.model.system import System
from mems_stereo.physics.pulse import pulse_sigma

#: wall plausibility: incidence of the beam on a wall beyond this is not a calibration target
MAX_TILT = math.radians(60.0)
#: a wall closer than this (m) along the optical axis is a degenerate fit
MIN_DISTANCE = 0.2
#: share of the sensor's analysed cells the fitted signal must explain: at least
MIN_SIGNAL_SHARE = 0.5
#: a measured distance farther than this many σ from the data is named
DISTANCE_PULL = 5.0
N_ROUNDS = 2
#: the fitted track must pass within this many pixels (or 3σ of a point's column,
#: when larger) of this share of the track points
TRACK_GATE = 2.0
MIN_ON_TRACK = 0.6
MAX_ITER = 100


class FitState:
    """The solver's state (for diagnostics)."""

    def __init__(self):
        self.iterations = 0
        self.converged = False
        self.message = ""


def _build_cells(prob: Problem, x, radius: int):
    lay = prob.layout
    _, walls = lay.unpack(x)
    window = prob.system.tdc.n_bins * prob.system.tdc.bin_width
    for j, w in enumerate(prob.walls):
        pred, ok, _ = prob.predictions(x, j)
        W = prob.system.receiver.width
        on = ok & (pred[:, 1] > -0.5) & (pred[:, 1] < W - 0.5)
        if not on.any():
            raise NotObservableError(f"{w.source}: the fitted beam never meets the sensor")
        t_max = min(float(np.max(pred[on, 0])) + 6.0 * prob.sigma, window)
        lgref = float(np.median(pred[on, 3]))
        old = prob.cells[j]
        if old is not None:  # keep μ_k: log μ_j is relative to the reference
            x[lay.wall_slice(j).start + lay.wall_names.index("logmu")] += lgref - old.log_gref
        prob.cells[j] = cells_near_track(w, pred, ok, radius, t_max, lgref, lay.two_d)
    return x


def _newton(prob: Problem, x, state: FitState, max_iter: int = MAX_ITER, tol: float = 1e-3):
    """Damped Newton ascent with the outer-product information (BHHH/Levenberg)."""
    sc = prob.layout.scales
    lam = 1e-3
    ll, g, H = prob.score(x)
    for _ in range(max_iter):
        state.iterations += 1
        gs = g * sc
        Hs = H * sc[:, None] * sc[None, :]
        dH = np.maximum(np.diag(Hs), 1e-12)
        improved = False
        for _ in range(12):
            try:
                step = np.linalg.solve(Hs + lam * np.diag(dH), gs)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            xn = x + step * sc
            lln = prob.loglik(xn)
            if np.isfinite(lln) and lln >= ll - 1e-9:
                improved = True
                break
            lam *= 10
        if not improved:
            state.message = "no step increases the likelihood"
            return x, ll, g, H
        expected = float(gs @ step)
        x = xn
        lam = max(lam / 5, 1e-6)
        ll, g, H = prob.score(x)
        if expected < tol:
            state.converged = True
            return x, ll, g, H
    state.message = f"no convergence in {max_iter} iterations"
    return x, ll, g, H


def _leave_one_out(prob: Problem, x, lay: Layout):
    """[(j, kind, d, σ_d, fitted, σ_fitted, log-likelihood)] for each measured distance:
    the wall's distance as fitted without that measurement (from the full fit's
    solution), and the log-likelihood of the data and the other distances then."""
    priors = list(prob.priors)
    out = []
    try:
        for i, (j, kind, d, sd) in enumerate(priors):
            prob.priors = priors[:i] + priors[i + 1:]
            st = FitState()
            xi, ll_i, _, H = _newton(prob, x.copy(), st, max_iter=30)
            cov, _, _ = obs.covariance(H, lay.scales)
            _, wp = lay.unpack(xi)
            f = distance_model(wp[j], kind)
            ws = lay.wall_slice(j)
            g = np.zeros(lay.size)
            for q, pn in enumerate(lay.wall_names):
                if pn in ("alpha", "beta", "dist"):
                    w2 = wp[j].copy()
                    w2[{"alpha": 0, "beta": 1, "dist": 2}[pn]] += 1e-7
                    g[ws.start + q] = (distance_model(w2, kind) - f) / 1e-7
            c = np.where(np.isfinite(cov), cov, 1e6)
            out.append((j, kind, d, sd, f, math.sqrt(max(float(g @ c @ g), 0.0)), ll_i))
    finally:
        prob.priors = priors
    return out


def _solve(walls, system, names, two_d, sigma, priors, values, wall_p, state, progress):
    """Likelihood fit rounds from start values: (problem, x, information)."""
    lay = Layout(names, len(walls), two_d)
    prob = Problem(walls, system, lay, sigma, priors)
    x = lay.pack({n: values[n] for n in names}, wall_p)
    H = None
    for rnd in range(N_ROUNDS):
        x = _build_cells(prob, x, radius=3 if rnd == 0 else 2)
        state.converged = False
        x, ll, g, H = _newton(prob, x, state)
        if progress:
            v, _ = lay.unpack(x)
            progress(f"round {rnd + 1}: log-likelihood {ll:.1f}, "
                     + ", ".join(f"{n} {obs.fmt(n, v[n])}" for n in names))
        if not state.converged:  # no point re-centring a fit that went nowhere
            break
    return prob, x, H


#: pinned at their nominal values while a degenerate first fit guides the search for
#: missed walls (the scale-like directions that a single wall cannot fix)
PINNED_FOR_GUIDE = ("tdc_offset", "baseline_x", "baseline_y", "baseline_z")


def _guide_values(prob, x, H, state, walls, system, names, two_d, sigma, priors, values0,
                  wall_p0, limits, progress):
    """System values (all of ``names``) and walls to search missed walls with.

    The converged fit of the walls found when it determines every parameter;
    otherwise (one wall, walls at one distance: the fit is degenerate or does not
    converge) a fit from the start values with the TDC offset and the baseline
    pinned at their nominal values (a mechanical tolerance away from the truth:
    a few pixels and ns, which the pose search over distances absorbs).  Returns
    (values dict, walls (T, 5)) or None.
    """
    lay = prob.layout
    if state.converged:
        cov, _, _ = obs.covariance(H, lay.scales)
        d = np.diag(cov)
        std = {n: float(math.sqrt(d[i])) if np.isfinite(d[i]) and d[i] >= 0 else math.inf
               for i, n in enumerate(lay.names)}
        if not obs.weak_parameters(std, limits, [])[0]:
            return lay.unpack(x)
    names_r = [n for n in names if n not in PINNED_FOR_GUIDE]
    if names_r == names:
        return lay.unpack(x) if state.converged else None
    if progress:
        progress("first fit degenerate: the offset and the baseline pinned at their "
                 "nominal values to search the missed walls")
    st = FitState()
    try:  # start values again, with the pinned parameters held
        v0, wp0, used, _, _ = initialise(walls, system, names_r, sigma, priors)
        if len(used) < len(walls):
            return None
        prob_r, x_r, _ = _solve(walls, system, names_r, two_d, sigma, priors,
                                {n: v0[n] for n in names_r}, wp0, st, progress)
    except NotObservableError:
        return None
    if not st.converged:
        return None
    v_r, wp_r = prob_r.layout.unpack(x_r)
    vals = {n: system.get_param(n) for n in names}
    vals.update(v_r)
    return vals, wp_r


def fit_walls(walls, system: System, *, free=None, fix=(), priors=(), jitter: float = 50e-12,
              max_std: dict | None = None, on_unobservable: str = "raise",
              initial=None, progress=None, sources=None, _tracks=None, _repair=True):
    """Calibrate from reduced wall recordings.

    Parameters
    ----------
    walls : list of :class:`~mems_stereo.calib.problem.WallData`, one per wall.
    system : nominal system (fixed parts; reported as "nominal").
    free, fix : names of :data:`~mems_stereo.calib.model.SYSTEM_PARAMS`.
    priors : [(wall index, "axis" | "normal", distance m, σ m)] measured distances.
    jitter : SPAD + TDC timing jitter σ, s (added to the pulse's).
    max_std : σ limits (SI) above which a parameter counts as not observable.
    on_unobservable : "raise" — a failure naming the parameter; "warn" — the
        result carries it with its σ and a warning.
    initial : optional (values dict, walls (T, 5)) to start from (skips the
        global search; tests and the benchmark's Fisher check use it).
    _tracks, _repair : internal (the re-fit of walls whose fitted plane missed
        their own track).

    Returns
    -------
    CalibrationResult, or CalibrationFailure (falsy, no system).
    """
    t_start = time.perf_counter()
    warns: list = []
    free = list(DEFAULT_FREE if free is None else free)
    for n in list(free) + list(fix):
        if n not in SYSTEM_PARAMS:
            raise ValueError(f"unknown calibration parameter {n!r}; known: {list(SYSTEM_PARAMS)}")
    if on_unobservable not in ("raise", "warn"):
        raise ValueError(f"on_unobservable: expected 'raise' or 'warn', found {on_unobservable!r}")
    limits = dict(obs.DEFAULT_MAX_STD, **(max_std or {}))
    walls = list(walls)
    if not walls:
        return CalibrationFailure("no recordings given: nothing to calibrate", "input")
    two_d = system.receiver.height > 1
    names = [n for n in SYSTEM_PARAMS if n in free and n not in fix]
    unobservable = []
    if not two_d and "baseline_y" in names:
        names.remove("baseline_y")  # a line sensor's data do not depend on it
        unobservable.append("baseline_y")
    sigma = pulse_sigma(system.laser.pulse_fwhm, jitter)

    def fail(reason, kind="estimate", **details):
        return CalibrationFailure(reason, kind, details, warns,
                                  time.perf_counter() - t_start)

    # 1. start values
    walls_in, priors_in = walls, list(priors)
    used = list(range(len(walls)))
    tracks = None
    if initial is None:
        try:
            values, wall_p, used, skipped, tracks = initialise(walls, system, names, sigma,
                                                               priors, progress)
        except NotObservableError as e:
            return fail(str(e), "input")
        for msg in skipped:
            warns.append(f"left out: {msg}")
        priors = [(used.index(j), kind, d, sd) for j, kind, d, sd in priors if j in used]
        walls = [walls[j] for j in used]
        tracks = list(tracks)
    else:
        values, wall_p = dict(initial[0]), np.array(initial[1], dtype=np.float64)
        tracks = None if _tracks is None else list(_tracks)
    all_walls, all_priors = walls_in, list(priors_in)
    state = FitState()
    try:
        prob, x, H = _solve(walls, system, names, two_d, sigma, priors, values, wall_p, state,
                            progress)
        left = [j for j in range(len(all_walls)) if j not in used]
        guide = None
        if left:  # walls the track search missed: search them with a trusted system
            guide = _guide_values(prob, x, H, state, walls, system, names, two_d, sigma,
                                  priors, values, wall_p, limits, progress)
        if guide is not None:
            values, wall_p = guide
            found, new_p = [], {}
            for j in left:
                f = find_wall(all_walls[j], system.with_params(**values), values, sigma)
                if f is not None:
                    found.append(j)
                    new_p[j] = np.array([[f[0], 0.0, f[1], math.log(f[2]), math.log(0.3)]])
            state2, sol2 = FitState(), None
            while found and not state2.converged:
                used2 = used + found
                walls2 = [all_walls[j] for j in used2]
                priors2 = [(used2.index(j), kind, d, sd) for j, kind, d, sd in all_priors
                           if j in used2]
                wp2 = np.vstack([wall_p[:len(used)]] + [new_p[j] for j in found])
                if progress:
                    progress(f"found {len(found)} more wall(s) with the fitted system")
                state2 = FitState()
                try:
                    sol2 = _solve(walls2, system, names, two_d, sigma, priors2, values,
                                  wp2, state2, progress)
                except NotObservableError as e:  # a found wall lost: without it
                    state2.converged = False
                    lost = [j for j in found if all_walls[j].source in str(e)]
                    found = [j for j in found if j not in lost] if lost else []
                    continue
                if not state2.converged:
                    break
            if found and state2.converged:
                tracks.extend([None] * len(found))
                prob, x, H = sol2
                used, walls, priors, state = used2, walls2, priors2, state2
                warns[:] = [m for m in warns
                            if not any(all_walls[j].source in m for j in found)]
    except NotObservableError as e:
        return fail(str(e))
    lay = prob.layout
    values, wall_p = lay.unpack(x)
    partial = {"values": values, "walls": wall_p.tolist(), "iterations": state.iterations}
    if not state.converged:
        return fail(f"the fit did not converge ({state.message})", **partial)

    # 3. covariance and observability
    cov, sv, _ = obs.covariance(H, lay.scales)
    std_all = np.sqrt(np.maximum(np.diag(cov), 0.0))
    std_all[~np.isfinite(np.diag(cov))] = np.inf
    labels = lay.labels
    corr_full, trade = obs.tradeoffs(cov, labels, lay.n_sys)
    std = {n: float(std_all[i]) for i, n in enumerate(names)}
    weak, msg = obs.weak_parameters(std, limits, trade)
    if weak:
        text = (f"not observable from these data: {msg}; record walls at more distances and "
                "tilts, give measured distances (--target-distances-file) or fix the parameter")
        if on_unobservable == "raise":
            return fail(text, "input", std=std, **partial)
        warns.append(text)
        unobservable += weak

    # 4. checks: poses, signal share, consistency, measured distances
    checks = {}
    targets = []
    rms_u, rms_t, wsum, n_sig = 0.0, 0.0, 0.0, 0.0
    bad = []
    bad_walls = set()
    for j, w in enumerate(walls):
        ws = lay.wall_slice(j)
        wall = wall_p[j]
        n_z = plane_normal(wall[0], wall[1])[2]
        z_axis = wall[2] / n_z
        gz = np.zeros(lay.size)
        for i, pn in enumerate(lay.wall_names):
            if pn in ("alpha", "beta", "dist"):
                wp = wall.copy()
                col = {"alpha": 0, "beta": 1, "dist": 2}[pn]
                wp[col] += 1e-7
                gz[ws.start + i] = (distance_model(wp) - z_axis) / 1e-7
        z_std = math.sqrt(max(float(gz @ np.where(np.isfinite(cov), cov, 0.0) @ gz), 0.0))
        c = prob.cells[j]
        pred, ok, jac = prob.predictions(x, j, c.shots, steps=True)
        pos = np.searchsorted(c.shots, c.shot)
        ll_c, d_c = cell_terms(c, np.where(ok[pos, None], pred[pos], [0, -1e6, -1e6, 0]),
                               wall[3], wall[4], sigma, two_d, prob.pitch_ratio)
        _, S, idx = prob.wall_terms(x, j, grad=True)
        p_cons, dt_q, du_q = obs.consistency_scores(d_c[:, :2], S, c.col,
                                                    width=system.receiver.width)
        # signal the fit explains vs the excess over the background in the cells
        fired = np.isfinite(c.t)
        n_fired = int(np.count_nonzero(fired))
        exp_bg = float(np.sum(-np.expm1(-c.lam * c.t_max)))
        mu_k = np.exp(wall[3] + pred[pos, 3] - c.log_gref)
        from mems_stereo.calib.problem import spot_share

        s_px = min(max(math.exp(wall[4]), 0.12), 6.0)
        share = spot_share(c.col, pred[pos, 1], s_px)[0]
        m = np.where(ok[pos], mu_k * share, 0.0)
        zz = (c.t_max - pred[pos, 0]) / sigma
        from scipy.special import ndtr

        p_sig = np.where(ok[pos], -np.expm1(-m * (ndtr(zz) - ndtr(-pred[pos, 0] / sigma))), 0.0)
        exp_sig = float(p_sig.sum())
        excess = n_fired - exp_bg
        share_expl = exp_sig / excess if excess > 0 else 0.0
        # signal-weighted residuals
        wsig = np.where(fired, m * np.exp(-0.5 * ((c.t - pred[pos, 0]) / sigma) ** 2)
                        / (sigma * math.sqrt(2 * math.pi)), 0.0)
        wsig = np.where(fired, wsig / (wsig + c.lam), 0.0)
        rms_u += float(np.sum(wsig * (c.col - pred[pos, 1]) ** 2))
        rms_t += float(np.nansum(wsig * (c.t - pred[pos, 0]) ** 2))
        wsum += float(np.sum(wsig))
        n_sig += exp_sig
        tilt = math.acos(min(1.0, abs(n_z)))
        big_shift = (np.max(np.abs(dt_q)) > obs.SHIFT_TIME) or (np.max(np.abs(du_q))
                                                                 > obs.SHIFT_PIXEL)
        t = {"source": w.source, "distance_axis": z_axis, "distance_axis_std": z_std,
             "mu": float(math.exp(wall[3])), "spot_px": s_px, "tilt": tilt,
             "consistency_p": p_cons, "time_shifts": dt_q.tolist(),
             "column_shifts": du_q.tolist(), "signal_expected": exp_sig,
             "signal_excess": excess, "signal_share": share_expl, "cells": int(c.t.size),
             "fired": n_fired, "background_expected": exp_bg}
        targets.append(t)
        if tracks is not None and tracks[j] is not None:  # beam must follow the track
            tr = tracks[j]
            u_fit = shot_model(system.with_params(**values), values, wall, tr.phase)[0][:, 1]
            gate = np.maximum(TRACK_GATE, 3.0 * tr.u_err)
            on_track = float(np.mean(np.abs(u_fit - tr.u) < gate))
            t["on_track"] = on_track
            checks[f"wall {j} track points followed"] = (on_track, MIN_ON_TRACK,
                                                         on_track >= MIN_ON_TRACK)
            if on_track < MIN_ON_TRACK:
                bad_walls.add(j)
                bad.append(f"wall {j} ({w.source}): the fitted beam follows only "
                           f"{on_track:.0%} of the returns found on the sensor (need "
                           f"{MIN_ON_TRACK:.0%}): the fit converged to a wrong geometry")
        checks[f"wall {j} distance"] = (z_axis, MIN_DISTANCE, z_axis >= MIN_DISTANCE)
        spot_ok = s_px > 1.05 * SPOT_MIN
        checks[f"wall {j} spot σ above its bound"] = (s_px, SPOT_MIN, spot_ok)
        if not spot_ok:  # pixel-share derivatives of a collapsed spot inflate the information
            warns.append(f"wall {j} ({w.source}): the fitted spot σ {s_px:.2f} px sits at "
                         f"its lower bound ({SPOT_MIN} px)")
        if z_axis < MIN_DISTANCE:
            bad_walls.add(j)
            bad.append(f"wall {j} ({w.source}) fitted at {z_axis:.3f} m (closer than "
                       f"{MIN_DISTANCE} m): a degenerate geometry")
        checks[f"wall {j} tilt"] = (tilt, MAX_TILT, tilt <= MAX_TILT)
        checks[f"wall {j} signal explained"] = (share_expl, MIN_SIGNAL_SHARE,
                                                share_expl >= MIN_SIGNAL_SHARE)
        checks[f"wall {j} flat-wall consistency p"] = (
            p_cons, obs.P_INCONSISTENT, not (p_cons < obs.P_INCONSISTENT and big_shift))
        if tilt > MAX_TILT:
            bad_walls.add(j)
            bad.append(f"wall {j} ({w.source}) fitted at {math.degrees(tilt):.0f}° to the "
                       f"optical axis (limit {math.degrees(MAX_TILT):.0f}°)")
        elif share_expl < MIN_SIGNAL_SHARE:
            bad_walls.add(j)
            bad.append(f"wall {j} ({w.source}): the fit explains {share_expl:.0%} of the "
                       f"returns above the background (need {MIN_SIGNAL_SHARE:.0%})")
        elif p_cons < obs.P_INCONSISTENT and big_shift:
            bad_walls.add(j)
            bad.append(f"wall {j} ({w.source}) is not a flat wall seen by this model: returns "
                       f"shifted by up to {np.max(np.abs(dt_q)) * 1e9:.2f} ns / "
                       f"{np.max(np.abs(du_q)):.2f} px across the sensor "
                       f"({obs.sigma_of_p(p_cons):.0f}σ)")
    b_fit = np.array([values.get(n, system.get_param(n))
                      for n in ("baseline_x", "baseline_y", "baseline_z")])
    ratio = float(np.linalg.norm(b_fit) / max(np.linalg.norm(system.baseline), 1e-9))
    checks["baseline length / nominal"] = (ratio, (0.5, 2.0), 0.5 <= ratio <= 2.0)
    if not 0.5 <= ratio <= 2.0:
        bad.append(f"fitted baseline {np.linalg.norm(b_fit) * 1e3:.1f} mm, nominal "
                   f"{np.linalg.norm(system.baseline) * 1e3:.1f} mm: a degenerate geometry")
    # measured distances against the data: each against a fit without it
    quick = []
    for j, kind, d, sd in priors:  # linear pull first: the refits only when needed
        var_fit = targets[j]["distance_axis_std"] ** 2
        quick.append(abs(distance_model(wall_p[j], kind) - d)
                     / math.sqrt(max(sd * sd - var_fit, 0.01 * sd * sd)))
    if priors and max(quick) > 0.5 * DISTANCE_PULL:
        loo = _leave_one_out(prob, x, lay)
        pulls = []
        for j, _kind, d, sd, fitted, f_std, _ in loo:
            pull = (fitted - d) / math.sqrt(sd * sd + f_std * f_std)
            pulls.append(pull)
            targets[j]["distance_measured"] = d
            targets[j]["distance_pull"] = pull
            checks[f"wall {j} measured distance pull"] = (pull, DISTANCE_PULL,
                                                          abs(pull) <= DISTANCE_PULL)
        if max(abs(p_) for p_ in pulls) > DISTANCE_PULL:
            # the culprit: the distance whose removal leaves the most consistent rest
            i = int(np.argmax([e[6] if abs(p_) > DISTANCE_PULL else -np.inf
                               for e, p_ in zip(loo, pulls)]))
            j, kind, d, sd, fitted, f_std, _ = loo[i]
            w_text = (f"the measured distance of wall {j} ({walls[j].source}), {d:.4f} m "
                      f"± {sd * 1e3:.1f} mm, contradicts the data by {abs(pulls[i]):.1f}σ "
                      f"(the data and the other distances put it at {fitted:.4f} m ± "
                      f"{f_std * 1e3:.1f} mm)")
            warns.append(w_text)
            bad.insert(0, w_text)
    details = dict(partial, std=std, checks=checks, targets=targets)
    off_track = [j for j in bad_walls if tracks is not None and tracks[j] is not None
                 and targets[j].get("on_track", 1.0) < MIN_ON_TRACK]
    # a spot collapsed onto its bound: a weak wall's spot size is poorly determined, but
    # the collapse can also be a degenerate optimum that inflates the pixel information
    # (an overconfident σ): the fit again from a typical spot, kept when it passes
    collapsed = [j for j in range(len(walls)) if targets[j]["spot_px"] <= 1.05 * SPOT_MIN]
    if (off_track or collapsed) and _repair:
        # the system is held by the other walls: each such wall's plane again from its
        # own track (triangulated with the fitted system), then one more fit
        wp = wall_p.copy()
        sys_fit = system.with_params(**values)
        for j in off_track:
            f = find_wall(walls[j], sys_fit, values, sigma)
            if f is not None:  # the pose search over the whole recording
                wp[j] = [f[0], 0.0, f[1], math.log(f[2]), math.log(0.3)]
            else:
                P = _triangulate(system, values, tracks[j].phase, tracks[j].u)
                wp[j, 0], wp[j, 2] = _fit_line(P)
        for j in collapsed:  # the spot again from the other walls' (or a typical) size
            others = [wall_p[i, 4] for i in range(len(walls)) if i not in collapsed]
            wp[j, 4] = float(np.median(others)) if others else math.log(0.3)
        if progress:
            progress(f"{len(off_track)} wall(s) off their track, {len(collapsed)} with a "
                     "collapsed spot: poses searched again with the fitted system")
        again = fit_walls(walls, system, free=free, fix=fix, priors=priors, jitter=jitter,
                          max_std=max_std, on_unobservable=on_unobservable,
                          initial=(values, wp), progress=progress, _tracks=tracks,
                          _repair=False)
        if again:
            again.warnings[:0] = [m for m in warns if "sits at its lower bound" not in m]
            return again
    guided = [j for j in bad_walls if tracks is not None and tracks[j] is None]
    if bad and guided and len(bad) == len(bad_walls) and set(guided) == bad_walls:
        # only walls found by the pose search with the fitted system fail: without them
        keep = [j for j in range(len(walls)) if j not in bad_walls]
        pri = [(keep.index(j), kind, d, sd) for j, kind, d, sd in priors if j in keep]
        again = fit_walls([walls[j] for j in keep], system, free=free, fix=fix, priors=pri,
                          jitter=jitter, max_std=max_std, on_unobservable=on_unobservable,
                          initial=(values, wall_p[keep]), progress=progress)
        why = {j: "; ".join(b.split(": ", 1)[-1] for b in bad if f"({walls[j].source})" in b)
               for j in guided}
        again.warnings[:0] = warns + [f"left out: {walls[j].source}: found with the fitted "
                                      f"system but not consistent with it ({why[j]})"
                                      for j in guided]
        return again
    if bad:
        return fail("implausible result: " + "; ".join(bad), **details)

    out_values = {n: float(values[n]) for n in names}
    n = lay.n_sys
    planes = wall_p[:, :3].copy()
    planes_std = np.zeros((lay.T, 3))
    for j in range(lay.T):
        ws = lay.wall_slice(j)
        for i, pn in enumerate(lay.wall_names):
            if pn in ("alpha", "beta", "dist"):
                planes_std[j, {"alpha": 0, "beta": 1, "dist": 2}[pn]] = std_all[ws.start + i]
    result = CalibrationResult(
        system=system.with_params(**out_values), names=names, values=out_values, std=std,
        initial={nm: system.get_param(nm) for nm in names}, covariance=cov[:n, :n],
        correlation=corr_full[:n, :n],
        rms={"pixel": math.sqrt(rms_u / max(wsum, 1e-12)),
             "time": math.sqrt(rms_t / max(wsum, 1e-12))},
        n_detections=int(round(n_sig)), fixed=[p for p in SYSTEM_PARAMS if p not in names],
        unobservable=unobservable, tradeoffs=trade, planes=planes, planes_std=planes_std,
        targets=targets, checks=checks, warnings=warns, iterations=state.iterations,
        elapsed=time.perf_counter() - t_start,
        extra={"labels": labels, "correlation_full": corr_full, "singular_values": sv.tolist(),
               "x": x, "layout": lay, "information": H,
               "axis_distance": [t["distance_axis"] for t in targets],
               "axis_distance_std": [t["distance_axis_std"] for t in targets]})
    result.system = result.system.replace(calibration=result.calibration_dict())
    result.report = format_report(result)
    return result


def fisher_std(walls, system: System, values: dict, wall_params, priors=(),
               jitter: float = 50e-12, names=None) -> dict:
    """σ of the free system parameters from the Fisher information at given
    parameters (e.g. the true system and walls): the outer product of the cell
    scores there, no fit.  Returns dict name → σ (SI, inf where not determined)."""
    two_d = system.receiver.height > 1
    names = [n for n in (DEFAULT_FREE if names is None else names)
             if not (n == "baseline_y" and not two_d)]
    lay = Layout(names, len(walls), two_d)
    prob = Problem(walls, system, lay, pulse_sigma(system.laser.pulse_fwhm, jitter), priors)
    x = lay.pack({n: values[n] for n in names}, np.asarray(wall_params, dtype=np.float64))
    x = _build_cells(prob, x, radius=2)
    _, _, H = prob.score(x)
    cov, _, _ = obs.covariance(H, lay.scales)
    d = np.diag(cov)
    return {n: (float(math.sqrt(max(d[i], 0.0))) if np.isfinite(d[i]) else math.inf)
            for i, n in enumerate(names)}
