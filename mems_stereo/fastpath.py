"""The fast classifier: accepted code intervals compiled ahead per scan-angle step.

The consistency test of :mod:`mems_stereo.classify` depends only on
(scan angle θ, pixel, TDC code).  So the accepted interval ``[lo, hi]`` of
every pixel can be computed once for a grid of scan angles
``θ_j = θ_min + j·Δθ`` (an :class:`IntervalTable`) and each shot then looks
its row up by the index of its angle on the grid.  One compiled (numba) pass
over the bins labels every detection and accumulates the signal and noise
histograms at once, near the speed of reading the bins.

Snapping θ to the grid is the only approximation: with the default
Δθ = 20 µrad the predicted path length moves by at most
``|∂L/∂θ|·Δθ/2`` (5 mm at 5 m for the paper's system), against a bound of
several metres.  The reference NumPy path
(:func:`mems_stereo.classify.classify_bins`) applied to the **snapped**
angles gives labels identical to the fast path; the tests check exactly that.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .classify import DEFAULT_CONFIDENCE, accepted_code_intervals
from .system import System, system_to_json
from .uncertainty import Spreads

DEFAULT_THETA_STEP = 2e-5  # rad


@dataclass(frozen=True)
class IntervalTable:
    """Accepted code intervals per scan-angle step and pixel.

    Attributes
    ----------
    theta_min : float, rad, angle of row 0.
    step : float, rad, grid spacing Δθ.
    lo, hi : (S, H*W) uint16 each; code N is signal iff lo <= N <= hi
        (lo > hi: nothing accepted).
    """

    theta_min: float
    step: float
    lo: np.ndarray
    hi: np.ndarray

    @property
    def n_steps(self) -> int:
        return int(self.lo.shape[0])

    def index(self, theta) -> np.ndarray:
        """Row index of each angle, (K,) int64; −1 for NaN or off the grid."""
        th = np.asarray(theta, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            j = np.rint((th - self.theta_min) / self.step)
        ok = np.isfinite(j) & (j >= 0) & (j < self.n_steps)
        return np.where(ok, j, -1).astype(np.int64)

    def snap(self, theta) -> np.ndarray:
        """The grid angle each shot is classified with, (K,) rad (NaN off the grid)."""
        j = self.index(theta)
        return np.where(j >= 0, self.theta_min + j * self.step, np.nan)


_TABLE_CACHE: dict = {}


def build_interval_table(system: System, confidence: float = DEFAULT_CONFIDENCE,
                         spreads: Spreads | None = None, step: float = DEFAULT_THETA_STEP,
                         margin: float = 0.1, min_range: float | None = None) -> IntervalTable:
    """Compile the accepted intervals for every scan angle the system can reach.

    The grid covers ``θ0 ± θ_mech,max·(1 + margin)``.  Tables are cached per
    (system, confidence, spreads, step, margin, min_range) in the process.
    Cost: one call of :func:`~mems_stereo.classify.accepted_code_intervals`
    over S = 2·θ_max·(1+margin)/Δθ angles (≈ 23,000 rows for the paper's
    system: about a second, 18 MB).
    """
    key = (system_to_json(system), confidence, repr(spreads), step, margin, min_range)
    if key in _TABLE_CACHE:
        return _TABLE_CACHE[key]
    sc = system.scanner
    half = sc.theta_mech_max * (1.0 + margin)
    n = int(math.ceil(2 * half / step)) + 1
    theta_min = sc.theta0 - half
    grid = theta_min + step * np.arange(n)
    lo, hi = accepted_code_intervals(system, grid, confidence, spreads, chunk_shots=512,
                                     min_range=min_range)
    P = system.receiver.width * system.receiver.height
    lo = np.clip(lo.reshape(n, P), 0, 65535).astype(np.uint16)
    hi = np.clip(hi.reshape(n, P), 0, 65535).astype(np.uint16)
    # nothing accepted: make the empty interval explicit for uint16 (lo=1 > hi=0)
    empty = lo > hi
    lo[empty], hi[empty] = 1, 0
    table = IntervalTable(float(theta_min), float(step), lo, hi)
    if len(_TABLE_CACHE) > 8:
        _TABLE_CACHE.clear()
    _TABLE_CACHE[key] = table
    return table


# --------------------------------------------------------------------------
# compiled kernel


def _kernel_py(bins, rows, lo, hi, labels, hist_s, hist_n, n_bins):
    """Reference semantics of the compiled kernel (pure Python; used when numba is absent).

    bins : (K, P) uint16; rows : (K,) int64 table row (−1: shot left out);
    lo, hi : (S, P) uint16; labels : (K, P) uint8 out (may be (0, 0): not written);
    hist_s, hist_n : (P, n_bins + 1) int64 accumulated in place (column 0 unused).
    """
    K, P = bins.shape
    write = labels.shape[0] == K
    for k in range(K):
        j = rows[k]
        for p in range(P):
            c = bins[k, p]
            lab = 0
            if c != 0 and j >= 0 and c <= n_bins:
                if lo[j, p] <= c and c <= hi[j, p]:
                    hist_s[p, c] += 1
                    lab = 1
                else:
                    hist_n[p, c] += 1
                    lab = 2
            if write:
                labels[k, p] = lab


try:  # pragma: no cover - exercised whenever numba is installed (a declared dependency)
    import numba

    _kernel = numba.njit(cache=True, nogil=True, boundscheck=False)(_kernel_py)
    HAVE_NUMBA = True
except ImportError:  # pragma: no cover
    _kernel = _kernel_py
    HAVE_NUMBA = False


def classify_and_accumulate(bins, theta, valid, table: IntervalTable, n_bins: int,
                            hist_signal=None, hist_noise=None, want_labels: bool = True):
    """Label a block of shots and add it to the signal and noise histograms.

    Parameters
    ----------
    bins : (K, H, W) uint16 TDC codes.
    theta : (K,) rad; valid : (K,) bool (False: shot left out, label 0).
    table : :class:`IntervalTable` of the system.
    n_bins : codes above it are ignored (validated on read).
    hist_signal, hist_noise : (H*W, n_bins + 1) int64, added to in place
        (allocated when None); column N counts code N, column 0 is unused.
    want_labels : return the (K, H, W) uint8 labels (else None; faster).

    Returns
    -------
    labels, hist_signal, hist_noise.  The raw histogram is their sum.
    """
    b = np.ascontiguousarray(bins)
    if b.dtype != np.uint16:
        b = b.astype(np.uint16)
    K = b.shape[0]
    P = int(np.prod(b.shape[1:]))
    b2 = b.reshape(K, P)
    rows = table.index(theta)
    rows[~np.asarray(valid, dtype=bool)] = -1
    if hist_signal is None:
        hist_signal = np.zeros((P, n_bins + 1), dtype=np.int64)
    if hist_noise is None:
        hist_noise = np.zeros((P, n_bins + 1), dtype=np.int64)
    labels = np.empty((K, P), dtype=np.uint8) if want_labels else np.empty((0, 0), np.uint8)
    _kernel(b2, rows, table.lo, table.hi, labels, hist_signal, hist_noise, int(n_bins))
    return (labels.reshape(b.shape) if want_labels else None), hist_signal, hist_noise
