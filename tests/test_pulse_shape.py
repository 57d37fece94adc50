"""The pulse shape from return residuals (calib/pulse_shape.py) and from wall returns by
the first-photon law (calib/pulse_returns.py): ex-Gaussian tail against the Gaussian, on
residuals drawn from the model of mems_stereo.model.hardware.PulseModel."""

from __future__ import annotations

from dataclasses import replace

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


def _first_photons(rng, n, w, tau, m_range, shift=0.1e-9, rate=1e6):
    """Cells of the first-photon law drawn photon by photon: Poisson(m) pulse photons
    ((1 − w)·N + w·EMG around ``shift``) and background at ``rate`` from the window's
    start; the first detection inside [lo, hi] per cell (lo = WINDOW[0])."""
    from mems_stereo.calib.pulse_returns import ReturnSamples

    lo = WINDOW[0]
    m = rng.uniform(*m_range, n)
    hi = rng.uniform(6e-9, WINDOW[1], n)
    k = rng.poisson(m)
    first = lo + rng.exponential(1.0 / rate, n)
    for j in range(1, k.max() + 1):
        sel = k >= j
        t = rng.normal(shift, CORE, sel.sum())
        t += np.where(rng.random(sel.sum()) < w, rng.exponential(tau, sel.sum()), 0.0)
        first[sel] = np.minimum(first[sel], np.where(t >= lo, t, np.inf))
    keep = first <= hi
    return ReturnSamples(first[keep], m[keep], np.full(keep.sum(), rate), hi[keep], lo)


def test_first_photon_fit_undoes_pile_up():
    """At up to 2 signal photons per cell the first photon is early and the tail is
    suppressed: the first-photon law recovers the mean delay w·τ within its σ (a
    profile-likelihood interval); the plain residual fit of the same times is off by
    many of its own σ."""
    from mems_stereo.calib import pulse_returns

    rng = np.random.default_rng(12)
    data = replace(_first_photons(rng, 3000, 0.3, 2e-9, (0.2, 2.0)), core=CORE)  # as the
    fit = pulse_returns.fit_pulse_shape(data)                  # calibration's: core held
    assert fit.sigma == pytest.approx(CORE) and fit.std["sigma"] == 0.0
    lo, hi = fit.mean_delay_interval
    assert lo < fit.mean_delay < hi and fit.std["mean_delay"] == pytest.approx(0.5 * (hi - lo))
    assert abs(fit.mean_delay - 0.6e-9) < 3 * fit.std["mean_delay"]
    assert abs(fit.shift - 0.1e-9) < 3 * fit.std["shift"]
    assert fit.signal_scale == pytest.approx(1.0, abs=4 * fit.std["signal_scale"])
    plain = fit_pulse_shape(data.residual, window=WINDOW)
    assert abs(plain.mean_delay - 0.6e-9) > 5 * plain.std["mean_delay"]  # off, σ too small
