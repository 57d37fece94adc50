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
coarse to fine (:class:`_BoxGrid`).  A
confirmation that no neighbour on the same surface supports — no first-stage
peak or confirmation grown from them within
:data:`~mems_stereo.pipeline.peaks.SUPPORT_COLUMNS` at an agreeing range
(:func:`mems_stereo.pipeline.peaks.neighbour_support`,
:func:`mems_stereo.pipeline.peaks.support_ranges`) — must pass the per-frame
level, as in the first stage: its box's scan p-value (:func:`scan_box_sf`) below
``MATCHED_SHARE · FRAME_FALSE_ALARMS / n_pixels``.
"""

from __future__ import annotations

import numpy as np
from scipy.special import pdtrc

from mems_stereo.model.system import System
from mems_stereo.pipeline.pass2 import PeakCounts, decode_peak_keys
from mems_stereo.pipeline.peaks import (
    FRAME_FALSE_ALARMS,
    SUPPORT_COLUMNS,
    Peaks,
    neighbour_support,
    scan_sf,
    support_ranges,
    window_rows,
)
from mems_stereo.pipeline.settings import Settings

#: share of ``false_alarm`` given to the matched-filter stage
MATCHED_SHARE = 0.5
#: cells of codes per half box (the box is ± one FWHM to within a cell; coarser
#: cells, 4 per half box, lost half the confirmations of sweep case 15015)
CELLS_PER_HALF_BOX = 24
#: the most (step × cell) positions a candidate's grid is searched at in full; beyond
#: (a whole scan's band of steps: candidates search it all, see
#: :data:`~mems_stereo.pipeline.peaks.CANDIDATE_WHOLE_SCAN`), coarse to fine
FULL_SCAN_CELLS = 400_000
#: the same for a whole scan's grid (thousands of steps × a narrow interval: the
#: exhaustive search took 40–50 ms a pixel on the dense floodlight, the coarse one 5)
WHOLE_SCAN_FULL_CELLS = 50_000
#: coarse blocks per box side in the coarse search (a box quantised to within 1/4;
#: sweep case 30003 keeps the 68 points of 1/8 with a quarter of the coarse grid)
COARSE_BOX_UNITS = 4
#: coarse boxes refined exactly
COARSE_TOP = 4
#: in the refinement the Poisson tail is evaluated only at boxes whose deviance
#: N ln(N/B) − (N − B) is within this of the largest
DEVIANCE_MARGIN = 5.0


def score_candidates(system: System, cands: Peaks, counts: PeakCounts, table, n_per_step,
                     settings: Settings, width: int, n_windows) -> dict:
    """Each candidate's best box and its tests (the per-candidate part of
    :func:`confirm`, which a Dask run computes in blocks of candidates on its workers,
    where their counts are: :func:`candidates_block`).

    Returns (C,) arrays ``found`` (bool: the box passes its test's per-pixel level),
    ``best`` (C, 4) (centre step, centre code, count, background), ``p_best``,
    ``p_frame`` (the box's scan p-value over the whole scan) and ``level``."""
    C = len(cands)
    W = system.receiver.width
    n_bins = system.tdc.n_bins
    S = table.n_steps
    bw = system.tdc.bin_width
    m = max(1, int(round(system.laser.pulse_fwhm / bw)))
    cell = max(1, m // CELLS_PER_HALF_BOX)
    n_per_step = np.asarray(n_per_step, np.float64)
    q, step, code = decode_peak_keys(counts.keys, S, n_bins + 1)
    cnt = counts.counts.astype(np.float64)
    order = np.argsort(q, kind="stable")
    q, step, code, cnt = q[order], step[order], code[order], cnt[order]
    start = np.searchsorted(q, np.arange(C + 1))
    found = np.zeros(C, bool)
    best = np.zeros((C, 4))  # j0, c0, count, background
    p_best = np.ones(C)
    p_frame = np.ones(C)  # the best box's scan p-value over the whole scan
    level = np.zeros(C)
    pix = cands.pixel(W)
    half_c = m // cell
    box_codes = (2 * half_c + 1) * cell
    local_lo = getattr(cands, "local_lo", None)
    local_hi = getattr(cands, "local_hi", None)

    def search(i, a, b, whole):
        """The candidate's best box over steps a..b: ``(p, j0, c0, count, background,
        level, code positions per window)`` or None."""
        steps = np.arange(a, b + 1)
        shot = n_per_step[steps] > 0  # steps without valid shots hold nothing
        table.ensure(steps[shot])
        lo = np.where(shot, table.lo[steps, pix[i]], 1).astype(np.int64)
        hi = np.where(shot, table.hi[steps, pix[i]], 0).astype(np.int64)
        okj = lo <= hi
        if not np.any(okj):
            return None
        sl = slice(start[i], start[i + 1])
        e_step, e_code, e_cnt = step[sl], code[sl], cnt[sl]
        inside = (e_step >= a) & (e_step <= b)
        if not np.all(inside):
            e_step, e_code, e_cnt = e_step[inside], e_code[inside], e_cnt[inside]
        if e_step.size == 0:
            return None
        # codes: the accepted ones within one box of a counted detection (elsewhere
        # no box reaches min_counts)
        c_lo = max(int(lo[okj].min()), int(e_code.min()) - m)
        c_hi = min(int(hi[okj].max()), int(e_code.max()) + m)
        # codes in cells of ``cell`` (a quarter of the box's half-width): the box is
        # ``2·(m // cell) + 1`` cells, ± m codes to within a cell
        n_cell = (c_hi - c_lo) // cell + 1
        h = -np.expm1(-float(np.nan_to_num(cands.rate_hz[i])) * bw)
        grid = _BoxGrid(e_step - a, (e_code - c_lo) // cell, e_cnt, lo, hi,
                        n_per_step[steps], c_lo, cell, np.log1p(-min(h, 1 - 1e-15)),
                        steps.size, n_cell)
        box = grid.best(width, 2 * half_c + 1, settings.min_counts,
                        WHOLE_SCAN_FULL_CELLS if whole else None)
        if box is None:
            return None
        p_min, jj, ci, n_box, b_box = box
        if whole:
            # the box positions of the whole scan: its accepted (step, code) area over
            # one box's, as code positions per footprint window (the widest interval
            # times the windows over-counts them where the width varies: a scan past
            # the beam's vanishing point accepts every code at a few steps)
            area = float(np.sum(hi[okj] - lo[okj] + 1))
            n_code_pos = max(1.0, area / (width * box_codes) / max(1.0, float(n_windows[i])))
        else:  # the first stage's window: the code boxes of its widest interval
            n_code_pos = max(1.0, float((hi[okj] - lo[okj] + 1).max()) / box_codes)
        lvl = settings.false_alarm * MATCHED_SHARE / (max(1.0, n_windows[i]) * n_code_pos)
        return (p_min, a + jj, c_lo + ci * cell + cell // 2, n_box, b_box, lvl, n_code_pos)

    for i in range(C):
        if start[i + 1] <= start[i]:
            continue
        # two tests, each at the stage's share of false_alarm: the footprints around
        # the first stage's strongest window (a near miss of that stage, the
        # confirmations of before), then the candidate's whole scan (where the
        # accepted interval is much wider than the pulse that window is where the
        # background bunched: sweep case 30003, the returns 1,000–8,000 steps from it)
        res = None
        if local_lo is not None and local_lo[i] >= 0:
            res = search(i, int(local_lo[i]), int(local_hi[i]), False)
        a, b = int(cands.step_lo[i]), int(cands.step_hi[i])
        if (res is None or not res[0] < res[5]) and not (
                local_lo is not None and (local_lo[i], local_hi[i]) == (a, b)):
            whole = search(i, a, b, True)
            if whole is not None and (res is None or whole[0] < whole[5]):
                res = whole
        if res is None:
            continue
        p_best[i], j0, c0, n_box, b_box, level[i], n_code_pos = res
        best[i] = (j0, c0, n_box, b_box)
        # per pixel the Bonferroni count of disjoint boxes (nominal; on background alone
        # it lets 10–30× more through, the box sliding by single steps and cells of
        # 1/24 FWHM: bench_false_alarms.py, docs/pipeline.md — a confirmation also needs
        # support on a surface a first-stage peak found, or the per-frame level); the
        # scan p-value over the whole scan's boxes for the per-frame level (at the
        # per-pixel level it kept 36 of sweep case 30018's 88 points)
        found[i] = p_best[i] < level[i]
        p_frame[i] = scan_box_sf(n_box, b_box, max(1.0, n_windows[i]), n_code_pos)
    return {"found": found, "best": best, "p_best": p_best, "p_frame": p_frame,
            "level": level}


def candidates_block(cands: Peaks, n_windows, i0: int, i1: int):
    """``(candidates i0..i1−1, their n_windows)``: the fields :func:`score_candidates`
    reads (no ``background_by_step``), for a block scored elsewhere."""
    sub = Peaks(**{f: np.asarray(getattr(cands, f))[i0:i1]
                   for f in Peaks.__dataclass_fields__ if f != "background_by_step"})
    for name in ("local_lo", "local_hi"):
        v = getattr(cands, name, None)
        if v is not None:
            setattr(sub, name, np.asarray(v)[i0:i1])
    return sub, np.asarray(n_windows)[i0:i1]


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


def join_scores(parts) -> dict:
    """:func:`score_candidates`'s results of consecutive blocks, joined."""
    parts = list(parts)
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def confirm(system: System, cands: Peaks, counts: PeakCounts, table, n_per_step,
            settings: Settings, width: int, n_windows, peak_pixels, peak_steps=None,
            log_range_of=None, scores: dict | None = None) -> Peaks:
    """The candidates that the matched filter confirms, as :class:`Peaks`.

    ``cands`` : candidate peaks (their ``step_lo..step_hi`` the steps counted in
    ``counts``, ``code`` unused, ``background_by_step`` over a band that holds
    every confirmed peak's); ``counts`` : their pass-2 counts; ``table`` :
    the run's interval table; ``n_per_step`` : (S,) valid shots per step;
    ``width`` : footprint in steps; ``n_windows`` : (C,) footprint-window
    positions of each candidate's scan (the first stage's); ``peak_pixels`` : (Q,)
    flat pixels of the first stage's peaks (neighbour support), ``peak_steps`` :
    (Q,) their centre steps;
    ``log_range_of(pix, j)`` : log range of pixel ``pix`` at step ``j``: given, support
    is by range (:func:`mems_stereo.pipeline.peaks.support_ranges`), optional.  The
    confirmed peaks count the steps ``j0 ± (w//2 + w + w//2)``
    in pass 2, as the first stage's for a cluster one footprint wide.
    ``scores`` : :func:`score_candidates`'s result, if computed elsewhere (``counts``
    is then not read).
    """
    C = len(cands)
    W = system.receiver.width
    P = W * system.receiver.height
    n_bins = system.tdc.n_bins
    S = table.n_steps
    if scores is None:
        scores = score_candidates(system, cands, counts, table, n_per_step, settings, width,
                                  n_windows)
    found = np.array(scores["found"], bool)
    best, p_frame = scores["best"], scores["p_frame"]
    pix = cands.pixel(W)
    # support grows from the first stage's peaks only (a chain of confirmations may
    # extend a surface they found); a confirmation without good support carries the
    # look-elsewhere of the whole sensor (two neighbouring near misses of
    # background do not support each other)
    if np.any(found):
        anchor = np.zeros(P, bool)
        peak_pixels = np.asarray(peak_pixels, np.int64)
        anchor[peak_pixels] = True
        lr = None
        if log_range_of is not None:  # ranges of the peaks: support_ranges (P, 3)
            lr = np.full((P, 3), np.inf)
            lr[:, 0] = np.nan
            if peak_pixels.size:
                lr[peak_pixels] = support_ranges(system, table, peak_pixels,
                                                 np.asarray(peak_steps, np.int64), width)
            lr[pix[found]] = support_ranges(system, table, pix[found],
                                            best[found, 0].astype(np.int64), width)
        supported = np.zeros(C, bool)
        while True:
            sup = neighbour_support(anchor, W, SUPPORT_COLUMNS, lr)
            new = found & ~supported & sup[pix]
            if not np.any(new):
                break
            supported |= new
            anchor[pix[new]] = True
        found &= supported | (p_frame < MATCHED_SHARE * FRAME_FALSE_ALARMS / P)
    sel = np.flatnonzero(found)
    j0 = best[sel, 0].astype(np.int64)
    half = width + width // 2
    step_lo = np.maximum(0, j0 - width // 2 - half)
    step_hi = np.minimum(S - 1, j0 + width // 2 + half)
    bbs = cands.background_by_step
    rows_bbs = None
    if bbs is not None and sel.size:
        dense = np.asarray(bbs[sel].todense())
        rows_bbs = window_rows(dense, np.arange(sel.size), step_lo, step_hi)
    return Peaks(row=cands.row[sel], col=cands.col[sel], code=best[sel, 1].astype(np.int64),
                 code_lo=np.ones(sel.size, np.int64), code_hi=np.full(sel.size, n_bins, np.int64),
                 step_lo=step_lo.astype(np.int64), step_hi=step_hi.astype(np.int64),
                 counts=np.rint(best[sel, 2]).astype(np.int64), background=best[sel, 3],
                 rate_hz=cands.rate_hz[sel], background_by_step=rows_bbs)


class _BoxGrid:
    """One candidate's counts and expected background over its counted steps × code
    cells, and the smallest Poisson p-value of the (footprint × code) box over them.

    ``ds``, ``dc``, ``cnt`` : (E,) each entry's step and cell index (0-based within
    the candidate's grid) and count; ``lo``, ``hi`` : (n_steps,) the accepted codes of
    each step; ``nps`` : (n_steps,) its valid shots; cell ``k`` holds codes
    ``c_lo + cell·k …`` ; ``log1mh`` : ln(1 − h), h the chance of a background first
    photon per code.  The background of cell k at step j is the valid shots times
    P(first photon in the cell's codes ∩ [lo_j, hi_j]), F(c) = 1 − (1 − h)^c the chance
    it came by code c (the free-running expectation: conservative).
    """

    def __init__(self, ds, dc, cnt, lo, hi, nps, c_lo, cell, log1mh, n_steps, n_cell):
        self.ds, self.dc, self.cnt = ds, dc, cnt
        self.lo, self.hi, self.nps = lo, hi, nps
        self.c_lo, self.cell, self.log1mh = c_lo, cell, log1mh
        self.n_steps, self.n_cell = n_steps, n_cell

    def counts(self, j0, j1, k0, k1, fs=1, fc=1):
        """(ceil((j1−j0)/fs), ceil((k1−k0)/fc)) counts of steps j0..j1−1 × cells
        k0..k1−1, summed in blocks of fs steps × fc cells."""
        m = (self.ds >= j0) & (self.ds < j1) & (self.dc >= k0) & (self.dc < k1)
        D = np.zeros((-(-(j1 - j0) // fs), -(-(k1 - k0) // fc)))
        np.add.at(D, ((self.ds[m] - j0) // fs, (self.dc[m] - k0) // fc), self.cnt[m])
        return D

    def background(self, j0, j1, k0, k1, fc=1):
        """The expected background of steps j0..j1−1 × cells k0..k1−1, the cells summed
        in blocks of fc (see :meth:`counts`; :meth:`coarse_background` blocks steps)."""
        e_lo = self.c_lo + self.cell * (k0 + fc * np.arange(-(-(k1 - k0) // fc)))
        e_hi = np.minimum(e_lo + self.cell * fc - 1, self.c_lo + self.cell * k1 - 1)
        a_c = np.maximum(e_lo[None, :], self.lo[j0:j1, None])
        b_c = np.minimum(e_hi[None, :], self.hi[j0:j1, None])
        pr = np.where(b_c >= a_c, np.exp((a_c - 1.0) * self.log1mh)
                      - np.exp(b_c * self.log1mh), 0.0)
        return self.nps[j0:j1, None] * pr

    def coarse_background(self, fs: int, fc: int):
        """The background of blocks of ``fs`` steps × ``fc`` cells over the whole grid,
        each block of steps taken as its valid shots over the union of its accepted
        codes (an over-estimate at the intervals' ends only: the coarse search ranks
        boxes, the exact background is the refinement's)."""
        n = self.n_steps
        starts = np.arange(0, n, fs)
        shot = (self.nps > 0) & (self.lo <= self.hi)
        big = np.iinfo(np.int64).max
        lo = np.minimum.reduceat(np.where(shot, self.lo, big), starts)
        hi = np.maximum.reduceat(np.where(shot, self.hi, -1), starts)
        nps = np.add.reduceat(np.where(shot, self.nps, 0.0), starts)
        g = _BoxGrid(None, None, None, lo, hi, nps, self.c_lo, self.cell, self.log1mh,
                     starts.size, self.n_cell)
        return g.background(0, starts.size, 0, self.n_cell, fc)

    def best(self, box_s: int, box_c: int, min_counts: int, full_cells: int | None = None):
        """``(p, j, k, count, background)`` of the box (``box_s`` steps × ``box_c``
        cells, whole in steps) with the smallest Poisson p-value, or None.

        Every box position where the grid holds at most ``full_cells`` (default
        :data:`FULL_SCAN_CELLS`) cells; a larger one (a scan's whole band of steps)
        is searched coarse to fine: boxes of blocks of about
        1/:data:`COARSE_BOX_UNITS` of a box, then the
        exact boxes around the :data:`COARSE_TOP` best of them (a subset of the
        positions: the false-alarm level, set for all of them, holds)."""
        n, nc = self.n_steps, self.n_cell
        if n * nc <= (FULL_SCAN_CELLS if full_cells is None else full_cells):
            return _smallest_p(self.counts(0, n, 0, nc), self.background(0, n, 0, nc),
                               box_s, box_c, min_counts)
        fs = max(1, box_s // COARSE_BOX_UNITS)
        fc = max(1, box_c // COARSE_BOX_UNITS)
        bs, bc = -(-box_s // fs) | 1, -(-box_c // fc) | 1
        coarse = _smallest_p(self.counts(0, n, 0, nc, fs, fc), self.coarse_background(fs, fc),
                             bs, bc, min_counts, top=COARSE_TOP)
        if coarse is None:
            return None
        out = None
        for jc, kc in coarse:
            j0 = max(0, (jc - bs // 2 - 1) * fs)
            j1 = min(n, (jc + bs // 2 + 2) * fs)
            k0 = max(0, (kc - bc // 2 - 1) * fc)
            k1 = min(nc, (kc + bc // 2 + 2) * fc)
            # boxes whole in the window's cells too, except at the grid's own edges
            # (the whole search's boxes run over them; a box cut at the window's edge
            # would lose background the whole one carries)
            r = _smallest_p(self.counts(j0, j1, k0, k1), self.background(j0, j1, k0, k1),
                            box_s, box_c, min_counts, cut=(k0 == 0, k1 == nc),
                            prefilter=True)
            if r is not None and (out is None or r[0] < out[0]):
                out = (r[0], r[1] + j0, r[2] + k0, r[3], r[4])
        return out


def _smallest_p(D, B, box_s: int, box_c: int, min_counts: int, top: int = 0,
                cut=(True, True), prefilter: bool = False):
    """Over the boxes of ``box_s`` × ``box_c`` (whole in the first axis) of counts ``D``
    against background ``B``: ``(p, j, k, count, background)`` of the smallest
    Poisson p-value, or with ``top`` the (j, k) of the ``top`` smallest; None if no
    box holds ``min_counts`` above its background.  ``cut`` : whether boxes may run
    over the first / last column (else they are whole there too); ``prefilter`` : the
    tail only at boxes whose Poisson deviance is within :data:`DEVIANCE_MARGIN` of the
    largest (the smallest p lies among them: ln p ≈ −deviance up to slowly varying
    terms)."""
    N_box = _box_sums(D, box_s, box_c)
    B_box = _box_sums(B, box_s, box_c)
    half = box_s // 2
    valid = np.zeros(N_box.shape, bool)
    if D.shape[0] > 2 * half:
        valid[half:D.shape[0] - half, :] = True
    hc = box_c // 2
    if not cut[0]:
        valid[:, :hc] = False
    if not cut[1]:
        valid[:, max(0, D.shape[1] - hc):] = False
    valid &= (N_box >= min_counts) & (N_box > B_box)
    if not np.any(valid):
        return None
    if top:  # ranked by the Poisson deviance (a monotone stand-in for the tail's p)
        flat = np.flatnonzero(valid)
        n_v, b_v = N_box.ravel()[flat], np.maximum(B_box.ravel()[flat], 1e-12)
        dev = n_v * np.log(n_v / b_v) - (n_v - b_v)
        order = flat[np.argsort(-dev, kind="stable")[:top]]
        return [divmod(int(k), D.shape[1]) for k in order]
    if prefilter:  # the tail only where the deviance is near its largest (ln p ≈ −deviance)
        n_v, b_v = N_box[valid], np.maximum(B_box[valid], 1e-12)
        dev = n_v * np.log(n_v / b_v) - (n_v - b_v)
        valid[valid] = dev >= dev.max() - DEVIANCE_MARGIN
    p = np.ones(N_box.shape)  # the tail at the valid boxes only (pdtrc is the cost)
    with np.errstate(invalid="ignore"):
        p[valid] = pdtrc(np.maximum(N_box[valid] - 1, 0), np.maximum(B_box[valid], 1e-12))
    k = int(np.argmin(p))
    jj, ci = divmod(k, D.shape[1])
    return p[jj, ci], jj, ci, N_box[jj, ci], B_box[jj, ci]


def scan_box_sf(k, mu, n_windows, n_code_pos) -> float:
    """P(the largest box count of a scan over angle × code reaches ``k``), background
    alone: the box's Poisson tail with the first-order clumping of a box sliding
    along each axis (:func:`mems_stereo.pipeline.peaks.scan_sf`), the two axes
    multiplied (``n_windows`` footprint windows, ``n_code_pos`` code boxes)."""
    tail = float(pdtrc(max(k - 1, 0), max(mu, 1e-12)))
    if tail <= 0.0:
        return 0.0
    c_w = float(scan_sf(k, max(mu, 1e-12), n_windows)) / tail  # 1 + (n_w − 1)·clump
    c_c = float(scan_sf(k, max(mu, 1e-12), n_code_pos)) / tail
    return min(1.0, tail * c_w * c_c)


def _box_sums(A, h: int, w: int) -> np.ndarray:
    """Centred box sums of (h, w) (odd) over a 2-D array, zeros beyond its edges."""
    a = np.pad(A, ((h // 2 + 1, h // 2), (w // 2 + 1, w // 2)))
    c = np.cumsum(np.cumsum(a, axis=0), axis=1)
    return c[h:, w:] - c[:-h, w:] - c[h:, :-w] + c[:-h, :-w]


def merge_peaks(a: Peaks, b: Peaks) -> Peaks:
    """The peaks of ``a`` and ``b`` (distinct pixels) in one :class:`Peaks`, ordered by
    pixel (row, then column) as the detector orders them."""
    if len(b) == 0:
        return a
    from scipy.sparse import csr_array, vstack

    fields = [f for f in Peaks.__dataclass_fields__ if f != "background_by_step"]
    cat = {f: np.concatenate([getattr(a, f), getattr(b, f)]) for f in fields}
    order = np.lexsort((cat["col"], cat["row"]))
    out = {f: v[order] for f, v in cat.items()}
    bbs = None
    if a.background_by_step is not None and b.background_by_step is not None:
        bbs = csr_array(vstack([a.background_by_step, b.background_by_step]))[order]
    return Peaks(**out, background_by_step=bbs)
