"""The fast classifier: accepted code intervals compiled ahead per scan-angle step.

The consistency test of :mod:`mems_stereo.pipeline.consistency` depends only on
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
(:func:`mems_stereo.pipeline.consistency.classify_bins`) applied to the **snapped**
angles gives labels identical to the fast path; the tests check exactly that.
"""

from __future__ import annotations

import math

import numpy as np

from mems_stereo.geometry.uncertainty import Spreads
from mems_stereo.model.system import System, system_to_json
from mems_stereo.pipeline.consistency import DEFAULT_CONFIDENCE, accepted_code_intervals

DEFAULT_THETA_STEP = 5e-5  # rad


class IntervalTable:
    """Accepted code intervals per scan-angle step and pixel, filled on demand.

    Row ``j`` holds the intervals for the angle ``θ_j = theta_min + j·step``;
    rows are computed by the reference
    :func:`~mems_stereo.pipeline.consistency.accepted_code_intervals` the first time a
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
