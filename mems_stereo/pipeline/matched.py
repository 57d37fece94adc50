"""Second detector stage: a matched filter over scan angle × code for near-miss pixels.

The peak detector (:func:`mems_stereo.pipeline.peaks.find_peaks`) counts, per
angle step, every detection the classifier accepted: the whole accepted code
interval, whose width is the pulse (±k·c·σ_t) combined with the pixel's extent
along the epipolar line.  Far away, or with a short baseline, the extent
dominates (hundreds of codes where the pulse is ~100), and so does the
background inside it.  A surface, though, returns at one path length L0 over
the footprint of steps in which the beam crosses the pixel: under the
hypothesis "a return at step j0 and code c0", the detections lie within one
footprint of j0 in angle and within ± one pulse FWHM of c0 in code.

Every pixel without a first-stage peak is a candidate
(:func:`mems_stereo.pipeline.peaks.peaks_of_scores`); pass 2 counts its accepted
detections by (step, code) over its whole scan
(:func:`mems_stereo.pipeline.pass2.peak_counts_range`), and
:func:`score_candidates` slides the (footprint × 2·FWHM) box over them, comparing
each box count with its exactly known background — per step the valid shots
times the first-photon probability ``h·(1 − h)^(c−1)`` of each accepted code,
``h = 1 − exp(−λΔt)``, the free-running expectation (signal that fires a shot
first only lowers it: conservative).  Two tests, each at ``false_alarm / 2``
(Bonferroni over its box positions): for a near miss of the first stage
(its strongest window's adjusted p below
:data:`~mems_stereo.pipeline.peaks.CANDIDATE_P`) the boxes within a few
footprints of that window, against the footprint windows of the scan times the
code boxes of that window's widest accepted interval; then the boxes of the
whole scan, against the scan's accepted (step, code) area over one box's.
Background alone therefore passes one of the stages with probability at most
2·``false_alarm`` per pixel (nominal: Bonferroni).  Large grids are searched
coarse to fine (:class:`~mems_stereo.pipeline.matched_boxes.BoxGrid`).  A
confirmation that no neighbour on the same surface supports — no first-stage
peak or confirmation grown from them within
:data:`~mems_stereo.pipeline.peak_support.SUPPORT_COLUMNS` at an agreeing range
(:func:`mems_stereo.pipeline.peak_support.neighbour_support`,
:func:`mems_stereo.pipeline.peak_support.support_ranges`) — must pass the per-frame
level, as in the first stage: its box's scan p-value (:func:`scan_box_sf`) below
``MATCHED_SHARE · FRAME_FALSE_ALARMS / n_pixels``.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

import numpy as np
from scipy.special import pdtrc

from mems_stereo.model.system import System
from mems_stereo.physics.pulse import effective_fwhm
from mems_stereo.pipeline.matched_best_kernel import BestBoxGrid, step_intervals_py
from mems_stereo.pipeline.matched_boxes import FULL_SCAN_CELLS, WHOLE_SCAN_FULL_CELLS, BoxGrid
from mems_stereo.pipeline.matched_frame_kernel import (
    BACKGROUND,
    BOX,
    CODE,
    CODE_POS,
    COUNT,
    END,
    FALLBACK,
    LEVEL,
    LOCAL_HI,
    LOCAL_LO,
    PIXEL,
    START,
    STATUS,
    STEP,
    STEP_HI,
    STEP_LO,
    P,
    frame_search,
)
from mems_stereo.pipeline.pass2 import PeakCounts, decode_peak_keys
from mems_stereo.pipeline.peak_support import (
    FRAME_FALSE_ALARMS,
    SUPPORT_COLUMNS,
    neighbour_support,
    scan_sf,
    support_ranges,
)
from mems_stereo.pipeline.peak_table import PEAK_ARRAYS, Candidates, Peaks, window_rows
from mems_stereo.pipeline.settings import Settings
from mems_stereo.util.lazy_numba import compiled_kernel

#: share of ``false_alarm`` given to the matched-filter stage
MATCHED_SHARE = 0.5
#: cells of codes per half box (the box is ± one FWHM to within a cell; coarser
#: cells lose confirmations)
CELLS_PER_HALF_BOX = 24


@dataclass(frozen=True, slots=True)
class BoxSearch:
    """A candidate's best box over a range of its steps (:func:`score_candidates`).

    p : float, the box's Poisson p-value; step, code : int, its centre (angle step of
    the interval table, TDC code); count, background : float, its count and expected
    background; level : float, the p-value the box must stay below (the stage's share
    of ``false_alarm`` over its box positions); n_code_pos : float, those positions
    per footprint window.
    """

    p: float
    step: int
    code: int
    count: float
    background: float
    level: float
    n_code_pos: float

    @property
    def passes(self) -> bool:
        """Whether the box passes its test's per-pixel level."""
        return self.p < self.level


@dataclass(frozen=True, slots=True)
class CandidateScores:
    """Each candidate's best box and its tests (:func:`score_candidates`), (C,) arrays.

    found : bool, the box passes its test's per-pixel level; step, code : float64, the
    box's centre (angle step, TDC code; integers); count, background : float64, its
    count and expected background; p_best : float64, its Poisson p-value; p_frame :
    float64, its scan p-value over the whole scan (:func:`scan_box_sf`); level :
    float64, its test's level.  A candidate without a box has found False, p 1 and
    zeros.  Blocks of consecutive candidates join with :meth:`concat`.
    """

    found: np.ndarray
    step: np.ndarray
    code: np.ndarray
    count: np.ndarray
    background: np.ndarray
    p_best: np.ndarray
    p_frame: np.ndarray
    level: np.ndarray

    @classmethod
    def concat(cls, parts) -> CandidateScores:
        """The scores of consecutive blocks of candidates, in order, as one."""
        parts = list(parts)
        return cls(*(np.concatenate([getattr(p, f) for p in parts])
                     for f in ("found", "step", "code", "count", "background", "p_best",
                               "p_frame", "level")))


class _CandidateSearch:
    """The box search of :func:`score_candidates` over the candidates' counted entries."""

    def __init__(self, system: System, cands: Candidates, counts: PeakCounts, table,
                 n_per_step, settings: Settings):
        C = len(cands)
        n_bins = system.tdc.n_bins
        self.cands, self.table, self.settings = cands, table, settings
        self.bw = system.tdc.bin_width
        self.m = max(1, int(round(effective_fwhm(system.laser) / self.bw)))
        self.cell = max(1, self.m // CELLS_PER_HALF_BOX)
        self.n_per_step = np.asarray(n_per_step, np.float64)
        q, step, code = decode_peak_keys(counts.keys, table.n_steps, n_bins + 1)
        cnt = counts.counts.astype(np.float64)
        order = np.argsort(q, kind="stable")
        q, self.step, self.code, self.cnt = q[order], step[order], code[order], cnt[order]
        self.start = np.searchsorted(q, np.arange(C + 1))
        self.pix = cands.pixel(system.receiver.width)
        self.half_c = self.m // self.cell
        self.box_codes = (2 * self.half_c + 1) * self.cell
        self.rate_hz = np.nan_to_num(cands.rate_hz)  # (as of each candidate alone)
        # a frame's table is filled at its start: no rows to compute
        self.filled = bool(np.all(getattr(table, "filled", False)))
        # one compiled kernel per window where numba is loaded (the same numbers; its
        # coarse blocks sum the valid shots in any order: whole numbers)
        self.compiled = ("numba" in sys.modules and self.step.dtype == self.code.dtype == np.int64
                         and bool(np.all(self.n_per_step == np.rint(self.n_per_step))))
        # the whole frame in one compiled call where the counts are whole numbers
        self.whole_counts = bool(np.all(self.cnt == np.rint(self.cnt)))

    def frame_scores(self) -> np.ndarray:
        """Every candidate's box by one compiled call
        (:func:`~mems_stereo.pipeline.matched_frame_kernel.frame_search`): (C, 8)
        float64, the kernel's columns (STATUS … CODE_POS)."""
        cands, C = self.cands, len(self.cands)
        ci = np.empty((C, 7), np.int64)
        ci[:, START], ci[:, END], ci[:, PIXEL] = self.start[:-1], self.start[1:], self.pix
        ci[:, LOCAL_LO], ci[:, LOCAL_HI] = cands.local_lo, cands.local_hi
        ci[:, STEP_LO], ci[:, STEP_HI] = cands.step_lo, cands.step_hi
        h = -np.expm1(-self.rate_hz * self.bw)
        cf = np.column_stack([np.log1p(-np.minimum(h, 1 - 1e-15)),
                              np.asarray(cands.n_windows, np.float64)])
        if not self.filled:  # the rows of every step a search may read
            busy = ci[:, END] > ci[:, START]
            local = busy & (ci[:, LOCAL_LO] >= 0)
            edge = np.zeros(self.table.n_steps + 1, np.int64)
            for sel, lo, hi in ((busy, STEP_LO, STEP_HI), (local, LOCAL_LO, LOCAL_HI)):
                np.add.at(edge, ci[sel, lo], 1)
                np.add.at(edge, ci[sel, hi] + 1, -1)
            steps = np.flatnonzero((np.cumsum(edge[:-1]) > 0) & (self.n_per_step > 0))
            self.table.ensure(steps)
        par_i = (self.m, self.cell, self.half_c, self.cands.width, FULL_SCAN_CELLS,
                 WHOLE_SCAN_FULL_CELLS)
        par_f = (self.settings.min_counts, self.settings.false_alarm * MATCHED_SHARE)
        return frame_search(np.stack([self.step, self.code]), self.cnt, ci, cf, self.table,
                            self.n_per_step, par_i, par_f)

    def has_entries(self, i: int) -> bool:
        """Whether candidate ``i`` has any counted entry."""
        return bool(self.start[i + 1] > self.start[i])

    def intervals(self, i: int, a: int, b: int):
        """``(lo, hi, accepted)``: candidate ``i``'s accepted codes at steps a..b
        ((b − a + 1,) int64; 1, 0 at a step without valid shots: it holds nothing) and
        (5,) int64 figures of the steps that accept a code: their number, the lowest
        and highest code, the area Σ(hi − lo + 1) and the widest interval, 0 where no
        step accepts (one compiled loop where numba is loaded,
        :func:`~mems_stereo.pipeline.matched_best_kernel.step_intervals_py`: integers)."""
        shot = self.n_per_step[a:b + 1] > 0
        if not self.filled:
            self.table.ensure(np.arange(a, b + 1)[shot])
        if self.compiled:
            return compiled_kernel(step_intervals_py)(self.n_per_step, self.table.lo,
                                                      self.table.hi, int(self.pix[i]), a, b)
        lo = np.where(shot, self.table.lo[a:b + 1, self.pix[i]], 1).astype(np.int64)
        hi = np.where(shot, self.table.hi[a:b + 1, self.pix[i]], 0).astype(np.int64)
        okj = lo <= hi
        if not np.any(okj):
            return lo, hi, np.zeros(5, np.int64)
        w = hi[okj] - lo[okj] + 1
        return lo, hi, np.array([okj.sum(), lo[okj].min(), hi[okj].max(), w.sum(), w.max()],
                                np.int64)

    def search(self, i: int, a: int, b: int, whole: bool) -> BoxSearch | None:
        """Candidate ``i``'s best box over steps a..b (``whole``: its whole scan, else
        the first stage's window), or None."""
        cands, m, cell = self.cands, self.m, self.cell
        lo, hi, accepted = self.intervals(i, a, b)
        if accepted[0] == 0:
            return None
        sl = slice(self.start[i], self.start[i + 1])
        e_step, e_code, e_cnt = self.step[sl], self.code[sl], self.cnt[sl]
        inside = (e_step >= a) & (e_step <= b)
        if not np.all(inside):
            e_step, e_code, e_cnt = e_step[inside], e_code[inside], e_cnt[inside]
        if e_step.size == 0:
            return None
        # codes: the accepted ones within one box of a counted detection (elsewhere
        # no box reaches min_counts)
        c_lo = max(int(accepted[1]), int(e_code.min()) - m)
        c_hi = min(int(accepted[2]), int(e_code.max()) + m)
        # codes in cells of ``cell`` (a quarter of the box's half-width): the box is
        # ``2·(m // cell) + 1`` cells, ± m codes to within a cell
        n_cell = (c_hi - c_lo) // cell + 1
        h = -np.expm1(-float(self.rate_hz[i]) * self.bw)
        grid = (BestBoxGrid if self.compiled and n_cell >= 1 else BoxGrid)(
            e_step - a, (e_code - c_lo) // cell, e_cnt, lo, hi, self.n_per_step[a:b + 1], c_lo,
            cell, np.log1p(-min(h, 1 - 1e-15)), n_cell)
        box = grid.best(cands.width, 2 * self.half_c + 1, self.settings.min_counts,
                        WHOLE_SCAN_FULL_CELLS if whole else None)
        if box is None:
            return None
        n_w = cands.n_windows[i]
        if whole:
            # the box positions of the whole scan: its accepted (step, code) area over
            # one box's, as code positions per footprint window (the widest interval
            # times the windows over-counts them where the width varies: a scan past
            # the beam's vanishing point accepts every code at a few steps)
            area = float(accepted[3])
            n_code_pos = max(1.0, area / (cands.width * self.box_codes) / max(1.0, float(n_w)))
        else:  # the first stage's window: the code boxes of its widest interval
            n_code_pos = max(1.0, float(accepted[4]) / self.box_codes)
        lvl = self.settings.false_alarm * MATCHED_SHARE / (max(1.0, n_w) * n_code_pos)
        return BoxSearch(box.p, a + box.j, c_lo + box.k * cell + cell // 2, box.count,
                         box.background, lvl, n_code_pos)


def _score_one(search: _CandidateSearch, i: int) -> BoxSearch | None:
    """Candidate ``i``'s box (:func:`score_candidates`) by the NumPy path, or None."""
    if not search.has_entries(i):
        return None
    cands = search.cands
    local_lo, local_hi = cands.local_lo, cands.local_hi
    # two tests, each at the stage's share of false_alarm: the footprints around
    # the first stage's strongest window (a near miss of that stage), then the
    # candidate's whole scan (where the accepted interval is much wider than the
    # pulse that window is where the background bunched)
    res = None
    if local_lo[i] >= 0:
        res = search.search(i, int(local_lo[i]), int(local_hi[i]), False)
    a, b = int(cands.step_lo[i]), int(cands.step_hi[i])
    if (res is None or not res.passes) and (local_lo[i], local_hi[i]) != (a, b):
        whole = search.search(i, a, b, True)
        if whole is not None and (res is None or whole.passes):
            res = whole
    return res


def score_candidates(system: System, cands: Candidates, counts: PeakCounts, table, n_per_step,
                     settings: Settings) -> CandidateScores:
    """Each candidate's best box and its tests (the per-candidate part of
    :func:`confirm`, which a Dask run computes in blocks of candidates on its workers,
    where their counts are: :func:`candidates_block`); ``counts`` : the candidates'
    pass-2 counts, ``table`` : the run's interval table, ``n_per_step`` : (S,) valid
    shots per step."""
    C = len(cands)
    best = np.zeros((4, C))  # step, code, count, background
    p_best = np.ones(C)
    level = np.zeros(C)
    n_code_pos = np.ones(C)
    has = np.zeros(C, bool)  # a box was found
    search = _CandidateSearch(system, cands, counts, table, n_per_step, settings)
    todo = range(C)
    if search.compiled and search.whole_counts:  # one compiled call, but for those it leaves
        out = search.frame_scores()
        has = out[:, STATUS] == BOX
        p_best[has], level[has], n_code_pos[has] = out[has, P], out[has, LEVEL], out[has, CODE_POS]
        best[:, has] = out[has][:, [STEP, CODE, COUNT, BACKGROUND]].T
        todo = np.flatnonzero(out[:, STATUS] == FALLBACK)
    for i in todo:
        res = _score_one(search, int(i))
        if res is None:
            continue
        has[i] = True
        p_best[i], level[i], n_code_pos[i] = res.p, res.level, res.n_code_pos
        best[:, i] = (res.step, res.code, res.count, res.background)
    # per pixel the Bonferroni count of disjoint boxes (nominal; on background alone
    # the box sliding by single steps and cells lets more through: a confirmation
    # also needs support on a surface a first-stage peak found, or the per-frame
    # level); the scan p-value over the whole scan's boxes for the per-frame level
    found = has & (p_best < level)
    p_frame = np.ones(C)  # the best box's scan p-value over the whole scan
    if np.any(has):
        p_frame[has] = scan_box_sf(best[2, has], best[3, has],
                                   np.maximum(1.0, cands.n_windows[has]), n_code_pos[has])
    return CandidateScores(found, *best, p_best, p_frame, level)


def candidates_block(cands: Candidates, i0: int, i1: int) -> Candidates:
    """Candidates ``i0..i1−1`` with the fields :func:`score_candidates` reads (no
    ``background_by_step``), for a block scored elsewhere."""
    return cands.take(slice(i0, i1))


def split_candidate_counts(counts: PeakCounts, edges, n_steps: int,
                           n_codes: int) -> list[PeakCounts]:
    """The counts of candidates ``i0..i1−1`` for each ``(i0, i1)`` of ``edges``,
    renumbered from 0 (keys of :func:`~mems_stereo.pipeline.pass2.encode_peak_keys`,
    sorted: contiguous slices)."""
    span = np.int64(n_steps) * np.int64(n_codes)
    out = []
    for i0, i1 in edges:
        a, b = np.searchsorted(counts.keys, [np.int64(i0) * span, np.int64(i1) * span])
        out.append(PeakCounts(counts.keys[a:b] - np.int64(i0) * span, counts.counts[a:b]))
    return out


def join_scores(parts) -> CandidateScores:
    """:func:`score_candidates`'s results of consecutive blocks, joined."""
    return CandidateScores.concat(parts)


def confirm(system: System, cands: Candidates, counts: PeakCounts, table, n_per_step,
            settings: Settings, first: Peaks, log_range_of=None,
            scores: CandidateScores | None = None) -> Peaks:
    """The candidates that the matched filter confirms, as :class:`Peaks`.

    ``cands`` : the candidates (their ``step_lo..step_hi`` the steps counted in
    ``counts``, ``background_by_step`` over a band that holds every confirmed peak's);
    ``counts`` : their pass-2 counts; ``table`` : the run's interval table;
    ``n_per_step`` : (S,) valid shots per step; ``first`` : the first stage's peaks
    (neighbour support grows from their pixels and centre steps);
    ``log_range_of(pix, j)`` : log range of pixel ``pix`` at step ``j``: given, support
    is by range (:func:`mems_stereo.pipeline.peak_support.support_ranges`), optional.
    The confirmed peaks count the steps ``j0 ± (w//2 + w + w//2)`` (``w`` the
    candidates' footprint) in pass 2, as the first stage's for a cluster one footprint
    wide.  ``scores`` : :func:`score_candidates`'s result, if computed elsewhere
    (``counts`` is then not read).
    """
    C = len(cands)
    W = system.receiver.width
    P = W * system.receiver.height
    width = cands.width
    if scores is None:
        scores = score_candidates(system, cands, counts, table, n_per_step, settings)
    found = np.array(scores.found, bool)
    pix = cands.pixel(W)
    # support grows from the first stage's peaks only (a chain of confirmations may
    # extend a surface they found); a confirmation without good support carries the
    # look-elsewhere of the whole sensor (two neighbouring near misses of
    # background do not support each other)
    if np.any(found):
        anchor = np.zeros(P, bool)
        peak_pixels = np.asarray(first.pixel(W), np.int64)
        anchor[peak_pixels] = True
        lr = None
        if log_range_of is not None:  # ranges of the peaks: support_ranges (P, 3)
            lr = np.full((P, 3), np.inf)
            lr[:, 0] = np.nan
            if peak_pixels.size:
                peak_steps = (first.step_lo + first.step_hi) // 2
                lr[peak_pixels] = support_ranges(system, table, peak_pixels,
                                                 np.asarray(peak_steps, np.int64), width)
            lr[pix[found]] = support_ranges(system, table, pix[found],
                                            scores.step[found].astype(np.int64), width)
        supported = np.zeros(C, bool)
        while True:
            sup = neighbour_support(anchor, W, SUPPORT_COLUMNS, lr)
            new = found & ~supported & sup[pix]
            if not np.any(new):
                break
            supported |= new
            anchor[pix[new]] = True
        found &= supported | (scores.p_frame < MATCHED_SHARE * FRAME_FALSE_ALARMS / P)
    return _confirmed_peaks(system, cands, scores, np.flatnonzero(found), table.n_steps)


def _confirmed_peaks(system: System, cands: Candidates, scores: CandidateScores, sel,
                     n_steps: int) -> Peaks:
    """The :class:`Peaks` of the confirmed candidates ``sel``: centred at their best
    box, counting ± 1.5 footprints around its footprint."""
    width = cands.width
    j0 = scores.step[sel].astype(np.int64)
    half = width + width // 2
    step_lo = np.maximum(0, j0 - width // 2 - half)
    step_hi = np.minimum(n_steps - 1, j0 + width // 2 + half)
    bbs = cands.background_by_step
    rows_bbs = None
    if bbs is not None and sel.size:
        dense = np.asarray(bbs[sel].todense())
        rows_bbs = window_rows(dense, np.arange(sel.size), step_lo, step_hi)
    return Peaks(row=cands.row[sel], col=cands.col[sel],
                 code=scores.code[sel].astype(np.int64),
                 code_lo=np.ones(sel.size, np.int64),
                 code_hi=np.full(sel.size, system.tdc.n_bins, np.int64),
                 step_lo=step_lo.astype(np.int64), step_hi=step_hi.astype(np.int64),
                 counts=np.rint(scores.count[sel]).astype(np.int64),
                 background=scores.background[sel], rate_hz=cands.rate_hz[sel],
                 background_by_step=rows_bbs)


def scan_box_sf(k, mu, n_windows, n_code_pos):
    """P(the largest box count of a scan over angle × code reaches ``k``), background
    alone: the box's Poisson tail with the first-order clumping of a box sliding
    along each axis (:func:`mems_stereo.pipeline.peak_support.scan_sf`), the two axes
    multiplied (``n_windows`` footprint windows, ``n_code_pos`` code boxes).  The
    arguments broadcast (float64 arrays; a float where all are scalars)."""
    k, mu = np.asarray(k, np.float64), np.maximum(np.asarray(mu, np.float64), 1e-12)
    tail = pdtrc(np.maximum(k - 1, 0), mu)
    with np.errstate(divide="ignore", invalid="ignore"):
        c_w = scan_sf(k, mu, n_windows) / tail  # 1 + (n_w − 1)·clump
        c_c = scan_sf(k, mu, n_code_pos) / tail
        p = tail * c_w * c_c
    out = np.where(tail <= 0.0, 0.0, np.where(p < 1.0, p, 1.0))
    return float(out) if out.ndim == 0 else out


def merge_peaks(a: Peaks, b: Peaks) -> Peaks:
    """The peaks of ``a`` and ``b`` (distinct pixels) in one :class:`Peaks`, ordered by
    pixel (row, then column) as the detector orders them."""
    if len(b) == 0:
        return a
    from scipy.sparse import csr_array, vstack

    cat = {f: np.concatenate([getattr(a, f), getattr(b, f)]) for f in PEAK_ARRAYS}
    order = np.lexsort((cat["col"], cat["row"]))
    out = {f: v[order] for f, v in cat.items()}
    bbs = None
    if a.background_by_step is not None and b.background_by_step is not None:
        bbs = csr_array(vstack([a.background_by_step, b.background_by_step]))[order]
    return Peaks(**out, background_by_step=bbs)
