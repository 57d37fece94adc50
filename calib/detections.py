"""Signal detections of one flat-target recording, as the calibration fit uses them.

The fit needs, per target (one recording = one target at one pose), the
monitor phase of every usable shot (to predict where the beam lands), which
shots produced a signal detection (to estimate the signal rate), and each
signal detection's pixel and TDC code.  Only the phase depends on nothing of
the system: θ follows from it and the candidate system's θ0, amplitude and
phase offset (``mems_stereo.model.scanner.scan_angle_from_phase``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mems_stereo.errors import FormatError
from mems_stereo.model.scanner import phase_from_zero_crossings


@dataclass
class TargetDetections:
    """Detections of one target.

    Attributes
    ----------
    phase : (K,) float64, rad: monitor phase φ of each usable shot.
    has_signal : (K,) bool: the shot has at least one signal detection.
    shot : (M,) int64: index into ``phase`` of each signal detection.
    column, row : (M,) float64: pixel of each detection (0-based, centres at integers).
    code : (M,) int64: TDC code N (1..n_bins) of each detection.
    noise_fraction : float: share of (shot, pixel) cells with a noise detection
        (estimates the background rate).
    n_pixels : int: pixels per shot (H·W).
    source : str: where the detections came from (for messages).
    """

    phase: np.ndarray
    has_signal: np.ndarray
    shot: np.ndarray
    column: np.ndarray
    row: np.ndarray
    code: np.ndarray
    noise_fraction: float = 0.0
    n_pixels: int = 1
    source: str = "<memory>"

    @property
    def n_detections(self) -> int:
        return int(self.shot.shape[0])


def detections_from_labels(phase, valid, bins, labels, source: str = "<memory>"
                           ) -> TargetDetections:
    """Collect the signal detections of one recording.

    Parameters
    ----------
    phase : (K,) float64, rad, monitor phase of each shot (NaN where unknown).
    valid : (K,) bool, shots with a known phase.
    bins : (K, H, W) uint16 TDC codes.
    labels : (K, H, W) uint8: 0 none, 1 signal, 2 noise.
    """
    bins = np.asarray(bins)
    labels = np.asarray(labels)
    phase = np.asarray(phase, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool) & np.isfinite(phase)
    if bins.ndim != 3 or labels.shape != bins.shape or phase.shape != (bins.shape[0],):
        raise FormatError(f"expected bins and labels (K, H, W) and phase (K,), found "
                          f"{bins.shape}, {labels.shape}, {phase.shape}", source)
    keep = np.flatnonzero(valid)
    new_index = np.full(bins.shape[0], -1, dtype=np.int64)
    new_index[keep] = np.arange(keep.size)
    lab = labels[keep]
    k, r, c = np.nonzero(lab == 1)
    code = bins[keep][k, r, c].astype(np.int64)
    has = np.zeros(keep.size, dtype=bool)
    has[k] = True
    n_pix = int(bins.shape[1] * bins.shape[2])
    noise = float(np.count_nonzero(lab == 2)) / max(1, keep.size * n_pix)
    return TargetDetections(phase[keep], has, k.astype(np.int64), c.astype(np.float64),
                            r.astype(np.float64), code, noise, n_pix, source)


def recording_phase(recording):
    """(K,) monitor phase and (K,) validity of a :class:`~mems_stereo.io.recording.Recording`."""
    return phase_from_zero_crossings(recording.shot_time, recording.zero_crossings,
                                     recording.rising)
