"""``--model full``: the ideal-model calibration extended by the hardware terms it needs.

:func:`add_hardware_terms` takes a converged ideal-model
:class:`~mems_stereo.calib.result.CalibrationResult`, runs the score tests of
:mod:`mems_stereo.calib.hardware_fit`, re-fits with the selected harmonics and edge
delay (forward selection from the ideal fit's solution, one block a round:
:func:`_select`, each new block started from the score test's Newton step:
:func:`newton_start`; a fit its checks refuse is tested on, the last that passes kept),
drops a term the walls do not determine (saying what to record), then the pulse's
ex-gaussian tail when its score test finds
one (:func:`_pulse_tail`: fitted in the time likelihood), then the per-pixel TDC
offsets when their test fails.
An ideal-hardware calibration selects nothing and is returned unchanged.
:func:`rescue` runs the same selection from an ideal-model fit its checks refused
or that did not converge.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from mems_stereo.calib import hardware_fit as hf
from mems_stereo.calib import pixel_offsets as pxo
from mems_stereo.calib.fit import fit_walls
from mems_stereo.calib.held_blocks import add_held_blocks
from mems_stereo.calib.model import PULSE_PARAMS
from mems_stereo.calib.nuisance import add_held_edges, add_held_tail, holds_edges, profile_tail
from mems_stereo.calib.solver import StartValues
from mems_stereo.calib.tail_profile import widen_share

from mems_stereo.errors import GeometryError

#: what to record when a hardware term is not observable
RECORD_ADVICE = {
    "harmonic": "record walls that the beam crosses over the whole scan (wide walls at "
                "two or more distances) so that the scan phase is sampled end to end",
    "edge": "record walls at two or more distances so that both sweeps' returns are seen "
            "at different ranges",
    "pulse": "record the walls with more shots at low pile-up (a fraction of a signal "
             "photon per shot and pixel) so that the pulse's tail is sampled",
}


#: rounds of forward selection (at most one per candidate block)
MAX_STEPS = 5

#: whether a newly selected block starts from the score test's Newton step
#: (:func:`newton_start`); False: at 0 (its nominal value), as the benchmarks' baseline
NEWTON_START = True
#: whether a block whose local refit its checks refuse is fitted again from a new
#: start search (:func:`_global_fit`)
GLOBAL_RETRY = True
#: Levenberg damping of the information in the Newton start (the solver's first λ)
NEWTON_DAMPING = 1e-3
#: fractions of the Newton step tried (the one of highest likelihood taken)
NEWTON_SHRINK = (1.0, 0.5, 0.25)


def _advice(name: str) -> str:
    return RECORD_ADVICE[name.split("_")[0] if name.startswith(("pulse", "edge"))
                         else "harmonic"]


def _refit_at(prob, x, names: list, extra: list, fit_kwargs: dict, start_values=None):
    """Fit ``prob``'s walls (its nominal system and measured distances) with the
    system parameters ``names`` + ``extra`` free, from ``prob``'s solution ``x`` (the
    ``extra`` at their nominal values; ``start_values``: dict name → SI value that
    replaces a start, e.g. the pulse's tail from :func:`_pulse`)."""
    values, walls = prob.layout.unpack(x)
    start = StartValues({**values, **{n: prob.system.get_param(n) for n in extra},
                         **(start_values or {})}, walls)
    return fit_walls(prob.walls, prob.system, free=list(names) + list(extra),
                     priors=prob.priors, initial=start, on_unobservable="warn", **fit_kwargs)


def _refit(result, names: list, fit_kwargs: dict, start_values=None):
    """:func:`_refit_at` from a result's solution with its parameters free too."""
    return _refit_at(result.extra["problem"], result.extra["x"], list(result.names), names,
                     fit_kwargs, start_values)


@dataclass(frozen=True)
class BlockStart:
    """Where a newly selected block's refit starts (:func:`newton_start`): ``x`` the
    fitted point's vector (its problem's layout, SI: the fitted parameters and walls
    moved by the step), ``block`` dict name → SI start value of the block's
    parameters, ``gain`` the log-likelihood's increase over the block at 0 and
    ``shrink`` the fraction of the Newton step taken."""

    x: np.ndarray
    block: dict
    gain: float
    shrink: float


def newton_start(prob, x, chosen: list) -> BlockStart | None:
    """The score test's Newton step for the block ``chosen`` at the fitted point
    (``prob`` a :class:`~mems_stereo.calib.problem.Problem`, ``x`` its (P,) SI
    solution): on ``prob``'s cells with ``chosen`` added at their nominal values
    (:func:`~mems_stereo.calib.hardware_fit.extended_problem`), δ = I⁻¹ g over every
    parameter (the fitted ones, the walls' and the block's; I the outer-product
    information, g the score), so that the block's part is its score divided by its
    information conditioned on the fitted parameters, [I⁻¹]_bb g_b where the fitted
    scores vanish.  I is damped as in the solver's first step
    (:data:`NEWTON_DAMPING` × its diagonal, Levenberg): at a refused fit's point the
    walls' signal levels can be nearly undetermined and the undamped step wild.  Of
    the fractions of δ in :data:`NEWTON_SHRINK` (one step of the outer-product
    information can overshoot a curved likelihood) the one with the highest
    log-likelihood is taken when it is higher than at 0; None when none is (the block
    then starts at 0)."""
    p2, x2 = hf.extended_problem(prob, x, list(chosen))
    sc = p2.layout.scales
    try:
        ll0, g, H = p2.score(x2)
        Hs = H * sc[:, None] * sc[None, :]
        damp = NEWTON_DAMPING * np.diag(np.maximum(np.diag(Hs), 1e-12))
        step = np.linalg.solve(Hs + damp, g * sc) * sc
    except (GeometryError, np.linalg.LinAlgError):
        return None
    if not (math.isfinite(ll0) and np.all(np.isfinite(step))):
        return None
    best, f_best = ll0, None
    for f in NEWTON_SHRINK:
        try:
            ll1 = p2.loglik(x2 + f * step)
        except GeometryError:  # a harmonic so strong that the mirror turns back
            continue
        if math.isfinite(ll1) and ll1 > best:
            best, f_best = ll1, f
    if f_best is None:
        return None
    values, walls = p2.layout.unpack(x2 + f_best * step)
    xs = prob.layout.pack({n: values[n] for n in prob.layout.names}, walls)
    return BlockStart(xs, {n: float(values[n]) for n in chosen}, best - ll0, f_best)


def _fit_block(prob, x, names: list, chosen: list, fit_kwargs: dict, progress=None):
    """:func:`_refit_at` with the block ``chosen`` from its Newton start
    (:func:`newton_start`, when :data:`NEWTON_START`), else from 0; from 0 too when
    the fit from the Newton start does not reach its checks (did not converge)."""
    st = newton_start(prob, x, chosen) if NEWTON_START else None
    if progress:
        progress("hardware terms: " + ", ".join(chosen) + (
            " from 0" if st is None else f" from {st.shrink:g} × the Newton step "
            f"(log-likelihood +{st.gain:.1f}): " + ", ".join(
                f"{k} {v:.3g}" for k, v in st.block.items())))
    if st is None:
        return _refit_at(prob, x, names, chosen, fit_kwargs)
    r = _refit_at(prob, st.x, names, chosen, fit_kwargs, st.block)
    if r or "checks" in (r.details or {}):
        return r
    if progress:
        progress(f"hardware terms: {', '.join(chosen)} again from 0 ({r.reason[:60]})")
    return _refit_at(prob, x, names, chosen, fit_kwargs)


@dataclass
class _Step:
    """Where forward selection stands: ``fit`` the last fit (a result, or a failure
    that converged and was refused by its checks: a misfit the next block may
    explain), ``walls``, ``nominal`` and ``priors`` it was given (to rebuild a
    failure's problem), ``good`` the last fit that passed its checks (or None) and
    ``notes`` the warnings of the steps."""

    fit: object
    walls: list
    nominal: object
    priors: list
    good: object = None
    notes: list = field(default_factory=list)


def _point(step: _Step, jitter: float):
    """(problem, x, free names) at the step's fit: a result's own, a failure's
    problem at its values on fresh cells (:func:`~mems_stereo.calib.goodness.
    failed_problem`); None for a failure that did not reach its checks."""
    from mems_stereo.calib.goodness import failed_problem

    f = step.fit
    if f:
        return f.extra["problem"], f.extra["x"], list(f.names)
    if "values" not in (f.details or {}):  # no fitted values: nothing to test at
        return None
    got = failed_problem(f, step.walls, step.nominal, step.priors, jitter)
    return None if got is None else (got[0], got[1], list(f.details["values"]))


def _add_block(step: _Step, point, chosen: list, fit_kwargs: dict, dropped: set,
               progress=None):
    """The fit of ``point`` (problem, x, names) with ``chosen`` free too; a term the
    walls do not determine is dropped (added to ``dropped``, a note says what to
    record) and the rest fitted again.  Returns the new :class:`_Step`, or None when
    nothing is left or the fit did not reach its checks (a note says so)."""
    prob, x, names = point
    r1 = _fit_block(prob, x, names, chosen, fit_kwargs, progress)
    weak = [n for n in chosen if r1 and n in r1.unobservable]
    if weak:
        step.notes.extend(f"{n} not observable from these walls (left ideal): {_advice(n)}"
                          for n in weak)
        dropped.update(weak)
        chosen = [n for n in chosen if n not in weak]
        if not chosen:
            return None
        r1 = _fit_block(prob, x, names, chosen, fit_kwargs, progress)
    if not r1 and "checks" in (r1.details or {}) and GLOBAL_RETRY:
        r2 = _global_fit(prob, names + chosen, fit_kwargs, progress)
        r1 = r2 if r2 else r1
    if not r1 and "checks" not in (r1.details or {}):
        step.notes.append(f"the fit with the hardware terms {', '.join(chosen)} failed "
                          f"({r1.reason[:80]}): the model without them is kept")
        return None
    return _Step(r1, prob.walls, prob.system, prob.priors, r1 if r1 else step.good,
                 step.notes)


def _select(step: _Step, blocks: dict, fit_kwargs: dict, progress=None) -> tuple:
    """Forward selection from ``step``: the score tests of the blocks not yet fitted
    (:func:`~mems_stereo.calib.hardware_fit.score_tests`), the most significant of
    them (the smallest :func:`~mems_stereo.calib.hardware_fit.log_p_value`) fitted, one
    block a round (a misfit leaks into the other blocks' scores), then test again.  A
    fit its checks refuse (a wall that is not flat, a measured distance contradicted:
    the misfit of a block still missing) is tested on; only a fit that passes its
    checks is kept.  Returns (the last :class:`_Step`, the tests)."""
    tests, dropped = [], set()
    jitter = fit_kwargs.get("jitter", 50e-12)
    for _ in range(MAX_STEPS):
        point = _point(step, jitter)
        if point is None:
            break
        prob, x, names = point
        todo = {k: v for k, v in blocks.items() if not set(v) & (set(names) | dropped)}
        if not todo:
            break
        found = hf.score_tests(prob, x, todo)
        tests = [t for t in tests if t.name not in todo] + found
        sel = [t for t in found if t.selected]
        if not sel:
            break
        best = min(sel, key=lambda t: hf.log_p_value(t.lm, t.dof))
        if progress:
            progress(f"hardware terms: {best.name} (score test p = {best.p_value:.1e})")
        nxt = _add_block(step, point, list(best.names), fit_kwargs, dropped, progress)
        if progress and nxt is not None:
            progress("hardware terms: the fit " + ("passes its checks" if nxt.fit else
                                                   "is refused: " + nxt.fit.reason[:160]))
        if nxt is None:
            break
        step = nxt
    return step, tests


def _pulse(result):
    """The pulse shape from the walls' low-pile-up returns
    (:mod:`mems_stereo.calib.pulse_shape`) at ``result``'s solution, or None when
    there are too few of them."""
    from mems_stereo.calib.pulse_returns import fit_pulse_shape, wall_return_residuals

    from mems_stereo.errors import ShapeError

    prob = result.extra["problem"]
    res, window = wall_return_residuals(prob, result.extra["x"])
    try:
        return fit_pulse_shape(res, window=window, quantum=prob.system.tdc.bin_width)
    except ShapeError:
        return None


def _pulse_tail(result, progress, fit_kwargs: dict):
    """``result`` with the pulse's ex-gaussian tail fitted in the time likelihood
    (``pulse_tail_fraction``, ``pulse_tail_decay`` free with the other terms; the TDC
    offset then refers to the core's peak, as the system's ``tdc.offset``) when the
    score test of a tail over all cells finds one
    (:func:`~mems_stereo.calib.hardware_fit.tail_score_test`: the model selection of
    :func:`add_hardware_terms`; the low-pile-up shape fit of
    :mod:`~mems_stereo.calib.pulse_shape` gives the start when it sees the tail too).
    ``result`` unchanged when the test passes, or with a warning when the fit does not
    separate the tail from ``tdc_offset`` (a tail short against the pulse σ is a
    shift: the Gaussian's ``tdc_offset`` then holds its delay) and the held tail's
    share in its σ (:func:`~mems_stereo.calib.nuisance.add_held_tail`, the share fitted
    at the best of a few held decays, :func:`~mems_stereo.calib.nuisance.profile_tail`).
    ``extra["pulse"]`` holds the shape fit (the report's) and ``extra["tail_test"]`` the
    score test."""
    fit = _pulse(result)
    result.extra["pulse"] = fit
    if "tdc_offset" not in result.names:
        return result
    if PULSE_PARAMS[0] in result.names:  # fitted with the other terms (:func:`joint_fit`)
        test = result.extra.get("tail_test")
        out = widen_share(result)
        out.extra["pulse"] = fit
        if test is not None:
            out.extra["tail_test"] = test
        return out
    test, decay = hf.tail_score_test(result.extra["problem"], result.extra["x"])
    result.extra["tail_test"] = test
    if not test.selected:  # on hardware the other terms found imperfect, a tail the
        return _weak_tail(result)  # local test misses can still move tdc_offset
    if progress:
        progress(f"hardware terms: pulse tail (score test p = {test.p_value:.1e})")
    shaped = fit is not None and fit.tail_significant
    w, tau_d = ((fit.tail_fraction, fit.tail_decay) if shaped else (0.1, decay))
    w = min(max(w, 0.02), 0.9)
    tau_d = max(tau_d, 0.05 * result.extra["problem"].sigma)
    start = {"pulse_tail_fraction": w, "pulse_tail_decay": tau_d,
             "tdc_offset": result.values["tdc_offset"] - w * tau_d}
    r1 = _refit(result, list(PULSE_PARAMS), fit_kwargs, start)
    weak = [n for n in r1.unobservable if n not in result.unobservable] if r1 else []
    if r1 and not weak:
        r1.warnings[:0] = [w for w in result.warnings if w not in r1.warnings]
        out = widen_share(r1)  # the share's σ from its profile likelihood
    else:  # the tail held out (the Gaussian kept): its share in the σ
        why = ", ".join(weak) if r1 else f"the fit failed: {r1.reason[:80]}"
        result.warnings.append(
            f"a pulse tail (score test p = {test.p_value:.1e}) is not separated from "
            f"tdc_offset by these walls ({why}): the Gaussian pulse is kept and tdc_offset "
            f"holds the tail's delay; {RECORD_ADVICE['pulse']}")
        prof = profile_tail(result.extra["problem"], result.extra["x"])
        out = add_held_tail(result, prof) if prof else result
    out.extra["pulse"], out.extra["tail_test"] = fit, test
    return out


def _weak_tail(result):
    """``result`` with a pulse tail's share in its σ when the result fits harmonics or
    an edge delay (imperfect hardware) and :func:`~mems_stereo.calib.nuisance.
    profile_tail` finds a share more than 2σ from 0 that the score test at share 0
    did not select; else ``result`` unchanged (ideal hardware: nothing is selected)."""
    if not any(n.startswith(("harmonic", "edge")) for n in result.names):
        return result
    prof = profile_tail(result.extra["problem"], result.extra["x"])
    if prof is None or prof.share < 2.0 * prof.share_std:
        return result
    return add_held_tail(result, prof)


def add_hardware_terms(result, orders=hf.DEFAULT_ORDERS, progress=None, **fit_kwargs):
    """The full-model calibration from an ideal-model ``result`` (see the module).

    Returns a CalibrationResult whose ``extra["hardware_tests"]`` lists the
    :class:`~mems_stereo.calib.hardware_fit.TermTest` of every candidate and
    ``extra["pixel_offsets"]`` the :class:`~mems_stereo.calib.pixel_offsets.PixelOffsets`;
    the ideal-model result when no term is selected or the extended fit fails.
    """
    step, tests = _select(_Step(result, [], None, [], result), hf.candidate_blocks(orders),
                          fit_kwargs, progress)
    out = step.good
    if out is not result:
        out.warnings[:0] = [w for w in result.warnings if w not in out.warnings]
    out.warnings.extend(w for w in step.notes if w not in out.warnings)
    if not step.fit:  # the last fit was refused by its checks
        more = [n for n in step.fit.details["values"] if n not in out.names]
        out.warnings.append(f"the fit with the hardware terms {', '.join(more)} was refused "
                            f"({step.fit.reason[:120]}): the model without them is kept")
    out = _pulse_tail(out, progress, fit_kwargs)
    po = pxo.pixel_offsets(out.extra["problem"], out.extra["x"])
    if po.test.selected:
        out.system = pxo.with_pixel_offsets(out.system, po)
        n_left = int((~po.covered).sum())
        if n_left:
            out.warnings.append(f"{n_left} pixels see no wall return: their TDC offsets are "
                                "left at 0, σ the offsets' spread (record walls whose returns "
                                "cover every pixel)")
    if holds_edges(out):  # the edge-delay difference held: its share in the σ
        out = add_held_edges(out)
    out = add_held_blocks(out, orders)  # the terms not selected, integrated out of σ
    out.system = hf.hardware_std(out.system, out.values, out.std, out.covariance, out.names)
    out.extra["hardware_tests"] = tests + [po.test] + (
        [out.extra["tail_test"]] if "tail_test" in out.extra else [])
    out.extra["pixel_offsets"] = po
    out.system = out.system.replace(calibration=out.calibration_dict())
    return out


#: share of a pulse tail that :func:`joint_fit` starts from (the tail test's decay)
JOINT_TAIL_SHARE = 0.1


def _tail_start(prob, x, names: list):
    """Start values of a pulse tail at the point ``x`` of ``prob`` (share
    :data:`JOINT_TAIL_SHARE`, the tail score test's decay, ``tdc_offset`` less the
    mean delay w·τ) and the test, or (None, test) when the test does not select a
    tail; (None, None) when ``tdc_offset`` is held or the tail is fitted already."""
    if "tdc_offset" not in names or PULSE_PARAMS[0] in names:
        return None, None
    test, decay = hf.tail_score_test(prob, x)
    if not test.selected:
        return None, test
    w, tau = JOINT_TAIL_SHARE, max(decay, 0.05 * prob.sigma)
    return {PULSE_PARAMS[0]: w, PULSE_PARAMS[1]: tau,
            "tdc_offset": prob.layout.unpack(x)[0]["tdc_offset"] - w * tau}, test


def _fit_joint(prob, x, names: list, chosen: list, tail: dict | None, fit_kwargs: dict,
               progress=None):
    """The fit of ``prob`` with the blocks ``chosen`` (from their joint Newton start,
    :func:`newton_start`) and, given ``tail`` (:func:`_tail_start`), the pulse tail
    free at once; a term the walls do not determine is dropped and the rest fitted
    again.  Returns the result or failure."""
    st = newton_start(prob, x, chosen) if chosen and NEWTON_START else None
    x0, start = (x, {}) if st is None else (st.x, dict(st.block))
    extra = list(chosen)
    if tail is not None:
        shift = prob.layout.unpack(x0)[0]["tdc_offset"] - prob.layout.unpack(x)[0]["tdc_offset"]
        start.update(tail, tdc_offset=tail["tdc_offset"] + shift)
        extra += list(PULSE_PARAMS)
    if progress:
        progress("hardware terms at once: " + ", ".join(extra))
    r = _refit_at(prob, x0, names, extra, fit_kwargs, start)
    weak = [n for n in extra if r and n in r.unobservable]
    if weak:
        keep = [n for n in extra if n not in weak and n not in PULSE_PARAMS]
        tail = tail if not set(weak) & set(PULSE_PARAMS) else None
        if not keep and tail is None:
            return r
        return _fit_joint(prob, x, names, keep, tail, fit_kwargs, progress)
    return r


def _global_fit(prob, names: list, fit_kwargs: dict, progress=None):
    """The walls of ``prob`` (its nominal system and measured distances) fitted afresh
    with ``names`` free, from the global start search of
    :func:`~mems_stereo.calib.fit.fit_walls`; a hardware term the walls do not
    determine is dropped and the rest fitted again."""
    if progress:
        progress("hardware terms from a new start search: " + ", ".join(
            n for n in names if hf.is_hardware(n)))
    r = fit_walls(prob.walls, prob.system, free=names, priors=prob.priors,
                  on_unobservable="warn", **fit_kwargs)
    weak = [n for n in names if r and hf.is_hardware(n) and n in r.unobservable]
    if weak:
        return _global_fit(prob, [n for n in names if n not in weak], fit_kwargs, progress)
    return r


def joint_fit(step: _Step, blocks: dict, fit_kwargs: dict, progress=None):
    """:func:`rescue`'s last try when forward selection finds no fit that passes its
    checks: every block significant at the failed fit's point fitted at once, from a
    new start search (:func:`_global_fit`); when that fit is refused and a pulse tail's
    score test selects one at its point, the tail added there (:func:`_fit_joint`).
    A misfit pulls the walls' poses of the ideal model's fit (a yaw trades with the
    harmonics through the disparity across the scan), and a local refit from there,
    one block a round, can end further off at every round; the start search under
    the model with the blocks free sees the returns on the sensor instead.  Returns
    the result that passes its checks, or None."""
    jitter = fit_kwargs.get("jitter", 50e-12)
    point = _point(step, jitter)
    if point is None:
        return None
    prob, x, names = point
    todo = {k: v for k, v in blocks.items() if not set(v) & set(names)}
    chosen = [n for t in hf.score_tests(prob, x, todo) if t.selected for n in t.names]
    if not chosen:
        return None
    r = _global_fit(prob, names + chosen, fit_kwargs, progress)
    if not r and "checks" in (r.details or {}):
        point = _point(_Step(r, prob.walls, prob.system, prob.priors), jitter)
        tail, test = (None, None) if point is None else _tail_start(*point)
        if tail is not None:
            r = _fit_joint(*point, [], tail, fit_kwargs, progress)
            if r:
                r.extra["tail_test"] = test
    if progress:
        progress("hardware terms at once: the fit " + (
            "passes its checks" if r else "is refused: " + r.reason[:160]))
    return r if r else None


def rescue(failure, walls, nominal, priors, orders=hf.DEFAULT_ORDERS, progress=None,
           **fit_kwargs):
    """A full-model calibration when the ideal model's fit failed its checks or did
    not converge (a misfit can keep the ideal model's likelihood from settling):
    forward selection (:func:`_select`) from the failed fit's values (the problem of
    the walls it fitted, on fresh cells: :func:`~mems_stereo.calib.goodness.
    failed_problem`), until a fit passes its checks.  Returns that result, or
    ``failure`` unchanged when the fit has no fitted values (no wall found), no block
    is significant, the failed fit's walls cannot be matched, or no fit with the
    hardware terms passes (a misfit no hardware term explains: a wrong distance, a
    wall that is not flat)."""
    if "values" not in (failure.details or {}):  # no wall fitted: no misfit to test
        return failure
    step0 = _Step(failure, list(walls), nominal, list(priors))
    step, _ = _select(step0, hf.candidate_blocks(orders), fit_kwargs, progress)
    r = step.good
    if r is None:
        r = joint_fit(step0, hf.candidate_blocks(orders), fit_kwargs, progress)
    if r is None:
        return failure
    keep = [n for n in r.names if hf.is_hardware(n)]
    r.warnings[:0] = ["the ideal model's fit was refused (" + failure.reason[:120]
                      + "...): the hardware terms " + ", ".join(keep) + " were fitted"]
    r.warnings.extend(w for w in step.notes if w not in r.warnings)
    return r
