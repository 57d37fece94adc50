"""Background inside a peak's inlier codes (pipeline.window_background)."""

import numpy as np
import pytest

from mems_stereo.pipeline.window_background import inlier_codes, window_background


def test_inlier_codes_find_the_crossings_of_monotone_margins():
    rng = np.random.default_rng(5)
    G = 400
    a = rng.integers(1, 200, G).astype(float)
    b = a + rng.integers(0, 4000, G)
    slope = rng.uniform(0.01, 0.2, G)  # range per code (m), slightly curved below
    curve = rng.uniform(0.0, 2e-6, G)
    centre = rng.uniform(-50, 500, G) * slope + a * slope
    bound = rng.uniform(0.5, 4.0, G)

    def rng_of(g, c):
        return slope[g] * c + curve[g] * c ** 2

    def margins(g, c):
        r = rng_of(g, c)
        return r - (centre[g] - bound[g]), centre[g] + bound[g] - r

    c1, c2 = inlier_codes(margins, a, b)
    # the exact interval, code by code
    n_ok = 0
    for g in range(G):
        c = np.arange(a[g], b[g] + 1)
        inside = np.abs(rng_of(np.full(c.size, g), c) - centre[g]) <= bound[g]
        if not inside.any():
            assert np.ceil(c1[g]) > np.floor(c2[g])
            continue
        n_ok += 1
        assert np.ceil(c1[g] - 1e-6) == pytest.approx(c[inside][0], abs=1)
        assert np.floor(c2[g] + 1e-6) == pytest.approx(c[inside][-1], abs=1)
    assert n_ok > 100


def test_inlier_codes_keep_the_interval_where_a_margin_is_nan():
    a, b = np.array([10.0, 10.0]), np.array([500.0, 500.0])

    def margins(g, c):
        f = np.where(g == 0, np.nan, c - 100.0)
        return f, 300.0 - c

    c1, c2 = inlier_codes(margins, a, b)
    assert (c1[0], c2[0]) == (10.0, 500.0)
    assert c1[1] == pytest.approx(100.0, abs=0.5) and c2[1] == pytest.approx(300.0, abs=0.5)


def test_background_over_a_sub_window_is_the_recorded_one():
    """A faint return under strong background in a wide accepted interval: the
    expected background over the inlier codes [a2, b2] (all detections of the
    step passed) matches the background detections recorded there (Monte-Carlo
    of first photons: background hazard h per code, a Gaussian return)."""
    rng = np.random.default_rng(11)
    n_shots, lo, hi = 400, 1, 4096
    bw, lam = 3.125e-10, 5.4e6
    h = -np.expm1(-lam * bw)
    a2, b2 = 120, 240
    trials, est, rec = 300, [], []
    for _ in range(trials):
        # first background photon (geometric) and the return (20 % of shots, code ~179)
        t_bg = rng.geometric(h, n_shots)
        t_sig = np.where(rng.random(n_shots) < 0.2, np.rint(rng.normal(179, 20, n_shots)),
                         np.inf)
        first = np.minimum(t_bg, t_sig)
        ok = (first >= lo) & (first <= hi)
        code, cnt = np.unique(first[ok].astype(np.int64), return_counts=True)
        is_bg = (t_bg < t_sig) & ok
        rec.append(np.sum(is_bg & (first >= a2) & (first <= b2)))
        g = np.zeros(code.size, np.int64)
        one = np.ones(code.size)
        _, bg, _ = window_background(g, code, cnt, a2 * one, b2 * one, n_shots * one, lo * one,
                                     lam * one, bw)
        est.append(bg.sum())
    est, rec = np.mean(est), np.mean(rec)
    # the estimate is exact in expectation: within 3 standard errors of the mean
    se = np.sqrt(rec / trials)
    assert abs(est - rec) < 3 * se + 0.5, (est, rec)


def _band_trials(shots, rng, trials=300):
    """Mean background expected over a 200-step band by :func:`window_background`,
    with the steps without a detection added (:func:`background_entries.with_empty_steps`) and
    without, and the mean background recorded (a faint return on 30 of the steps)."""
    from types import SimpleNamespace

    from mems_stereo.pipeline.background_entries import StepEntries, with_empty_steps

    S, lo, hi, bw, lam = shots.size, 20, 400, 3.125e-10, 0.5e6
    h = -np.expm1(-lam * bw)
    table = SimpleNamespace(theta_min=0.0, step=1e-4, n_steps=S)
    band = (np.array([0]), np.array([S - 1]))
    full, sel, rec = [], [], []
    for _ in range(trials):
        step = np.repeat(np.arange(S), shots)
        t_bg = rng.geometric(h, step.size)
        lit = (step >= 85) & (step < 115) & (rng.random(step.size) < 0.3)
        t_sig = np.where(lit, np.rint(rng.normal(150, 15, step.size)), np.inf)
        first = np.minimum(t_bg, t_sig)
        ok = (first >= lo) & (first <= hi)
        rec.append(np.sum(ok & (t_bg < t_sig)))
        key, cnt = np.unique(step[ok] * 4096 + first[ok].astype(np.int64), return_counts=True)
        q, st, code = np.zeros(key.size, np.int64), key // 4096, key % 4096
        counted = StepEntries(q, st, code, cnt.astype(float), np.zeros(q.size))
        for out, e in ((full, with_empty_steps(band, counted, shots, table)), (sel, counted)):
            se, ce, we = e.step, e.code, e.weight
            one = np.ones(se.size)
            _, bg, _ = window_background(se, ce, we, lo * one, hi * one, shots[se], lo * one,
                                         lam * one, bw)
            out.append(bg.sum())
    return np.mean(full), np.mean(sel), np.mean(rec)


def test_dense_band_background_counts_the_steps_without_detections():
    """A band the scan revisits (1-5 shots per step, 3 on average; strong background,
    a faint return on 30 of 200 steps): the background expected over it is that of
    every counted step, detections or not, and matches the background recorded; over
    the steps that hold a detection alone it falls short (sweep case 28036: 5-24 of
    ~120 steps empty, the stereo and ToF of a 4.7 m wall 9 and 13 cm short)."""
    from mems_stereo.pipeline.background_entries import DENSE_BAND_SHOTS

    rng = np.random.default_rng(7)
    shots = rng.integers(1, 6, 200)
    assert shots.mean() >= DENSE_BAND_SHOTS
    full, sel, rec = _band_trials(shots, rng)
    se = np.sqrt(rec / 300)
    assert abs(full - rec) < 3 * se + 0.05, (full, rec)
    assert sel < rec - 5 * se, (sel, rec)  # the detections' steps alone: too little


def test_sparse_band_keeps_the_detections_steps_background():
    """A band sampled about once per step (below DENSE_BAND_SHOTS): its empty steps are
    most of it and are not added (their subtraction trades the bias for more noise:
    the floodlight sample), so the expectation is the detections' steps' alone."""
    rng = np.random.default_rng(8)
    shots = rng.integers(0, 3, 200)  # 1 shot per step on average
    full, sel, _ = _band_trials(shots, rng, trials=50)
    assert full == sel


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_compiled_entry_loop_and_sorted_groups_give_the_same_bits(monkeypatch, seed):
    """window_background's per-entry loop compiled (numba loaded, at least
    COMPILED_ENTRIES entries) equals its NumPy form bit for bit, sorted groups (one
    pass) or not (np.unique), with empty intervals (a > b), codes outside [a, b] and
    a NaN rate."""
    pytest.importorskip("numba")
    import mems_stereo.pipeline.window_background as wb

    rng = np.random.default_rng(seed)
    G, M = 700, 9000
    g = np.sort(rng.integers(0, G, M))
    code = rng.integers(1, 400, M).astype(np.float64)
    key = np.unique(g * 1000 + code.astype(np.int64))  # distinct (group, code), sorted
    g, code = key // 1000, (key % 1000).astype(np.float64)
    cnt = rng.integers(1, 30, g.size).astype(np.float64)
    per = lambda x: x[g]  # noqa: E731 - the group's value per entry
    lo = rng.integers(1, 150, G).astype(np.float64)
    a = lo + rng.integers(0, 60, G)
    b = a + rng.integers(-5, 200, G)  # some empty
    a[::113] = np.nan  # NaN propagates as in NumPy's np.maximum
    rate = rng.uniform(1e5, 2e7, G)
    rate[::97] = np.nan
    args = (g, code, cnt, per(a), per(b), per(rng.integers(1, 50, G).astype(np.float64)),
            per(lo), per(rate), 3.125e-10)
    assert g.size >= wb.COMPILED_ENTRIES and wb.compiled_if_loaded(wb._closed_py)
    got = wb.window_background(*args)
    monkeypatch.setattr(wb, "COMPILED_ENTRIES", 10 ** 12)
    want = wb.window_background(*args)
    for x, y in zip(got, want):
        assert np.array_equal(x, y, equal_nan=True)
    assert np.any(want[1] > 0) and np.any(np.isnan(want[1]))
    # groups not sorted: np.unique's first and inverse, the same as the one pass's
    perm = rng.permutation(g.size)
    f1, i1 = wb._groups(g)
    _, f2, i2 = np.unique(g, return_index=True, return_inverse=True)
    assert np.array_equal(f1, f2) and np.array_equal(i1, i2)
    f3, i3 = wb._groups(g[perm])
    _, f4, i4 = np.unique(g[perm], return_index=True, return_inverse=True)
    assert np.array_equal(f3, f4) and np.array_equal(i3, i4)
