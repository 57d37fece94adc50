"""Settings of a processing run (confidence, false-alarm rate, chunking, …).
"""

from __future__ import annotations

from dataclasses import dataclass

from mems_stereo.pipeline.consistency import DEFAULT_CONFIDENCE

DEFAULT_CHUNK_SHOTS = 8192


@dataclass(frozen=True)
class Settings:
    """Processing settings (all documented in docs/pipeline.md).

    Attributes
    ----------
    confidence : two-sided coverage of the consistency bound (0.997 = 3σ).
    min_range : optional prior, m: no target nearer than this (None: none).
    chunk_shots : shots per chunk read from the file.
    smoothing_bins : width of the moving-average filter of the histograms
        (default: the laser pulse's FWHM in bins, at least 1).
    false_alarm : per-pixel probability that background alone crosses the
        peak threshold (first stage; the matched filter's two tests, around a
        near miss's window and over the whole scan, half of it each: ≤
        2·false_alarm per pixel in all, nominal Bonferroni; a
        peak that no neighbour on its surface supports must pass the per-frame
        level ``peaks.FRAME_FALSE_ALARMS`` / pixels, docs/pipeline.md section 5).
    min_counts : fewest signal counts for a peak.

    Examples
    --------
    >>> settings = ms.Settings(confidence=0.99)
    >>> settings.confidence, settings.min_counts
    (0.99, 3)
    >>> result = ms.process_recording(ms.data.path("room.h5"), settings=settings)
    >>> len(result.cloud) > 0
    True
    """

    confidence: float = DEFAULT_CONFIDENCE
    min_range: float | None = None
    chunk_shots: int = DEFAULT_CHUNK_SHOTS
    smoothing_bins: int | None = None
    false_alarm: float = 1e-3
    min_counts: int = 3
