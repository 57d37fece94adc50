"""The TDC convention, in one place: code N ↔ time ↔ path length.

A detection in code N (1-based; 0 = none) has the time of flight
``t = (N − ½)·bin_width − offset`` and the path length ``L = c·t``
(mirror → target → projection centre), FORMAT v1 and docs/conventions.md.
"""

from __future__ import annotations

import numpy as np

from mems_stereo.model.hardware import TDC

# --------------------------------------------------------------------------
# codes <-> path length


def path_length_from_codes(codes, tdc: TDC, speed_of_light: float) -> np.ndarray:
    """Path length L = c · ((N − ½)·bin_width − offset), metres; NaN for code 0.

    ``codes`` : (...) integer TDC codes (0 = no detection, 1..n_bins).
    Returns float64 of the same shape.
    """
    n = np.asarray(codes, dtype=np.float64)
    L = speed_of_light * ((n - 0.5) * tdc.bin_width - tdc.offset)
    return np.where(n > 0, L, np.nan)


def codes_from_path_length(L, tdc: TDC, speed_of_light: float) -> np.ndarray:
    """Continuous TDC code of a path length (inverse of :func:`path_length_from_codes`).

    ``N = (L / c + offset) / bin_width + ½``; float64, same shape as ``L``.
    """
    L = np.asarray(L, dtype=np.float64)
    return (L / speed_of_light + tdc.offset) / tdc.bin_width + 0.5


def path_length(code, bin_width: float, offset: float = 0.0,
                speed_of_light: float = 299704644.5):
    """Path length L = c·((N − ½)·bin_width − offset), m, for (fractional) codes N.

    ``code`` : array of 1-based codes (NaN or 0 → NaN); ``bin_width``,
    ``offset`` : s; ``speed_of_light`` : m/s (in air by default, as the
    system JSON).  L is measured mirror → target → projection centre
    (FORMAT v1); points are :mod:`mems_stereo.pipeline.fusion`' job.
    """
    n = np.asarray(code, dtype=np.float64)
    n = np.where(n > 0, n, np.nan)
    return speed_of_light * ((n - 0.5) * bin_width - offset)
