"""Goodness of fit, named (mems_stereo/pipeline/goodness.py): each effect injected into
synthetic residuals is named; clean residuals fail at the documented false-alarm rate."""

from __future__ import annotations

import numpy as np
import pytest

from mems_stereo.pipeline.cloud import PointCloud
from mems_stereo.pipeline.goodness import ALPHA, stereo_tof_agreement, structure_tests


def _covariates(rng, n):
    return {"phase": rng.uniform(0, 2 * np.pi, n), "pixel": rng.integers(0, 48, n),
            "code": rng.integers(200, 320, n), "signal": rng.lognormal(0.0, 1.0, n)}


@pytest.mark.parametrize("effect, name, words", [
    ("harmonic", "scan phase", "third harmonic"),
    ("direction", "scan direction", "rising and falling sweeps disagree"),
    ("pixel", "pixel", "per-pixel TDC offsets"),
    ("code", "TDC code", "code-density test"),
    ("signal", "signal level", "pulse shape"),
])
def test_each_effect_is_named(effect, name, words):
    rng = np.random.default_rng(5)
    n = 6000
    cv = _covariates(rng, n)
    ph = cv["phase"]
    inject = {"harmonic": 0.3 * np.cos(3 * ph + 0.7),
              "direction": 0.25 * -np.sign(np.sin(ph)),
              "pixel": rng.normal(0, 0.3, 48)[cv["pixel"]],
              "code": rng.normal(0, 0.4, 400)[cv["code"]],
              "signal": 0.3 * np.log(cv["signal"])}[effect]
    rep = structure_tests(rng.standard_normal(n) + inject, **cv)
    assert not rep.passed
    assert [f.name for f in rep.failed] == [name]
    assert words in rep.lines()[0]
    # the structure's size: RMS of the injected pattern (σ units); a sweep offset is
    # mostly sin φ, which the phase offset absorbs
    assert effect == "direction" or rep.failed[0].effect == pytest.approx(np.sqrt(np.mean(
        (inject - inject.mean()) ** 2)), rel=0.35)


def test_direction_difference_in_physical_units():
    rng = np.random.default_rng(6)
    n = 8000
    ph = rng.uniform(0, 2 * np.pi, n)
    d = -np.sign(np.sin(ph))
    rep = structure_tests(rng.standard_normal(n) + 0.2 * d, phase=ph, units=(0.5, "ns"))
    # the sweeps' means differ by 0.4 σ = 0.2 ns
    msg = rep.lines()[0]
    val = float(msg.split("disagree by ")[1].split(" ns")[0])
    assert val == pytest.approx(0.2, abs=0.05)


def test_clean_residuals_fail_at_the_false_alarm_rate():
    rng = np.random.default_rng(7)
    alpha, trials = 0.05, 80
    rejected = np.zeros(5)
    for _ in range(trials):
        n = 800
        rep = structure_tests(rng.standard_normal(n), **_covariates(rng, n), alpha=alpha,
                              min_effect=0.0)
        rejected += [not f.passed for f in rep.findings]
    # each test's rate is alpha within 3 binomial σ
    sd = np.sqrt(alpha * (1 - alpha) / trials)
    assert np.all(np.abs(rejected / trials - alpha) < 3 * sd + 1e-9), rejected
    # pooled over the five tests (400 draws)
    assert abs(rejected.sum() / (5 * trials) - alpha) < 3 * sd / np.sqrt(5)
    # at the default per-test alpha a clean recording passes
    assert ALPHA * 5 <= 0.005
    rep = structure_tests(rng.standard_normal(20000), **_covariates(rng, 20000))
    assert rep.passed and rep.lines() == []


def test_weighted_tests_hold_their_rate_when_the_variance_differs_by_group():
    """Scores whose variance differs between TDC codes by up to 400×, the rare codes
    the variable ones (a return cut by the TDC start, pile-up): scaled by one common
    RMS, the code test refuses clean data far above its rate (the group means' spread
    follows the groups' variance, the F test's denominator the cells'); each score over
    its own RMS with the variances as weights (weighted least squares) keeps the rate,
    and still finds a per-code shift of the working response (score / variance) of RMS
    0.4 (about 2σ of a code's mean) in 4 of 4 recordings."""
    rng = np.random.default_rng(9)
    n, codes, alpha, trials = 3000, 40, 0.01, 20
    var = np.exp(rng.uniform(np.log(0.05), np.log(20.0), codes))
    freq = (1.0 / var) / np.sum(1.0 / var)
    common = weighted = 0
    for _ in range(trials):
        code = rng.choice(codes, n, p=freq)
        v = var[code] * rng.uniform(0.5, 2.0, n)  # each score's own variance
        s = rng.standard_normal(n) * np.sqrt(v)
        rep = structure_tests(s / np.sqrt(np.mean(s * s)), code=code, alpha=alpha,
                              min_effect=0.0)
        common += not rep.passed
        rep = structure_tests(s / np.sqrt(v), code=code, weights=v / v.mean(), alpha=alpha,
                              min_effect=0.0)
        weighted += not rep.passed
    # binomial: 20 draws at 1 %: P(≥ 3) ≈ 0.1 %
    assert weighted <= 2 and common >= 15, (weighted, common)
    for _ in range(4):  # power: shift δ_c of y = s/v, i.e. s += δ_c·v
        code = rng.choice(codes, n, p=freq)
        v = var[code]
        s = rng.standard_normal(n) * np.sqrt(v) + 0.4 * rng.normal(0, 1, codes)[code] * v
        rep = structure_tests(s / np.sqrt(v), code=code, weights=v / v.mean())
        assert [f.name for f in rep.failed] == ["TDC code"]


def _cloud(rng, n, pixel_offset=0.0, scale=1.0):
    pixel = rng.integers(0, 64, n)
    r = rng.uniform(1.0, 4.0, n)
    s_st, s_tf = 0.01 * r ** 2, np.full(n, 0.3)
    st = r + s_st * rng.standard_normal(n) * scale
    tf = r + s_tf * rng.standard_normal(n) * scale + pixel_offset * rng.normal(0, 1, 64)[pixel]
    return PointCloud(np.zeros((n, 3)), {
        "range_stereo": st, "sigma_r_stereo": s_st, "range_tof": tf, "sigma_r_tof": s_tf,
        "pixel": pixel.astype(np.int32), "code": np.rint(tf / 0.05),
        "counts": rng.integers(3, 40, n).astype(np.int32)})


def test_stereo_tof_agreement():
    rng = np.random.default_rng(8)
    ok = stereo_tof_agreement(_cloud(rng, 3000))
    assert ok.warnings == () and ok.rms == pytest.approx(1.0, abs=0.05)
    wide = stereo_tof_agreement(_cloud(rng, 3000, scale=1.6))
    assert "disagree" in wide.warnings[0] and wide.rms == pytest.approx(1.6, abs=0.1)
    pix = stereo_tof_agreement(_cloud(rng, 3000, pixel_offset=0.15))
    assert any("per-pixel TDC offsets" in w for w in pix.warnings)
    # a cloud without the two ranges (another producer) is not judged
    none = stereo_tof_agreement(PointCloud(np.zeros((100, 3)), {}))
    assert none.n == 0 and none.warnings == ()
