"""Peak detection: the background model in scan angle, the window test, both detectors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from oracles import find_code_peaks

from mems_stereo.model.system import burkard2022
from mems_stereo.physics.background import expected_background_by_angle
from mems_stereo.pipeline.intervals import interval_table
from mems_stereo.pipeline.peaks import SUPPORT_COLUMNS, neighbour_support, strongest_window
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
    j, cnt, mu, keep = strongest_window(counts, bg, 11, bg > 0, Settings())
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


def test_isolated_peaks_carry_the_whole_sensors_look_elsewhere(rng):
    """Pure background: a lone window that passes the per-pixel threshold is dropped
    unless it passes at false_alarm / n_pixels; with a neighbour it stays."""
    st = Settings()
    P, S, w = 200, 2000, 21
    bg = np.full((P, S), 0.02)
    counts = rng.poisson(bg).astype(float)
    # the same marginal cluster (just above the per-pixel threshold) in a lone pixel
    # and in two neighbouring pixels
    _, c0, mu0, keep0 = strongest_window(counts, bg, w, bg > 0, st)
    n_fa = int(keep0.sum())
    _, _, _, keep1 = strongest_window(counts, bg, w, bg > 0, st, support_pixels=(P, P))
    # per pixel the nominal level, overall (isolated) at most a few in 10^3 pixels
    assert keep1.sum() <= n_fa and keep1.sum() <= 1
    # 6 counts over 0.42 expected (p 5e-6 per window): past the per-pixel threshold
    # (1e-3 over ~95 windows), short of the whole sensor's (a further / 200)
    cl = counts.copy()
    for p in (50, 52, 120):
        cl[p] = 0
        cl[p, 1000:1006] = 1
    _, cnt, mu, keep = strongest_window(cl, bg, w, bg > 0, st, support_pixels=(P, P))
    _, _, _, keep_pix = strongest_window(cl, bg, w, bg > 0, st)
    assert keep_pix[50] and keep_pix[52] and keep_pix[120]
    assert keep[50] and keep[52] and not keep[120]


def test_angle_detector_covers_more_than_the_papers_code_detector():
    """Under the 6 MHz floodlight, peaks in scan angle find far more pixels than peaks in code."""
    from mems_stereo.model.system import load_system

    res = process_recording(SAMPLES / "floodlight.h5",
                            system=load_system(SAMPLES / "calib_true_system.json"))
    sig, noise = res.histograms["signal"], res.histograms["noise"]
    code_peaks, _ = find_code_peaks(res.system, sig, noise, np.nan_to_num(res.theta), res.valid,
                                    Settings())
    assert len(res.peaks["row"]) > 3 * len(code_peaks["row"])
    assert len(res.cloud) >= 0.5 * 180  # at least half of the ~180 illuminated pixels
