"""The pulse shape from return residuals (calib/pulse_shape.py): ex-Gaussian tail against
the Gaussian, on residuals drawn from the model of mems_stereo.model.hardware.PulseModel."""

from __future__ import annotations

import numpy as np
import pytest
from mems_stereo.calib.pulse_shape import fit_pulse_shape

from mems_stereo.errors import ShapeError

CORE = 0.4e-9
WINDOW = (-4e-9, 16e-9)


def _residuals(rng, n, w, tau, shift=0.1e-9, background=0.02):
    """(1 − w)·N(shift, CORE) + w·EMG(shift, CORE, τ), plus uniform background."""
    x = rng.normal(shift, CORE, n)
    tail = rng.random(n) < w
    x[tail] += rng.exponential(tau, tail.sum())
    x = np.concatenate([x, rng.uniform(*WINDOW, int(background * n))])
    return x[(x >= WINDOW[0]) & (x <= WINDOW[1])]


def test_tail_recovered_with_sigma():
    rng = np.random.default_rng(7)
    fit = fit_pulse_shape(_residuals(rng, 6000, 0.3, 2e-9), window=WINDOW)
    assert fit.tail_significant
    for name, true in (("tail_fraction", 0.3), ("tail_decay", 2e-9), ("sigma", CORE),
                       ("shift", 0.1e-9), ("mean_delay", 0.6e-9)):
        val = getattr(fit, name)
        assert abs(val - true) < 4 * fit.std[name], name
    # the Gaussian-only fit is wider and much less likely
    assert fit.gaussian_sigma > 1.2 * CORE and fit.loglik - fit.loglik_gaussian > 100
    # the density is normalised and the model's pulse carries the σ
    x = np.linspace(-5e-9, 40e-9, 20001)
    assert np.trapezoid(fit.pdf(x), x) == pytest.approx(1.0, abs=2e-3)
    pm = fit.to_pulse_model()
    assert pm.model == "ex-gaussian" and pm.tail_decay_std == fit.std["tail_decay"]
    assert "tail significant" in fit.summary()


def test_gaussian_pulse_needs_no_tail():
    rng = np.random.default_rng(8)
    fit = fit_pulse_shape(_residuals(rng, 6000, 0.0, 1e-9), window=WINDOW)
    assert not fit.tail_significant
    assert fit.gaussian_sigma == pytest.approx(CORE, rel=0.05)
    assert abs(fit.mean_delay) < 0.05e-9


def test_quantisation_is_removed_from_the_core():
    rng = np.random.default_rng(9)
    q = 0.5e-9
    x = _residuals(rng, 6000, 0.0, 1e-9, background=0.0)
    o = rng.random(x.size) * q  # a code's time less a continuous prediction
    x = (np.floor((x + o) / q) + 0.5) * q - o
    fit = fit_pulse_shape(x, window=WINDOW, quantum=q)
    assert fit.gaussian_sigma == pytest.approx(CORE, rel=0.06)


def test_too_few_residuals_named():
    with pytest.raises(ShapeError, match="at least"):
        fit_pulse_shape(np.zeros(10))
