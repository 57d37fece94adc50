"""The code-density test (calib/code_density.py): first-photon background with known code
widths, signal windows, pixel groups; tables checked against a per-shot loop."""

from __future__ import annotations

import numpy as np
import pytest
from mems_stereo.calib.code_density import (
    code_edges,
    code_widths,
    first_photon_tables,
    widths_from_tables,
)

from mems_stereo.errors import ShapeError


def _widths(rng, m, periodic=0.3, random=0.05, period=8):
    k = np.arange(m)
    w = 1.0 + periodic * np.sin(2 * np.pi * k / period) + random * rng.standard_normal(m)
    return w / w.mean()


def _first_photons(rng, widths, rate, n_shots, signal=None):
    """First-photon codes (K, P) of a TDC with ``widths`` (LSB) for background
    ``rate`` (P,) per LSB; ``signal`` (K, P) extra photon times (LSB) or None."""
    edges = code_edges(widths, 1.0)
    t = rng.exponential(1.0 / np.asarray(rate), size=(n_shots, len(rate)))
    if signal is not None:
        t = np.minimum(t, signal)
    return np.where(t < edges[-1], np.searchsorted(edges, t, side="right"), 0)


def _tables_by_loop(codes, n_codes, lo, hi):
    """Independent derivation: walk each shot and pixel code by code."""
    K, P = codes.shape
    ev = np.zeros((P, n_codes + 1), dtype=np.int64)
    ar = np.zeros((P, n_codes + 1), dtype=np.int64)
    for k in range(K):
        for p in range(P):
            c = codes[k, p]
            for n in range(1, n_codes + 1):
                if lo[k, p] <= n <= hi[k, p]:
                    if c == n:
                        break  # fired inside the window: censored
                    continue
                ar[p, n] += 1
                if c == n:
                    ev[p, n] += 1
                    break
    return ev, ar


def test_tables_match_a_per_shot_loop():
    rng = np.random.default_rng(4)
    n_codes = 12
    codes = rng.integers(0, n_codes + 1, size=(60, 3))
    lo = rng.integers(1, n_codes + 1, size=(60, 3))
    hi = lo + rng.integers(-2, 4, size=(60, 3))  # some empty windows (lo > hi)
    ev, ar = first_photon_tables(codes, n_codes, (lo, hi))
    ev0, ar0 = _tables_by_loop(codes, n_codes, lo, np.minimum(hi, n_codes))
    np.testing.assert_array_equal(ev[:, 1:], ev0[:, 1:])
    np.testing.assert_array_equal(ar[:, 1:], ar0[:, 1:])


def test_widths_recovered_within_their_sigma_despite_signal():
    rng = np.random.default_rng(11)
    m, K, P = 96, 12000, 12
    w = _widths(rng, m)
    rate = rng.uniform(0.004, 0.015, P)  # pixels of unequal background
    centre = rng.integers(8, m - 8, size=(K, 1))
    sig = np.where(rng.random((K, P)) < 0.6,
                   code_edges(w, 1.0)[centre] + rng.normal(0, 0.8, (K, P)), np.inf)
    codes = _first_photons(rng, w, rate, K, sig)
    est = code_widths(codes, m, window=(centre - 4, centre + 4))
    pull = (est.width[0] - w) / est.width_sigma[0]
    assert 0.8 < pull.std() < 1.2 and np.abs(pull).max() < 4.5
    # the plain estimator's σ is Poisson: w/√n
    plain = code_widths(codes, m, window=(centre - 4, centre + 4), structured=False)
    np.testing.assert_allclose(plain.width_sigma[0], plain.width[0] / np.sqrt(plain.counts[0]))
    pull = (plain.width[0] - w) / plain.width_sigma[0]
    assert 0.8 < pull.std() < 1.2 and np.abs(pull).max() < 4.5
    # the pixels' rates per mean-width code, from independent draws
    np.testing.assert_allclose(est.rate, rate, rtol=0.05)
    # INL is the running sum of the DNL and closes at 0 (widths have mean 1)
    np.testing.assert_allclose(est.inl[0], np.cumsum(est.dnl[0]))
    assert abs(est.inl[0, -1]) < 1e-9 and est.inl_sigma[0, -1] < 1e-9
    # without the windows the returns bias the codes they fall in
    raw = code_widths(codes, m)
    assert np.sqrt(np.mean((raw.width[0] - w) ** 2)) > 3 * np.sqrt(np.mean((est.width[0] - w) ** 2))


def test_equal_widths_give_dnl_and_inl_within_sigma():
    rng = np.random.default_rng(2)
    m = 64
    codes = _first_photons(rng, np.ones(m), np.full(8, 0.01), 8000)
    est = code_widths(codes.reshape(8000, 2, 4), m, structured=False)  # (K, H, W) accepted
    assert np.abs(est.dnl / est.width_sigma).max() < 4.5
    inner = est.inl_sigma[0] > 0
    assert np.abs(est.inl[0][inner] / est.inl_sigma[0][inner]).max() < 4.5
    # 2 % RMS needs ≈ 2500 detections per code: σ follows 1/√n
    assert est.width_sigma.mean() == pytest.approx(1 / np.sqrt(est.counts.mean()), rel=0.05)
    # the structured estimator sees no pattern and no random part: widths near 1
    st = code_widths(codes, m)
    assert np.abs(st.dnl / st.width_sigma).max() < 4.5
    assert np.sqrt(np.mean(st.dnl ** 2)) < 0.5 * np.sqrt(np.mean(est.dnl ** 2))


def test_pixel_groups_have_their_own_widths():
    rng = np.random.default_rng(3)
    m, K = 48, 10000
    wa, wb = _widths(rng, m, 0.3, 0.0, 6), _widths(rng, m, 0.0, 0.1)
    ca = _first_photons(rng, wa, np.full(4, 0.012), K)
    cb = _first_photons(rng, wb, np.full(4, 0.012), K)
    est = code_widths(np.hstack([ca, cb]), m, groups=[0] * 4 + [1] * 4)
    assert est.width.shape == (2, m)
    for g, w in enumerate((wa, wb)):
        assert np.abs((est.width[g] - w) / est.width_sigma[g]).max() < 4.5


def test_bad_shapes_are_named():
    with pytest.raises(ShapeError, match="codes"):
        code_widths(np.zeros(10, dtype=int), 16)
    with pytest.raises(ShapeError, match="codes"):
        code_widths(np.full((4, 2), 20), 16)
    with pytest.raises(ShapeError, match="groups"):
        code_widths(np.zeros((4, 2), dtype=int), 16, groups=[0, 1, 2])


def test_calibration_cells_use_the_measured_code_centres():
    """With code widths the calibration's cells read each code's centre
    (mems_stereo.model.tdc.code_centres), without them (N − ½)·bin_width."""
    from mems_stereo.calib.association import cells_near_track
    from mems_stereo.calib.problem import WallData

    from mems_stereo.model.hardware import TDC
    from mems_stereo.model.tdc import code_centres

    rng = np.random.default_rng(3)
    bins = rng.integers(0, 64, (20, 1, 8)).astype(np.uint16)
    w = WallData(np.zeros(20), bins, np.full((1, 8), 1e5), 1e-9)
    pred = np.tile([10e-9, 3.0, 0.0, 0.0], (20, 1))
    ok = np.ones(20, bool)
    c0 = cells_near_track(w, pred, ok, 2, 1.0, 0.0, False)
    code = bins[c0.shot, 0, c0.col.astype(int)].astype(np.int64)
    fired = code > 0
    np.testing.assert_allclose(c0.t[fired], (code[fired] - 0.5) * 1e-9)
    widths = 1.0 + 0.3 * np.sin(np.arange(64) * 2 * np.pi / 16)
    tdc = TDC(1e-9, 64, code_widths=widths)
    w.code_centres = code_centres(tdc)
    c1 = cells_near_track(w, pred, ok, 2, 1.0, 0.0, False)
    expect = 1e-9 * (np.concatenate([[0.0], np.cumsum(widths)])[code - 1] + widths[code - 1] / 2)
    np.testing.assert_allclose(c1.t[fired], expect[fired])
    assert np.isnan(c1.t[~fired]).all()


def _multinomial_tables(rng, widths, rate, shots):
    """First-photon tables of equal-rate pixels drawn from their exact law: each
    pixel's codes are multinomial (code edges e: exp(−r·e_{N−1}) − exp(−r·e_N))."""
    surv = np.exp(-rate * code_edges(widths, 1.0))
    p = np.append(surv[:-1] - surv[1:], surv[-1])
    ev = np.zeros((4, widths.size + 1), dtype=np.int64)
    for i in range(4):
        ev[i, 1:] = rng.multinomial(shots, p)[:-1]
    ar = np.zeros_like(ev)
    ar[:, 1:] = shots - np.cumsum(ev[:, :-1], axis=1)[:, : widths.size]
    return ev, ar


@pytest.mark.parametrize("random", [0.02, 0.05])
def test_structured_widths_reach_the_bayes_bound(random):
    """Periodic DNL + a random part: the structured estimator's error is the Bayes
    bound τσ/√(τ² + σ²) of the random part (σ Poisson), its pulls have std ≈ 1, and
    the plain estimator's error is σ."""
    rng = np.random.default_rng(21)
    m = 1024
    w = _widths(rng, m, periodic=0.25, random=random, period=32)
    ev, ar = _multinomial_tables(rng, w, 1.0 / m, 200000)   # ≈ 500 per code
    est = widths_from_tables(ev, ar)
    plain = widths_from_tables(ev, ar, structured=False)
    sig = np.sqrt(np.mean(plain.width_sigma[0] ** 2))
    tau = np.std(w - (1.0 + 0.25 * np.sin(2 * np.pi * np.arange(m) / 32)) / w.mean() * 1.0)
    bound = tau * sig / np.hypot(tau, sig)
    rms = np.sqrt(np.mean((est.width[0] - w) ** 2))
    assert rms == pytest.approx(bound, rel=0.15)
    assert np.sqrt(np.mean((plain.width[0] - w) ** 2)) == pytest.approx(sig, rel=0.1)
    assert 0.85 < np.std((est.width[0] - w) / est.width_sigma[0]) < 1.15
    assert est.random_rms[0] == pytest.approx(tau, rel=0.25)
    # the periodic model is the sine: one Fourier component
    np.testing.assert_allclose(est.periodic[0], 1.0 + 0.25 * np.sin(2 * np.pi * np.arange(m) / 32)
                               / w.mean(), atol=4 * sig * np.sqrt(3.0 / m))


def test_structured_widths_keep_a_defect_code_plain():
    """A code far off the periodic pattern (a defect, not the Gaussian random part)
    keeps its plain estimate and Poisson σ."""
    rng = np.random.default_rng(5)
    m = 512
    w = _widths(rng, m, periodic=0.2, random=0.01, period=16)
    w[100] *= 2.0
    w = w / w.mean()
    ev, ar = _multinomial_tables(rng, w, 1.0 / m, 100000)
    est = widths_from_tables(ev, ar)
    plain = widths_from_tables(ev, ar, structured=False)
    assert est.width[0, 100] == pytest.approx(plain.width[0, 100], rel=0.01)  # mean-1 scale
    assert est.width_sigma[0, 100] == pytest.approx(plain.width_sigma[0, 100], rel=0.05)
    assert abs(est.width[0, 100] - w[100]) < 4 * est.width_sigma[0, 100]
