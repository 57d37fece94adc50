"""The calibration: start values, the likelihood fit, checks, the outcome.

:func:`fit_walls` runs, each step in its own module:

1. start values — :func:`mems_stereo.calib.initialisation.initialise`: the
   beam's track on the sensor (per phase bin, or for a weak wall a pose search
   over the whole recording), a grid over θ0 (not the nominal system);
2. the likelihood fit — :func:`mems_stereo.calib.solver.solve`: rounds of a
   damped Newton (BHHH) ascent of the exact first-photon likelihood of
   :mod:`mems_stereo.calib.problem` on the cells of
   :mod:`mems_stereo.calib.association`; a wall the fit loses is left out;
3. missed walls — :mod:`mems_stereo.calib.missed`: walls without a start
   searched with the system the others fix, then all fitted together;
4. observability — :mod:`mems_stereo.calib.observability`: the covariance, a
   parameter the data do not determine named (refusal or warning);
5. plausibility — :mod:`mems_stereo.calib.checks`: poses, signal share, the
   flat-wall consistency test, measured distances; a wall off its track or
   with a collapsed spot gets one more fit, walls found only by the guided
   search are dropped when they alone fail;

and returns a :class:`~mems_stereo.calib.result.CalibrationResult` or, when any
step fails, a :class:`~mems_stereo.calib.result.CalibrationFailure` saying why
(it tests false and carries no system).
"""

from __future__ import annotations

import math
import time

import numpy as np
from mems_stereo.calib import observability as obs
from mems_stereo.calib.checks import MIN_ON_TRACK, check_distances, check_walls
from mems_stereo.calib.initialisation import _fit_line, _triangulate, find_wall, initialise
from mems_stereo.calib.missed import add_missed_walls, guide_values
from mems_stereo.calib.model import DEFAULT_FREE, SYSTEM_PARAMS
from mems_stereo.calib.problem import SPOT_MIN, Layout, Problem
from mems_stereo.calib.result import CalibrationFailure, CalibrationResult, format_report
from mems_stereo.calib.solver import FitState, build_cells, solve

from mems_stereo.errors import NotObservableError
from mems_stereo.model.system import System
from mems_stereo.physics.pulse import pulse_sigma


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
        (prob, x, H), used, walls, priors, wall_p, tracks = _solve_without_lost(
            walls, system, names, two_d, sigma, priors, values, wall_p, state, progress, used,
            tracks, warns)
        left = [j for j in range(len(all_walls)) if j not in used]
        guide = None
        if left:  # walls the track search missed: search them with a trusted system
            guide = guide_values(prob, x, H, state, walls, system, names, two_d, sigma,
                                 priors, values, wall_p, limits, progress)
        if guide is not None:
            values, wall_p = guide
            more = add_missed_walls(all_walls, all_priors, used, left, values, wall_p, system,
                                    names, two_d, sigma, progress)
            if more is not None:
                found, used, walls, priors, state, (prob, x, H) = more
                tracks.extend([None] * len(found))
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
    corr_full, trade = obs.tradeoffs(cov, lay.labels, lay.n_sys)
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
    chk = check_walls(prob, x, cov, walls, tracks, system, values, sigma, two_d, warns)
    check_distances(prob, x, priors, walls, chk, warns)
    checks, targets, bad, bad_walls = chk.checks, chk.targets, chk.bad, chk.bad_walls
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
        wp = _repair_start(walls, wall_p, values, system, tracks, sigma, off_track, collapsed)
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
    if (bad and guided and len(bad) == len(bad_walls) and set(guided) == bad_walls
            and len(guided) < len(walls)):
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

    return _result(system, names, values, std, std_all, cov, sv, corr_full, trade, lay, x, H,
                   wall_p, chk, unobservable, warns, state, t_start)


def _solve_without_lost(walls, system, names, two_d, sigma, priors, values, wall_p, state,
                        progress, used, tracks, warns):
    """:func:`~mems_stereo.calib.solver.solve`; a wall whose fitted beam leaves the
    sensor is left out (a warning in ``warns``) and the rest fitted again.  Returns
    ((prob, x, H), used, walls, priors, wall_p, tracks) of the walls kept; raises
    :class:`NotObservableError` when no wall is left."""
    while True:
        try:
            sol = solve(walls, system, names, two_d, sigma, priors, values, wall_p, state,
                        progress)
            return sol, used, walls, priors, wall_p, tracks
        except NotObservableError as e:  # a wall the fit lost: on without it
            lost = [i for i, w in enumerate(walls) if str(e).startswith(f"{w.source}:")]
            if not lost or len(lost) == len(walls):
                raise
            warns.append(f"left out: {e} (lost by the fit)")
            keep = [i for i in range(len(walls)) if i not in lost]
            priors = [(keep.index(j), kind, d, sd) for j, kind, d, sd in priors if j in keep]
            used = [used[i] for i in keep]
            walls = [walls[i] for i in keep]
            wall_p = wall_p[keep]
            tracks = None if tracks is None else [tracks[i] for i in keep]
            state.__init__()


def _repair_start(walls, wall_p, values, system, tracks, sigma, off_track, collapsed):
    """Start planes (T, 5) for one more fit: each wall off its track searched again
    with the fitted system (else its track triangulated), each collapsed spot set
    to the other walls' median (or a typical) size."""
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
    return wp


def _result(system, names, values, std, std_all, cov, sv, corr_full, trade, lay, x, H, wall_p,
            chk, unobservable, warns, state, t_start) -> CalibrationResult:
    """The :class:`CalibrationResult` of a fit that passed every check."""
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
        rms={"pixel": math.sqrt(chk.rms_u / max(chk.wsum, 1e-12)),
             "time": math.sqrt(chk.rms_t / max(chk.wsum, 1e-12))},
        n_detections=int(round(chk.n_sig)), fixed=[p for p in SYSTEM_PARAMS if p not in names],
        unobservable=unobservable, tradeoffs=trade, planes=planes, planes_std=planes_std,
        targets=chk.targets, checks=chk.checks, warnings=warns, iterations=state.iterations,
        elapsed=time.perf_counter() - t_start,
        extra={"labels": lay.labels, "correlation_full": corr_full, "singular_values": sv.tolist(),
               "x": x, "layout": lay, "information": H,
               "axis_distance": [t["distance_axis"] for t in chk.targets],
               "axis_distance_std": [t["distance_axis_std"] for t in chk.targets]})
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
    x = build_cells(prob, x, radius=2)
    _, _, H = prob.score(x)
    cov, _, _ = obs.covariance(H, lay.scales)
    d = np.diag(cov)
    return {n: (float(math.sqrt(max(d[i], 0.0))) if np.isfinite(d[i]) else math.inf)
            for i, n in enumerate(names)}
