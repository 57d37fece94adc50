"""The compiled classifier against the NumPy reference: identical labels and histograms."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mems_stereo.model.system import burkard2022
from mems_stereo.pipeline.classify_kernel import (
    Pass1Histograms,
    _kernel_nolabels_py,
    _kernel_py,
    classify_and_accumulate,
)
from mems_stereo.pipeline.consistency import classify_bins
from mems_stereo.pipeline.histograms import accumulate_histograms
from mems_stereo.pipeline.intervals import interval_table


@pytest.fixture(scope="module")
def table():
    return interval_table(burkard2022())


def _random_block(rng, system, k):
    sc = system.scanner
    theta = sc.theta0 + sc.theta_mech_max * np.cos(rng.uniform(0, 2 * np.pi, k))
    # codes everywhere, plus a return-like cluster near the predicted path of each shot
    bins = rng.integers(0, system.tdc.n_bins + 1, size=(k, 1, 192)).astype(np.uint16)
    bins[rng.random(bins.shape) < 0.3] = 0
    valid = rng.random(k) > 0.1
    return bins, theta, valid


@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.integers(0, 2**32 - 1), st.integers(1, 300))
def test_fast_labels_equal_the_reference_on_snapped_angles(table, seed, k):
    rng = np.random.default_rng(seed)
    s = burkard2022()
    bins, theta, valid = _random_block(rng, s, k)
    labels, hists = classify_and_accumulate(bins, theta, valid, table, s.tdc.n_bins)
    raw, sig = hists.raw, hists.signal
    ref = classify_bins(s, bins, table.snap(theta), valid)
    np.testing.assert_array_equal(labels, ref)
    # the NumPy reference of histogram formation (only valid shots are read)
    armed = np.broadcast_to(valid[:, None, None], bins.shape)
    h = accumulate_histograms(bins, ref, s.tdc.n_bins, armed=armed)
    np.testing.assert_array_equal(raw[:, 1:], h.raw.reshape(192, -1))
    np.testing.assert_array_equal(sig[:, 1:], h.signal.reshape(192, -1))
    assert not sig[:, 0].any()
    # column 0 counts the valid empty pixel-slots
    assert raw[:, 0].sum() == int(((bins == 0) & valid[:, None, None]).sum())
    # signal detections per pixel and angle step
    angle = np.zeros((192, table.n_steps), np.int64)
    classify_and_accumulate(bins, theta, valid, table, s.tdc.n_bins,
                            Pass1Histograms(np.zeros_like(raw), np.zeros_like(sig), angle))
    kk, pp = np.nonzero(ref.reshape(k, 192) == 1)
    expect = np.zeros_like(angle)
    np.add.at(expect, (pp, table.index(theta)[kk]), 1)
    np.testing.assert_array_equal(angle, expect)


def test_compiled_kernel_equals_its_python_semantics(table, rng):
    s = burkard2022()
    bins, theta, valid = _random_block(rng, s, 64)
    rows = table.index(theta)
    rows[~valid] = -1
    table.ensure(rows)
    out = []
    for fn in (None, _kernel_py):
        lab = np.empty((64, 192), np.uint8)
        raw = np.zeros((192, 4097), np.int32)
        sig = np.zeros_like(raw)
        if fn is None:
            lab, h = classify_and_accumulate(bins, theta, valid, table, 4096)
            lab, raw, sig = lab.reshape(64, 192), h.raw, h.signal
        else:
            fn(bins.reshape(64, 192), rows, table.lo, table.hi, lab, raw, sig,
               np.zeros((192, table.n_steps), np.int64))
        out.append((lab, raw, sig))
    for a, b in zip(*out):
        np.testing.assert_array_equal(a, b)


def test_histograms_add_over_chunks(table, rng):
    s = burkard2022()
    bins, theta, valid = _random_block(rng, s, 200)
    _, h = classify_and_accumulate(bins, theta, valid, table, 4096, want_labels=False)
    raw, sig = h.raw, h.signal
    h2 = Pass1Histograms.zeros(192, 4096, table.n_steps)
    for a in range(0, 200, 37):
        classify_and_accumulate(bins[a:a + 37], theta[a:a + 37], valid[a:a + 37], table, 4096,
                                h2, want_labels=False)
    raw2, sig2 = h2.raw, h2.signal
    np.testing.assert_array_equal(raw, raw2)
    np.testing.assert_array_equal(sig, sig2)


def test_snapping_is_within_half_a_step(table, rng):
    th = burkard2022().scanner.theta0 + rng.uniform(-0.2, 0.2, 1000)
    assert np.max(np.abs(table.snap(th) - th)) <= table.step / 2 + 1e-15
    assert table.index([np.nan, 10.0]).tolist() == [-1, -1]


def test_peak_window_keys_equal_a_numpy_reference(table, rng):
    from mems_stereo.pipeline.pass2 import PeakWindows, _window_keys_py, peak_window_keys

    s = burkard2022()
    bins, theta, valid = _random_block(rng, s, 120)
    pix = np.array([5, 60, 61, 150])
    lo = np.array([1, 100, 900, 30])
    hi = np.array([4096, 800, 1500, 60])
    keys = peak_window_keys(bins, theta, valid, table, PeakWindows(pix, lo, hi, None, None),
                            4096)
    labels = classify_bins(s, bins, table.snap(theta), valid).reshape(120, -1)
    b = bins.reshape(120, -1).astype(np.int64)
    rows = table.index(theta)
    expect = []
    for k in range(120):
        for q, p in enumerate(pix):
            if labels[k, p] == 1 and lo[q] <= b[k, p] <= hi[q]:
                expect.append((q * table.n_steps + rows[k]) * 4097 + b[k, p])
    np.testing.assert_array_equal(keys, expect)
    out = np.empty(120 * 4, np.int64)
    r = rows.copy()
    r[~valid] = -1
    n = _window_keys_py(bins.reshape(120, -1), r, table.lo, table.hi, pix, lo, hi,
                        np.zeros(4, np.int64), np.full(4, table.n_steps), table.n_steps, 4097, out)
    np.testing.assert_array_equal(out[:n], keys)


def test_kernel_without_labels_counts_the_same(table, rng):
    s = burkard2022()
    bins, theta, valid = _random_block(rng, s, 50)
    rows = table.index(theta)
    rows[~valid] = -1
    table.ensure(rows)
    raw_a = np.zeros((192, 4097), np.int32)
    sig_a = np.zeros_like(raw_a)
    _kernel_nolabels_py(bins.reshape(50, 192), rows, table.lo, table.hi, raw_a, sig_a,
                        np.zeros((192, table.n_steps), np.int64))
    _, hb = classify_and_accumulate(bins, theta, valid, table, 4096, want_labels=False)
    raw_b, sig_b = hb.raw, hb.signal
    np.testing.assert_array_equal(raw_a, raw_b)
    np.testing.assert_array_equal(sig_a, sig_b)


def test_codes_above_n_bins_are_refused(table):
    from mems_stereo.errors import FormatError

    bins = np.full((2, 1, 192), 5000, np.uint16)
    with pytest.raises(FormatError, match="codes 0..4096"):
        classify_and_accumulate(bins, np.array([0.76, 0.77]), np.ones(2, bool), table, 4096)
