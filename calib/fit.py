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
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from mems_stereo.calib import observability as obs
from mems_stereo.calib.checks import MIN_ON_TRACK, Checks, check_distances, check_walls
from mems_stereo.calib.initialisation import FOUND_SPOT, fit_line, initialise, triangulate
from mems_stereo.calib.missed import add_missed_walls, guide_values
from mems_stereo.calib.model import DEFAULT_FREE, HARDWARE_PARAMS, PULSE_PARAMS, SYSTEM_PARAMS
from mems_stereo.calib.problem import SPOT_MIN, Layout, Problem, WallData
from mems_stereo.calib.result import CalibrationFailure, CalibrationResult, format_report
from mems_stereo.calib.solver import (
    FitSetup,
    FitState,
    Solution,
    StartValues,
    build_cells,
    solve,
)
from mems_stereo.calib.track import Track, find_wall

from mems_stereo.errors import NotObservableError
from mems_stereo.model.system import System
from mems_stereo.physics.pulse import pulse_sigma

#: spot σ, px, a collapsed spot starts again from when no other wall's is known
TYPICAL_SPOT = 0.3


@dataclass(frozen=True, slots=True)
class FitOptions:
    """The caller's choices of :func:`fit_walls`, kept for its re-fits.

    free, fix : names of :data:`~mems_stereo.calib.model.SYSTEM_PARAMS`; jitter :
    s, SPAD + TDC timing σ; max_std : σ limits (SI) or None; on_unobservable :
    "raise" | "warn"; progress : optional callable(str).
    """

    free: list[str]
    fix: tuple[str, ...]
    jitter: float
    max_std: dict | None
    on_unobservable: str
    progress: Callable[[str], None] | None = None


@dataclass(frozen=True, slots=True)
class WallSet:
    """The walls in a fit: ``walls`` their :class:`~mems_stereo.calib.problem.WallData`,
    ``priors`` [(index among them, kind, distance m, σ m)], ``used`` their
    indices among the walls given, ``tracks`` per wall its
    :class:`~mems_stereo.calib.track.Track` or None (None for all: no tracks)."""

    walls: list[WallData]
    priors: list[tuple[int, str, float, float]]
    used: list[int]
    tracks: list[Track | None] | None


@dataclass(frozen=True, slots=True)
class WallFit:
    """The likelihood fit of ``walls``: its ``solution`` and the solver's ``state``
    (converged or not, iterations)."""

    walls: WallSet
    solution: Solution
    state: FitState


@dataclass(frozen=True, slots=True)
class Uncertainty:
    """What the information of a fit says (SI units, P parameters, n system ones).

    cov : (P, P) covariance; singular : (P,) relative singular values of the
    information; std_all : (P,) σ (inf where not determined); correlation : (P, P);
    tradeoffs : [(a, b, correlation)] beyond ``CORRELATION_REPORT``; std : dict
    system parameter → σ.
    """

    cov: np.ndarray
    singular: np.ndarray
    std_all: np.ndarray
    correlation: np.ndarray
    tradeoffs: list[tuple[str, str, float]]
    std: dict[str, float]


def fit_walls(walls, system: System, *, free=None, fix=(), priors=(), jitter: float = 50e-12,
              max_std: dict | None = None, on_unobservable: str = "raise",
              initial=None, progress=None):
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
    initial : optional (values dict, walls (T, 5)) or
        :class:`~mems_stereo.calib.solver.StartValues` to start from (skips the
        global search; tests and the benchmark's Fisher check use it).

    Returns
    -------
    CalibrationResult, or CalibrationFailure (falsy, no system).
    """
    free = list(DEFAULT_FREE if free is None else free)
    for n in list(free) + list(fix):
        if n not in SYSTEM_PARAMS + HARDWARE_PARAMS + PULSE_PARAMS:
            raise ValueError(f"unknown calibration parameter {n!r}; known: {list(SYSTEM_PARAMS)}"
                             " and the hardware model's harmonic{k}_cos/_sin, edge_rising_delay,"
                             " pulse_tail_fraction, pulse_tail_decay")
    if on_unobservable not in ("raise", "warn"):
        raise ValueError(f"on_unobservable: expected 'raise' or 'warn', found {on_unobservable!r}")
    if initial is not None and not isinstance(initial, StartValues):
        initial = StartValues(initial[0], initial[1])
    opts = FitOptions(free, fix, jitter, max_std, on_unobservable, progress)
    return _fit(walls, system, priors, opts, initial)


def _setup(system: System, opts: FitOptions) -> tuple[FitSetup, list]:
    """The fit's setup and the parameters unobservable by the sensor's kind."""
    two_d = system.receiver.height > 1
    names = [n for n in SYSTEM_PARAMS + HARDWARE_PARAMS + PULSE_PARAMS
             if n in opts.free and n not in opts.fix]
    unobservable = []
    if not two_d and "baseline_y" in names:
        names.remove("baseline_y")  # a line sensor's data do not depend on it
        unobservable.append("baseline_y")
    sigma = pulse_sigma(system.laser.pulse_fwhm, opts.jitter)
    return FitSetup(system, names, two_d, sigma), unobservable


def _fit(walls, system: System, priors, opts: FitOptions, initial: StartValues | None,
         tracks=None, repair: bool = True):
    """:func:`fit_walls` after its arguments are checked; ``tracks`` (with
    ``initial``): the walls' tracks, ``repair``: whether a wall off its track or
    with a collapsed spot gets one more fit."""
    t_start = time.perf_counter()
    warns: list = []
    limits = dict(obs.DEFAULT_MAX_STD, **(opts.max_std or {}))
    walls = list(walls)
    if not walls:
        return CalibrationFailure("no recordings given: nothing to calibrate", "input")
    setup, unobservable = _setup(system, opts)

    def fail(reason, kind="estimate", **details):
        return CalibrationFailure(reason, kind, details, warns,
                                  time.perf_counter() - t_start)

    try:  # 1. start values
        ws, start = _start(walls, setup, priors, initial, tracks, opts.progress, warns)
    except NotObservableError as e:
        return fail(str(e), "input")
    try:  # 2. the fit, with the walls the start missed
        fitted = _fit_all(setup, walls, list(priors), ws, start, limits, opts.progress, warns)
    except NotObservableError as e:
        return fail(str(e))
    ws, sol, state = fitted.walls, fitted.solution, fitted.state
    lay = sol.problem.layout
    values, wall_p = lay.unpack(sol.x)
    partial = {"values": values, "walls": wall_p.tolist(), "iterations": state.iterations,
               "sources": [w.source for w in ws.walls]}
    if not state.converged:
        return fail(f"the fit did not converge ({state.message})", **partial)

    # 3. covariance and observability
    unc = _uncertainty(sol, setup.names)
    weak, msg = obs.weak_parameters(unc.std, limits, unc.tradeoffs)
    if weak:
        text = (f"not observable from these data: {msg}; record walls at more distances and "
                "tilts, give measured distances (--target-distances-file) or fix the parameter")
        if opts.on_unobservable == "raise":
            return fail(text, "input", std=unc.std, **partial)
        warns.append(text)
        unobservable += weak

    # 4. checks: poses, signal share, consistency, measured distances
    chk = check_walls(sol, unc.cov, ws.walls, ws.tracks, setup, values, warns)
    check_distances(sol, ws.priors, ws.walls, chk, warns)
    fit = StartValues(values, wall_p)
    again = _fit_again(ws, setup, opts, fit, chk, warns, repair)
    if again is not None:
        return again
    if chk.bad:
        return fail("implausible result: " + "; ".join(chk.bad),
                    **dict(partial, std=unc.std, checks=chk.checks, targets=chk.targets))
    return _result(setup, fit, unc, sol, chk, unobservable, warns, state.iterations, t_start)


def _start(walls, setup: FitSetup, priors, initial: StartValues | None, tracks, progress,
           warns: list) -> tuple[WallSet, StartValues]:
    """The walls to fit and where the fit starts: the global search of
    :func:`initialise` (walls it leaves out named in ``warns``), or ``initial``."""
    if initial is not None:
        return (WallSet(walls, list(priors), list(range(len(walls))),
                        None if tracks is None else list(tracks)),
                StartValues(dict(initial.values), np.array(initial.walls, dtype=np.float64)))
    guess = initialise(walls, setup.system, setup.names, setup.sigma, priors, progress)
    for msg in guess.skipped:
        warns.append(f"left out: {msg}")
    used = guess.used
    priors = [(used.index(j), kind, d, sd) for j, kind, d, sd in priors if j in used]
    return (WallSet([walls[j] for j in used], priors, used, list(guess.tracks)),
            StartValues(guess.values, guess.walls))


def _fit_all(setup: FitSetup, all_walls, all_priors, ws: WallSet, start: StartValues,
             limits: dict, progress, warns: list) -> WallFit:
    """The likelihood fit of the walls ``ws`` (a wall it loses left out), then of
    those and the walls the start missed, when the first fit finds them."""
    fitted = _solve_without_lost(setup, ws, start, progress, warns)
    ws = fitted.walls
    left = [j for j in range(len(all_walls)) if j not in ws.used]
    guide = None
    if left:  # walls the track search missed: search them with a trusted system
        guide = guide_values(fitted.solution, fitted.state, setup, ws.walls, ws.priors, limits,
                             progress)
    if guide is None:
        return fitted
    more = add_missed_walls(setup, all_walls, all_priors, ws.used, left, guide, progress)
    if more is None:
        return fitted
    warns[:] = [m for m in warns if not any(all_walls[j].source in m for j in more.found)]
    tracks = None if ws.tracks is None else ws.tracks + [None] * len(more.found)
    return WallFit(WallSet(more.walls, more.priors, more.used, tracks), more.solution,
                   more.state)


def _solve_without_lost(setup: FitSetup, ws: WallSet, start: StartValues, progress,
                        warns: list) -> WallFit:
    """:func:`~mems_stereo.calib.solver.solve`; a wall whose fitted beam leaves the
    sensor is left out (a warning in ``warns``) and the rest fitted again.  Raises
    :class:`NotObservableError` when no wall is left."""
    walls, priors, used, tracks = ws.walls, ws.priors, ws.used, ws.tracks
    wall_p = start.walls
    state = FitState()
    while True:
        try:
            sol = solve(setup, walls, priors, start.values, wall_p, state, progress)
            return WallFit(WallSet(walls, priors, used, tracks), sol, state)
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
            state = FitState()


def _uncertainty(sol: Solution, names: list) -> Uncertainty:
    """Covariance, σ and trade-offs from the fit's information."""
    lay = sol.problem.layout
    cov, sv, _ = obs.covariance(sol.info, lay.scales)
    std_all = np.sqrt(np.maximum(np.diag(cov), 0.0))
    std_all[~np.isfinite(np.diag(cov))] = np.inf
    corr_full, trade = obs.tradeoffs(cov, lay.labels, lay.n_sys)
    std = {n: float(std_all[i]) for i, n in enumerate(names)}
    return Uncertainty(cov, sv, std_all, corr_full, trade, std)


def _fit_again(ws: WallSet, setup: FitSetup, opts: FitOptions, fit: StartValues, chk: Checks,
               warns: list, repair: bool):
    """One more fit when the checks ask for it, else None: the walls off their
    track or with a collapsed spot started again (when ``repair``), or the walls
    found only by the guided search left out when they alone fail."""
    walls, tracks, targets = ws.walls, ws.tracks, chk.targets
    bad, bad_walls = chk.bad, chk.bad_walls
    off_track = [j for j in bad_walls if tracks is not None and tracks[j] is not None
                 and targets[j].get("on_track", 1.0) < MIN_ON_TRACK]
    # a spot collapsed onto its bound: a weak wall's spot size is poorly determined, but
    # the collapse can also be a degenerate optimum that inflates the pixel information
    # (an overconfident σ): the fit again from a typical spot, kept when it passes
    collapsed = [j for j in range(len(walls)) if targets[j]["spot_px"] <= 1.05 * SPOT_MIN]
    if (off_track or collapsed) and repair:
        # the system is held by the other walls: each such wall's plane again from its
        # own track (triangulated with the fitted system), then one more fit
        wp = _repair_start(walls, fit, setup, tracks, off_track, collapsed)
        if opts.progress:
            opts.progress(f"{len(off_track)} wall(s) off their track, {len(collapsed)} with a "
                          "collapsed spot: poses searched again with the fitted system")
        again = _fit(walls, setup.system, ws.priors, opts, StartValues(fit.values, wp),
                     tracks=tracks, repair=False)
        if again:
            again.warnings[:0] = [m for m in warns if "sits at its lower bound" not in m]
            return again
    guided = [j for j in bad_walls if tracks is not None and tracks[j] is None]
    if (bad and guided and len(bad) == len(bad_walls) and set(guided) == bad_walls
            and len(guided) < len(walls)):
        # only walls found by the pose search with the fitted system fail: without them
        keep = [j for j in range(len(walls)) if j not in bad_walls]
        pri = [(keep.index(j), kind, d, sd) for j, kind, d, sd in ws.priors if j in keep]
        again = _fit([walls[j] for j in keep], setup.system, pri, opts,
                     StartValues(fit.values, fit.walls[keep]))
        why = {j: "; ".join(b.split(": ", 1)[-1] for b in bad if f"({walls[j].source})" in b)
               for j in guided}
        again.warnings[:0] = warns + [f"left out: {walls[j].source}: found with the fitted "
                                      f"system but not consistent with it ({why[j]})"
                                      for j in guided]
        return again
    return None


def _repair_start(walls, fit: StartValues, setup: FitSetup, tracks, off_track: list,
                  collapsed: list) -> np.ndarray:
    """Start walls (T, 5) for one more fit from the fit ``fit``: each wall off its
    track searched again with the fitted system (else its track triangulated),
    each collapsed spot set to the other walls' median (or a typical) size."""
    wall_p, values, system = fit.walls, fit.values, setup.system
    wp = wall_p.copy()
    sys_fit = system.with_params(**values)
    for j in off_track:
        f = find_wall(walls[j], sys_fit, values, setup.sigma)
        if f is not None:  # the pose search over the whole recording
            wp[j] = [f.alpha, 0.0, f.dist, math.log(f.mu), math.log(FOUND_SPOT)]
        else:
            P = triangulate(system, values, tracks[j].phase, tracks[j].u)
            wp[j, 0], wp[j, 2] = fit_line(P)
    for j in collapsed:  # the spot again from the other walls' (or a typical) size
        others = [wall_p[i, 4] for i in range(len(walls)) if i not in collapsed]
        wp[j, 4] = float(np.median(others)) if others else math.log(TYPICAL_SPOT)
    return wp


def _result(setup: FitSetup, fit: StartValues, unc: Uncertainty, sol: Solution, chk: Checks,
            unobservable: list, warns: list, iterations: int,
            t_start: float) -> CalibrationResult:
    """The :class:`CalibrationResult` of a fit ``sol`` (its values and walls ``fit``)
    that passed every check."""
    system, names = setup.system, setup.names
    values, wall_p = fit.values, fit.walls
    lay, x, H = sol.problem.layout, sol.x, sol.info
    cov, std_all, corr_full = unc.cov, unc.std_all, unc.correlation
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
        system=system.with_params(**out_values), names=names, values=out_values, std=unc.std,
        initial={nm: system.get_param(nm) for nm in names}, covariance=cov[:n, :n],
        correlation=corr_full[:n, :n],
        rms={"pixel": math.sqrt(chk.rms_u / max(chk.wsum, 1e-12)),
             "time": math.sqrt(chk.rms_t / max(chk.wsum, 1e-12))},
        n_detections=int(round(chk.n_sig)), fixed=[p for p in SYSTEM_PARAMS if p not in names],
        unobservable=unobservable, tradeoffs=unc.tradeoffs, planes=planes,
        planes_std=planes_std, targets=chk.targets, checks=chk.checks, warnings=warns,
        iterations=iterations, elapsed=time.perf_counter() - t_start,
        extra={"labels": lay.labels, "correlation_full": corr_full,
               "singular_values": unc.singular.tolist(), "x": x, "layout": lay,
               "problem": sol.problem,
               "information": H,
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
