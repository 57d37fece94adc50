"""What the fusion of detections into points takes: the entries (detections or
distinct counted keys), the peaks they belong to and the fusion's options.

Plain frozen records, read by :class:`~mems_stereo.pipeline.peak_accumulator.PeakAccumulator`
and :func:`~mems_stereo.pipeline.fusion.points_from_peak_detections`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mems_stereo.geometry.uncertainty import Spreads


@dataclass(frozen=True, eq=False)
class FusionEntries:
    """The entries the fusion sums: detections, or distinct (peak, step, code) keys
    weighted by their counts.

    shot : (M,) int, index into ``theta`` of each entry's shot (or its own angle).
    peak : (M,) int, the entry's peak, 0..Q−1.
    code : (M,) TDC code of the entry (integer or float, 1..n_bins).
    theta : (K,) float64 rad, scan angle indexed by ``shot``.
    weight : (M,) float64 multiplicity of each entry (default 1; negative for a
        subtracted background entry), or None.
    background : (M,) float64 expected background subtracted at each entry, or None
        (see :meth:`~mems_stereo.pipeline.peak_accumulator.PeakAccumulator.add_inliers`).
    """

    shot: np.ndarray
    peak: np.ndarray
    code: np.ndarray
    theta: np.ndarray
    weight: np.ndarray | None = None
    background: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class FusionPeaks:
    """The Q peaks the entries are fused into.

    rows, cols : (Q,) int, each peak's pixel.
    code : (Q,) the detector's peak code (kept as the cloud's ``code`` attribute), or None.
    rate_hz : (Q,) float64 background rate of the peak's pixel, Hz, or None (0).
    step_window : ``(step_lo, step_hi)`` (Q,) int each, the angle steps pass 2
        counted, or None (every step).
    accept : ``accept(steps (Q', B), centre (Q',) m, q=None) -> (Q', B) bool``,
        whether a return from the peak's centre range at each step is classified
        signal, or None (every step).
    turning : (Q,) bool, where the scan turns inside the peak's footprint
        (:class:`~mems_stereo.pipeline.peak_table.Peaks`), or None (nowhere).
    """

    rows: np.ndarray
    cols: np.ndarray
    code: np.ndarray | None = None
    rate_hz: np.ndarray | None = None
    step_window: tuple[np.ndarray, np.ndarray] | None = None
    accept: Callable | None = None
    turning: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class FusionOptions:
    """How the entries are fused.

    spreads : the input spreads (default :func:`~mems_stereo.geometry.uncertainty.spreads_for`).
    confidence : sets the inlier bound ``k`` around each peak's centre.
    shots_per_step : (S,) int, valid shots per scan-angle step of the grid
        ``step_grid = (theta_min, dtheta)`` (rad; the interval table's): with both
        (and ``first_photon``) the ToF and fused estimates are corrected for the
        first-photon delay; without them the result is the uncorrected one.
    first_photon : apply that correction when the data allow it.
    spot_sigma : the spot model's σ (default the simulator's spot at the peak's range).
    r_min, r_max, rel_step : the range grid of the mode (m, m, relative step).
    """

    spreads: Spreads | None = None
    confidence: float = 0.997
    shots_per_step: np.ndarray | None = None
    step_grid: tuple[float, float] | None = None
    first_photon: bool = True
    spot_sigma: float | None = None
    r_min: float = 0.01
    r_max: float = 1000.0
    rel_step: float = 2e-3
