"""The frames' compiled fusion loops against their NumPy forms on seeded random inputs:
the first-photon band loops (:mod:`mems_stereo.physics.first_photon_band_kernel`) and
the points' shot times (:mod:`mems_stereo.pipeline.point_times_kernel`).

Tolerances: the kernels add their sums in another order than NumPy (sequential, not
pairwise) and take ``ln(μ0·f)`` as ``ln μ0 + ln f``; a sum of at most B terms then
differs by about B·ε times the sum of the terms' magnitudes (B ≤ 400 here: 5e-14), so
1e-11 relative to the scale of the terms.  Integer counts are equal."""

from types import SimpleNamespace

import numpy as np
import pytest

from mems_stereo.physics import first_photon as fp
from mems_stereo.pipeline import first_photon_correction as fpc

REL = 1e-11


def _band(rng, Q, B, zero_share):
    """(f, n, f_full) (Q, B): spot shares where shots count (most 0, as a frame's
    padding), valid shots, spot shares everywhere."""
    f_full = rng.random((Q, B)) ** 3 * 0.6
    n = rng.integers(0, 5, (Q, B)).astype(np.float64)
    n[rng.random((Q, B)) < zero_share] = 0.0
    return np.where(n > 0, f_full, 0.0), n, f_full


def _starts(Q, B):
    return np.arange(Q + 1, dtype=np.int64) * B


@pytest.mark.parametrize(("Q", "B", "zero_share"), [(16, 400, 0.85), (3, 7, 0.5),
                                                    (5, 300, 0.0), (2, 1, 1.0)])
def test_band_likelihood_moments_equal_numpy(monkeypatch, Q, B, zero_share):
    pytest.importorskip("numba")
    from mems_stereo.physics.first_photon_band_kernel import band_likelihood_moments, kernels

    rng = np.random.default_rng(Q * 100 + B)
    f, n, _ = _band(rng, Q, B, zero_share)
    a = rng.normal(-3.0, 3.0, Q)
    log_miss, dj, vj = band_likelihood_moments(
        kernels()[0], _starts(Q, B), n.ravel(), f.ravel(), fp.MU_GRID,
        fp.OUTLIER_PROBABILITY, a, fp.first_photon_table())
    monkeypatch.setattr(fp, "band_kernel", lambda: None)
    monkeypatch.setattr(fp, "firing_kernels", lambda: None)
    ref_miss = fp.band_log_miss(n, f)
    ref_d, ref_v = fp._band_sums(f, n, a)
    scale = np.sum(n, axis=1)[:, None] * 30.0  # |ln(1 − P)| ≤ ln 10¹² ≈ 28 per shot
    assert np.all(np.abs(log_miss - ref_miss) <= REL * np.maximum(scale, 1.0))
    # the moments are in pulse σ (|d| ≲ 6, v ≲ 1): 1e-11 absolute
    assert np.allclose(dj, ref_d, rtol=0, atol=REL * 10)
    assert np.allclose(vj, ref_v, rtol=0, atol=REL * 40)
    # independent: one peak's mean delay at one μ0, the weighted mean written out
    q, j = Q // 2, fp.MU_GRID.size // 2
    w = n[q] * -np.expm1(-fp.MU_GRID[j] * f[q])
    d, _ = fp._table_lookup(np.full(B, a[q]), np.log(np.clip(fp.MU_GRID[j] * f[q], 1e-4,
                                                             fp.MU_MAX)))
    want = np.sum(w * d) / w.sum() if w.sum() > 0 else 0.0
    assert dj[q, j] == pytest.approx(want, rel=1e-9, abs=1e-12)


@pytest.mark.parametrize(("Q", "B", "zero_share"), [(16, 400, 0.85), (4, 9, 0.3),
                                                    (3, 50, 1.0)])
def test_band_figures_equal_numpy(Q, B, zero_share):
    pytest.importorskip("numba")
    from mems_stereo.physics.first_photon_band_kernel import band_figures, kernels

    rng = np.random.default_rng(7 * Q + B)
    f, n, f_full = _band(rng, Q, B, zero_share)
    steps = rng.integers(0, 5000, Q)[:, None] + np.arange(B)[None, :]
    mu = np.exp(rng.uniform(np.log(0.01), np.log(fp.MU_MAX), Q))
    theta_bar = steps[:, B // 3] + rng.normal(0.0, 2.0, Q)
    theta_bar[0] = np.nan  # a peak without inliers
    top = fpc.MU_BEYOND_GRID * fp.MU_MAX
    bias, ab, k_top = band_figures(kernels()[1], _starts(Q, B), steps.ravel(), n.ravel(),
                                   f.ravel(), f_full.ravel(), mu, theta_bar, top,
                                   fpc.BINOMIAL_MIN_SHOTS)
    # the bias is a difference of two mean steps (values of thousands): 1e-11 steps
    ref_bias = fpc.mean_angle_bias(steps, n, f, f_full, mu)
    assert np.allclose(bias, ref_bias, rtol=0, atol=1e-11 * steps.max())
    assert np.allclose(ab, fpc.angle_binomial_factor(steps, n, f, mu, theta_bar),
                       rtol=0, atol=REL)
    assert ab[0] == 1.0
    ref_top = np.sum(n * -np.expm1(-top * f), axis=1)
    assert np.allclose(k_top, ref_top, rtol=REL, atol=0)
    # independent: a band of one step with shots has its mean firing step there
    one_f, one_n = np.zeros(B), np.zeros(B)
    one_f[B // 2], one_n[B // 2] = 0.3, 2.0
    b1, _, k1 = band_figures(kernels()[1], _starts(1, B), steps[0], one_n, one_f, one_f,
                             mu[:1], theta_bar[1:2], top, fpc.BINOMIAL_MIN_SHOTS)
    assert b1[0] == 0.0 and k1[0] == pytest.approx(2.0 * -np.expm1(-top * 0.3))


def test_point_times_kernel_equals_numpy(monkeypatch):
    pytest.importorskip("numba")
    from mems_stereo.pipeline import point_times_kernel
    from mems_stereo.pipeline.frames import FrameShots, point_times

    rng = np.random.default_rng(31)
    K, H, W, S, n_bins = 300, 2, 9, 40, 60
    bins = np.where(rng.random((K, H, W)) < 0.6, rng.integers(1, n_bins + 1, (K, H, W)),
                    0).astype(np.uint16)
    times = 0.5 + np.cumsum(rng.uniform(1e-6, 2e-6, K))
    steps = rng.integers(-1, S, K)  # −1: a shot without a table row
    lo = rng.integers(1, 20, (S, H * W)).astype(np.uint16)
    hi = (lo + rng.integers(0, 40, (S, H * W))).astype(np.uint16)
    table = SimpleNamespace(lo=lo, hi=hi, system=SimpleNamespace(
        receiver=SimpleNamespace(width=W)))
    P = 25
    s_lo = rng.integers(0, S, P)
    c_lo = rng.integers(1, 30, P)
    peaks = SimpleNamespace(row=rng.integers(0, H, P), col=rng.integers(0, W, P),
                            code_lo=c_lo, code_hi=c_lo + rng.integers(0, 40, P),
                            step_lo=s_lo, step_hi=s_lo + rng.integers(0, 20, P))
    band = rng.permutation(P)[:20]
    shots = FrameShots(times, bins, None, np.zeros(2), np.zeros(2, np.uint8))
    got = point_times(shots, steps, peaks, band, table)
    monkeypatch.setattr(point_times_kernel, "compiled_if_loaded", lambda f: None)
    ref = point_times(shots, steps, peaks, band, table)
    assert np.allclose(got, ref, rtol=1e-14, atol=0)
    # independent: one point's shots written out
    i = 3
    q = band[i]
    r, c = peaks.row[q], peaks.col[q]
    sel = [k for k in range(K) if steps[k] >= 0 and peaks.step_lo[q] <= steps[k]
           <= peaks.step_hi[q] and peaks.code_lo[q] <= bins[k, r, c] <= peaks.code_hi[q]
           and lo[steps[k], r * W + c] <= bins[k, r, c] <= hi[steps[k], r * W + c]]
    want = times[sel].mean() if sel else times.mean()
    assert got[i] == pytest.approx(want, rel=1e-13)


def test_step_directions_same_bits_as_scan_direction():
    from mems_stereo.model.scanner import scan_direction
    from mems_stereo.model.system import preset
    from mems_stereo.physics.spot import step_directions

    scanner = preset("burkard2022").scanner
    t0, dt = float(scanner.theta0) - 0.01, 1.3e-5
    rng = np.random.default_rng(5)
    for steps in (rng.integers(-40, 900, 500), rng.integers(2000, 2100, (7, 3)).ravel(),
                  np.array([-50, 3000])):  # the table of steps grows to hold them all
        got = step_directions(scanner, t0, dt, steps)
        want = scan_direction(t0 + steps * dt, scanner)
        assert np.array_equal(got.view(np.int64), want.view(np.int64))
    # independent: the reflection of a unit laser direction is a unit vector
    assert np.allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-12)


def test_log_odds_kernel_near_numpy(monkeypatch):
    """The frames' log-odds (``ln(1 − P)`` in closed form up to CLOSED_BELOW) against
    NumPy's form: where P is rounded near 1 NumPy's ``log1p(−P)`` is off the exact value
    by up to 2.2e-16 / (1 − P), ≤ 2.5e-13 below CLOSED_BELOW (above it both are NumPy's
    form); the closed form is exact (independent check on ``ln(1 − P)`` itself)."""
    pytest.importorskip("numba")
    from mems_stereo.physics.first_photon_band_kernel import CLOSED_BELOW, kernels, log_odds

    rng = np.random.default_rng(12)
    f = np.concatenate([rng.random(300) ** 3 * 0.9, [0.0, 1e-300, 1.0, 0.07]])
    got = log_odds(kernels()[2], f, fp.MU_GRID, fp.OUTLIER_PROBABILITY)
    monkeypatch.setattr(fp, "firing_kernels", lambda: None)
    ref = fp.detection_log_odds(f)
    x = f[:, None] * fp.MU_GRID[None, :]
    e = fp.OUTLIER_PROBABILITY
    one_minus_p = np.maximum((1 - e) * np.exp(-x), 1e-12)
    bound = 4.4e-16 / one_minus_p + 1e-15 * np.abs(ref)
    assert np.all(np.abs(got - ref) <= bound)
    small = x <= CLOSED_BELOW
    assert np.all(np.abs(got - ref)[small] <= 3e-13 + 1e-15 * np.abs(ref)[small])
    # independent: ln P − ln(1 − P) with 1 − P = (1 − e)·exp(−x), exact in long double
    xl = x.astype(np.longdouble)
    p_l = e + (1 - e) * -np.expm1(-xl)
    want = np.log(p_l) - (np.log1p(np.longdouble(-e)) - xl)
    assert np.allclose(got[small], want[small].astype(np.float64), rtol=1e-14, atol=1e-14)


def test_frame_fusion_in_peak_blocks_equals_the_whole(monkeypatch):
    """A frame's compiled fusion of peaks cut into blocks at multiples of FP_BLOCK (as
    the fusion in blocks and the frames split across workers cut them) gives the
    whole's cloud bit for bit: each peak's loops are its own and the posterior is
    taken per block of FP_BLOCK peaks."""
    pytest.importorskip("numba")
    from pathlib import Path

    from mems_stereo.pipeline import block_fusion
    from mems_stereo.pipeline.classify_kernel import compiled_blocks
    from mems_stereo.pipeline.frame_bias import every_bias_removed
    from mems_stereo.pipeline.run import process_recording

    path = Path(__file__).resolve().parents[1] / "samples" / "room.h5"
    with compiled_blocks(), every_bias_removed():
        whole = process_recording(path)
        monkeypatch.setattr(block_fusion, "FUSE_ENTRIES", 150)  # 4 blocks of ~600 keys
        parts = process_recording(path)
    assert len(whole.peaks.row) > 3 * fpc.FP_BLOCK
    assert np.array_equal(parts.cloud.points.view(np.int64),
                          whole.cloud.points.view(np.int64))
    for k, v in whole.cloud.attributes.items():
        assert np.array_equal(np.asarray(parts.cloud.attributes[k]).view(np.uint8),
                              np.asarray(v).view(np.uint8)), k
