"""Walls the first search missed, found with the system the other walls fix.

:func:`guide_values` — the system to search with: the fit of the walls found
(or, when that fit is degenerate, one with the offset and the baseline pinned);
:func:`add_missed_walls` — the pose search (:func:`mems_stereo.calib.initialisation.find_wall`:
the matched filter over every shot of :mod:`mems_stereo.calib.wall_search`) for each
missed wall with that system, then the fit of all walls found.
"""

from __future__ import annotations

import math

import numpy as np
from mems_stereo.calib import observability as obs
from mems_stereo.calib.initialisation import find_wall, initialise
from mems_stereo.calib.solver import FitState, solve

from mems_stereo.errors import NotObservableError

#: pinned at their nominal values while a degenerate first fit guides the search for
#: missed walls (the scale-like directions that a single wall cannot fix)
PINNED_FOR_GUIDE = ("tdc_offset", "baseline_x", "baseline_y", "baseline_z")


def guide_values(prob, x, H, state, walls, system, names, two_d, sigma, priors, values0,
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
        prob_r, x_r, _ = solve(walls, system, names_r, two_d, sigma, priors,
                                {n: v0[n] for n in names_r}, wp0, st, progress)
    except NotObservableError:
        return None
    if not st.converged:
        return None
    v_r, wp_r = prob_r.layout.unpack(x_r)
    vals = {n: system.get_param(n) for n in names}
    vals.update(v_r)
    return vals, wp_r

def add_missed_walls(all_walls, all_priors, used, left, values, wall_p, system, names, two_d,
                     sigma, progress):
    """Search the walls ``left`` (indices into ``all_walls``) with the system
    ``values``, then fit the walls ``used`` (their planes ``wall_p``) and those
    found together.  Returns (found, used, walls, priors, state, (prob, x, H))
    of a converged fit with at least one more wall, else None."""
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
            sol2 = solve(walls2, system, names, two_d, sigma, priors2, values,
                         wp2, state2, progress)
        except NotObservableError as e:  # a found wall lost: without it
            state2.converged = False
            lost = [j for j in found if all_walls[j].source in str(e)]
            found = [j for j in found if j not in lost] if lost else []
            continue
        if not state2.converged:
            break
    if found and state2.converged:
        return found, used2, walls2, priors2, state2, sol2
    return None
