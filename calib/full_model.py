"""``--model full``: the ideal-model calibration extended by the hardware terms it needs.

:func:`add_hardware_terms` takes a converged ideal-model
:class:`~mems_stereo.calib.result.CalibrationResult`, runs the score tests of
:mod:`mems_stereo.calib.hardware_fit`, re-fits with the selected harmonics and edge
delay (from the ideal fit's solution), drops a term the walls do not determine
(saying what to record), then adds the per-pixel TDC offsets when their test fails.
An ideal-hardware calibration selects nothing and is returned unchanged.
"""

from __future__ import annotations

import numpy as np
from mems_stereo.calib import hardware_fit as hf
from mems_stereo.calib.fit import fit_walls
from mems_stereo.calib.solver import StartValues

#: what to record when a hardware term is not observable
RECORD_ADVICE = {
    "harmonic": "record walls that the beam crosses over the whole scan (wide walls at "
                "two or more distances) so that the scan phase is sampled end to end",
    "edge": "record walls at two or more distances so that both sweeps' returns are seen "
            "at different ranges",
}


#: a term of the rescue fit further than this many σ from ideal is kept
KEEP_SIGMA = 3.0
#: rounds of forward selection
MAX_STEPS = 4


def _advice(name: str) -> str:
    return RECORD_ADVICE["harmonic" if name.startswith("harmonic") else "edge"]


def _refit(result, names: list, fit_kwargs: dict):
    """Fit ``result``'s walls with the system parameters ``result.names`` + ``names``
    free, from ``result``'s solution."""
    prob, x = result.extra["problem"], result.extra["x"]
    values, walls = prob.layout.unpack(x)
    start = StartValues({**values, **{n: prob.system.get_param(n) for n in names}}, walls)
    return fit_walls(prob.walls, prob.system, free=list(result.names) + list(names),
                     priors=prob.priors, initial=start, on_unobservable="warn", **fit_kwargs)


def _fit_terms(result, chosen: list, fit_kwargs: dict):
    """``result`` re-fitted with ``chosen`` free too; a term the walls do not determine
    is dropped (a warning says what to record); ``result`` itself when nothing is left
    or the fit fails (a warning says so)."""
    r1 = _refit(result, chosen, fit_kwargs)
    weak = [n for n in chosen if r1 and n in r1.unobservable]
    if weak:
        for n in weak:
            result.warnings.append(f"{n} not observable from these walls (left ideal): "
                                   f"{_advice(n)}")
        chosen = [n for n in chosen if n not in weak]
        if not chosen:
            return result
        r1 = _refit(result, chosen, fit_kwargs)
    if not r1:
        result.warnings.append(f"the fit with the hardware terms failed ({r1.reason}): "
                               "the model without them is kept")
        return result
    r1.warnings[:0] = [w for w in result.warnings if w not in r1.warnings]
    return r1


def _pulse(result) -> None:
    """``result.extra["pulse"]``: the pulse shape from the walls' low-pile-up returns
    (:mod:`mems_stereo.calib.pulse_shape`; for the report, not written), when there
    are enough of them."""
    from mems_stereo.calib.pulse_shape import fit_pulse_shape, wall_return_residuals

    from mems_stereo.errors import ShapeError

    prob = result.extra["problem"]
    res, window = wall_return_residuals(prob, result.extra["x"])
    try:
        result.extra["pulse"] = fit_pulse_shape(res, window=window,
                                                quantum=prob.system.tdc.bin_width)
    except ShapeError:
        pass


def add_hardware_terms(result, orders=hf.DEFAULT_ORDERS, progress=None, **fit_kwargs):
    """The full-model calibration from an ideal-model ``result`` (see the module).

    Returns a CalibrationResult whose ``extra["hardware_tests"]`` lists the
    :class:`~mems_stereo.calib.hardware_fit.TermTest` of every candidate and
    ``extra["pixel_offsets"]`` the :class:`~mems_stereo.calib.hardware_fit.PixelOffsets`;
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
    po = hf.pixel_offsets(out.extra["problem"], out.extra["x"])
    if po.test.selected:
        out.system = hf.with_pixel_offsets(out.system, po)
        n_left = int((~po.covered).sum())
        if n_left:
            out.warnings.append(f"{n_left} pixels see no wall return: their TDC offsets are "
                                "left at 0 (record walls whose returns cover every pixel)")
    out.system = hf.hardware_std(out.system, out.values, out.std, out.covariance, out.names)
    out.extra["hardware_tests"] = tests + [po.test]
    _pulse(out)
    out.extra["pixel_offsets"] = po
    out.system = out.system.replace(calibration=out.calibration_dict())
    return out


def rescue(failure, walls, nominal, priors, orders=hf.DEFAULT_ORDERS, progress=None,
           **fit_kwargs):
    """A full-model calibration when the ideal model's fit converged but failed its
    checks (a misfit the hardware terms may explain): every candidate term free from
    the failed fit's values, then the terms within :data:`KEEP_SIGMA` σ of ideal
    dropped and the rest fitted again.  Returns the result, or ``failure`` unchanged
    when the failed fit has no values for every wall or the extended fits fail too."""
    d = failure.details or {}
    if "values" not in d or "walls" not in d or len(d["walls"]) != len(walls):
        return failure
    names = [n for b in hf.candidate_blocks(orders).values() for n in b]
    free = list(d["values"]) + names
    start = StartValues({**d["values"], **{n: nominal.get_param(n) for n in names}},
                        np.asarray(d["walls"], dtype=np.float64))
    if progress:
        progress("the ideal model failed its checks: fitting every hardware term")
    r = fit_walls(walls, nominal, free=free, priors=priors, initial=start,
                  on_unobservable="warn", **fit_kwargs)
    if not r:
        return failure
    keep = [n for n in names if n in r.names and n not in r.unobservable
            and abs(r.values[n]) > KEEP_SIGMA * r.std[n]]
    blocks = {n.split("_")[0] for n in keep}  # a harmonic keeps both its terms
    keep = [n for n in names if n.split("_")[0] in blocks]
    values, wp = r.extra["problem"].layout.unpack(r.extra["x"])
    r2 = fit_walls(walls, nominal, free=list(d["values"]) + keep, priors=priors,
                   initial=StartValues(values, wp), on_unobservable="warn", **fit_kwargs)
    if not r2:
        return failure
    r2.warnings.insert(0, "the ideal model failed its checks (" + failure.reason[:120]
                       + "...): the hardware terms " + (", ".join(keep) or "none")
                       + " were fitted")
    return r2
