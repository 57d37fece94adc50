"""The fusion's and the matched filter's per-frame fast paths give the same bits as their
NumPy forms: the first-photon band sums (:mod:`mems_stereo.physics.first_photon_kernel`),
the band's likelihood over the steps with shots (:func:`band_log_miss`) and the matched
filter's valid boxes (:func:`mems_stereo.pipeline.matched_boxes.valid_boxes`)."""

import numpy as np
import pytest

from mems_stereo.physics import first_photon as fp
from mems_stereo.pipeline import matched_boxes as mb


def _bits(a):
    return np.asarray(a, np.float64).view(np.int64)


def _band(rng, Q, B, zero_share):
    """(f, n) (Q, B): spot shares (most 0, as a frame's padding) and valid shots."""
    f = rng.random((Q, B)) ** 3 * 0.5
    f[rng.random((Q, B)) < zero_share] = 0.0
    n = rng.integers(0, 5, (Q, B)).astype(np.float64)
    n[(f == 0) & (rng.random((Q, B)) < 0.7)] = 0.0
    return f, n


@pytest.mark.parametrize(("Q", "B", "zero_share"), [(16, 400, 0.85), (3, 7, 0.5),
                                                    (5, 300, 0.0), (1, 1, 0.0)])
def test_band_sums_kernel_equals_numpy(monkeypatch, Q, B, zero_share):
    pytest.importorskip("numba")
    rng = np.random.default_rng(Q * 1000 + B)
    f, n = _band(rng, Q, B, zero_share)
    a = rng.normal(-3.0, 3.0, Q)
    assert fp.band_kernel() is not None
    fast = fp._band_sums(f, n, a)
    monkeypatch.setattr(fp, "band_kernel", lambda: None)
    ref = fp._band_sums(f, n, a)
    for x, y in zip(fast, ref):
        assert x.shape == (Q, fp.MU_GRID.size)
        assert np.array_equal(_bits(x), _bits(y))
    # independent: one peak's band-weighted mean delay at one μ0, summed directly
    q, j = Q // 2, fp.MU_GRID.size // 2
    w = n[q] * -np.expm1(-fp.MU_GRID[j] * f[q])
    d, _ = fp._table_lookup(np.full(B, a[q]), np.log(np.clip(fp.MU_GRID[j] * f[q], 1e-4,
                                                             fp.MU_MAX)))
    if w.sum() > 0:
        assert fast[0][q, j] == pytest.approx(np.sum(w * d) / w.sum(), rel=1e-9, abs=1e-12)


def test_band_log_miss_equals_einsum():
    rng = np.random.default_rng(8)
    for Q, B in [(16, 500), (2, 3), (1, 130)]:
        f, n = _band(rng, Q, B, 0.6)
        got = fp.band_log_miss(n, f)
        want = np.einsum("qb,qbj->qj", n, fp.log_miss_probability(f))
        assert np.array_equal(_bits(got), _bits(want))
        # independent: the log-probability that none of a step's shots fires, summed
        p = np.minimum(fp.OUTLIER_PROBABILITY + (1 - fp.OUTLIER_PROBABILITY)
                       * (1 - np.exp(-fp.MU_GRID[None, None, :] * f[..., None])), 1 - 1e-12)
        assert np.allclose(got, np.sum(n[..., None] * np.log(1 - p), axis=1), rtol=1e-9)


@pytest.mark.parametrize("cut", [(True, True), (False, True), (True, False), (False, False)])
def test_valid_boxes_kernel_equals_numpy(monkeypatch, cut):
    pytest.importorskip("numba")
    rng = np.random.default_rng(3)
    for n, m, h, w in [(84, 73, 51, 49), (20, 9, 5, 5), (4, 30, 7, 3)]:
        D = rng.poisson(0.3, (n, m)).astype(np.float64)
        B = rng.random((n, m)) * 0.4
        fast = mb.valid_boxes(D, B, h, w, 3, cut)
        with monkeypatch.context() as mp:
            mp.setattr(mb, "compiled_kernel", lambda *a, **k: None)
            ref = mb.valid_boxes(D, B, h, w, 3, cut)
        for x, y in zip(fast, ref):
            assert x.shape == y.shape and np.array_equal(x, y)
        # independent: a valid box holds at least 3 counts, more than its background,
        # and lies whole in the steps
        flat = fast[2]
        i, j = np.divmod(flat, m)
        assert np.all((i >= h // 2) & (i < n - h // 2))
        assert np.all(fast[0].ravel()[flat] >= 3)
        assert np.all(fast[0].ravel()[flat] > fast[1].ravel()[flat])
