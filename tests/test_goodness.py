"""Goodness of fit, named (mems_stereo/pipeline/goodness.py): each effect injected into
synthetic residuals is named; clean residuals fail at the documented false-alarm rate."""

from __future__ import annotations

import numpy as np
import pytest

from mems_stereo.pipeline.cloud import PointCloud
from mems_stereo.pipeline.goodness import ALPHA, Weights, stereo_tof_agreement, structure_tests


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


def test_blocks_are_tested_by_exact_least_squares():
    """Each block's extra sum of squares and dof are those of two weighted least-squares
    fits of the explicit design (numpy lstsq, rank by SVD): with the block and
    without it; the nuisance (constant, cos φ, sin φ, pixel quadratic, code cubic) is
    collinear with the group means, which the dof count once."""
    rng = np.random.default_rng(12)
    n = 700
    cv = _covariates(rng, n)
    cv["pixel"] = rng.integers(0, 12, n)
    cv["code"] = rng.integers(200, 215, n)
    w = rng.uniform(0.2, 3.0, n)
    r = rng.standard_normal(n)
    rep = structure_tests(r, **cv, weights=Weights(w, 1.0, 0.0), min_effect=0.0)
    ph, sw = cv["phase"], np.sqrt(w)

    def std(v):
        return (v - v.mean()) / v.std()

    p, c = std(cv["pixel"]), std(cv["code"])
    ls = std(np.log(cv["signal"]))
    blocks = {
        "scan phase": [f(k * ph) for k in range(2, 6) for f in (np.cos, np.sin)],
        "scan direction": [-np.sign(np.sin(ph)), -np.sign(np.sin(ph)) * np.cos(ph)],
        "signal level": [ls, ls * ls],
        "pixel": [(cv["pixel"] == k).astype(float) for k in range(12)],
        "TDC code": [(cv["code"] == k).astype(float) for k in range(200, 215)],
        "nuisance": [np.ones(n), np.cos(ph), np.sin(ph), p, p * p, c, c * c, c ** 3]}

    def fit(names):
        X = np.column_stack([col for k in names for col in blocks[k]]) * sw[:, None]
        beta, _, rank, _ = np.linalg.lstsq(X, r, rcond=None)
        return float(np.sum((r - X @ beta) ** 2)), rank

    rss, rank = fit(list(blocks))
    assert [f.name for f in rep.findings] == list(blocks)[:-1]
    for f in rep.findings:
        rss_k, rank_k = fit([k for k in blocks if k != f.name])
        assert f.dof == rank - rank_k
        assert f.statistic * f.dof == pytest.approx(rss_k - rss, rel=1e-6)
    assert [f.dof for f in rep.findings] == [8, 2, 2, 11 - 2, 14 - 3]


def _photon_scores(rng, n, tiny=0.5):
    """First-photon-like scores: each cell expects m photons (a share ``tiny`` of the
    cells 10⁻³, the rest 0.02–2), its score is the sum of a unit normal per photon
    (mean 0, variance m): normalised r = s/√m is heavy-tailed where m is small."""
    m = np.where(rng.random(n) < tiny, 1e-3, rng.uniform(0.02, 2.0, n))
    s = rng.standard_normal(n) * np.sqrt(rng.poisson(m))
    return s / np.sqrt(m), m


def test_known_variance_holds_the_rate_on_heavy_tailed_scores():
    """Scores over their expected RMS have variance 1 by the model, but when rare large
    scores carry their mean square the residuals' own mean square is mostly below 1
    (its median far under its mean): an F test over it refuses clean scores far above
    its rate; the χ² test with the model's variance (:class:`Weights`) keeps it."""
    rng = np.random.default_rng(13)
    alpha, trials, n = 0.01, 60, 1500
    f_test = chi2 = 0
    for _ in range(trials):
        r, m = _photon_scores(rng, n)
        ph = rng.uniform(0, 2 * np.pi, n)
        f_test += not structure_tests(r, phase=ph, weights=m, alpha=alpha,
                                      min_effect=0.0).passed
        chi2 += not structure_tests(r, phase=ph, weights=Weights(m, 1.0), alpha=alpha,
                                    min_effect=0.0).passed
    # two tests at 1 % each: about 2 % of 60; binomial P(≥ 5) ≈ 0.8 %
    assert chi2 <= 4 and f_test >= 10, (chi2, f_test)
