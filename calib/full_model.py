"""``--model full``: the ideal-model calibration extended by the hardware terms it needs.

:func:`add_hardware_terms` takes a converged ideal-model
:class:`~mems_stereo.calib.result.CalibrationResult`, runs the score tests of
:mod:`mems_stereo.calib.hardware_fit`, re-fits with the selected harmonics and edge
delay (from the ideal fit's solution), drops a term the walls do not determine
(saying what to record), then the pulse's ex-gaussian tail when its score test finds
one (:func:`_pulse_tail`: fitted in the time likelihood), then the per-pixel TDC
offsets when their test fails.
An ideal-hardware calibration selects nothing and is returned unchanged.
"""

from __future__ import annotations

import numpy as np
from mems_stereo.calib import hardware_fit as hf
from mems_stereo.calib import pixel_offsets as pxo
from mems_stereo.calib.fit import fit_walls
from mems_stereo.calib.model import PULSE_PARAMS
from mems_stereo.calib.nuisance import add_held_edges, add_held_tail, holds_edges, profile_tail
from mems_stereo.calib.solver import StartValues

#: what to record when a hardware term is not observable
RECORD_ADVICE = {
    "harmonic": "record walls that the beam crosses over the whole scan (wide walls at "
                "two or more distances) so that the scan phase is sampled end to end",
    "edge": "record walls at two or more distances so that both sweeps' returns are seen "
            "at different ranges",
    "pulse": "record the walls with more shots at low pile-up (a fraction of a signal "
             "photon per shot and pixel) so that the pulse's tail is sampled",
}


#: rounds of forward selection
MAX_STEPS = 4


def _advice(name: str) -> str:
    return RECORD_ADVICE[name.split("_")[0] if name.startswith(("pulse", "edge"))
                         else "harmonic"]


def _refit(result, names: list, fit_kwargs: dict, start_values=None):
    """Fit ``result``'s walls with the system parameters ``result.names`` + ``names``
    free, from ``result``'s solution (``start_values``: dict name → SI value that
    replaces it, e.g. the pulse's tail from :func:`_pulse`)."""
    prob, x = result.extra["problem"], result.extra["x"]
    values, walls = prob.layout.unpack(x)
    start = StartValues({**values, **{n: prob.system.get_param(n) for n in names},
                         **(start_values or {})}, walls)
    return fit_walls(prob.walls, prob.system, free=list(result.names) + list(names),
                     priors=prob.priors, initial=start, on_unobservable="warn", **fit_kwargs)


def _fit_terms(result, chosen: list, fit_kwargs: dict, start_values=None):
    """``result`` re-fitted with ``chosen`` free too; a term the walls do not determine
    is dropped (a warning says what to record); ``result`` itself when nothing is left
    or the fit fails (a warning says so)."""
    r1 = _refit(result, chosen, fit_kwargs, start_values)
    weak = [n for n in chosen if r1 and n in r1.unobservable]
    if weak:
        for n in weak:
            result.warnings.append(f"{n} not observable from these walls (left ideal): "
                                   f"{_advice(n)}")
        chosen = [n for n in chosen if n not in weak]
        if not chosen:
            return result
        r1 = _refit(result, chosen, fit_kwargs, start_values)
    if not r1:
        result.warnings.append(f"the fit with the hardware terms failed ({r1.reason}): "
                               "the model without them is kept")
        return result
    r1.warnings[:0] = [w for w in result.warnings if w not in r1.warnings]
    return r1


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
        out = r1
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
    blocks = hf.candidate_blocks(orders)
    out, tests = result, []
    for _ in range(MAX_STEPS):  # forward selection: test, fit the significant, test again
        prob, x = out.extra["problem"], out.extra["x"]
        todo = {k: v for k, v in blocks.items() if not set(v) & set(out.names)}
        if not todo:
            break
        step = hf.score_tests(prob, x, todo)
        tests = [t for t in tests if t.name not in todo] + step
        sel = [t for t in step if t.selected]
        if not sel:
            break
        best = min(sel, key=lambda t: (t.p_value, -t.lm))  # one block a round: a misfit
        chosen = list(best.names)  # leaks into the other blocks' scores
        if progress:
            progress(f"hardware terms: {best.name} (score test p = {best.p_value:.1e})")
        nxt = _fit_terms(out, chosen, fit_kwargs)
        if nxt is out:
            break
        out = nxt
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
    out.system = hf.hardware_std(out.system, out.values, out.std, out.covariance, out.names)
    out.extra["hardware_tests"] = tests + [po.test] + (
        [out.extra["tail_test"]] if "tail_test" in out.extra else [])
    out.extra["pixel_offsets"] = po
    out.system = out.system.replace(calibration=out.calibration_dict())
    return out


def _failed_problem(failure, walls, nominal, priors, fit_kwargs):
    """The ideal problem at a failed fit's values, on fresh cells: (problem, x) or None."""
    from mems_stereo.calib.problem import Layout, Problem
    from mems_stereo.calib.solver import build_cells

    from mems_stereo.errors import NotObservableError
    from mems_stereo.physics.pulse import pulse_sigma

    d = failure.details or {}
    if "values" not in d or "walls" not in d or len(d["walls"]) != len(walls):
        return None
    lay = Layout(list(d["values"]), len(walls), nominal.receiver.height > 1)
    sigma = pulse_sigma(nominal.laser.pulse_fwhm, fit_kwargs.get("jitter", 50e-12))
    prob = Problem(walls, nominal, lay, sigma, priors)
    x = lay.pack(d["values"], np.asarray(d["walls"], dtype=np.float64))
    try:
        return prob, build_cells(prob, x, radius=2)
    except NotObservableError:
        return None


def rescue(failure, walls, nominal, priors, orders=hf.DEFAULT_ORDERS, progress=None,
           **fit_kwargs):
    """A full-model calibration when the ideal model's fit converged but failed its
    checks: the score tests of :mod:`~mems_stereo.calib.hardware_fit` at the failed
    fit's values; the significant blocks fitted from there.  Returns the result, or
    ``failure`` unchanged when the fit did not reach its checks (did not converge), no
    block is significant, the failed fit has no values
    for every wall, or the extended fit fails too (a misfit no hardware term explains:
    a wrong distance, a wall that is not flat)."""
    if "checks" not in (failure.details or {}):  # not converged, or no wall: no misfit
        return failure
    got = _failed_problem(failure, walls, nominal, priors, fit_kwargs)
    if got is None:
        return failure
    prob, x = got
    tests = hf.score_tests(prob, x, hf.candidate_blocks(orders))
    keep = [n for t in tests if t.selected for n in t.names]
    if not keep:
        return failure
    if progress:
        progress("the ideal model failed its checks: fitting "
                 + ", ".join(t.name for t in tests if t.selected))
    d = failure.details
    start = StartValues({**d["values"], **{n: nominal.get_param(n) for n in keep}},
                        np.asarray(d["walls"], dtype=np.float64))
    r = fit_walls(walls, nominal, free=list(d["values"]) + keep, priors=priors,
                  initial=start, on_unobservable="warn", **fit_kwargs)
    if not r:
        return failure
    r.warnings.insert(0, "the ideal model failed its checks (" + failure.reason[:120]
                      + "...): the hardware terms " + ", ".join(keep) + " were fitted")
    return r
