"""Goodness of fit of a wall calibration, named: the cells' residuals tested for structure.

The residual of a cell (shot k, pixel c near the beam's image) is its **score**: the
derivative of the cell's exact first-photon log-likelihood
(:func:`mems_stereo.calib.problem.cell_terms`) by the return's time τ (and, in a
second report, by the beam's image column u).  Under the model every cell's score
has mean zero whatever the pile-up, the background or whether the pixel fired, so
structure in the scores against scan phase, sweep direction, pixel, the return's
TDC code or its signal level is structure the model does not explain; the tests
are :func:`mems_stereo.pipeline.goodness.structure_tests` on the scores scaled to
unit RMS (cells with an expected signal of at least :data:`MIN_SIGNAL` photons).

:func:`judge` turns a failed test into a refusal naming the effect (exit 1 from the
CLI) or, when asked, into σ inflated by the square root of the largest failed F
statistic (the scale factor of inconsistent data, PDG Review §5.2) and a warning.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from mems_stereo.calib.problem import Problem, cell_terms
from mems_stereo.calib.result import CalibrationFailure

from mems_stereo.pipeline.goodness import GoodnessReport, structure_tests

#: cells with fewer expected signal photons than this are left out of the tests
MIN_SIGNAL = 0.02


@dataclass(frozen=True)
class CellResiduals:
    """Score residuals of the analysed cells (N,): ``time`` and ``column`` (unit RMS),
    ``phase`` (rad, monitor phase + phase offset), ``pixel`` (flat index), ``code``
    (the return's predicted TDC code), ``signal`` (expected photons per shot)."""

    time: np.ndarray
    column: np.ndarray
    phase: np.ndarray
    pixel: np.ndarray
    code: np.ndarray
    signal: np.ndarray


def _wall_residuals(prob: Problem, x, j: int) -> dict:
    lay = prob.layout
    values, walls = lay.unpack(x)
    c = prob.cells[j]
    ph = prob.phase(values, j, c.shots)
    pred, ok, _ = prob.predictions(x, j, c.shots)
    pos = np.searchsorted(c.shots, c.shot)
    good = ok[pos]
    pc = np.where(good[:, None], pred[pos], [0.0, -1e6, -1e6, 0.0])
    W = prob.system.receiver.width
    pix = (c.row * W + c.col).astype(np.int64)
    if prob.pixel_offsets is not None:
        pc[:, 0] += prob.pixel_offsets[pix]
    _, d = cell_terms(c, pc, walls[j, 3], walls[j, 4], prob.sigma, lay.two_d,
                      prob.pitch_ratio, prob.pulse(values))
    mu = np.exp(walls[j, 3] + pc[:, 3] - c.log_gref)
    off = values.get("phase_offset", prob.system.get_param("phase_offset"))
    return {"time": d[:, 0] * prob.sigma, "column": d[:, 1], "phase": ph[pos] + off,
            "pixel": pix,
            "code": np.floor(pc[:, 0] / prob.walls[j].bin_width).astype(np.int64) + 1,
            "signal": mu, "keep": good & (mu >= MIN_SIGNAL)}


def cell_residuals(prob: Problem, x) -> CellResiduals:
    """The score residuals of every wall's cells at the fitted ``x``."""
    parts = [_wall_residuals(prob, x, j) for j in range(prob.layout.T)]
    cat = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    keep = cat.pop("keep")
    cat = {k: v[keep] for k, v in cat.items()}
    for k in ("time", "column"):
        rms = math.sqrt(float(np.mean(cat[k] ** 2))) if cat[k].size else 1.0
        cat[k] = cat[k] / (rms or 1.0)
    return CellResiduals(**cat)


def calibration_goodness(prob: Problem, x) -> tuple:
    """(time report, column report): :class:`~mems_stereo.pipeline.goodness.GoodnessReport`
    of the time scores (phase, direction, pixel, code, signal level) and of the column
    scores (phase, direction)."""
    r = cell_residuals(prob, x)
    t = structure_tests(r.time, phase=r.phase, pixel=r.pixel, code=r.code, signal=r.signal)
    u = structure_tests(r.column, phase=r.phase)
    return t, u


def judge(result, inflate_sigma: bool = False):
    """Test a :class:`~mems_stereo.calib.result.CalibrationResult`'s residuals.

    Passed: the result, with ``extra["goodness"]`` (the two reports). Failed: a
    :class:`~mems_stereo.calib.result.CalibrationFailure` whose reason names the effect
    and what to do; with ``inflate_sigma`` instead the result with its covariance
    scaled by the largest failed F statistic and a warning saying so.
    """
    prob, x = result.extra["problem"], result.extra["x"]
    reps = calibration_goodness(prob, x)
    result.extra["goodness"] = reps
    failed = [f for rep in reps for f in rep.failed]
    if not failed:
        return result
    words = "; ".join(dict.fromkeys(f.message for f in failed))
    if not inflate_sigma:
        return CalibrationFailure(
            "the model does not fit these walls: " + words + " (or --inflate-sigma to "
            "write σ that cover the misfit)", "estimate",
            {"goodness": [rep.to_dict() for rep in reps]}, list(result.warnings),
            result.elapsed)
    k = math.sqrt(max(f.statistic for f in failed))
    return inflate(result, k, words)


def inflate(result, k: float, why: str):
    """``result`` with every σ multiplied by ``k`` (covariance by k²) and a warning."""
    result.covariance = result.covariance * k * k
    result.std = {n: s * k for n, s in result.std.items()}
    result.planes_std = result.planes_std * k
    result.warnings.append(f"σ inflated ×{k:.2f} to cover a misfit the model does not "
                           f"explain: {why}")
    result.system = result.system.replace(calibration=result.calibration_dict())
    return result


def reports_lines(reps: tuple[GoodnessReport, ...]) -> list:
    """The failed tests' lines of several reports, each once."""
    return list(dict.fromkeys(line for rep in reps for line in rep.lines()))
