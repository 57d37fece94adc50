"""Histogram formation, pile-up MLE, Coates, filter, threshold, peaks, ranges."""

from __future__ import annotations

import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from oracles import detect_peaks, peak_centroid
from scipy.optimize import minimize_scalar

from mems_stereo.errors import FormatError
from mems_stereo.model.tdc import path_length
from mems_stereo.physics.background import (
    armed_shots,
    background_rate_mle,
    coates_correction,
    expected_background,
    poisson_threshold,
)
from mems_stereo.pipeline.histograms import (
    Histograms,
    accumulate_histograms,
    moving_average,
)

DT = 312.5e-12
NB = 4096


def first_photon_codes(rng, n_shots, n_pix, rate, signal_code=None, signal_prob=0.0,
                       signal_sigma_bins=0.0, n_bins=NB, bin_width=DT):
    """Codes of the first photon per shot: exponential background ∧ an optional return."""
    t = rng.exponential(1.0 / rate, size=(n_shots, n_pix)) if rate > 0 else \
        np.full((n_shots, n_pix), np.inf)
    if signal_code is not None:
        hit = rng.random((n_shots, n_pix)) < signal_prob
        ts = ((signal_code - 0.5) + signal_sigma_bins * rng.standard_normal((n_shots, n_pix))) \
            * bin_width
        t = np.where(hit & (ts < t) & (ts >= 0), ts, t)
    code = np.floor(t / bin_width).astype(np.float64) + 1
    code[~np.isfinite(t) | (code > n_bins)] = 0
    return code.astype(np.uint16)


# --------------------------------------------------------------------------- formation
def reference_histograms(bins, labels, n_bins):
    K, H, W = bins.shape
    raw = np.zeros((H, W, n_bins), np.int64)
    sig = np.zeros_like(raw)
    noi = np.zeros_like(raw)
    for k in range(K):
        for y in range(H):
            for x in range(W):
                c = int(bins[k, y, x])
                if c:
                    raw[y, x, c - 1] += 1
                    if labels is not None and labels[k, y, x] == 1:
                        sig[y, x, c - 1] += 1
                    if labels is not None and labels[k, y, x] == 2:
                        noi[y, x, c - 1] += 1
    return raw, sig, noi


def test_accumulate_matches_loop_reference(rng):
    bins = rng.integers(0, 9, size=(40, 2, 5)).astype(np.uint16)
    labels = np.where(bins > 0, rng.integers(0, 3, size=bins.shape), 0).astype(np.uint8)
    h = accumulate_histograms(bins, labels, n_bins=8)
    raw, sig, noi = reference_histograms(bins, labels, 8)
    np.testing.assert_array_equal(h.raw, raw)
    np.testing.assert_array_equal(h.signal, sig)
    np.testing.assert_array_equal(h.noise, noi)
    np.testing.assert_array_equal(h.n_shots, np.full((2, 5), 40))
    assert h.raw.sum() == np.count_nonzero(bins)


def test_accumulate_armed_mask(rng):
    bins = rng.integers(0, 5, size=(30, 1, 4)).astype(np.uint16)
    armed = rng.random(bins.shape) < 0.6
    h = accumulate_histograms(bins, None, n_bins=4, armed=armed)
    raw, _, _ = reference_histograms(np.where(armed, bins, 0), None, 4)
    np.testing.assert_array_equal(h.raw, raw)
    np.testing.assert_array_equal(h.n_shots, armed.sum(0))


@settings(max_examples=25, deadline=None)
@given(st.lists(st.integers(0, 50), min_size=1, max_size=4), st.integers(0, 2**31 - 1))
def test_chunks_add_to_whole(cuts, seed):
    g = np.random.default_rng(seed)
    bins = g.integers(0, 7, size=(50, 2, 3)).astype(np.uint16)
    labels = g.integers(0, 3, size=bins.shape).astype(np.uint8)
    edges = [0, *sorted(cuts), 50]
    total = Histograms.zeros((2, 3), 6)
    for a, b in zip(edges[:-1], edges[1:]):
        total = total + accumulate_histograms(bins[a:b], labels[a:b], n_bins=6)
    whole = accumulate_histograms(bins, labels, n_bins=6)
    for name in ("raw", "signal", "noise", "n_shots"):
        np.testing.assert_array_equal(getattr(total, name), getattr(whole, name))


def test_accumulate_rejects_bad_input():
    with pytest.raises(FormatError, match="0..8"):
        accumulate_histograms(np.full((2, 1, 3), 9, np.uint16), n_bins=8)
    with pytest.raises(FormatError, match="K, H, W"):
        accumulate_histograms(np.zeros((2, 3), np.uint16), n_bins=8)
    with pytest.raises(FormatError, match="labels"):
        accumulate_histograms(np.zeros((2, 1, 3), np.uint16), np.zeros((2, 3), np.uint8), 8)


def test_accumulate_dense_frame_is_fast(rng):
    bins = rng.integers(1, NB + 1, size=(3200, 1, 192)).astype(np.uint16)
    labels = rng.integers(1, 3, size=bins.shape).astype(np.uint8)
    t0 = time.perf_counter()
    h = accumulate_histograms(bins, labels, n_bins=NB)
    dt = time.perf_counter() - t0
    assert h.raw.sum() == bins.size
    assert dt < 1.0, f"accumulation took {dt:.3f} s"


# --------------------------------------------------------------------------- pile-up MLE
@pytest.mark.parametrize("rate", [1e5, 6e6])
def test_background_mle_recovers_rate_under_pileup(rng, rate):
    K = 3000
    codes = first_photon_codes(rng, K, 8, rate)
    h = accumulate_histograms(codes[:, None, :], n_bins=NB)
    est, std = background_rate_mle(h.raw, h.n_shots, DT, return_std=True)
    # 8 pixels: each within 4 of its own σ, pooled mean within 1 %
    assert np.all(np.abs(est - rate) < 4 * std)
    assert abs(est.mean() / rate - 1) < 0.01 + 3 * std.mean() / rate / np.sqrt(8)
    naive = h.raw.sum(-1) / (K * NB * DT)
    if rate == 6e6:
        assert np.all(naive < 0.2 * rate)       # the naive count/time estimate is badly biased


def test_background_mle_is_the_likelihood_maximum(rng):
    codes = first_photon_codes(rng, 500, 1, 2e6, signal_code=900, signal_prob=0.3)
    h = accumulate_histograms(codes[:, None, :], n_bins=NB)
    excl = np.zeros(NB, bool)
    excl[860:940] = True
    est = background_rate_mle(h.raw[0, 0], h.n_shots[0, 0], DT, exclude=excl)
    nj = armed_shots(h.raw[0, 0], 500)
    use = ~excl

    def nll(lam):
        p = -np.expm1(-lam * DT)
        return -(h.raw[0, 0][use] * np.log(p) + (nj - h.raw[0, 0])[use] * np.log1p(-p)).sum()

    num = minimize_scalar(nll, bounds=(1e4, 2e7), method="bounded",
                          options={"xatol": 1.0}).x
    assert est == pytest.approx(num, rel=1e-4)


def test_background_mle_excluding_the_return_is_unbiased(rng):
    rate = 6e6
    codes = first_photon_codes(rng, 4000, 6, rate, signal_code=200, signal_prob=0.5,
                               signal_sigma_bins=10)
    h = accumulate_histograms(codes[:, None, :], n_bins=NB)
    excl = np.zeros(NB, bool)
    excl[150:250] = True
    est, std = background_rate_mle(h.raw, h.n_shots, DT, exclude=excl, return_std=True)
    assert np.all(np.abs(est - rate) < 4 * std)
    biased = background_rate_mle(h.raw, h.n_shots, DT)
    assert np.all(biased > rate + 4 * std)     # including the return biases it up


def test_background_mle_from_noise_histogram_needs_raw_for_arming(rng):
    # the return is labelled signal; N alone would wrongly count armed shots
    rate = 3e6
    K = 4000
    t_bg = rng.exponential(1 / rate, size=(K, 4))
    hit = rng.random((K, 4)) < 0.6
    t_sig = (100 - 0.5) * DT
    first_sig = hit & (t_sig < t_bg)
    t = np.where(first_sig, t_sig, t_bg)
    code = np.floor(t / DT).astype(np.int64) + 1
    code[code > NB] = 0
    labels = np.where(code > 0, np.where(first_sig, 1, 2), 0).astype(np.uint8)
    h = accumulate_histograms(code.astype(np.uint16)[:, None, :], labels[:, None, :], NB)
    excl = np.zeros(NB, bool)
    excl[95:105] = True
    est, std = background_rate_mle(h.noise, h.n_shots, DT, exclude=excl, raw=h.raw,
                                   return_std=True)
    assert np.all(np.abs(est - rate) < 4 * std)
    wrong = background_rate_mle(h.noise, h.n_shots, DT, exclude=excl)
    assert np.all(wrong < rate - 4 * std)


def test_coates_correction_flattens_pileup(rng):
    rate = 6e6
    K = 20000
    codes = first_photon_codes(rng, K, 1, rate, n_bins=1024)
    h = accumulate_histograms(codes[:, None, :], n_bins=1024)
    mu = coates_correction(h.raw, h.n_shots)[0, 0]
    nj = armed_shots(h.raw, h.n_shots)[0, 0]
    good = nj > 2000
    # per bin the expected photons per shot are λΔ: the raw histogram decays, Coates' is flat
    assert np.polyfit(np.arange(1024)[good], mu[good], 1)[0] == pytest.approx(0, abs=2e-6)
    assert np.average(mu[good], weights=nj[good]) == pytest.approx(rate * DT, rel=0.02)
    raw = h.raw[0, 0].astype(float)
    assert raw[:50].mean() > 3 * raw[-50:].mean()          # e^{-λΔ·1000} ≈ 0.15
    # one pooled bin: Coates equals the MLE
    one = coates_correction(h.raw.sum(-1, keepdims=True), h.n_shots)[..., 0]
    mle = background_rate_mle(h.raw.sum(-1, keepdims=True), h.n_shots, 1024 * DT) * 1024 * DT
    assert one == pytest.approx(mle)


def test_expected_background_matches_simulation(rng):
    rate, K = 4e6, 5000
    e = expected_background(rate, K, DT, NB)
    assert e.sum() == pytest.approx(K * -np.expm1(-rate * NB * DT))
    codes = first_photon_codes(rng, K, 1, rate)
    h = accumulate_histograms(codes[:, None, :], n_bins=NB).raw[0, 0]
    # compare in 32 coarse blocks with a chi-square-like bound
    eb = e.reshape(128, 32).sum(1)
    hb = h.reshape(128, 32).sum(1)
    m = eb > 20
    z = (hb[m] - eb[m]) / np.sqrt(eb[m])
    assert np.mean(z ** 2) < 2.0


def test_armed_shots_rejects_too_many_detections():
    with pytest.raises(FormatError, match="more detections than shots"):
        armed_shots(np.array([3, 3]), 5)


# --------------------------------------------------------------------------- filter, threshold
def test_moving_average_matches_convolution(rng):
    h = rng.poisson(5, size=(3, 50)).astype(float)
    w = 7
    ma = moving_average(h, w)
    ref = np.array([np.convolve(r, np.ones(w) / w, mode="same") for r in h])
    np.testing.assert_allclose(ma[:, 3:-3], ref[:, 3:-3])
    np.testing.assert_allclose(ma[:, 0], h[:, :4].mean(1))        # ends: mean of what exists
    with pytest.raises(FormatError):
        moving_average(h, 4)


def test_poisson_threshold_false_alarm_rate(rng):
    mu = 2.0
    w = 5
    pfa = 1e-2
    bg = np.full(400, mu)
    thr = poisson_threshold(bg, w, pfa)
    sims = rng.poisson(mu, size=(2000, 400))
    ma = moving_average(sims, w)
    frac = (ma[:, 10:-10] > thr[10:-10]).mean()
    assert frac <= pfa
    assert frac > pfa / 4              # the quantile is tight, not merely safe


# --------------------------------------------------------------------------- peaks
def test_detect_peaks_finds_two_returns():
    x = np.arange(1, 513)
    hist = np.stack([
        5 + 80 * np.exp(-0.5 * ((x - 100) / 8) ** 2) + 40 * np.exp(-0.5 * ((x - 300) / 8) ** 2),
        5 + 60 * np.exp(-0.5 * ((x - 420) / 8) ** 2),
    ])
    p = detect_peaks(hist, threshold=20, min_separation=24)
    assert [(int(i[0]), int(c)) for i, c in zip(p.index, p.code)] == [(0, 100), (0, 300),
                                                                      (1, 420)]
    code, value = p.strongest((2,))
    np.testing.assert_array_equal(code, [100, 420])
    one = detect_peaks(hist, threshold=20, min_separation=24, max_peaks=1)
    np.testing.assert_array_equal(one.code, [100, 420])
    none = detect_peaks(hist, threshold=200, min_separation=24)
    assert len(none) == 0


def test_detect_peaks_flat_top_and_pixel_threshold():
    h = np.array([[0, 3, 3, 3, 0, 0, 0, 0], [0, 0, 0, 0, 0, 2, 0, 0]], float)
    p = detect_peaks(h, threshold=np.array([1.0, 2.5]), min_separation=2)
    np.testing.assert_array_equal(p.code, [2])          # first bin of the flat top; pixel 1 below


def test_threshold_rule_detects_return_in_floodlight(rng):
    # 6 MHz background (pile-up: the background decays by e^-0.75 before the return)
    # and a weak return at code 400: the pile-up-aware Poisson threshold finds only it.
    rate, K = 6e6, 3200
    codes = first_photon_codes(rng, K, 1, rate, signal_code=400, signal_prob=0.15,
                               signal_sigma_bins=8)
    h = accumulate_histograms(codes[:, None, :], n_bins=NB)
    excl = np.zeros(NB, bool)
    excl[330:470] = True
    lam = background_rate_mle(h.raw, h.n_shots, DT, exclude=excl)
    bg = expected_background(lam, h.n_shots, DT, NB)
    w = 25
    thr = poisson_threshold(bg, w, 1e-5)
    ma = moving_average(h.raw, w)
    p = detect_peaks(ma, thr, min_separation=48)
    assert len(p) >= 1
    assert np.all(np.abs(p.code - 400) <= 16)          # no false peak in the pile-up
    assert abs(int(p.strongest((1, 1))[0][0, 0]) - 400) <= 8


# --------------------------------------------------------------------------- ranges
def test_peak_centroid_against_monte_carlo(rng):
    centre = 200.3            # return centre in units of bins: t = centre·Δ
    n_sig, bg = 400, 2.0
    cens = []
    stds = []
    for _ in range(200):
        codes = np.floor(centre + 6 * rng.standard_normal(n_sig)).astype(int) + 1
        h = np.bincount(codes - 1, minlength=512)[:512] + rng.poisson(bg, 512)
        c, s, sw = peak_centroid(h[None], np.array([200]), 24, background=np.array([bg]))
        cens.append(c[0])
        stds.append(s[0])
    cens = np.array(cens)
    # code N spans [N−1, N)·Δ, so the centroid code is the centre + ½ (FORMAT: t = (N − ½)Δ)
    assert cens.mean() - 0.5 == pytest.approx(centre, abs=0.1)
    assert path_length(cens.mean(), DT) == pytest.approx(299704644.5 * centre * DT, rel=1e-3)
    assert np.mean(stds) == pytest.approx(cens.std(), rel=0.25)


def test_peak_centroid_no_peak_is_nan():
    c, s, sw = peak_centroid(np.ones((2, 10)), np.array([0, 5]), 2)
    assert np.isnan(c[0]) and c[1] == pytest.approx(5.0)


def test_path_length_follows_format():
    c = 299704644.5
    assert path_length(1, DT) == pytest.approx(c * DT / 2)
    assert path_length(101, DT, offset=1e-9) == pytest.approx(c * (100.5 * DT - 1e-9))
    assert np.isnan(path_length(0, DT))


@pytest.mark.parametrize("key,value,field", [("format", "mems-stereo/labels", "attrs/format"),
                                             ("version", 2, "attrs/version"),
                                             ("version", "1", "attrs/version")])
def test_histogram_file_format_and_version_checked(tmp_path, key, value, field):
    # the histogram reader and the recording reader share one format/version check
    import h5py

    from mems_stereo.io.histograms import read_histograms, write_histograms

    h = np.zeros((1, 4, 8), np.int32)
    p = write_histograms(tmp_path / "h.h5", h, h, h)
    assert read_histograms(p).raw.shape == (1, 4, 8)
    with h5py.File(p, "r+") as f:
        f.attrs[key] = value
    with pytest.raises(FormatError) as e:
        read_histograms(p)
    assert e.value.field == field and repr(value)[:20] in str(e.value)
