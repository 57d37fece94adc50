"""One frame on several cores: a frame's stages in shares of its pixels and peaks.

:func:`~mems_stereo.pipeline.frames.frame_cloud` runs a frame's stages one after the
other.  Every stage after pass 1 is a function of each pixel's (or each peak's) own
data, but for two small joins over the whole sensor: the neighbour support of the
first-stage peaks, and the matched filter's confirmations (support grown from those
peaks).  A frame cut into ``n`` shares therefore runs in three steps, each share's
work on a core of its own
(:class:`~mems_stereo.pipeline.frame_workers.SplitFrameProcessor`: one worker process
per share) and the joins, small, in the caller:

1. :func:`share_scores` — each share: pass 1 of the whole frame (its shots' angles,
   classification, histograms: a few ms, the same in every share), then the peak
   detector's per-pixel scores of its pixels (every n-th pixel,
   :func:`share_pixels`).  The caller joins the shares' support inputs
   (:func:`supported_blocks`).
2. :func:`share_peaks` — each share: the first-stage peaks of its pixels, its matched
   filter candidates' pass-2 counts and each candidate's box search (the costly part of
   that stage).  The caller joins the peaks and scores, confirms the candidates and
   orders the peaks by pixel (:func:`joined_peaks`), then cuts the peaks into one
   block per share at multiples of the first-photon block
   (:data:`~mems_stereo.pipeline.first_photon_correction.FP_BLOCK`), balanced by the
   peaks' scan-angle bands (:func:`fusion_blocks`: room-light peaks cluster where the
   objects are; blocks of pixels would not balance them).
3. :func:`share_means` — each share: pass 2 of its block of peaks, their fusion up to
   the peak means and the time of each one's point.  The caller makes the cloud of the
   joined means and stamps each point with its time and band (:func:`frame_of_means`).

Each step calls the functions one process calls, on a block, as the Dask runner does
(:mod:`~mems_stereo.pipeline.dask_split`), so the cloud and counts are
:func:`frame_cloud`'s bit for bit; :func:`split_frame_cloud` runs the steps of every
share in one process (the reference the tests compare).  Every step runs inside
:func:`~mems_stereo.pipeline.frames.frame_stages` (the frames' compiled kernels and
bias removal), in the shares and in the caller alike.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from mems_stereo.model.system import System
from mems_stereo.pipeline.block_fusion import (
    cloud_of_means,
    fuse_in_blocks,
    fused_sums,
    peak_blocks,
)
from mems_stereo.pipeline.cloud import PointCloud
from mems_stereo.pipeline.frames import (
    FrameShots,
    frame_cloud,
    frame_recording,
    frame_stages,
    is_empty_frame,
    point_times,
    stamped_cloud,
)
from mems_stereo.pipeline.intervals import IntervalTable
from mems_stereo.pipeline.matched import CandidateScores, score_candidates
from mems_stereo.pipeline.pass1 import Counts, RangeAccumulation
from mems_stereo.pipeline.pass2 import PeakCounts, peak_counts_range
from mems_stereo.pipeline.peak_means import PeakMeans
from mems_stereo.pipeline.peak_support import SupportInputs
from mems_stereo.pipeline.peak_table import PEAK_ARRAYS, Candidates, Peaks
from mems_stereo.pipeline.peaks import PeakScores, peak_scores, peaks_of_scores
from mems_stereo.pipeline.run import (
    CandidateCounts,
    Histograms,
    RunInputs,
    candidates_of,
    checked_header,
    matched_stage,
    pass1_stage,
    recording_angles,
)
from mems_stereo.pipeline.settings import Settings


@dataclass(frozen=True, slots=True)
class ShareFrame:
    """What a share keeps of a frame between its steps.

    shots : the frame's :class:`~mems_stereo.pipeline.frames.FrameShots`.  run : its
    :class:`~mems_stereo.pipeline.run.RunInputs` (the shots as a Recording, their
    angles, the table).  acc : pass 1 of the whole frame.  scores : the peak detector's
    :class:`~mems_stereo.pipeline.peaks.PeakScores` of the share's ``pixels`` ((Pb,)
    int64 flat pixels ``row·width + col``, increasing).
    """

    shots: FrameShots
    run: RunInputs
    acc: RangeAccumulation
    pixels: np.ndarray
    scores: PeakScores


@dataclass(frozen=True, slots=True)
class ShareSupport:
    """Step 1's answer of a share.

    support : the :class:`~mems_stereo.pipeline.peak_support.SupportInputs` of its
    pixels.  counts : :class:`~mems_stereo.pipeline.pass1.Counts` of the frame's pass 1
    (shots, unknown angle, raw, signal, noise; peaks and points 0).  n_per_step : (S,)
    int, the frame's valid shots per angle step.
    """

    support: SupportInputs
    counts: Counts
    n_per_step: np.ndarray


@dataclass(frozen=True, slots=True)
class ShareMeans:
    """Step 3's answer of a share: its block of peaks' ``means``
    (:class:`~mems_stereo.pipeline.peak_means.PeakMeans`) and ``times``, (Qb,) float64
    s, the time of each one's point (:func:`~mems_stereo.pipeline.frames.point_times`)."""

    means: PeakMeans
    times: np.ndarray


@dataclass(frozen=True, slots=True)
class SharePeaks:
    """Step 2's answer of a share: its pixels' first-stage peaks (light: the (Q,)
    arrays), their candidates (without ``background_by_step``; None: none) and the
    candidates' :class:`~mems_stereo.pipeline.matched.CandidateScores` (None: none)."""

    first: Peaks
    candidates: Candidates | None
    scores: CandidateScores | None


def share_pixels(n_pixels: int, n_shares: int) -> list[np.ndarray]:
    """The shares' flat pixels, (Pb,) int64 each, increasing: pixel p in share p mod
    ``n_shares`` (fewer shares where there are fewer pixels).  Interleaved, so that the
    shares' work stays even where it changes across the sensor (the matched filter's
    candidates and their searches follow the scene)."""
    n = max(1, min(int(n_pixels), int(n_shares)))
    return [np.arange(r, n_pixels, n, dtype=np.int64) for r in range(n)]


def pixel_order(parts: Sequence[np.ndarray]) -> np.ndarray:
    """The permutation that puts the concatenated ``parts`` (flat pixels, or the pixels
    of peaks) in increasing order (stable: each part's own order kept)."""
    return np.argsort(np.concatenate(parts), kind="stable")


def share_scores(system: System, shots: FrameShots, settings: Settings, table: IntervalTable,
                 source: str, pixels: np.ndarray) -> tuple[ShareFrame, ShareSupport]:
    """Step 1 of a share: pass 1 of the frame's ``shots`` (as
    :func:`~mems_stereo.pipeline.run.process_recording` runs it on them) and the peak
    scores of the flat ``pixels`` (Pb,) int64, increasing; returns what the share keeps
    and what it answers."""
    rec = frame_recording(system, shots, source)
    header = checked_header(rec, system)
    theta, valid = recording_angles(header, system)
    run = RunInputs(rec, system, settings, table, theta, valid, header.shape)
    acc = pass1_stage(run, None, None, None)
    h, w = system.receiver.height, system.receiver.width
    hists = Histograms.of(acc, h, w)
    pixels = np.asarray(pixels, np.int64)
    n_bins = hists.signal.shape[2]
    sc = peak_scores(system, hists.signal.reshape(h * w, n_bins)[pixels],
                     hists.noise.reshape(h * w, n_bins)[pixels],
                     acc.hist_angle.reshape(h * w, table.n_steps)[pixels], acc.n_per_step,
                     table, settings, pixels)
    counts = Counts(int(header.shape[0]), int(acc.n_unknown), int(hists.raw.sum()),
                    int(hists.signal.sum()), int(hists.noise.sum()), 0, 0)
    return (ShareFrame(shots, run, acc, pixels, sc),
            ShareSupport(sc.support_inputs(), counts, acc.n_per_step))


def supported_blocks(answers: Sequence[ShareSupport], pixels: Sequence[np.ndarray],
                     width: int) -> list[np.ndarray]:
    """Per share, (Pb,) bool: its ``pixels``' first-stage peaks after the neighbour
    support (:func:`~mems_stereo.pipeline.peak_support.supported` over the whole sensor,
    the shares' inputs put in pixel order)."""
    order = pixel_order(pixels)
    joined = SupportInputs.concat([a.support for a in answers])
    whole = SupportInputs(*(getattr(joined, f)[order] for f in
                            ("keep", "cnt", "thr_frame", "log_range", "rate")))
    keep = np.empty(order.size, bool)
    keep[order] = whole.supported(width)
    edges = np.cumsum([0] + [p.size for p in pixels])
    return [keep[a:b] for a, b in zip(edges[:-1], edges[1:])]


def share_peaks(sf: ShareFrame, keep) -> SharePeaks:
    """Step 2 of a share: the first-stage peaks of its pixels (``keep``: their support,
    :func:`supported_blocks`), its candidates' pass-2 counts from the frame's shots and
    their box search (:func:`~mems_stereo.pipeline.matched.score_candidates`)."""
    run, nps = sf.run, sf.acc.n_per_step
    first = peaks_of_scores(run.system, sf.scores, keep, nps, run.table, run.settings)
    cands = candidates_of(first)
    if cands is None:
        return SharePeaks(first.light(), None, None)
    counts = peak_counts_range(run.source, run.system, run.shots, run.settings, cands,
                               table=run.table)
    scores = score_candidates(run.system, cands, counts, run.table, nps, run.settings)
    return SharePeaks(first.light(), cands.take(slice(None)), scores)


def joined_peaks(system: System, answers: Sequence[SharePeaks], table: IntervalTable,
                 n_per_step, settings: Settings) -> Peaks:
    """The frame's peaks from the shares' (in pixel order): the first-stage peaks joined,
    the candidates confirmed by the matched filter over the whole sensor
    (:func:`~mems_stereo.pipeline.run.matched_stage` with the shares' scores) and
    merged in."""
    W = system.receiver.width
    order = pixel_order([a.first.pixel(W) for a in answers])
    first = Peaks(**{k: np.concatenate([getattr(a.first, k) for a in answers])[order]
                     for k in PEAK_ARRAYS})
    parts = [a for a in answers if a.candidates is not None]
    if not parts:
        return first
    c = [p.candidates for p in parts]
    order = pixel_order([x.pixel(W) for x in c])
    cands = Candidates(**{k: np.concatenate([getattr(x, k) for x in c])[order]
                          for k in PEAK_ARRAYS},
                       n_windows=np.concatenate([x.n_windows for x in c])[order],
                       local_lo=np.concatenate([x.local_lo for x in c])[order],
                       local_hi=np.concatenate([x.local_hi for x in c])[order],
                       width=c[0].width)
    joined = CandidateScores.concat([p.scores for p in parts])
    scores = CandidateScores(*(getattr(joined, f)[order] for f in (
        "found", "step", "code", "count", "background", "p_best", "p_frame", "level")))
    return matched_stage(system, first, CandidateCounts(cands, None), table, n_per_step,
                         settings, scores=scores)


def fusion_blocks(peaks: Peaks, n_shares: int) -> list[tuple[int, int]]:
    """At most ``n_shares`` blocks of consecutive peaks ``(q0, q1)``, cut at multiples of
    ``FP_BLOCK`` (the fusion's first-photon groups, as the whole frame's), each near an
    equal share of the peaks' scan-angle bands (steps ``step_lo..step_hi``: the fusion's
    entries and pass 2's windows grow with them)."""
    band = np.asarray(peaks.step_hi, np.int64) - np.asarray(peaks.step_lo, np.int64) + 1
    return peak_blocks(band, n_shares)


def share_means(sf: ShareFrame, peaks: Peaks) -> ShareMeans:
    """Step 3 of a share: pass 2 of the block ``peaks`` (light) from the frame's shots,
    their fusion up to the peak means
    (:func:`~mems_stereo.pipeline.block_fusion.fused_sums`) and the time of each one's
    point."""
    run = sf.run
    counts = peak_counts_range(run.source, run.system, run.shots, run.settings, peaks,
                               table=run.table)
    means = fused_sums(run.system, peaks, counts, run.settings, sf.acc.n_per_step,
                       run.table).peak_means()
    steps = run.table.rows(run.theta, run.valid)
    return ShareMeans(means, point_times(sf.shots, steps, peaks, np.arange(len(peaks)),
                                         run.table))


def frame_of_means(system: System, shots: FrameShots, table: IntervalTable, peaks: Peaks,
                   blocks: Sequence[ShareMeans], pass1: ShareSupport,
                   settings: Settings) -> tuple[PointCloud, Counts]:
    """``(cloud, counts)`` of the frame, as :func:`frame_cloud` gives them, from its
    joined ``peaks``, the step-3 answers of their blocks in order and share 0's step-1
    answer ``pass1``."""
    if len(peaks):
        cloud = cloud_of_means([b.means for b in blocks], settings)
    else:  # no peak: the whole's (empty) cloud, its attributes included
        cloud = fuse_in_blocks(system, peaks, PeakCounts(), settings, pass1.n_per_step, table)
    c = pass1.counts
    counts = Counts(c.shots, c.shots_unknown_angle, c.raw, c.signal, c.noise, len(peaks),
                    len(cloud))
    times = (np.concatenate([b.times for b in blocks]) if blocks
             else np.zeros(0, np.float64))
    return stamped_cloud(system, shots, table, peaks, cloud, peak_times=times), counts


def split_frame_cloud(system: System, shots: FrameShots, settings: Settings,
                      table: IntervalTable, source: str,
                      n_shares: int = 2) -> tuple[PointCloud, Counts]:
    """:func:`~mems_stereo.pipeline.frames.frame_cloud`'s ``(cloud, counts)`` by the three
    steps of ``n_shares`` shares run here, one after another (the worker processes'
    reference: the same arrays, bit for bit)."""
    if is_empty_frame(shots):
        return frame_cloud(system, shots, settings, table, source)
    P = system.receiver.height * system.receiver.width
    with frame_stages():
        pixels = share_pixels(P, n_shares)
        done = [share_scores(system, shots, settings, table, source, e) for e in pixels]
        keeps = supported_blocks([a for _, a in done], pixels, system.receiver.width)
        nps = done[0][1].n_per_step
        peaks = joined_peaks(system, [share_peaks(sf, k) for (sf, _), k in zip(done, keeps)],
                             table, nps, settings)
        means = [share_means(sf, peaks.take(slice(a, b)))
                 for (sf, _), (a, b) in zip(done, fusion_blocks(peaks, n_shares))]
        return frame_of_means(system, shots, table, peaks, means, done[0][1], settings)
