"""The peaks of a recording and the matched filter's candidates: typed tables, one row a peak.

:class:`Peaks` is what the peak detector (:func:`mems_stereo.pipeline.peaks.find_peaks`)
finds and pass 2 and the fusion read: per peak its pixel, the code and scan-angle
windows pass 2 counts, and its background.  :class:`Candidates` are the pixels
without a first-stage peak, with the windows pass 2 counts for the matched filter
(:mod:`mems_stereo.pipeline.matched`) and what its search needs besides.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from scipy.sparse import csr_array

#: the (Q,) per-peak arrays of :class:`Peaks`, in field order
PEAK_ARRAYS = ("row", "col", "code", "code_lo", "code_hi", "step_lo", "step_hi", "counts",
               "background", "rate_hz", "turning")


@dataclass(frozen=True, slots=True)
class Peaks:
    """The peaks of a recording, one per pixel at most (Q peaks).

    row, col : (Q,) int64 pixel; code : (Q,) int64, strongest code of the
    pixel's signal histogram; code_lo, code_hi : (Q,) int64, the code window
    counted in pass 2; step_lo, step_hi : (Q,) int64, the scan-angle steps
    of the interval table counted in pass 2; counts : (Q,) int64, signal
    detections in the peak's angle band; background : (Q,) float64, their
    expected background; rate_hz : (Q,) float64, the pixel's ML background
    rate; turning : (Q,) bool, the scan turns inside the peak's footprint (its
    shots bunch at one edge: the stereo mean is biased, see
    :func:`~mems_stereo.pipeline.peak_estimates.peak_means_of`; None: no peak's,
    stored as all False); background_by_step : (Q, S) ``scipy.sparse.csr_array`` float64,
    the expected background detections per angle step over each peak's
    counted steps ``step_lo..step_hi`` (zero elsewhere; stored at those of the
    steps with valid shots, or all of them, :func:`window_rows`;
    None in a light copy, :meth:`light`); candidates : the matched filter's
    :class:`Candidates` found with the first stage's peaks (None otherwise).
    """

    row: np.ndarray
    col: np.ndarray
    code: np.ndarray
    code_lo: np.ndarray
    code_hi: np.ndarray
    step_lo: np.ndarray
    step_hi: np.ndarray
    counts: np.ndarray
    background: np.ndarray
    rate_hz: np.ndarray
    turning: np.ndarray | None = None
    background_by_step: csr_array | None = None
    candidates: Candidates | None = None

    def __post_init__(self):
        if self.turning is None:
            object.__setattr__(self, "turning", np.zeros(np.shape(self.row)[0], bool))

    def __len__(self) -> int:
        return int(self.row.size)

    def pixel(self, width: int) -> np.ndarray:
        """(Q,) int64 flat pixel index ``row·width + col``."""
        return self.row * int(width) + self.col

    def arrays(self) -> dict[str, np.ndarray]:
        """The (Q,) per-peak arrays by name (:data:`PEAK_ARRAYS`)."""
        return {k: getattr(self, k) for k in PEAK_ARRAYS}

    def light(self) -> Peaks:
        """These peaks without ``background_by_step`` and ``candidates``: the (Q,) arrays
        that pass 2 and the fusion read (small, to send to workers)."""
        return Peaks(**self.arrays())

    def take(self, rows) -> Peaks:
        """The light copy (:meth:`light`) of the peaks ``rows`` (an index array or a
        slice)."""
        return Peaks(**{k: np.asarray(v)[rows] for k, v in self.arrays().items()})

    @classmethod
    def concat(cls, parts) -> Peaks:
        """Consecutive :class:`Peaks` as one (``background_by_step`` stacked; no
        candidates)."""
        from scipy.sparse import csr_array

        parts = list(parts)
        out = {k: np.concatenate([getattr(p, k) for p in parts]) for k in PEAK_ARRAYS}
        mats = [p.background_by_step for p in parts]
        off = np.cumsum([0] + [m.nnz for m in mats[:-1]])
        indptr = np.concatenate([[0]] + [m.indptr[1:] + o for m, o in zip(mats, off)])
        bbs = csr_array((np.concatenate([m.data for m in mats]),
                         np.concatenate([m.indices for m in mats]),
                         indptr.astype(mats[0].indptr.dtype)),
                        shape=(int(indptr.size - 1), mats[0].shape[1]))
        return cls(**out, background_by_step=bbs)


@dataclass(frozen=True, slots=True, kw_only=True)
class Candidates(Peaks):
    """The matched filter's candidates: every pixel without a first-stage peak whose
    scan can hold one, as :class:`Peaks` (``step_lo..step_hi`` the steps pass 2
    counts for it, ``code`` unused, ``counts`` and ``background`` its strongest
    window's), and what the search needs besides (C candidates).

    n_windows : (C,) float64, footprint-window positions of the candidate's scan
    (the first stage's); local_lo, local_hi : (C,) int64, the steps around the first
    stage's strongest window that the search tries first (−1: none, the candidate
    was no near miss); width : int, the footprint in angle steps.
    """

    n_windows: np.ndarray = field(default_factory=lambda: np.zeros(0))
    local_lo: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    local_hi: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    width: int = 0

    def take(self, rows) -> Candidates:
        """The candidates ``rows`` (an index array or a slice), without
        ``background_by_step``."""
        return Candidates(**{k: np.asarray(v)[rows] for k, v in self.arrays().items()},
                          n_windows=np.asarray(self.n_windows)[rows],
                          local_lo=np.asarray(self.local_lo)[rows],
                          local_hi=np.asarray(self.local_hi)[rows], width=self.width)

    @classmethod
    def concat(cls, parts) -> Candidates:
        """Consecutive :class:`Candidates` as one."""
        parts = list(parts)
        joined = Peaks.concat(parts)
        return cls(**joined.arrays(), background_by_step=joined.background_by_step,
                   n_windows=np.concatenate([p.n_windows for p in parts]),
                   local_lo=np.concatenate([p.local_lo for p in parts]),
                   local_hi=np.concatenate([p.local_hi for p in parts]),
                   width=parts[0].width)


def window_rows(B, q, lo, hi):
    """(Q, S) ``scipy.sparse.csr_array`` of rows ``q`` (Q,) of ``B`` (P, S) over the
    columns ``lo[i]..hi[i]`` of each row (zero outside), without a dense (Q, S) copy."""
    from scipy.sparse import csr_array

    q, lo, hi = (np.asarray(x, np.int64).ravel() for x in (q, lo, hi))
    n = np.maximum(hi - lo + 1, 0)
    indptr = np.zeros(q.size + 1, np.int64)
    np.cumsum(n, out=indptr[1:])
    row = np.repeat(np.arange(q.size), n)
    col = np.arange(indptr[-1]) - indptr[:-1][row] + lo[row]
    return csr_array((np.asarray(B)[q[row], col], col, indptr), shape=(q.size, B.shape[1]))
