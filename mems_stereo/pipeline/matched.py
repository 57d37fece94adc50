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

For the pixels whose strongest footprint window missed the threshold but is
not far from it (candidates, :func:`mems_stereo.pipeline.peaks.candidate_rows`), pass 2 counts the
accepted detections by (step, code) over a few footprints around the window
(:func:`mems_stereo.pipeline.pass2.peak_counts_range`); :func:`confirm` slides
the (footprint × 2·FWHM) box over them, compares each box count with its
exactly known background — per step the valid shots times the first-photon
probability ``h·(1 − h)^(c−1)`` of each accepted code, ``h = 1 − exp(−λΔt)``,
the free-running expectation (signal that fires a shot first only lowers it:
conservative) — and keeps the pixel when the smallest Poisson p-value passes
``false_alarm / 2`` spread (Bonferroni) over every box position the whole scan
allows: the footprint windows of the scan times the code boxes of the widest
accepted interval.  Background alone therefore passes one of the two stages
with probability at most 1.5·``false_alarm`` per pixel (nominal: Bonferroni).  A
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


def confirm(system: System, cands: Peaks, counts: PeakCounts, table, n_per_step,
            settings: Settings, width: int, n_windows, peak_pixels, peak_steps=None,
            log_range_of=None) -> Peaks:
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
    """
    C = len(cands)
    W = system.receiver.width
    P = W * system.receiver.height
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
    for i in range(C):
        a, b = int(cands.step_lo[i]), int(cands.step_hi[i])
        if start[i + 1] <= start[i]:
            continue
        steps = np.arange(a, b + 1)
        shot = n_per_step[steps] > 0  # steps without valid shots hold nothing
        table.ensure(steps[shot])
        lo = np.where(shot, table.lo[steps, pix[i]], 1).astype(np.int64)
        hi = np.where(shot, table.hi[steps, pix[i]], 0).astype(np.int64)
        okj = lo <= hi
        if not np.any(okj):
            continue
        sl = slice(start[i], start[i + 1])
        # codes: the accepted ones within one box of a counted detection (elsewhere
        # no box reaches min_counts)
        c_lo = max(int(lo[okj].min()), int(code[sl].min()) - m)
        c_hi = min(int(hi[okj].max()), int(code[sl].max()) + m)
        # codes in cells of ``cell`` (a quarter of the box's half-width): the box is
        # ``2·(m // cell) + 1`` cells, ± m codes to within a cell
        n_cell = (c_hi - c_lo) // cell + 1
        D = np.zeros((steps.size, n_cell))
        np.add.at(D, (step[sl] - a, (code[sl] - c_lo) // cell), cnt[sl])
        h = -np.expm1(-float(np.nan_to_num(cands.rate_hz[i])) * bw)
        log1mh = np.log1p(-min(h, 1 - 1e-15))
        # background of cell k at step j: the valid shots times P(first photon in the
        # cell's codes ∩ [lo_j, hi_j]), F(c) = 1 − (1 − h)^c the chance it came by code c
        e_lo = c_lo + cell * np.arange(n_cell)
        a_c = np.maximum(e_lo[None, :], lo[:, None])
        b_c = np.minimum(e_lo[None, :] + cell - 1, hi[:, None])
        pr = np.where(b_c >= a_c, np.exp((a_c - 1.0) * log1mh) - np.exp(b_c * log1mh), 0.0)
        B = n_per_step[steps][:, None] * pr
        half_c = m // cell
        N_box = _box_sums(D, width, 2 * half_c + 1)
        B_box = _box_sums(B, width, 2 * half_c + 1)
        # whole boxes only: the box's steps inside the counted band
        half = width // 2
        valid = np.zeros(N_box.shape, bool)
        if steps.size > 2 * half:
            valid[half:steps.size - half, :] = True
        valid &= (N_box >= settings.min_counts) & (N_box > B_box)
        if not np.any(valid):
            continue
        with np.errstate(invalid="ignore"):
            p = np.where(valid, pdtrc(np.maximum(N_box - 1, 0), np.maximum(B_box, 1e-12)), 1.0)
        k = int(np.argmin(p))
        jj, ci = divmod(k, n_cell)
        n_code_pos = max(1.0, float((hi[okj] - lo[okj] + 1).max()) / ((2 * half_c + 1) * cell))
        level[i] = settings.false_alarm * MATCHED_SHARE / (max(1.0, n_windows[i]) * n_code_pos)
        p_best[i] = p[jj, ci]
        best[i] = (a + jj, c_lo + ci * cell + cell // 2, N_box[jj, ci], B_box[jj, ci])
        # per pixel the Bonferroni count of disjoint boxes (nominal; on background alone
        # it lets ~10× more through, the box sliding by single steps and cells of
        # 1/24 FWHM: bench_false_alarms.py, docs/pipeline.md); the scan p-value over
        # the whole scan's boxes for the per-frame level
        found[i] = p_best[i] < level[i]
        p_frame[i] = scan_box_sf(N_box[jj, ci], B_box[jj, ci], max(1.0, n_windows[i]),
                                 n_code_pos)
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
