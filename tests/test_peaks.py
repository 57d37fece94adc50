"""Peak detection: the background model in scan angle, the window test, both detectors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from oracles import find_code_peaks

from mems_stereo.model.system import burkard2022
from mems_stereo.physics.background import expected_background_by_angle
from mems_stereo.pipeline.intervals import interval_table
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
    j, cnt, mu, keep = strongest_window(counts, bg, 11, bg > 0, Settings())
    assert keep[1] and abs(j[1] - 205) <= 3
    assert cnt[1] >= 60 and mu[1] == 5.5


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
