"""Goodness of fit of a wall calibration, named: the cells' residuals tested for structure.

The residual of a cell (shot k, pixel c near the beam's image) is its **score**: the
derivative of the cell's exact first-photon log-likelihood
(:func:`mems_stereo.calib.problem.cell_terms`) by the return's time τ (and, in a
second report, by the beam's image column u).  Under the model every cell's score
has mean zero whatever the pile-up, the background or whether the pixel fired, so
structure in the scores against scan phase, sweep direction, pixel, the return's
TDC code or its signal level is structure the model does not explain; the tests
are :func:`mems_stereo.pipeline.goodness.structure_tests` (cells with an expected
signal of at least :data:`MIN_SIGNAL` photons).

The scores' variance differs from cell to cell by orders of magnitude (a return cut
by the TDC start, pile-up, the spot's edge): each score is divided by its expected
RMS under the model, √F of the cell's expected information
(:func:`~mems_stereo.calib.expected_info.cell_fisher`), and the tests weight the
cells by F (weighted least squares: a structure is measured as the information-
weighted shift it implies).  Scores scaled by one common RMS instead let the groups
of high-variance cells (early codes, central pixels) look like structure on ideal
hardware.  The seven tests (five on the time scores, two on the column scores) share
the false-alarm probability :data:`ALPHA_FAMILY` (Bonferroni).

The scores' null distribution: a cell expecting m ≪ 1 signal photons has a time
score of about z/σ when a signal photon arrives (probability ≈ m) and about 0
otherwise — over its RMS √m/σ it is 0 mostly and z/√m now and then (excess
kurtosis ≈ 3/m).  The cells' own mean square is then no estimate of their
variance: on seed 1043's fit it spreads ±18 % from draw to draw with its median
below 1, and on cells drawn from the model at nine of the family's fits an F test
over it put 2 of 72 pixel-test p-values below the per-test level 1.4·10⁻⁴
(expected 0.01; ``benchmarks/results/goodness_null_replicas.log``).  The
tests therefore use the variance the model gives (1: χ² tests), give a pixel or a
code its own mean only where its cells carry :data:`MIN_GROUP_INFO` expected photons
(σ²·F summed), and refer the pixel and code blocks to the χ² scaled for their
groups' excess kurtosis (3 over each cell's σ²·F).  Cells drawn from the model at a
fit (:mod:`mems_stereo.calib.goodness_null`) give p-values uniform on the family's
designs; ``benchmarks/bench_goodness_null.py`` measures the tests' null on fits.

:func:`judge` turns a failed test into a refusal naming the effect (exit 1 from the
CLI) or, when asked, into σ inflated by the square root of the largest failed F
statistic (the scale factor of inconsistent data, PDG Review §5.2) and a warning.
:func:`name_failure` runs the same tests on the residuals of a fit that another check
refused first (not converged, not observable, implausible), so that such a refusal
names the effect too, its own reason kept.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from mems_stereo.calib import hardware_fit as hf
from mems_stereo.calib.expected_info import cell_fisher
from mems_stereo.calib.problem import Layout, Problem, cell_terms, spot_px, spot_share
from mems_stereo.calib.result import CalibrationFailure
from mems_stereo.calib.solver import FitState, build_cells, newton

from mems_stereo.errors import MemsStereoError
from mems_stereo.physics.pulse import pulse_sigma
from mems_stereo.pipeline.goodness import ADVICE, GoodnessReport, Weights, structure_tests

#: cells with fewer expected signal photons than this are left out of the tests
MIN_SIGNAL = 0.02


#: cells whose scores' expected square (σ² F_ττ, or the column score's) is below this
#: carry no information for the tests and are left out
MIN_INFO = 1e-6
#: smallest information (σ²·F_ττ summed: about the expected signal photons) of a
#: pixel or TDC code for its own mean in the tests
MIN_GROUP_INFO = 5.0
#: false-alarm probability of the whole goodness-of-fit verdict on clean residuals
ALPHA_FAMILY = 1e-3
#: tests it runs (time scores: phase, direction, pixel, code, signal; column: two)
N_TESTS = 7
#: Newton steps that re-centre a failed fit on fresh cells (:func:`failed_problem`)
REFIT_ITER = 10


@dataclass(frozen=True)
class CellResiduals:
    """Score residuals of the analysed cells (N,): ``time`` and ``column`` (each score
    over its expected RMS under the model: unit variance), ``time_info`` and
    ``column_info`` (their information, relative: mean 1; the tests' weights),
    ``phase`` (rad, monitor phase + phase offset), ``pixel`` (flat index), ``code``
    (the return's predicted TDC code), ``signal`` (expected photons per shot);
    ``time_scale`` (pulse σ) and ``column_scale`` (px): the shift of the return's
    time and column that one unit of the weighted tests' structure means."""

    time: np.ndarray
    column: np.ndarray
    time_info: np.ndarray
    column_info: np.ndarray
    phase: np.ndarray
    pixel: np.ndarray
    code: np.ndarray
    signal: np.ndarray
    time_scale: float = 1.0
    column_scale: float = 1.0


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
    pulse = prob.pulse(values)
    _, d = cell_terms(c, pc, walls[j, 3], walls[j, 4], prob.sigma, lay.two_d,
                      prob.pitch_ratio, pulse)
    mu = np.exp(walls[j, 3] + pc[:, 3] - c.log_gref)
    info = _score_information(c, pc, good, walls[j], prob, pulse)
    off = values.get("phase_offset", prob.system.get_param("phase_offset"))
    keep = good & (mu >= MIN_SIGNAL) & (info[:, 0] > MIN_INFO) & (info[:, 1] > MIN_INFO)
    info = np.where(keep[:, None], info, 1.0)
    return {"time": d[:, 0] * prob.sigma / np.sqrt(info[:, 0]),
            "column": d[:, 1] / np.sqrt(info[:, 1]), "time_info": info[:, 0],
            "column_info": info[:, 1], "phase": ph[pos] + off, "pixel": pix,
            "code": np.floor(pc[:, 0] / prob.walls[j].bin_width).astype(np.int64) + 1,
            "signal": mu, "keep": keep}


def _score_information(c, pc, good, wall, prob: Problem, pulse) -> np.ndarray:
    """(N, 2) expected square of each cell's time score ∂ℓ/∂τ (times σ², so 1 for
    a return far above the background seen whole) and column score ∂ℓ/∂u under the
    model (:func:`~mems_stereo.calib.expected_info.cell_fisher`): F_ττ σ² and
    F_mm (μ ∂share/∂u)²."""
    s = spot_px(wall[4])
    mu = np.exp(wall[3] + pc[:, 3] - c.log_gref)
    share, dsu, _ = spot_share(c.col, pc[:, 1], s)
    if prob.layout.two_d:
        fr, _, _ = spot_share(c.row, pc[:, 2], s * prob.pitch_ratio)
        share, dsu = share * fr, dsu * fr
    m = np.where(good, mu * share, 0.0)
    F = cell_fisher(pc[:, 0], m, c.lam, c.t_max, prob.sigma, pulse)
    return np.column_stack([F[:, 0] * prob.sigma ** 2, F[:, 2] * (mu * dsu) ** 2])


def cell_residuals(prob: Problem, x) -> CellResiduals:
    """The score residuals of every wall's cells at the fitted ``x``."""
    parts = [_wall_residuals(prob, x, j) for j in range(prob.layout.T)]
    cat = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    keep = cat.pop("keep")
    cat = {k: v[keep] for k, v in cat.items()}
    scale = {}
    for k in ("time_info", "column_info"):  # relative information, mean 1
        mean = float(np.mean(cat[k])) if cat[k].size else 1.0
        cat[k] = cat[k] / mean
        scale[k] = 1.0 / math.sqrt(mean)
    return CellResiduals(**cat, time_scale=scale["time_info"],
                         column_scale=scale["column_info"])


def calibration_goodness(prob: Problem, x) -> tuple:
    """(time report, column report): :class:`~mems_stereo.pipeline.goodness.GoodnessReport`
    of the time scores (phase, direction, pixel, code, signal level) and of the column
    scores (phase, direction)."""
    r = cell_residuals(prob, x)
    # time_info is relative (mean 1): the group floor in its units
    # time_info is relative (mean 1): the group floor in its units; a score carried by
    # rare photons (information F σ² ≈ expected photons m ≪ 1) has excess kurtosis 3/m
    info = r.time_info / r.time_scale ** 2
    tw = Weights(r.time_info, 1.0, MIN_GROUP_INFO * r.time_scale ** 2, 3.0 / info)
    t = structure_tests(r.time, phase=r.phase, pixel=r.pixel, code=r.code, signal=r.signal,
                        weights=tw, alpha=ALPHA_FAMILY / N_TESTS, units=(r.time_scale, "σ"))
    u = structure_tests(r.column, phase=r.phase, weights=Weights(r.column_info, 1.0),
                        alpha=ALPHA_FAMILY / N_TESTS, units=(r.column_scale, "px"))
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


def failed_problem(failure, walls, nominal, priors=(), jitter: float = 50e-12):
    """The ideal problem at a failed fit's values (``failure.details``: ``values``,
    ``walls`` and, where the fit left walls out, ``sources`` or ``targets`` naming its
    walls by source, else its "left out: <source>: …" warnings), on fresh cells within
    2 px of the fitted beam: (problem, x), or None where the failure has no fitted
    values (no wall found) or its walls cannot be matched.

    ``walls``: the :class:`~mems_stereo.calib.problem.WallData` given to the fit;
    ``priors``: [(index among them, kind, distance m, σ m)]; ``jitter``: s.
    """
    d = failure.details or {}
    if "values" not in d or "walls" not in d or not d["values"]:
        return None
    used = list(range(len(walls)))
    if len(d["walls"]) != len(walls):  # walls left out: the fitted ones by source
        names = [w.source for w in walls]
        out = {m.split(": ")[1] for m in failure.warnings if m.startswith("left out: ")}
        src = (d.get("sources") or [t.get("source") for t in d.get("targets", ())]
               or [n for n in names if n not in out])
        if len(src) != len(d["walls"]) or any(s not in names for s in src):
            return None
        used = [names.index(s) for s in src]
    fitted = [walls[j] for j in used]
    pri = [(used.index(j), kind, dist, sd) for j, kind, dist, sd in priors if j in used]
    lay = Layout(list(d["values"]), len(fitted), nominal.receiver.height > 1)
    prob = Problem(fitted, nominal, lay, pulse_sigma(nominal.laser.pulse_fwhm, jitter), pri)
    try:
        x = lay.pack(d["values"], np.asarray(d["walls"], dtype=np.float64))
        x = build_cells(prob, x, radius=2)
        # the fit's log μ refer to the cells it last built (at the start of its last
        # round): a few Newton steps from its values bring the fresh cells' optimum
        return prob, newton(prob, x, FitState(), max_iter=REFIT_ITER).x
    except (MemsStereoError, ValueError, KeyError, np.linalg.LinAlgError):
        return None


def name_failure(failure, walls, nominal, priors=(), jitter: float = 50e-12):
    """A refused fit (:class:`~mems_stereo.calib.result.CalibrationFailure` of
    :func:`~mems_stereo.calib.fit.fit_walls`) whose residuals show structure the model
    does not explain: the failure with a reason that names the effect first and keeps
    its own ("the model does not fit these walls: <effect>: <what to do>; refused
    besides: <reason>"), the same ``kind`` (exit code), the reports in
    ``details["goodness"]``.  ``failure`` unchanged where the tests pass or cannot run
    (see :func:`failed_problem`; arguments as there)."""
    got = failed_problem(failure, walls, nominal, priors, jitter)
    if got is None:
        return failure
    try:  # a fit that failed may leave too few cells for a test: then no verdict
        reps = calibration_goodness(*got)
        words = [f.message for rep in reps for f in rep.failed] or _score_test_words(*got)
    except (MemsStereoError, ValueError, np.linalg.LinAlgError):
        return failure
    if not words:
        return failure
    words = "; ".join(dict.fromkeys(words))
    details = dict(failure.details or {}, goodness=[rep.to_dict() for rep in reps])
    return CalibrationFailure(f"the model does not fit these walls: {words}; refused "
                              f"besides: {failure.reason}", failure.kind, details,
                              list(failure.warnings), failure.elapsed)


_ORDINAL = {2: "second", 3: "third", 4: "fourth", 5: "fifth"}


def _score_test_words(prob: Problem, x) -> list:
    """Messages of the hardware terms' score tests
    (:func:`~mems_stereo.calib.hardware_fit.score_tests`: each mirror harmonic 2–5 and
    the edge delay, Rao's test with the fit's geometry free, Bonferroni over the
    blocks at :data:`ALPHA_FAMILY`) that fail, most significant first: a failed fit
    can absorb a harmonic into a wrong pose, where the residuals' structure left is
    below the structure tests' smallest effect but the score along the term is not."""
    out = []
    for t in (t for t in score_test_results(prob, x) if t.selected):
        size = f"score test χ² = {t.lm:.1f} with {t.dof} dof"
        if t.name.startswith("harmonic"):
            k = int(t.name.split()[1])
            what, todo = ADVICE["scan phase"]
            detail = f"{_ORDINAL.get(k, f'order {k}')} harmonic of the mirror ({size})"
        else:
            what, todo = ADVICE["scan direction"]
            detail = f"more than the model allows ({size})"
        out.append(f"{what.format(detail=detail)}: {todo} (p = {t.p_value:.1e})")
    return out


def score_test_results(prob: Problem, x) -> list:
    """The hardware terms' score tests of :func:`_score_test_words`
    (:class:`~mems_stereo.calib.hardware_fit.TermTest`, most significant first)."""
    blocks = hf.candidate_blocks()
    return sorted(hf.score_tests(prob, x, blocks, ALPHA_FAMILY / len(blocks)),
                  key=lambda t: t.p_value)


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
