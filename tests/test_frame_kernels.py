"""The per-frame fast paths give the same bits as their reference forms: the compiled
moving sum and background-rate sums (:mod:`mems_stereo.physics.background`), the
spot-share functions evaluated only where the share is not 0
(:mod:`mems_stereo.physics.first_photon`), the matched filter's box sums and count grids
and the acceptance counts of the peak search."""

import numpy as np
import pytest

from mems_stereo.errors import FormatError
from mems_stereo.physics import background as bg
from mems_stereo.physics import first_photon as fp


def _bits(a):
    a = np.asarray(a, np.float64)
    return a.view(np.int64)


@pytest.mark.parametrize(("shape", "width"), [((40, 700), 15), ((3, 40), 41), ((2, 3, 900), 9),
                                              ((5000,), 1)])
def test_moving_sum_compiled_equals_numpy(monkeypatch, shape, width):
    pytest.importorskip("numba")
    rng = np.random.default_rng(5)
    h = rng.poisson(0.4, shape) * rng.random(shape)  # sparse, non-integer counts
    monkeypatch.setattr(bg, "COMPILED_SUM_ENTRIES", 1)
    fast = bg.moving_sum(h, width)
    monkeypatch.setattr(bg, "COMPILED_SUM_ENTRIES", 1 << 62)
    ref = bg.moving_sum(h, width)
    assert fast.shape == ref.shape == shape
    assert np.array_equal(_bits(fast), _bits(ref))
    # independent: the centred window sum, zeros beyond the ends
    flat = h.reshape(-1, shape[-1])
    i = shape[-1] // 2
    direct = flat[:, max(0, i - width // 2):i + width // 2 + 1].sum(axis=1)
    assert np.allclose(fast.reshape(-1, shape[-1])[:, i], direct, rtol=1e-12)


def _firing_direct(f):
    e = fp.OUTLIER_PROBABILITY
    pf = -np.expm1(-fp.MU_GRID * np.asarray(f, np.float64)[..., None])
    return np.minimum(e + (1 - e) * pf, 1.0 - 1e-12)


def test_share_functions_skip_zero_shares_with_same_bits():
    rng = np.random.default_rng(3)
    f = np.where(rng.random((7, 30)) < 0.8, 0.0, rng.random((7, 30)))  # mostly padding
    assert np.array_equal(_bits(fp.firing_probability(f)), _bits(_firing_direct(f)))
    assert np.array_equal(_bits(fp.log_miss_probability(f)),
                          _bits(np.log1p(-_firing_direct(f))))
    assert np.array_equal(_bits(fp.firing_probability(np.zeros((2, 3)))),
                          _bits(_firing_direct(np.zeros((2, 3)))))
    # the delay: its (Q, J, B) functions evaluated where μ0·f is not 0 only
    n = np.where(f > 0, rng.integers(1, 6, f.shape), 0).astype(np.float64)
    ll = rng.normal(size=(7, fp.MU_GRID.size))
    tau = rng.uniform(-2e-9, 30e-9, 7)
    got = fp.first_photon_delay(ll, f, n, tau, 0.5e-9, mu_factor=2.0)
    mu_s = fp.MU_GRID[None, :, None] * f[:, None, :]
    w = n[:, None, :] * -np.expm1(-mu_s)
    w = w / np.maximum(w.sum(axis=2, keepdims=True), 1e-300)
    d, v = fp._table_lookup((-tau / 0.5e-9)[:, None, None], np.log(np.clip(mu_s, 1e-4,
                                                                            fp.MU_MAX)))
    dj = np.sum(w * d, axis=2)
    post = np.exp(ll - ll.max(axis=1, keepdims=True))
    post /= post.sum(axis=1, keepdims=True)
    assert np.allclose(got[0], np.sum(post * dj, axis=1) * 0.5e-9, rtol=1e-12, atol=0)
    assert np.all(np.isfinite(got[1])) and np.all(got[3] > 0)


@pytest.mark.parametrize(("shape", "h", "w"), [((2, 153, 40), 7, 9), ((2, 600, 6), 3, 5),
                                               ((1, 4, 3), 9, 11), ((2, 1, 1), 1, 1)])
def test_box_sums_kernel_equals_numpy(monkeypatch, shape, h, w):
    pytest.importorskip("numba")
    from mems_stereo.pipeline import matched_boxes as mb

    rng = np.random.default_rng(11)
    A = rng.poisson(0.5, shape) * rng.random(shape)
    fast = mb.box_sums(A, h, w)
    monkeypatch.setattr(mb, "compiled_if_loaded", lambda f: None)
    ref = mb.box_sums(A, h, w)
    assert np.array_equal(_bits(fast), _bits(ref))
    # independent: one box by direct summation, zeros beyond the edges
    q, i, j = shape[0] - 1, shape[1] // 2, shape[2] // 2
    box = A[q, max(0, i - h // 2):i + h // 2 + 1, max(0, j - w // 2):j + w // 2 + 1].sum()
    assert fast[q, i, j] == pytest.approx(box, rel=1e-12, abs=1e-12)


def test_box_grid_counts_add_entries_in_order():
    from mems_stereo.pipeline.matched_boxes import BoxGrid

    rng = np.random.default_rng(2)
    ds, dc, cnt = rng.integers(0, 60, 400), rng.integers(0, 25, 400), rng.random(400) * 3
    g = BoxGrid(ds, dc, cnt, np.zeros(60), np.zeros(60), np.zeros(60), 0, 1, -0.01, 25)
    for j0, j1, k0, k1, fs, fc in [(0, 60, 0, 25, 1, 1), (7, 41, 3, 20, 4, 3),
                                   (0, 60, 0, 25, 7, 5)]:
        D = g.counts(j0, j1, k0, k1, fs, fc)
        ref = np.zeros((-(-(j1 - j0) // fs), -(-(k1 - k0) // fc)))
        for a, b, c in zip(ds, dc, cnt):  # one by one, in the entries' order
            if j0 <= a < j1 and k0 <= b < k1:
                ref[(a - j0) // fs, (b - k0) // fc] += c
        assert np.array_equal(_bits(D), _bits(ref))


def test_acceptance_counts_kernel_equals_difference_array(monkeypatch):
    pytest.importorskip("numba")
    from mems_stereo.model.system import burkard2022
    from mems_stereo.pipeline import acceptance as pk
    from mems_stereo.pipeline.intervals import interval_table

    system = burkard2022()
    table = interval_table(system, 0.997)
    rng = np.random.default_rng(4)
    n_per_step = np.zeros(table.n_steps, np.int64)
    steps = rng.choice(np.arange(table.n_steps // 3, table.n_steps // 2), 40, replace=False)
    n_per_step[steps] = rng.integers(1, 8, steps.size)
    for pixels in (None, np.array([5, 0, 191, 77])):
        fast = pk.acceptance_counts(system, None, None, 0.997, table=table,
                                    n_per_step=n_per_step, pixels=pixels)
        with monkeypatch.context() as m:
            m.setattr(pk, "compiled_if_loaded", lambda f: None)
            ref = pk.acceptance_counts(system, None, None, 0.997, table=table,
                                       n_per_step=n_per_step, pixels=pixels)
        assert fast.dtype == np.int64 and np.array_equal(fast, ref)
        # independent: code by code, the valid shots of the steps accepting it
        p = 77 if pixels is None else 191
        i = p if pixels is None else 2
        lo, hi = table.lo[steps, p].astype(int), table.hi[steps, p].astype(int)
        codes = np.arange(1, system.tdc.n_bins + 1)
        want = ((codes[:, None] >= lo) & (codes[:, None] <= hi)) @ n_per_step[steps]
        assert np.array_equal(fast[i], want)


def test_pairwise_plan_covers_the_values_once():
    for n in (1, 7, 128, 129, 300, 4096, 4101):
        plan = bg.pairwise_plan(n)
        blocks = plan[plan[:, 0] == 0]
        assert blocks[:, 2].sum() == n and np.all(blocks[:, 2] <= 128)
        assert np.array_equal(blocks[:, 1], np.cumsum(blocks[:, 2]) - blocks[:, 2])
        assert np.count_nonzero(plan[:, 0] == 1) == len(blocks) - 1  # joins: a binary tree


@pytest.mark.parametrize("n_bins", [5, 129, 300, 4096, 4101])
def test_background_rate_from_noise_kernel_equals_reference(monkeypatch, n_bins):
    pytest.importorskip("numba")
    import sys

    rng = np.random.default_rng(n_bins)
    raw = rng.poisson(0.3, (30, n_bins))
    noise = rng.binomial(raw, 0.8)
    n_valid, bw = 2 * n_bins + 50, 65e-12  # the sum of the trials is not an integer: its
    # rounding depends on the order of the additions (NumPy's pairwise order)
    acc = rng.integers(0, n_valid // 2, raw.shape)
    fast = bg.background_rate_from_noise(noise, raw, acc, n_valid, bw)
    with monkeypatch.context() as m:
        m.delitem(sys.modules, "numba")  # the NumPy reference
        ref = bg.background_rate_from_noise(noise, raw, acc, n_valid, bw)
    assert np.array_equal(_bits(fast), _bits(ref))
    # independent: the ML estimate of one pixel from its sums
    armed = n_valid - (np.cumsum(raw[4]) - raw[4])
    p = noise[4].sum() / np.sum(armed * (1 - acc[4] / n_valid))
    assert fast[4] == pytest.approx(-np.log1p(-p) / bw, rel=1e-11)
    with pytest.raises(FormatError):  # refused as the reference refuses it
        bg.background_rate_from_noise(noise, raw * 0 + n_valid, acc, n_valid, bw)
