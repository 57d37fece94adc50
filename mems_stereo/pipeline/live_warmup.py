"""Warm-up of a live run: compile the kernels and fill the tables before the clock starts.

The first frame a process makes pays for the numba compilation (or the load of its
disk cache) and for the rows of the interval table; in a live run that would be the
first frames' latency, or drops.  :func:`warm_up` processes one small synthetic frame of
the run's system (seeded noise plus a return in every pixel) with the run's settings
and table, and throws the result away.
"""

from __future__ import annotations

import time

import numpy as np

from mems_stereo.pipeline.frames import FrameProcessor, FrameShots, frame_cloud

#: shots of the synthetic frame (a few mechanical periods of the line sensor)
WARMUP_SHOTS = 512


def synthetic_shots(system, n_shots: int = WARMUP_SHOTS, seed: int = 0) -> FrameShots:
    """A frame of ``n_shots`` shots of ``system``: background detections in about half of
    the pixel-slots, a return at a fixed code per pixel in a quarter, zero crossings of a
    cosine at ``f_mech`` over the whole span."""
    rng = np.random.default_rng(seed)
    h, w = system.receiver.height, system.receiver.width
    n_bins = system.tdc.n_bins
    times = np.arange(n_shots, dtype=np.float64) / float(system.laser.f_rep)
    bins = np.where(rng.random((n_shots, h, w)) < 0.5,
                    rng.integers(1, n_bins + 1, (n_shots, h, w)), 0)
    ret = rng.integers(n_bins // 8, n_bins // 2, (h, w))
    hit = rng.random((n_shots, h, w)) < 0.25
    bins = np.where(hit, ret[None], bins).astype(np.uint16)
    half = 0.5 / float(system.scanner.f_mech)
    zc = np.arange(-half, times[-1] + 3 * half, half)
    rising = (np.arange(zc.size) % 2).astype(np.uint8)
    return FrameShots(times, bins, None, zc, rising)


def warm_up(proc: FrameProcessor, n_shots: int = WARMUP_SHOTS) -> float:
    """Process a synthetic frame with ``proc``'s system, settings and table (the result is
    discarded; ``proc`` is not changed); returns the seconds it took."""
    t0 = time.perf_counter()
    frame_cloud(proc.system, synthetic_shots(proc.system, n_shots), proc.settings, proc.table,
                "warm-up")
    return time.perf_counter() - t0
