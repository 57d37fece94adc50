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


def test_band_log_miss_equals_einsum(monkeypatch):
    # NumPy's form (the compiled one: test_search_kernels.py)
    monkeypatch.setattr(fp, "firing_kernels", lambda: None)
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


def test_segment_dot_is_one_product_per_segment():
    from mems_stereo.physics.spot import segment_dot

    rng = np.random.default_rng(3)
    d, p = rng.normal(size=(300, 3)), rng.normal(size=3)
    cuts = np.array([0, 0, 17, 18, 150, 300])
    got = segment_dot(d, p, cuts)
    for a, b in zip(cuts[:-1], cuts[1:]):
        assert np.array_equal(_bits(got[a:b]), _bits(d[a:b] @ p))
    assert np.array_equal(_bits(segment_dot(d, p)), _bits(d @ p))
    assert np.allclose(got, np.einsum("ni,i->n", d, p), rtol=1e-13, atol=1e-15)


def test_band_log_miss_rows_adds_each_rows_entries_in_order():
    rng = np.random.default_rng(4)
    f, n = _band(rng, 6, 40, 0.5)
    qi, bi = np.nonzero(n)
    # the rows' entries interleaved with another block's: each row still adds its own
    got = fp.band_log_miss_rows(9, qi + 3, n[qi, bi], f[qi, bi])
    assert np.array_equal(_bits(got[3:]), _bits(fp.band_log_miss(n, f)))
    assert not np.any(got[:3])


def test_block_band_steps_equal_band_steps_of_each_block():
    from types import SimpleNamespace

    from mems_stereo.model.system import burkard2022
    from mems_stereo.pipeline.first_photon_correction import band_steps, block_band_steps
    from mems_stereo.pipeline.fusion import _acceptance
    from mems_stereo.pipeline.run import run_table

    # a scanner off the axis: the scan directions' products d·p round by their place
    system = burkard2022().with_params(baseline_x=-0.1237, baseline_y=0.0113,
                                       baseline_z=0.0071)
    table = run_table(system, None)
    rng = np.random.default_rng(5)
    Q, S = 40, table.n_steps
    lo = rng.integers(50, S - 200, Q)
    hi = lo + rng.integers(-1, 40, Q)  # some peaks without a band (hi < lo)
    peaks = SimpleNamespace(row=np.zeros(Q, np.int64), col=rng.integers(0, 192, Q),
                            step_lo=lo - 5, step_hi=hi + 5)
    acc = SimpleNamespace(
        Q=Q, system=system, rows=peaks.row, cols=peaks.col, spot_sigma=None,
        band=(lo, hi), centre=np.where(rng.random(Q) < 0.1, np.nan, rng.uniform(0.5, 6, Q)),
        shots_per_step=rng.integers(0, 4, S), step_grid=(table.theta_min, table.step),
        step_window=(peaks.step_lo, peaks.step_hi), accept=_acceptance(system, table, peaks))
    idx = np.flatnonzero(rng.random(Q) < 0.8)
    cut = np.searchsorted(idx, np.arange(0, Q + 16, 16))
    got = block_band_steps(acc, idx, cut)
    assert [(a, b) for a, b, _ in got.blocks] == [(int(a), int(b)) for a, b in
                                                   zip(cut[:-1], cut[1:]) if b > a]
    for a, b, band in got.blocks:
        want = band_steps(acc, idx[a:b], full=True)
        for x, y in zip((band.steps, band.shots, band.spot, band.spot_full),
                        (want.steps, want.shots, want.spot, want.spot_full)):
            assert x.shape == y.shape and np.array_equal(_bits(x), _bits(y))
        assert np.array_equal(_bits(got.log_miss[a:b]),
                              _bits(fp.band_log_miss(want.shots, want.spot)))
    assert np.any(got.log_miss < 0)  # (not all bands empty: the comparison means something)


def test_row_local_evaluations_keep_each_rows_bits():
    # the variants of a central difference, and several stereo evaluations, laid end to
    # end in one call: every row is its own, so the bits of one call per variant
    from mems_stereo.geometry.uncertainty import (
        DIFF_STEPS,
        INPUTS,
        as_inputs,
        central_differences,
        spreads_for,
        stereo_point_est,
    )
    from mems_stereo.model.system import burkard2022
    from mems_stereo.pipeline.peak_geometry import stereo_points

    system = burkard2022().with_params(baseline_x=-0.1237, baseline_y=0.0113,
                                       baseline_z=0.0071)
    rng = np.random.default_rng(6)
    n = 257
    u, v = rng.uniform(0, 191, n), np.zeros(n)
    th = system.scanner.theta0 + rng.uniform(-0.3, 0.3, n)
    th[:3] = np.nan
    inp = as_inputs(u, v, np.zeros(n), th)
    x0, J0 = central_differences(stereo_point_est, system, inp, DIFF_STEPS, INPUTS)
    x1, J1 = central_differences(stereo_point_est, system, inp, DIFF_STEPS, INPUTS,
                                 row_local=True)
    assert np.array_equal(_bits(x0), _bits(x1)) and np.array_equal(_bits(J0), _bits(J1))
    assert np.isnan(x1[:3]).all() and np.isfinite(x1).all(axis=1).sum() > n // 2
    parts = [(u, v, th), (u[:10] + 0.5, v[:10], th[:10]), (u[:0], v[:0], th[:0])]
    for got, (a, b, c) in zip(stereo_points(system, parts), parts):
        assert np.array_equal(_bits(got), _bits(stereo_point_est(system, a, b, np.zeros(a.size),
                                                                 c)))
    # independent: the stereo point lies on its scanner ray p + s·d(θ)
    from mems_stereo.model.scanner import scan_direction

    x = stereo_points(system, parts)[0]
    ok = np.isfinite(x).all(axis=1)
    off = np.cross(x[ok] - np.asarray(system.scanner.position), scan_direction(th[ok],
                                                                               system.scanner))
    assert np.all(np.linalg.norm(off, axis=1) < 1e-9 * np.linalg.norm(x[ok], axis=1))
    assert not spreads_for(system).param_names  # (the propagation without parameters)
