"""The calibration's damped Newton ascent (calib/solver.py) on a problem with a known answer."""

from types import SimpleNamespace

import numpy as np
import pytest
from mems_stereo.calib.solver import FitState, newton

from mems_stereo.errors import GeometryError


class Quadratic:
    """log L = −(x − 2)²; the model is undefined (GeometryError) for x > 3, as a trial
    step with harmonics so strong that the mirror turns back is.  The information 0.5
    underestimates the curvature 2, so the first full step (x = 8) leaves the model."""

    layout = SimpleNamespace(scales=np.ones(1))

    def __init__(self):
        self.raised = 0

    def loglik(self, x):
        if x[0] > 3:
            self.raised += 1
            raise GeometryError("scanner.harmonics: harmonics too strong")
        return -float((x[0] - 2.0) ** 2)

    def score(self, x):
        return self.loglik(x), np.array([-2.0 * (x[0] - 2.0)]), np.array([[0.5]])


def test_a_step_outside_the_model_is_damped_not_raised():
    prob, state = Quadratic(), FitState()
    res = newton(prob, np.zeros(1), state)
    assert prob.raised >= 1  # the undamped step did leave the model
    assert state.converged
    assert res.x[0] == pytest.approx(2.0, abs=0.02)  # closed form: the maximum at x = 2
