"""TDC histograms per pixel: formation, background, pile-up, filtering, peaks, ranges.

The stage after classification (paper Sec. 3.2, Figs. 8–9): the TDC codes of
many shots are accumulated per pixel into the raw histogram, and, given the
per-detection labels of :mod:`mems_stereo.pipeline.consistency`, into the signal
histogram S and the noise histogram N.  From N (or from the raw histogram
with the return's window excluded) a maximum-likelihood estimate of the
background rate per pixel that accounts for first-photon pile-up; the
paper's moving-average filter, a threshold and a peak detector; and the
path length of each peak.  Method and derivations: ``docs/histograms.md``.

Conventions (``docs/conventions.md``): TDC code N is 1-based, 0 means no
detection, and histogram index ``j = N − 1``; a detection in code N has
``t_TOF = (N − ½)·bin_width − offset`` and path length ``L = c·t_TOF``
(mirror → target → projection centre).  A SPAD pixel records at most one
photon per shot, its first.  Counts are int64, rates in Hz, times in s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mems_stereo.errors import FormatError
from mems_stereo.io.labels import LABEL_NOISE, LABEL_SIGNAL
from mems_stereo.physics.background import moving_sum


# --------------------------------------------------------------------------- formation
@dataclass
class Histograms:
    """Per-pixel TDC histograms of a block of shots.

    Attributes
    ----------
    raw : (H, W, n_bins) int64, every detection; index j counts code j + 1.
    signal : (H, W, n_bins) int64, detections labelled 1 (signal S); zeros
        when no labels were given.
    noise : (H, W, n_bins) int64, detections labelled 2 (noise N); zeros when
        no labels were given.
    n_shots : (H, W) int64, shots in which the pixel was armed (read out):
        the number of trials of the pile-up model (K for a line sensor).

    Histograms of disjoint blocks of shots add (``a + b``): the histogram of
    the whole is the sum of the histograms of its chunks.
    """

    raw: np.ndarray
    signal: np.ndarray
    noise: np.ndarray
    n_shots: np.ndarray

    @property
    def n_bins(self) -> int:
        return int(self.raw.shape[-1])

    def __add__(self, other: Histograms) -> Histograms:
        if not isinstance(other, Histograms):
            return NotImplemented
        if other.raw.shape != self.raw.shape:
            raise FormatError(f"cannot add histograms of shape {self.raw.shape} and "
                              f"{other.raw.shape}", field="histograms")
        return Histograms(self.raw + other.raw, self.signal + other.signal,
                          self.noise + other.noise, self.n_shots + other.n_shots)

    @classmethod
    def zeros(cls, shape: tuple[int, int], n_bins: int) -> Histograms:
        """Empty histograms for an (H, W) sensor: the start of an accumulation."""
        h, w = shape
        z = np.zeros((h, w, n_bins), dtype=np.int64)
        return cls(z, z.copy(), z.copy(), np.zeros((h, w), dtype=np.int64))


def accumulate_histograms(bins, labels=None, n_bins: int = 4096, armed=None) -> Histograms:
    """Histograms of a block of shots (raw, and signal S / noise N from the labels).

    Parameters
    ----------
    bins : (K, H, W) uint16 TDC codes, 0 = no detection, 1..n_bins the bin of
        the first detected photon (``/shots/bins`` of FORMAT v1).
    labels : (K, H, W) uint8 or None; 1 signal, 2 noise, 0 none (or left out:
        a detection labelled 0 counts in ``raw`` only).
    n_bins : number of TDC bins; a code above it raises :class:`FormatError`.
    armed : (K, H, W) bool or None; False where the pixel was not read out in
        that shot (epipolar readout).  Those slots add neither counts nor
        trials.  Default: every pixel armed in every shot.

    Returns
    -------
    :class:`Histograms` with int64 arrays.  One ``np.bincount`` over
    ``(label·P + pixel)·n_bins + code − 1`` (most of the time goes to allocating
    the three (H, W, n_bins) outputs).

    Examples
    --------
    >>> rec = ms.read_recording(ms.data.path("room.h5"))
    >>> h = ms.accumulate_histograms(rec.bins, rec.truth["label"], n_bins=4096)
    >>> h.raw.shape, int(h.raw.sum()), int(h.signal.sum()), int(h.noise.sum())
    ((1, 192, 4096), 19518, 952, 18566)
    """
    b = np.asarray(bins)
    if b.ndim != 3:
        raise FormatError(f"expected (K, H, W) codes, found shape {b.shape}", field="bins")
    if not np.issubdtype(b.dtype, np.integer):
        raise FormatError(f"expected integer codes, found dtype {b.dtype}", field="bins")
    n_bins = int(n_bins)
    if n_bins < 1:
        raise FormatError(f"n_bins must be >= 1, found {n_bins}", field="n_bins")
    K, H, W = b.shape
    P = H * W
    if armed is None:
        n_shots = np.full((H, W), K, dtype=np.int64)
        arm = None
    else:
        arm = np.asarray(armed, dtype=bool)
        if arm.shape != b.shape:
            raise FormatError(f"expected armed of shape {b.shape}, found {arm.shape}",
                              field="armed")
        n_shots = arm.sum(axis=0, dtype=np.int64)
    flat = b.reshape(K, P)
    det = flat > 0
    if arm is not None:
        det &= arm.reshape(K, P)
    shot_idx, pix = np.nonzero(det)
    codes = flat[shot_idx, pix].astype(np.int64)
    if codes.size and (codes.max() > n_bins or codes.min() < 0):
        bad = codes.max() if codes.max() > n_bins else codes.min()
        raise FormatError(f"TDC codes must lie in 0..{n_bins}, found {bad}", field="bins")
    if labels is None:
        cls = np.zeros_like(codes)
    else:
        lab = np.asarray(labels)
        if lab.shape != b.shape:
            raise FormatError(f"expected labels of shape {b.shape}, found {lab.shape}",
                              field="labels")
        cls = lab.reshape(K, P)[shot_idx, pix].astype(np.int64)
        if cls.size and cls.max() > LABEL_NOISE:
            raise FormatError(f"labels must lie in 0..2, found {cls.max()}", field="labels")
    idx = (cls * P + pix) * n_bins + (codes - 1)
    counts = np.bincount(idx, minlength=3 * P * n_bins).reshape(3, H, W, n_bins)
    counts = counts.astype(np.int64, copy=False)
    raw = counts.sum(axis=0)
    return Histograms(raw, counts[LABEL_SIGNAL].copy(), counts[LABEL_NOISE].copy(), n_shots)


def moving_average(hist, width: int) -> np.ndarray:
    """The paper's moving-average filter along the codes (last axis).

    ``hist`` : (..., n_bins); ``width`` : odd number of bins.  Returns (...,
    n_bins) float64, the mean over the bins of a centred window; at the ends
    the mean over the bins that exist (no loss of height at code 1).

    Examples
    --------
    >>> ms.moving_average(np.array([0, 0, 3, 0, 0, 6, 0]), 3)
    array([0., 1., 1., 1., 2., 2., 3.])
    """
    s = moving_sum(hist, width)
    n_bins = np.asarray(hist).shape[-1]
    norm = moving_sum(np.ones(n_bins), width)
    return s / norm


def moving_average_argmax(hist, width: int) -> np.ndarray:
    """``np.argmax(moving_average(hist, width), axis=1)`` of (R, n_bins) integer rows:
    (R,) int64, the first bin of each row's largest moving average.  Where numba is
    loaded a compiled pass slides the window sums along the row (integers: exact, the
    same numbers as the running sums' differences) and divides each by its bin count,
    without the (R, n_bins) averages."""
    from mems_stereo.util.lazy_numba import compiled_if_loaded

    h = np.asarray(hist)
    kernel = compiled_if_loaded(_average_argmax_py)
    if (kernel is None or h.ndim != 2 or h.shape[1] == 0 or h.dtype != np.int64
            or int(width) < 1 or int(width) % 2 == 0):
        return np.argmax(moving_average(h, width), axis=-1)
    out = np.zeros(h.shape[0], np.int64)
    kernel(np.ascontiguousarray(h), int(width) // 2, out)
    return out


def _average_argmax_py(h, half, out):  # pragma: no cover - compiled by numba
    """:func:`moving_average_argmax` row by row (the numba kernel)."""
    R, n = h.shape
    for r in range(R):
        s = np.int64(0)
        for i in range(min(half, n)):
            s += h[r, i]
        best, bv = 0, -1.0
        for i in range(n):
            if i + half < n:
                s += h[r, i + half]
            if i - half - 1 >= 0:
                s -= h[r, i - half - 1]
            v = np.float64(s) / np.float64(min(i + half + 1, n) - max(i - half, 0))
            if i == 0 or v > bv:
                best, bv = i, v
        out[r] = best
