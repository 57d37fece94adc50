"""The TDC convention, in one place: code N ↔ time ↔ path length.

A detection in code N (1-based; 0 = none) has the time of flight
``t = (N − ½)·bin_width − offset`` and the path length ``L = c·t``
(mirror → target → projection centre), FORMAT v1 and docs/conventions.md.
With the hardware model (``docs/hardware.md``) code widths, per-pixel offsets
and the pulse's mean delay enter: :func:`detection_path_length`.
"""

from __future__ import annotations

import numpy as np

from mems_stereo.model.hardware import TDC, pulse_mean_delay

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


# --------------------------------------------------------------------------
# the hardware model: code widths (DNL/INL), per-pixel offsets, pulse delay


def code_edges(tdc: TDC) -> np.ndarray:
    """(n_bins + 1,) float64 s: code N covers ``[edges[N−1], edges[N])`` of TDC time.

    Equal widths give ``edges = bin_width · (0, 1, …, n_bins)``; with
    ``tdc.code_widths`` w (LSB) ``edges = bin_width · (0, w1, w1 + w2, …)``.
    """
    if tdc.code_widths is None:
        return tdc.bin_width * np.arange(tdc.n_bins + 1, dtype=np.float64)
    w = np.asarray(tdc.code_widths, dtype=np.float64)
    return tdc.bin_width * np.concatenate([[0.0], np.cumsum(w)])


def code_centres(tdc: TDC) -> np.ndarray:
    """(n_bins,) float64 s: code N's centre ``bin_width · (Σ_{i<N} w_i + w_N/2)``
    (``(N − ½)·bin_width`` for equal widths); index N − 1."""
    e = code_edges(tdc)
    return 0.5 * (e[:-1] + e[1:])


def code_of_time(t, tdc: TDC) -> np.ndarray:
    """The code (1..n_bins, int64) a TDC time ``t`` (s, ≥ 0) falls in, by the code
    edges (:func:`code_edges`); times beyond the last edge give n_bins."""
    t = np.asarray(t, dtype=np.float64)
    if tdc.code_widths is None:
        return np.minimum(np.floor(t / tdc.bin_width) + 1, tdc.n_bins).astype(np.int64)
    e = code_edges(tdc)
    return np.clip(np.searchsorted(e, t, side="right"), 1, tdc.n_bins).astype(np.int64)


def _pixel_offset(tdc: TDC, pixel) -> np.ndarray | float:
    if tdc.pixel_offsets is None or pixel is None:
        return 0.0
    off = np.asarray(tdc.pixel_offsets, dtype=np.float64)
    return off[np.asarray(pixel, dtype=np.int64)]


def _centre_of(codes, tdc: TDC) -> np.ndarray:
    """Centre time (s) of (fractional) codes: linear between centres, equal widths
    outside 1..n_bins."""
    n = np.asarray(codes, dtype=np.float64)
    if tdc.code_widths is None:
        return (n - 0.5) * tdc.bin_width
    c = code_centres(tdc)
    k = np.arange(1, tdc.n_bins + 1, dtype=np.float64)
    t = np.interp(n, k, c)
    return t + np.where(n < 1, (n - 1) * tdc.bin_width, 0.0) + np.where(
        n > tdc.n_bins, (n - tdc.n_bins) * tdc.bin_width, 0.0)


def _code_of_centre(t, tdc: TDC) -> np.ndarray:
    """Inverse of :func:`_centre_of`: the fractional code whose centre is ``t`` (s)."""
    t = np.asarray(t, dtype=np.float64)
    if tdc.code_widths is None:
        return t / tdc.bin_width + 0.5
    c = code_centres(tdc)
    k = np.arange(1, tdc.n_bins + 1, dtype=np.float64)
    n = np.interp(t, c, k)
    return n + np.where(t < c[0], (t - c[0]) / tdc.bin_width, 0.0) + np.where(
        t > c[-1], (t - c[-1]) / tdc.bin_width, 0.0)


def detection_path_length(codes, system, pixel=None) -> np.ndarray:
    """Path length L (m) of detections in ``codes`` at flat pixels ``pixel``
    (row·W + column, broadcast with ``codes``; None: no per-pixel offset).

    With ideal hardware (``system.ideal_hardware``) exactly
    :func:`path_length_from_codes`.  Otherwise ``L = c · (t_N − offset −
    pixel_offsets[pixel] − d̄)`` with ``t_N`` the code's centre (:func:`code_centres`)
    and d̄ the pulse's mean delay (:func:`mems_stereo.model.hardware.pulse_mean_delay`);
    NaN for code 0.
    """
    tdc, c = system.tdc, system.speed_of_light
    if system.ideal_hardware:
        return path_length_from_codes(codes, tdc, c)
    n = np.asarray(codes, dtype=np.float64)
    t = _centre_of(n, tdc) - tdc.offset - _pixel_offset(tdc, pixel) - pulse_mean_delay(
        system.laser)
    return np.where(n > 0, c * t, np.nan)


def detection_codes(L, system, pixel=None) -> np.ndarray:
    """Continuous code of path lengths ``L`` (m) at flat pixels ``pixel``: the inverse
    of :func:`detection_path_length` (exactly :func:`codes_from_path_length` for ideal
    hardware); float64 of the broadcast shape."""
    tdc, c = system.tdc, system.speed_of_light
    if system.ideal_hardware:
        return codes_from_path_length(L, tdc, c)
    t = np.asarray(L, dtype=np.float64) / c + tdc.offset + _pixel_offset(tdc, pixel)
    return _code_of_centre(t + pulse_mean_delay(system.laser), tdc)
