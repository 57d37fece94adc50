"""The fusion's sums per peak: the range mode of a peak's detections
(:class:`RangeMode`), weighted sums of point estimates (:class:`EstimateSums`) and
all of a peak's sums (:class:`PeakSums`); each adds with ``+`` so partial
results of chunks, parts and workers combine exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mems_stereo.physics.first_photon import (
    MU_GRID,
)
from mems_stereo.pipeline.classify_kernel import compiles
from mems_stereo.util.lazy_numba import compiled_if_loaded


def add_rows(A, q, V) -> None:
    """``np.add.at(A, q, V)`` for A (Q, ...) float64 and V (N, ...), the same bits,
    one ``np.bincount`` per column instead of the slow multi-dimensional ``add.at``:
    bincount adds the weights one after the other in entry order, starting here
    from the row's current value (a sum that starts from +0 never holds −0, so
    ``0 + A`` is ``A``)."""
    q = np.asarray(q, np.int64)
    Q = A.shape[0]
    if q.size == 0:  # nothing to add (also no peaks at all: A of shape (0, ...))
        return
    Af = A.reshape(Q, -1)
    if Af.shape[1] == 1 or not A.flags.c_contiguous:
        np.add.at(A, q, V)
        return
    Vf = np.asarray(V, np.float64).reshape(q.size, -1)
    kernel = _compiled("rows") if compiles(q.size, COMPILED_ROWS) else None
    if kernel is not None:
        kernel(Af, q, np.ascontiguousarray(Vf))
        return
    idx = np.concatenate([np.arange(Q), q])
    for j in range(Af.shape[1]):
        Af[:, j] = np.bincount(idx, weights=np.concatenate([Af[:, j], Vf[:, j]]),
                               minlength=Q)


def add_rows_gathered(A, q, rows, run, m) -> None:
    """``np.add.at(A, q, rows[run] * m[:, None])`` without the (N, J) temporaries, the
    same bits: A (Q, J), q (N,) row of A, rows (R, J), run (N,) row of ``rows``, m (N,);
    one contiguous gather and ``np.bincount`` per column (see :func:`add_rows`)."""
    q = np.asarray(q, np.int64)
    Q = A.shape[0]
    if q.size == 0:
        return
    if not A.flags.c_contiguous:  # pragma: no cover - the sums are contiguous
        np.add.at(A, q, rows[run] * m[:, None])
        return
    kernel = _compiled("gathered") if compiles(q.size, COMPILED_ROWS) else None
    if kernel is not None:
        kernel(A, q, np.ascontiguousarray(rows, np.float64), np.asarray(run, np.int64),
               np.asarray(m, np.float64))
        return
    cols = np.ascontiguousarray(np.asarray(rows, np.float64).T)
    idx = np.concatenate([np.arange(Q), q])
    for j in range(A.shape[1]):
        A[:, j] = np.bincount(idx, weights=np.concatenate([A[:, j], cols[j][run] * m]),
                              minlength=Q)


#: entries from which :func:`add_rows` and :func:`add_rows_gathered` run compiled, where
#: numba is loaded already (a dense run's pass 1 loaded it; small runs load no numba)
COMPILED_ROWS = 4096


def _add_rows_py(A, q, V):
    """A[q[i], j] += V[i, j] in entry order (A (Q, J), q (N,), V (N, J)): np.add.at's
    sums, bit for bit (the compiled form of :func:`add_rows`)."""
    for i in range(q.size):
        r = q[i]
        for j in range(A.shape[1]):
            A[r, j] += V[i, j]


def _add_rows_gathered_py(A, q, rows, run, m):
    """A[q[i], j] += rows[run[i], j] · m[i] in entry order (the compiled form of
    :func:`add_rows_gathered`)."""
    for i in range(q.size):
        r, g, w = q[i], run[i], m[i]
        for j in range(A.shape[1]):
            A[r, j] += rows[g, j] * w


def _add_scaled_py(A, q, V, m):
    """A[q[i], j] += V[i, j] · m[i] in entry order (A (Q, J), V (N, J)): add_rows of the
    products ``V · m[:, None]``, bit for bit."""
    for i in range(q.size):
        r, w = q[i], m[i]
        for j in range(A.shape[1]):
            A[r, j] += V[i, j] * w


def _add_outer_scaled_py(A, q, g, m):
    """A[q[i], 3a + b] += (g[i, a] · g[i, b]) · m[i] in entry order (A (Q, 9), g (N, 3)):
    add_rows of ``g[:, :, None] * g[:, None, :] * m[:, None, None]``, bit for bit."""
    for i in range(q.size):
        r, w = q[i], m[i]
        for a in range(3):
            for b in range(3):
                A[r, 3 * a + b] += (g[i, a] * g[i, b]) * w


_PY_KERNELS = {"rows": _add_rows_py, "gathered": _add_rows_gathered_py,
               "scaled": _add_scaled_py, "outer": _add_outer_scaled_py}


def _compiled(name: str):
    """The numba form of ``_add_rows_py`` ("rows"), ``_add_rows_gathered_py``
    ("gathered"), ``_add_scaled_py`` ("scaled") or ``_add_outer_scaled_py`` ("outer")
    where numba is imported already, else None (:func:`compiled_if_loaded`)."""
    return compiled_if_loaded(_PY_KERNELS[name])


class RangeMode:
    """The centre range of each of Q peaks: the mode of its detections' range intervals.

    Each detection adds its interval ``[r_i − σ_i, r_i + σ_i]`` (weight m_i) to
    a coverage count on a logarithmic range grid (relative step ``rel_step``,
    from ``r_min`` to ``r_max`` m); coverages of chunks add (``a + b``).
    :meth:`finish` gives the middle of the contiguous range where the coverage
    stays above half its maximum, and half that range's width: a strong
    return fires the pixel while the spot's tails are still on it, its
    detections' stereo ranges then cover a plateau (several σ of one
    detection wide) whose first maximum is anywhere on it; its middle is
    where the spot was centred on the pixel.  A sharp cluster of a few
    near-range background detections cannot outvote a broad cluster of many
    true returns.
    """

    def __init__(self, Q: int, r_min: float = 0.01, r_max: float = 1000.0,
                 rel_step: float = 2e-3):
        self.log_min = float(np.log(r_min))
        self.dlog = float(np.log1p(rel_step))
        self.n_grid = int(np.ceil((np.log(r_max) - self.log_min) / self.dlog)) + 1
        self.cover = np.zeros((int(Q), self.n_grid + 1), np.float64)

    def __add__(self, other: RangeMode) -> RangeMode:
        new = object.__new__(RangeMode)
        new.__dict__.update(self.__dict__)
        new.cover = self.cover + other.cover
        return new

    def zeroed(self) -> RangeMode:
        new = object.__new__(RangeMode)
        new.__dict__.update(self.__dict__)
        new.cover = np.zeros_like(self.cover)
        return new

    def _bin(self, r):
        with np.errstate(divide="ignore", invalid="ignore"):
            b = np.floor((np.log(np.maximum(r, 1e-300)) - self.log_min) / self.dlog)
        return np.clip(np.nan_to_num(b, nan=0), 0, self.n_grid - 1).astype(np.int64)

    def add(self, peak, r, sr, m) -> None:
        """Intervals r ± sr (N,) m of peaks ``peak`` (N,) with weights m (N,)."""
        lo = self._bin(r - sr)
        hi = self._bin(r + sr)
        np.add.at(self.cover, (peak, lo), m)
        np.add.at(self.cover, (peak, hi + 1), -m)

    def finish(self):
        """(centre (Q,) m, NaN without detections; halfwidth (Q,) m).  Where numba is
        loaded a compiled pass per peak (:func:`_mode_band_py`) gives the band's
        ends without the (Q, n_grid) temporaries: the same numbers."""
        Q = self.cover.shape[0]
        kernel = compiled_if_loaded(_mode_band_py) if Q else None
        if kernel is not None:
            lo, hi = np.zeros(Q, np.int64), np.zeros(Q, np.int64)
            top = np.zeros(Q)
            kernel(np.ascontiguousarray(self.cover), self.n_grid, lo, hi, top)
        else:
            density = np.cumsum(self.cover, axis=1)[:, :self.n_grid]
            j = np.argmax(density, axis=1)
            top = density[np.arange(Q), j]
            below = density < 0.5 * top[:, None]
            idx = np.arange(self.n_grid)[None, :]
            lo = np.where(below & (idx < j[:, None]), idx, -1).max(axis=1) + 1
            hi = np.where(below & (idx > j[:, None]), idx, self.n_grid).min(axis=1) - 1
        r_lo = np.exp(self.log_min + lo * self.dlog)
        r_hi = np.exp(self.log_min + (hi + 1) * self.dlog)
        ok = top > 0
        return np.where(ok, 0.5 * (r_lo + r_hi), np.nan), np.where(ok, 0.5 * (r_hi - r_lo), 0.0)


def _mode_band_py(cover, n_grid, lo, hi, top):  # pragma: no cover - compiled by numba
    """:meth:`RangeMode.finish`'s band row by row (the numba kernel): the coverage
    density (``np.cumsum``'s running sum of the row's first ``n_grid`` entries), its
    first maximum (the first NaN, as ``np.argmax``) ``top``, and the last grid point
    before it and the first after it where the density is below half of it: writes
    ``lo`` (one after that, 0 if none), ``hi`` (one before, n_grid − 1 if none), ``top``."""
    d = np.empty(n_grid)
    for q in range(cover.shape[0]):
        # the row's density is 0 before its first nonzero entry a and constant after
        # its last b: a maximum above 0 lies in a..b, and the band's ends are found
        # within a − 1 .. b + 1 (the density there is 0, resp. the row's sum, below
        # half of it: the intervals' +m and −m add to 0 but for rounding)
        a, b = 0, -1
        for k in range(n_grid):
            if cover[q, k] != 0:
                if b < 0:
                    a = k
                b = k
        if b < 0 or a == 0 or b + 1 >= n_grid:  # nothing, or the whole row: every entry
            a, b = 0, n_grid - 1
        else:
            a, b = a - 1, b + 1
        acc = cover[q, 0] if a == 0 else 0.0
        d[a] = acc
        for k in range(a + 1, b + 1):
            acc = acc + cover[q, k]
            d[k] = acc
        j, v = a, d[a]
        if v == v:
            for k in range(a + 1, b + 1):
                if d[k] != d[k]:
                    j = k
                    break
                if d[k] > v:
                    j, v = k, d[k]
        if a > 0 and d[j] <= 0:  # no maximum above 0: the first maximum is a 0 before a
            j = a
        top[q] = d[j]
        thr = 0.5 * d[j]
        lo[q] = 0
        for k in range(j - 1, a - 1, -1):
            if d[k] < thr:
                lo[q] = k + 1
                break
        hi[q] = n_grid - 1
        for k in range(j + 1, b + 1):
            if d[k] < thr:
                hi[q] = k - 1
                break


@dataclass
class EstimateSums:
    """Per-peak sums of one estimate (fused, stereo or time of flight), Q peaks.

    W : (Q,) Σ m·w; X : (Q, 3) Σ m·w·x; C : (Q, 3, 3) Σ |m|·w²·C_i (a
    subtracted background entry, m < 0, adds its variance as a detection
    does); D : (Q, 3) Σ m·w·∂x/∂L and G : (Q, 3, 3) Σ |m|·w²·(∂x/∂L)(∂x/∂L)ᵀ
    for the first-photon correction (None for the stereo estimate, which has
    no time).  Sums of disjoint chunks add (``a + b``).
    """

    W: np.ndarray
    X: np.ndarray
    C: np.ndarray
    D: np.ndarray | None = None
    G: np.ndarray | None = None

    @classmethod
    def zeros(cls, Q: int, timed: bool) -> EstimateSums:
        return cls(np.zeros(Q), np.zeros((Q, 3)), np.zeros((Q, 3, 3)),
                   np.zeros((Q, 3)) if timed else None,
                   np.zeros((Q, 3, 3)) if timed else None)

    def __add__(self, other: EstimateSums) -> EstimateSums:
        def add(a, b):
            return None if a is None else a + b

        return EstimateSums(self.W + other.W, self.X + other.X, self.C + other.C,
                            add(self.D, other.D), add(self.G, other.G))

    @classmethod
    def concat(cls, parts) -> EstimateSums:
        """The sums of consecutive blocks of peaks as one (rows concatenated)."""
        def cat(name):
            vals = [getattr(p, name) for p in parts]
            return None if vals[0] is None else np.concatenate(vals)

        return cls(*(cat(k) for k in ("W", "X", "C", "D", "G")))

    def add(self, q, x, C, m, g=None) -> None:
        """Add entries of peaks ``q`` (N,): points x (N, 3), covariances C (N, 3, 3),
        multiplicities m (N,), ∂x/∂L g (N, 3) (timed estimates)."""
        np.add.at(self.W, q, m)
        q = np.asarray(q, np.int64)
        kernel = _compiled("scaled") if compiles(q.size, COMPILED_ROWS) else None
        if kernel is not None and all(a is None or a.flags.c_contiguous
                                      for a in (self.X, self.C, self.D, self.G)):
            # the products below, added entry after entry: the same bits, no temporaries
            m = np.asarray(m, np.float64)
            am = np.abs(m)
            kernel(self.X, q, np.ascontiguousarray(x, np.float64), m)
            kernel(self.C.reshape(self.C.shape[0], 9), q,
                   np.ascontiguousarray(C, np.float64).reshape(-1, 9), am)
            if self.D is not None and g is not None:
                g = np.ascontiguousarray(g, np.float64)
                kernel(self.D, q, g, m)
                _compiled("outer")(self.G.reshape(self.G.shape[0], 9), q, g, am)
            return
        add_rows(self.X, q, x * m[:, None])
        add_rows(self.C, q, C * np.abs(m)[:, None, None])
        if self.D is not None and g is not None:
            add_rows(self.D, q, g * m[:, None])
            add_rows(self.G, q, g[:, :, None] * g[:, None, :] * np.abs(m)[:, None, None])

    def mean(self):
        """(x̄ (Q, 3), covariance (Q, 3, 3)) = (X / W, C / W²)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return self.X / self.W[:, None], self.C / (self.W ** 2)[:, None, None]

    def dL(self):
        """(Q, 3) mean ∂x/∂L and (Q, 3, 3) its second moment, each / W (resp. W²)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return self.D / self.W[:, None], self.G / (self.W ** 2)[:, None, None]


#: the scalar per-peak sums of :class:`PeakSums` (each (Q,))
_SCALARS = ("n", "detections", "code", "weight", "theta", "w", "wr", "wrr", "window", "b0",
            "b1", "b2", "bt1", "bt2")


@dataclass
class PeakSums:
    """Everything the inliers of Q peaks add up to (sums of chunks add: ``a + b``).

    n : Σ m (inliers); detections : Σ m over the inliers that are detections (m > 0,
    not subtracted background: the count ``min_counts`` applies to); code, weight,
    theta : Σ m·code, Σ m·stereo weight, Σ m·θ; w, wr, wrr : Σ m/σ², Σ m·r/σ²,
    Σ m·r²/σ² (the scatter test);
    window : Σ m over the whole window; b0, b1, b2 : Σ b, Σ b·θ, Σ b·θ² of the
    subtracted background (its variance; θ the entries' scan angles, rad), bt1, bt2 :
    Σ b·r_tof, Σ b·r_tof² (the same for the time-of-flight ranges); loglik : (Q, J) the detections'
    log-odds on the μ0 grid; fused, stereo, tof : :class:`EstimateSums`.
    """

    n: np.ndarray
    detections: np.ndarray
    code: np.ndarray
    weight: np.ndarray
    theta: np.ndarray
    w: np.ndarray
    wr: np.ndarray
    wrr: np.ndarray
    window: np.ndarray
    b0: np.ndarray
    b1: np.ndarray
    b2: np.ndarray
    bt1: np.ndarray
    bt2: np.ndarray
    loglik: np.ndarray
    fused: EstimateSums
    stereo: EstimateSums
    tof: EstimateSums

    @classmethod
    def zeros(cls, Q: int) -> PeakSums:
        return cls(*(np.zeros(Q) for _ in _SCALARS), np.zeros((Q, MU_GRID.size)),
                   EstimateSums.zeros(Q, True), EstimateSums.zeros(Q, False),
                   EstimateSums.zeros(Q, True))

    def __add__(self, other: PeakSums) -> PeakSums:
        return PeakSums(*(getattr(self, k) + getattr(other, k) for k in _SCALARS),
                        self.loglik + other.loglik, self.fused + other.fused,
                        self.stereo + other.stereo, self.tof + other.tof)

    @classmethod
    def concat(cls, parts) -> PeakSums:
        """The sums of consecutive blocks of peaks as one (rows concatenated)."""
        return cls(*(np.concatenate([getattr(p, k) for p in parts]) for k in _SCALARS),
                   np.concatenate([p.loglik for p in parts]),
                   *(EstimateSums.concat([getattr(p, k) for p in parts])
                     for k in ("fused", "stereo", "tof")))

    def estimate(self, name: str) -> EstimateSums:
        return getattr(self, name)
