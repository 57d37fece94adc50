"""The fast classifier: accepted code intervals compiled ahead per scan-angle step.

The consistency test of :mod:`mems_stereo.classify` depends only on
(scan angle θ, pixel, TDC code).  So the accepted interval ``[lo, hi]`` of
every pixel can be computed once for a grid of scan angles
``θ_j = θ_min + j·Δθ`` (an :class:`IntervalTable`) and each shot then looks
its row up by the index of its angle on the grid.  One compiled (numba) pass
over the bins labels every detection and accumulates the signal and noise
histograms at once, near the speed of reading the bins.

Snapping θ to the grid is the only approximation: with the default
Δθ = 50 µrad the predicted path length moves by at most
``|∂L/∂θ|·Δθ/2`` (about 5 mm at 5 m for the paper's system), against a bound of
several metres.  The reference NumPy path
(:func:`mems_stereo.classify.classify_bins`) applied to the **snapped**
angles gives labels identical to the fast path; the tests check exactly that.
"""

from __future__ import annotations

import math

import numpy as np

from .classify import DEFAULT_CONFIDENCE, accepted_code_intervals
from .system import System, system_to_json
from .uncertainty import Spreads

DEFAULT_THETA_STEP = 5e-5  # rad


class IntervalTable:
    """Accepted code intervals per scan-angle step and pixel, filled on demand.

    Row ``j`` holds the intervals for the angle ``θ_j = theta_min + j·step``;
    rows are computed by the reference
    :func:`~mems_stereo.classify.accepted_code_intervals` the first time a
    shot needs them (:meth:`ensure`), so the cost is proportional to the
    number of distinct angle steps seen, never more than once per step.

    Attributes
    ----------
    theta_min : float, rad, angle of row 0.
    step : float, rad, grid spacing Δθ.
    lo, hi : (S, H*W) uint16 each; code N is signal iff lo <= N <= hi
        (lo > hi: nothing accepted).  Valid only where ``filled``.
    filled : (S,) bool.
    """

    def __init__(self, system: System, confidence: float = DEFAULT_CONFIDENCE,
                 spreads: Spreads | None = None, step: float = DEFAULT_THETA_STEP,
                 margin: float = 0.1, min_range: float | None = None):
        sc = system.scanner
        half = sc.theta_mech_max * (1.0 + margin)
        n = int(math.ceil(2 * half / step)) + 1
        P = system.receiver.width * system.receiver.height
        self.system, self.confidence, self.spreads = system, confidence, spreads
        self.min_range = min_range
        self.theta_min = float(sc.theta0 - half)
        self.step = float(step)
        self.lo = np.ones((n, P), dtype=np.uint16)
        self.hi = np.zeros((n, P), dtype=np.uint16)
        self.filled = np.zeros(n, dtype=bool)

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

    def ensure(self, rows) -> None:
        """Compute the rows not yet filled among ``rows`` ((K,) int, −1 ignored)."""
        r = np.unique(np.asarray(rows)[np.asarray(rows) >= 0])
        need = r[~self.filled[r]]
        if need.size == 0:
            return
        grid = self.theta_min + self.step * need
        lo, hi = accepted_code_intervals(self.system, grid, self.confidence, self.spreads,
                                         chunk_shots=512, min_range=self.min_range)
        lo = lo.reshape(need.size, -1)
        hi = hi.reshape(need.size, -1)
        empty = lo > hi
        self.lo[need] = np.where(empty, 1, np.clip(lo, 0, 65535)).astype(np.uint16)
        self.hi[need] = np.where(empty, 0, np.clip(hi, 0, 65535)).astype(np.uint16)
        self.filled[need] = True

    def fill_all(self) -> IntervalTable:
        """Compute every row now (e.g. before sending the table to workers)."""
        self.ensure(np.arange(self.n_steps))
        return self


def shots_per_step(table: IntervalTable, theta, valid, block: int = 1 << 20) -> np.ndarray:
    """Number of valid shots classified with each angle step of ``table``, (S,) int64."""
    n = np.zeros(table.n_steps, np.int64)
    th = np.asarray(theta)
    va = np.asarray(valid, dtype=bool)
    for a in range(0, th.size, block):  # blocks keep the temporaries small
        rows = table.index(th[a:a + block])
        n += np.bincount(rows[(rows >= 0) & va[a:a + block]], minlength=table.n_steps)
    return n


_TABLE_CACHE: dict = {}


def table_key(system: System, confidence: float = DEFAULT_CONFIDENCE,
              spreads: Spreads | None = None, step: float = DEFAULT_THETA_STEP,
              margin: float = 0.1, min_range: float | None = None) -> tuple:
    """The cache key of a table: everything its rows depend on."""
    return (system_to_json(system), confidence, repr(spreads), step, margin, min_range)


def install_tables(tables: dict) -> None:
    """Put ready tables ({key: IntervalTable}) into this process's cache (Dask workers)."""
    for key, table in tables.items():
        _TABLE_CACHE[key] = table


def interval_table(system: System, confidence: float = DEFAULT_CONFIDENCE,
                   spreads: Spreads | None = None, step: float = DEFAULT_THETA_STEP,
                   margin: float = 0.1, min_range: float | None = None) -> IntervalTable:
    """The (cached, lazily filled) :class:`IntervalTable` of a system and settings.

    The grid covers ``θ0 ± θ_mech,max·(1 + margin)``; shots outside it are
    left out like shots of unknown angle.  Filling all rows of the paper's
    system (≈ 9,100 steps of 50 µrad × 192 pixels) takes a few seconds once.
    """
    key = table_key(system, confidence, spreads, step, margin, min_range)
    table = _TABLE_CACHE.get(key)
    if table is None:
        if len(_TABLE_CACHE) >= 8:
            _TABLE_CACHE.clear()
        table = _TABLE_CACHE[key] = IntervalTable(system, confidence, spreads, step, margin,
                                                  min_range)
    return table


# --------------------------------------------------------------------------
# compiled kernel


def _kernel_py(bins, rows, lo, hi, labels, hist_raw, hist_signal, hist_angle):
    """Reference semantics of the compiled kernel (pure Python; used when numba is absent).

    bins : (K, P) uint16, codes <= n_bins (checked by the caller: the kernel
    does no bounds checks); rows : (K,) int64 table row (−1: shot left out,
    label 0, not counted); lo, hi : (S, P) uint16; labels : (K, P) uint8 out;
    hist_raw, hist_signal : (P, n_bins + 1) int32 added to in place (column N
    counts code N; column 0 of ``hist_raw`` counts the slots without a
    detection); hist_angle : (P, S) int64, signal detections per pixel and
    angle step, added to in place.  Codes are cast to int64 before any arithmetic (numba would
    otherwise mix unsigned and signed integers through float64); the loop
    body has a single data-dependent branch (the rare signal count).
    """
    K, P = bins.shape
    for k in range(K):
        j = rows[k]
        if j < 0:
            for p in range(P):
                labels[k, p] = 0
            continue
        for p in range(P):
            c = np.int64(bins[k, p])
            hist_raw[p, c] += 1
            ok = (c != 0) & (np.int64(lo[j, p]) <= c) & (c <= np.int64(hi[j, p]))
            if ok:
                hist_signal[p, c] += 1
                hist_angle[p, j] += 1
            labels[k, p] = (c != 0) * (2 - ok)


def _kernel_nolabels_py(bins, rows, lo, hi, hist_raw, hist_signal, hist_angle):
    """As :func:`_kernel_py` without writing labels."""
    K, P = bins.shape
    for k in range(K):
        j = rows[k]
        if j < 0:
            continue
        for p in range(P):
            c = np.int64(bins[k, p])
            hist_raw[p, c] += 1
            if (c != 0) & (np.int64(lo[j, p]) <= c) & (c <= np.int64(hi[j, p])):
                hist_signal[p, c] += 1
                hist_angle[p, j] += 1


try:  # pragma: no cover - exercised whenever numba is installed (a declared dependency)
    import numba

    _jit = numba.njit(cache=True, nogil=True, boundscheck=False)
    _kernel = _jit(_kernel_py)
    _kernel_nolabels = _jit(_kernel_nolabels_py)
    HAVE_NUMBA = True
except ImportError:  # pragma: no cover
    _kernel, _kernel_nolabels = _kernel_py, _kernel_nolabels_py
    HAVE_NUMBA = False


def classify_and_accumulate(bins, theta, valid, table: IntervalTable, n_bins: int,
                            hist_raw=None, hist_signal=None, want_labels: bool = True,
                            hist_angle=None):
    """Label a block of shots and add it to the raw and signal histograms.

    Parameters
    ----------
    bins : (K, H, W) uint16 TDC codes.
    theta : (K,) rad; valid : (K,) bool (False: shot left out, label 0,
        not counted).
    table : :class:`IntervalTable` of the system (rows filled on demand).
    n_bins : codes above it raise :class:`~mems_stereo.errors.FormatError`.
    hist_raw, hist_signal : (H*W, n_bins + 1) int32, added to in place
        (allocated when None).  Column N counts code N; column 0 of
        ``hist_raw`` counts valid pixel-slots without a detection.  The noise
        histogram is ``hist_raw − hist_signal`` (columns 1..n_bins).
    want_labels : return the (K, H, W) uint8 labels (else None).
    hist_angle : (H*W, S) int64, signal detections per pixel and angle step of
        ``table``, added to in place (allocated when None).

    Returns
    -------
    labels, hist_raw, hist_signal (and hist_angle is filled in place).
    """
    b = np.ascontiguousarray(bins)
    if b.dtype != np.uint16:
        b = b.astype(np.uint16)
    K = b.shape[0]
    P = int(np.prod(b.shape[1:]))
    b2 = b.reshape(K, P)
    if b2.size and int(b2.max()) > n_bins:  # the kernel indexes without bounds checks
        from .errors import FormatError

        raise FormatError(f"expected codes 0..{n_bins}, found {int(b2.max())}", field="bins")
    rows = table.index(theta)
    rows[~np.asarray(valid, dtype=bool)] = -1
    table.ensure(rows)
    if hist_raw is None:
        hist_raw = np.zeros((P, n_bins + 1), dtype=np.int32)
    if hist_signal is None:
        hist_signal = np.zeros((P, n_bins + 1), dtype=np.int32)
    if hist_angle is None:
        hist_angle = np.zeros((P, table.n_steps), dtype=np.int64)
    if want_labels:
        labels = np.empty((K, P), dtype=np.uint8)
        _kernel(b2, rows, table.lo, table.hi, labels, hist_raw, hist_signal, hist_angle)
    else:
        labels = None
        _kernel_nolabels(b2, rows, table.lo, table.hi, hist_raw, hist_signal, hist_angle)
    return (labels.reshape(b.shape) if want_labels else None), hist_raw, hist_signal


def _window_keys_py(bins, rows, lo, hi, pix, win_lo, win_hi, step_lo, step_hi, n_steps, nb,
                    out):
    """Reference semantics of the compiled peak-window kernel (see :func:`peak_window_keys`)."""
    K = bins.shape[0]
    Q = pix.shape[0]
    n = 0
    for k in range(K):
        j = rows[k]
        if j < 0:
            continue
        for q in range(Q):
            if j < step_lo[q] or j > step_hi[q]:
                continue
            p = pix[q]
            c = np.int64(bins[k, p])
            if (c != 0 and win_lo[q] <= c and c <= win_hi[q]
                    and np.int64(lo[j, p]) <= c and c <= np.int64(hi[j, p])):
                out[n] = (q * n_steps + j) * nb + c
                n += 1
    return n


try:  # pragma: no cover - numba is a declared dependency
    _window_keys = numba.njit(cache=True, nogil=True, boundscheck=False)(_window_keys_py)
except NameError:  # pragma: no cover
    _window_keys = _window_keys_py


def peak_window_keys(bins, theta, valid, table: IntervalTable, peak_pixel, code_lo, code_hi,
                     n_bins: int, step_lo=None, step_hi=None) -> np.ndarray:
    """Keys of the signal detections inside the peak windows of a block of shots.

    A detection of pixel ``peak_pixel[q]`` counts when its code lies in the
    peak's window ``[code_lo[q], code_hi[q]]``, its shot's angle step in
    ``[step_lo[q], step_hi[q]]`` (default: any) and the classifier accepted it
    (signal).  Its key is ``(q · S + step) · (n_bins + 1) + code``, with
    ``step`` the shot's angle step in ``table`` (S steps).  Returns (M,) int64,
    in shot order.  One compiled pass over the peak pixels only.
    """
    b = np.ascontiguousarray(bins)
    K = b.shape[0]
    b2 = b.reshape(K, -1)
    if b2.dtype != np.uint16:
        b2 = b2.astype(np.uint16)
    rows = table.index(theta)
    rows[~np.asarray(valid, dtype=bool)] = -1
    table.ensure(rows)
    pix = np.asarray(peak_pixel, dtype=np.int64)
    s_lo = np.zeros(pix.size, np.int64) if step_lo is None else np.asarray(step_lo, np.int64)
    s_hi = (np.full(pix.size, table.n_steps, np.int64) if step_hi is None
            else np.asarray(step_hi, np.int64))
    out = np.empty(K * max(1, pix.size), np.int64)
    n = _window_keys(b2, rows, table.lo, table.hi, pix, np.asarray(code_lo, np.int64),
                     np.asarray(code_hi, np.int64), s_lo, s_hi, int(table.n_steps),
                     int(n_bins) + 1, out)
    return out[:n].copy()
