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

import contextlib
import hashlib
import math
import os
from pathlib import Path

import numpy as np

from mems_stereo.geometry.uncertainty import Spreads
from mems_stereo.model.system import System
from mems_stereo.pipeline.consistency import DEFAULT_CONFIDENCE, accepted_code_intervals
from mems_stereo.util.cache import cache_dir

DEFAULT_THETA_STEP = 5e-5  # rad
FILL_BLOCK = 128  # rows computed per call of the reference (bounded, cache-sized temporaries)


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
        self._n_saved = 0  # filled rows the disk cache holds (see save_cache)

    @classmethod
    def for_settings(cls, system: System, settings) -> IntervalTable:
        """The (empty) table of a run: ``settings`` is a
        :class:`~mems_stereo.pipeline.settings.Settings` (confidence, min_range)."""
        return cls(system, settings.confidence, min_range=settings.min_range)

    @property
    def n_steps(self) -> int:
        return int(self.lo.shape[0])

    @property
    def n_pixels(self) -> int:
        return int(self.lo.shape[1])

    def index(self, theta) -> np.ndarray:
        """Row index of each angle, (K,) int64; −1 for NaN or off the grid."""
        th = np.asarray(theta, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            j = np.rint((th - self.theta_min) / self.step)
        ok = np.isfinite(j) & (j >= 0) & (j < self.n_steps)
        return np.where(ok, j, -1).astype(np.int64)

    def rows(self, theta, valid) -> np.ndarray:
        """Row of each shot, (K,) int64; −1 where the shot is left out (not
        ``valid``, NaN or off the grid)."""
        r = self.index(theta)
        r[~np.asarray(valid, dtype=bool)] = -1
        return r

    def snap(self, theta) -> np.ndarray:
        """The grid angle each shot is classified with, (K,) rad (NaN off the grid)."""
        j = self.index(theta)
        return np.where(j >= 0, self.theta_min + j * self.step, np.nan)

    def compute_rows(self, rows) -> tuple[np.ndarray, np.ndarray]:
        """``(lo, hi)`` (R, P) uint16 of the given rows ((R,) int, each 0..S−1), computed
        by the reference in blocks of :data:`FILL_BLOCK` rows; the table is not changed
        (workers compute blocks of rows for one table, see
        :mod:`mems_stereo.pipeline.distributed`)."""
        need = np.asarray(rows, dtype=np.int64)
        lo_out = np.empty((need.size, self.n_pixels), np.uint16)
        hi_out = np.empty((need.size, self.n_pixels), np.uint16)
        for a in range(0, need.size, FILL_BLOCK):
            grid = self.theta_min + self.step * need[a:a + FILL_BLOCK]
            lo, hi = accepted_code_intervals(self.system, grid, self.confidence, self.spreads,
                                             chunk_shots=FILL_BLOCK, min_range=self.min_range)
            lo = lo.reshape(grid.size, -1)
            hi = hi.reshape(grid.size, -1)
            empty = lo > hi
            lo_out[a:a + grid.size] = np.where(empty, 1, np.clip(lo, 0, 65535))
            hi_out[a:a + grid.size] = np.where(empty, 0, np.clip(hi, 0, 65535))
        return lo_out, hi_out

    def put_rows(self, rows, lo, hi) -> None:
        """Store rows computed by :meth:`compute_rows` (here or on a worker)."""
        r = np.asarray(rows, dtype=np.int64)
        self.lo[r] = lo
        self.hi[r] = hi
        self.filled[r] = True

    def missing(self, rows) -> np.ndarray:
        """The distinct rows among ``rows`` ((K,) int, −1 ignored) not yet filled, sorted."""
        r = np.asarray(rows)
        r = r[r >= 0]
        if self.filled[r].all():  # the usual case once filled: no sort of the rows
            return r[:0]
        r = np.unique(r)
        return r[~self.filled[r]]

    def ensure(self, rows) -> None:
        """Compute the rows not yet filled among ``rows`` ((K,) int, −1 ignored)."""
        need = self.missing(rows)
        if need.size:
            self.put_rows(need, *self.compute_rows(need))

    def fill_all(self) -> IntervalTable:
        """Compute every row now (e.g. before sending the table to workers)."""
        self.ensure(np.arange(self.n_steps))
        return self

    def load_cache(self) -> int:
        """Take the rows the disk cache holds for this table (see the module
        docstring); returns how many rows were added."""
        n = _cache_load(self)
        self._n_saved = int(np.count_nonzero(self.filled))
        return n

    def save_cache(self) -> bool:
        """Write the filled rows to the disk cache if rows were filled since
        :meth:`load_cache` (or ever); returns whether a file was written."""
        if int(np.count_nonzero(self.filled)) <= self._n_saved:
            return False
        ok = _cache_save(self)
        self._n_saved = int(np.count_nonzero(self.filled))
        return ok

    def shots_per_step(self, theta, valid, block: int = 1 << 20) -> np.ndarray:
        """Number of valid shots classified with each angle step, (S,) int64."""
        n = np.zeros(self.n_steps, np.int64)
        th = np.asarray(theta)
        va = np.asarray(valid, dtype=bool)
        for a in range(0, th.size, block):  # blocks keep the temporaries small
            rows = self.index(th[a:a + block])
            n += np.bincount(rows[(rows >= 0) & va[a:a + block]], minlength=self.n_steps)
        return n


# --------------------------------------------------------------------------
# disk cache of filled rows

#: sources whose text changes the rows (relative to the package folder)
_ROW_SOURCES = ("errors.py", "model", "geometry", "physics", "pipeline/consistency.py",
                "pipeline/intervals.py", "io/labels.py")
_MAX_CACHED_TABLES = 16


_SOURCE_DIGEST: list = []


def _source_digest() -> bytes:
    if not _SOURCE_DIGEST:
        import cv2
        import scipy

        h = hashlib.sha256()
        root = Path(__file__).resolve().parents[1]
        for rel in _ROW_SOURCES:
            p = root / rel
            for f in sorted(p.rglob("*.py")) if p.is_dir() else [p]:
                h.update(str(f.relative_to(root)).encode())
                h.update(f.read_bytes())
        h.update(f"{np.__version__} {scipy.__version__} {cv2.__version__}".encode())
        _SOURCE_DIGEST.append(h.digest())
    return _SOURCE_DIGEST[0]


def _cache_key(table: IntervalTable) -> str:
    from mems_stereo.model.system import system_to_json

    h = hashlib.sha256(_source_digest())
    h.update(system_to_json(table.system).encode())
    h.update(repr((float(table.confidence), repr(table.spreads), table.min_range,
                   table.theta_min, table.step, table.lo.shape)).encode())
    return h.hexdigest()[:32]


def _load_rows(path: Path, table: IntervalTable):
    try:
        with np.load(path) as z:
            lo, hi, filled = z["lo"], z["hi"], z["filled"]
    except Exception:  # noqa: BLE001 - an unreadable cache file is ignored
        return None
    if lo.shape != table.lo.shape or hi.shape != lo.shape or filled.shape != table.filled.shape:
        return None
    return lo, hi, filled.astype(bool)


def _cache_load(table: IntervalTable) -> int:
    d = cache_dir()
    if d is None:
        return 0
    path = d / f"intervals-{_cache_key(table)}.npz"
    got = _load_rows(path, table)
    if got is None:
        return 0
    # used now: the oldest files are evicted (_cache_save), so a table that is read at
    # every run but not written again would otherwise go first (least recently used)
    with contextlib.suppress(OSError):
        os.utime(path)
    lo, hi, filled = got
    new = filled & ~table.filled
    table.put_rows(np.flatnonzero(new), lo[new], hi[new])
    return int(np.count_nonzero(new))


def _cache_save(table: IntervalTable) -> bool:
    d = cache_dir()
    if d is None:
        return False
    from mems_stereo.util.atomic import atomic_output

    path = d / f"intervals-{_cache_key(table)}.npz"
    try:
        got = _load_rows(path, table) if path.exists() else None
        if got is not None:  # another process may have added rows meanwhile
            lo, hi, filled = got
            new = filled & ~table.filled
            table.put_rows(np.flatnonzero(new), lo[new], hi[new])
        with atomic_output(path) as tmp, open(tmp, "wb") as f:
            np.savez(f, lo=table.lo, hi=table.hi, filled=table.filled)
        old = sorted(d.glob("intervals-*.npz"), key=lambda p: p.stat().st_mtime)
        for p in old[:-_MAX_CACHED_TABLES]:
            with contextlib.suppress(OSError):
                p.unlink()
    except OSError:
        return False
    return True


def shots_per_step(table: IntervalTable, theta, valid, block: int = 1 << 20) -> np.ndarray:
    """Number of valid shots classified with each angle step of ``table``, (S,) int64
    (:meth:`IntervalTable.shots_per_step`)."""
    return table.shots_per_step(theta, valid, block)


def interval_table(system: System, confidence: float = DEFAULT_CONFIDENCE,
                   spreads: Spreads | None = None, step: float = DEFAULT_THETA_STEP,
                   margin: float = 0.1, min_range: float | None = None) -> IntervalTable:
    """A new, empty (lazily filled) :class:`IntervalTable` of a system and settings.

    Build one per run and pass it to the stages; nothing is cached between
    calls.  The grid covers ``θ0 ± θ_mech,max·(1 + margin)``; shots outside it
    are left out like shots of unknown angle.  Filling all rows of the paper's
    system (≈ 9,100 steps of 50 µrad × 192 pixels) takes about a second.
    """
    return IntervalTable(system, confidence, spreads, step, margin, min_range)
