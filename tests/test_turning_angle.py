"""The angle of a footprint the scan's turning point cuts (mems_stereo.pipeline.turning_angle).

Checked against a footprint of known position: a Gaussian spot profile over integer
angle steps, shots bunching towards a turning step beyond which there are none (the
arcsine density of a sinusoidal scan), firings 1 − exp(−μ f).  The expected mean
firing angle is computed here from the true profile; the solver gets the profile about
a misjudged centre and must find the true one.
"""

from __future__ import annotations

import numpy as np

from mems_stereo.pipeline.turning_angle import TURNING_MIN_SLOPE, solve_shift

STEPS = np.arange(0, 240)
WIDTH = 12.0  # steps, the footprint's σ
MU = 0.8
TURN = 104  # the last step the shots reach


def profile(centre: float) -> np.ndarray:
    """(B,) the spot's share of the pixel at each step, centred at ``centre`` steps."""
    return 0.8 * np.exp(-0.5 * ((STEPS - centre) / WIDTH) ** 2)


def shots(turn: int = TURN) -> np.ndarray:
    """(B,) valid shots per step: arcsine density ∝ 1/√(turn + 1 − s) up to ``turn``."""
    n = np.zeros(STEPS.size)
    s = STEPS <= turn
    n[s] = np.rint(20.0 / np.sqrt(turn + 1.0 - STEPS[s]))
    return n


def expected_mean(n: np.ndarray, f: np.ndarray) -> float:
    """Σ N p s / Σ N p, p = 1 − exp(−μ f)."""
    p = 1.0 - np.exp(-MU * f)
    return float(np.sum(n * p * STEPS) / np.sum(n * p))


def test_the_solved_angle_is_the_footprints_own_where_the_subtraction_is_not():
    """The footprint centred at 100.3, 3.7 steps before the turning step, its profile
    given about 96.3 (the centre range misjudged): the solved angle is 100.3 to 0.05
    step; the mean angle less the expected bias ``em − tc`` at the given profile is
    off by more than 2 steps (the mean angle follows the footprint a third as much)."""
    c = 100.3
    n = shots()
    em_obs = expected_mean(n, profile(c))
    given = profile(c - 4.0)
    tc, slope, _ = solve_shift(STEPS, n, given, MU, em_obs, 40.0)
    assert abs(tc - c) < 0.05
    p = 1.0 - np.exp(-MU * given)
    bias = expected_mean(n, given) - float(np.sum(p * STEPS) / np.sum(p))
    assert abs(em_obs - bias - c) > 2.0
    assert TURNING_MIN_SLOPE < slope < 0.7


def test_the_slope_is_the_mean_angles_change_with_the_footprint():
    """dem/dδ at the solution against a central difference of the expected mean over
    the true profile moved by ±0.5 step; 1 where the shots cover the whole footprint
    evenly (no turning point within reach)."""
    c = 100.3
    n = shots()
    _, slope, _ = solve_shift(STEPS, n, profile(c), MU, expected_mean(n, profile(c)), 40.0)
    d = expected_mean(n, profile(c + 0.5)) - expected_mean(n, profile(c - 0.5))
    assert abs(slope - d) < 0.02 * d
    even = np.ones(STEPS.size)
    _, slope_even, _ = solve_shift(STEPS, even, profile(c), MU,
                                   expected_mean(even, profile(c)), 40.0)
    assert abs(slope_even - 1.0) < 1e-3


def test_the_variance_is_that_of_binomial_firings_given_the_shots():
    """The mean firing angle's variance against 20,000 draws of binomial firings at the
    true profile (seeded): within 5 % (the draws' own spread of a variance is 1 %)."""
    c = 100.3
    n = shots()
    f = profile(c)
    _, _, var = solve_shift(STEPS, n, f, MU, expected_mean(n, f), 40.0)
    rng = np.random.default_rng(7)
    k = rng.binomial(n.astype(np.int64), 1.0 - np.exp(-MU * f), size=(20000, STEPS.size))
    em = (k @ STEPS) / k.sum(axis=1)
    assert abs(np.var(em) / var - 1.0) < 0.05


def test_a_mean_angle_no_footprint_gives_is_not_solved():
    """A mean angle beyond every expected mean within reach (past the turning step)
    has no solution."""
    n = shots()
    assert solve_shift(STEPS, n, profile(100.3), MU, TURN + 5.0, 40.0) is None
