"""Walls the first search missed, found with the system the other walls fix.

:func:`guide_values` — the system to search with: the fit of the walls found
(or, when that fit is degenerate, one with the offset and the baseline pinned);
:func:`add_missed_walls` — the pose search (:func:`mems_stereo.calib.track.find_wall`:
the matched filter over every shot of :mod:`mems_stereo.calib.wall_search`) for each
missed wall with that system, then the fit of all walls found.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from mems_stereo.calib import observability as obs
from mems_stereo.calib.initialisation import FOUND_SPOT, initialise
from mems_stereo.calib.problem import WallData
from mems_stereo.calib.solver import FitSetup, FitState, Solution, StartValues, solve
from mems_stereo.calib.track import find_wall

from mems_stereo.errors import NotObservableError

#: pinned at their nominal values while a degenerate first fit guides the search for
#: missed walls (the scale-like directions that a single wall cannot fix)
PINNED_FOR_GUIDE = ("tdc_offset", "baseline_x", "baseline_y", "baseline_z")


@dataclass(frozen=True, slots=True)
class MissedWalls:
    """The fit of all walls after :func:`add_missed_walls` found more.

    found : indices (into all walls) of the walls found; used : indices of the
    walls fitted (those used before, then those found); walls, priors : the
    fitted walls' data and measured distances (wall indices among them); state :
    the fit's solver state (converged); solution : the fit.
    """

    found: list[int]
    used: list[int]
    walls: list[WallData]
    priors: list[tuple[int, str, float, float]]
    state: FitState
    solution: Solution


def guide_values(sol: Solution, state: FitState, setup: FitSetup, walls, priors, limits: dict,
                 progress=None) -> StartValues | None:
    """System values (all of ``setup.names``) and walls to search missed walls with.

    The converged fit ``sol`` of the walls found when it determines every
    parameter (σ within ``limits``); otherwise (one wall, walls at one
    distance: the fit is degenerate or does not converge) a fit from the start
    values with the TDC offset and the baseline pinned at their nominal values
    (a mechanical tolerance away from the truth: a few pixels and ns, which the
    pose search over distances absorbs).  None when neither works.
    """
    names, system = setup.names, setup.system
    lay = sol.problem.layout
    if state.converged:
        cov, _, _ = obs.covariance(sol.info, lay.scales)
        d = np.diag(cov)
        std = {n: float(math.sqrt(d[i])) if np.isfinite(d[i]) and d[i] >= 0 else math.inf
               for i, n in enumerate(lay.names)}
        if not obs.weak_parameters(std, limits, [])[0]:
            return StartValues(*lay.unpack(sol.x))
    names_r = [n for n in names if n not in PINNED_FOR_GUIDE]
    if names_r == names:
        return StartValues(*lay.unpack(sol.x)) if state.converged else None
    if progress:
        progress("first fit degenerate: the offset and the baseline pinned at their "
                 "nominal values to search the missed walls")
    st = FitState()
    try:  # start values again, with the pinned parameters held
        guess = initialise(walls, system, names_r, setup.sigma, priors)
        if len(guess.used) < len(walls):
            return None
        sol_r = solve(replace(setup, names=names_r), walls, priors,
                      {n: guess.values[n] for n in names_r}, guess.walls, st, progress)
    except NotObservableError:
        return None
    if not st.converged:
        return None
    v_r, wp_r = sol_r.problem.layout.unpack(sol_r.x)
    vals = {n: system.get_param(n) for n in names}
    vals.update(v_r)
    return StartValues(vals, wp_r)


def add_missed_walls(setup: FitSetup, all_walls, all_priors, used: list, left: list,
                     start: StartValues, progress=None) -> MissedWalls | None:
    """Search the walls ``left`` (indices into ``all_walls``) with the system
    ``start.values``, then fit the walls ``used`` (their planes ``start.walls``)
    and those found together.  None unless that fit converges with at least one
    more wall."""
    values, wall_p, system = start.values, start.walls, setup.system
    found, new_p = [], {}
    for j in left:
        f = find_wall(all_walls[j], system.with_params(**values), values, setup.sigma)
        if f is not None:
            found.append(j)
            new_p[j] = np.array([[f.alpha, 0.0, f.dist, math.log(f.mu),
                                  math.log(FOUND_SPOT)]])
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
            sol2 = solve(setup, walls2, priors2, values, wp2, state2, progress)
        except NotObservableError as e:  # a found wall lost: without it
            state2.converged = False
            lost = [j for j in found if all_walls[j].source in str(e)]
            found = [j for j in found if j not in lost] if lost else []
            continue
        if not state2.converged:
            break
    if found and state2.converged:
        return MissedWalls(found, used2, walls2, priors2, state2, sol2)
    return None
