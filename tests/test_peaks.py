"""Peak detection: the background model in scan angle, the window test, both detectors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from oracles import find_code_peaks

from mems_stereo.model.system import burkard2022
from mems_stereo.physics.background import expected_background_by_angle
from mems_stereo.pipeline.intervals import interval_table
from mems_stereo.pipeline.peak_support import SUPPORT_COLUMNS, neighbour_support
from mems_stereo.pipeline.peaks import strongest_window
from mems_stereo.pipeline.run import process_recording
from mems_stereo.pipeline.settings import Settings

SAMPLES = Path(__file__).resolve().parents[1] / "samples"


def test_background_by_angle_matches_first_photon_monte_carlo(rng):
    """Expected background passing [lo, hi] at a step = shots x P(first photon in [lo, hi])."""
    s = burkard2022()
    table = interval_table(s)
    step = table.n_steps // 2
    n = np.zeros(table.n_steps, np.int64)
    n[step] = 20000
    rate = np.full(192, 6e6)
    B = expected_background_by_angle(table, n, rate)
    bw = s.tdc.bin_width
    for p in (40, 96, 150):
        lo, hi = int(table.lo[step, p]), int(table.hi[step, p])
        t = rng.exponential(1 / 6e6, size=20000)
        code = np.floor(t / bw).astype(int) + 1
        mc = np.count_nonzero((code >= lo) & (code <= hi))
        assert abs(B[p, step] - mc) <= 4 * np.sqrt(max(B[p, step], 1.0)) + 1
    assert B[:, :step].sum() == 0 and B[:, step + 1:].sum() == 0


def test_strongest_window_finds_an_injected_cluster(rng):
    bg = np.full((3, 400), 0.5)
    counts = rng.poisson(bg).astype(float)
    counts[1, 200:211] += 6  # a clear cluster in row 1 only
    ws = strongest_window(counts, bg, 11, bg > 0, Settings())
    j, cnt, mu, keep = ws.j, ws.cnt, ws.mu, ws.keep
    assert keep[1] and abs(j[1] - 205) <= 3
    assert cnt[1] >= 60 and mu[1] == 5.5


def test_neighbour_support_line_and_array_sensors():
    R = SUPPORT_COLUMNS
    k = np.zeros(60, bool)
    k[[5, 5 + R, 40]] = True  # two within reach of each other, one alone
    sup = neighbour_support(k, 60)
    assert sup[5] and sup[5 + R] and not sup[40]
    a = np.zeros((6, 30), bool)
    a[1, 3] = a[1 + R if 1 + R < 6 else 5, 3 + R] = True  # diagonal, within reach
    a[0, 29] = True
    sup = neighbour_support(a.ravel(), 30).reshape(a.shape)
    assert sup[1, 3] and not sup[0, 29]


def test_unsupported_peaks_pass_the_per_frame_level(rng):
    """Pure background: a window that passes the per-pixel threshold but that no
    neighbour supports is dropped unless it passes the per-frame level (scan
    statistics at FRAME_FALSE_ALARMS / n_pixels); with a neighbour it stays."""
    st = Settings()
    P, S, w = 200, 2000, 21
    bg = np.full((P, S), 0.02)
    counts = rng.poisson(bg).astype(float)
    ws0 = strongest_window(counts, bg, w, bg > 0, st)
    keep0 = ws0.keep
    n_fa = int(keep0.sum())
    keep1 = strongest_window(counts, bg, w, bg > 0, st, support_pixels=(P, P)).keep
    assert keep1.sum() <= n_fa and keep1.sum() <= 1
    # 6 counts over 0.42 expected (p 5e-6 per window): past the per-pixel threshold
    # (1e-3 over ~95 windows), short of the frame's (scan p 2.6e-3 > 1e-3 / 200)
    cl = counts.copy()
    for p in (50, 52, 120):
        cl[p] = 0
        cl[p, 1000:1006] = 1
    cl[150] = 0
    cl[150, 1000:1012] = 1  # 12 counts: significant for the whole sensor too
    ws = strongest_window(cl, bg, w, bg > 0, st, support_pixels=(P, P))
    keep = ws.keep
    keep_pix = strongest_window(cl, bg, w, bg > 0, st).keep
    assert keep_pix[50] and keep_pix[52] and keep_pix[120]
    assert keep[50] and keep[52] and not keep[120] and keep[150]


def test_scan_p_value_is_calibrated_where_bonferroni_is_not(rng):
    """On Poisson background the largest sliding-window count reaches the Bonferroni
    level (window positions × Poisson tail) more often than it promises (the windows
    overlap: ~2.5× at 10⁻³ in the recordings of bench_false_alarms.py); the scan
    p-value (first-order clumping) is not optimistic."""
    from scipy.special import pdtrc

    from mems_stereo.pipeline.peak_support import scan_isf, scan_sf
    from mems_stereo.pipeline.peaks import window_scores

    st = Settings()
    w = 21
    for lam in (0.05, 0.5):  # per step: ~1 and ~10 per window
        bg = np.full((20000, 420), lam)
        counts = rng.poisson(bg).astype(float)
        ws = window_scores(counts, bg, w, bg > 0, st)
        cnt, mu, nw = ws.cnt, ws.mu, ws.n_windows
        p_bonf = pdtrc(np.maximum(cnt - 1, 0), mu) * nw
        p_scan = scan_sf(cnt, mu, nw)
        for x in (0.1, 0.01):
            n = counts.shape[0]
            # binomial noise at 4σ
            assert np.mean(p_scan < x) <= x + 4 * np.sqrt(x / n)
        assert np.mean(p_bonf < 0.01) > 1.3 * np.mean(p_scan < 0.01)
        thr = scan_isf(0.01, mu, nw)
        assert np.array_equal(cnt > thr, scan_sf(cnt, mu, nw) <= 0.01)


def test_per_frame_false_peaks_within_budget(rng):
    """Background alone over 300 frames of 192 pixels (rates per step from 10⁻³ to 5,
    one per frame): the peaks that survive the neighbour support stay within the
    per-frame budget FRAME_FALSE_ALARMS (expected ≤ 3 in all; per pixel the first
    stage lets ~10⁻³ through, ~58 in all)."""
    from mems_stereo.pipeline.peak_support import FRAME_FALSE_ALARMS

    st = Settings()
    P, S, w = 192, 600, 21
    n_frames, n_pix, n_sup = 300, 0, 0
    for lam in np.geomspace(1e-3, 5.0, n_frames):
        bg = np.full((P, S), lam)
        counts = rng.poisson(bg).astype(float)
        k_pix = strongest_window(counts, bg, w, bg > 0, st).keep
        k = strongest_window(counts, bg, w, bg > 0, st, support_pixels=(P, P)).keep
        n_pix += int(k_pix.sum())
        n_sup += int(k.sum())
    assert n_pix >= 10  # the per-pixel level does let background through
    # Poisson(≤ 3): more than 10 has probability < 4·10⁻⁴
    assert n_sup <= 10 * max(1.0, FRAME_FALSE_ALARMS * n_frames / 3)
    assert n_sup < 0.2 * n_pix


def test_support_needs_an_agreeing_range():
    """A peak next to a surface is supported only when its range agrees with the
    surface's within both peaks' range resolution (and the slope allowance)."""
    lr = np.zeros((20, 3))
    lr[:, 0] = np.log(6.0)
    lr[:, 1] = 0.05
    lr[:, 2] = 0.02
    k = np.zeros(20, bool)
    k[[3, 6, 10]] = True
    lr[6, 0] = np.log(6.3)  # within 0.05 + 0.05 + 3·0.02
    lr[10, 0] = np.log(4.5)  # 0.29 below peak 3 (> 0.1 + 7·0.02), 0.34 below peak 6
    sup = neighbour_support(k, 20, SUPPORT_COLUMNS, lr)
    assert sup[3] and sup[6] and not sup[10]
    # with the plain range ratio (2) all three support each other
    assert neighbour_support(k, 20, SUPPORT_COLUMNS, lr[:, 0])[[3, 6, 10]].all()


def test_angle_detector_covers_more_than_the_papers_code_detector():
    """Under the 6 MHz floodlight, peaks in scan angle find far more pixels than peaks in code."""
    from mems_stereo.model.system import load_system

    res = process_recording(SAMPLES / "floodlight.h5",
                            system=load_system(SAMPLES / "calib_true_system.json"))
    sig, noise = res.histograms["signal"], res.histograms["noise"]
    code_peaks, _ = find_code_peaks(res.system, sig, noise, np.nan_to_num(res.theta), res.valid,
                                    Settings())
    assert len(res.peaks) > 3 * len(code_peaks["row"])
    assert len(res.cloud) >= 0.5 * 180  # at least half of the ~180 illuminated pixels


_CASE_22006 = {"objects": [
    {"type": "plane", "center": [0.0, 0.0, 7.569272443625735],
     "normal": [-0.7274860463183153, 0.0, -0.6861224762476055],
     "size": [29.579888087262436, 3.0], "reflectivity": 0.27037785669936126},
    {"type": "cylinder", "center": [0.3164030212105668, 0.0, 1.342977769899173],
     "radius": 0.06864147157827388, "height": 1.2, "axis": [0, 1, 0],
     "reflectivity": 0.8076269353451413}]}


def test_weak_sparse_wall_is_found_without_its_false_point():
    """Sweep case 22006 (a dark wall at 7.6 m, 47° incidence, 1,839 shots, 0.44 MHz):
    the detector sees the wall in one pixel in three (the oracle covers 0.32 of the
    lit pixels); its sparse peaks still support each other, while the background peak
    they lent their support to (1 of 32 points, 1.3 m off) no longer passes."""
    from test_generalise import _error, _sweep_case

    scene, c = _sweep_case(-0.19473608, -0.00654018, 0.7719837429165121,
                           -0.03306548858984507, _CASE_22006, 1839, 22006, 442242.3160343027)
    assert len(c) >= 20
    bad = np.abs(_error(scene, c)) > np.maximum(3 * c["sigma_r"], 0.10)
    assert not np.any(bad)
