"""Processing a two-axis recording: angles, classification, per-pixel histograms, peaks, cloud.

Stages (``docs/two_axis.md``), on the gated event list of
:mod:`mems_stereo.io.recording2d`:

1. :func:`shot_directions` — θ1, θ2 of every shot from the two monitors, and
   the beam direction d(θ1, θ2) (gimbal model of :mod:`mems_stereo.model.scanner2d`).
2. :func:`classify_events` — per detection, the consistency test: the beam
   ``p + s·d`` must image within ``margin`` px of the pixel's centre for some
   s in the working range, which bounds the path length to an interval
   ``[L(s_lo), L(s_hi)]`` (closed form: the image coordinates are Möbius
   functions of s); the detection is signal when its path length lies in the
   interval widened by ``k_sigma`` timing σ.  Everything else is noise.
3. :func:`pixel_histograms` — per pixel, the signal codes (a dense
   (H·W, n_bins) int32 histogram; a pixel's path length does not depend on
   the beam, so one histogram per pixel suffices).
4. :func:`find_pixel_peaks` — the strongest window of each pixel's signal
   histogram, tested against the expected background in that window (Poisson,
   rate estimated from the noise-classified detections and each pixel's
   exposure, i.e. how often the gate read it), then the mean path length of
   its detections.
5. :func:`cloud_from_peaks` — the pixel ray ∩ path-length ellipsoid
   (:func:`mems_stereo.geometry.twoaxis.pixel_point_2d`), with the 3 × 3
   covariance from the pixel's 2-D extent and the timing spread of the mean
   (:func:`mems_stereo.geometry.twoaxis.propagate_2d`) →
   :class:`~mems_stereo.pipeline.cloud.PointCloud`.

:func:`process_recording_2d` runs them; the gate is recomputed from the
recording's /readout parameters (the same function the hardware uses) to know
each pixel's exposure.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.stats import poisson

from mems_stereo.errors import FormatError
from mems_stereo.geometry.gating import GateSpec, gate_half_width, gate_pixels
from mems_stereo.geometry.twoaxis import jacobian_2d, pixel_point_2d, timing_sigma
from mems_stereo.geometry.uncertainty import polar_from_cartesian
from mems_stereo.io.recording2d import Recording2D, read_recording_2d
from mems_stereo.io.recording_checks import check_codes_fit
from mems_stereo.model.camera import normalized_coordinates
from mems_stereo.model.scanner2d import require_two_axis, scan_angles_2d, scan_direction_2d
from mems_stereo.model.system import System
from mems_stereo.pipeline.cloud import PointCloud
from mems_stereo.pipeline.gate_check import check_gate, recompute_gate
from mems_stereo.pipeline.twoaxis_pileup import pileup_correction


@dataclass(frozen=True)
class Settings2D:
    """Options of the two-axis pipeline.

    r_min, r_max : m, working range of the classification (None: the gate's,
        or 0.3 / 30 m for a full readout).
    margin_px : px, how far from the pixel centre the beam's image may pass
        (pixel half width + spot); default 0.5 + 3σ of the gate's spot.
    k_sigma : timing σ added on each side of the path-length interval.
    timing_jitter : s, SPAD/TDC jitter in the timing σ.
    false_alarm : per-pixel false-alarm probability of a peak.
    min_counts : fewest signal detections in a peak.
    window_sigma : half width of a peak window, in timing σ.
    pileup_correction : correct each peak for the first-photon bias
        (:func:`~mems_stereo.pipeline.twoaxis_pileup.pileup_correction`).
    """

    r_min: float | None = None
    r_max: float | None = None
    margin_px: float = 1.25
    k_sigma: float = 5.0
    timing_jitter: float = 50e-12
    false_alarm: float = 1e-3
    min_counts: int = 3
    window_sigma: float = 3.0
    pileup_correction: bool = True


@dataclass
class Result2D:
    """Output of :func:`process_recording_2d`.

    cloud : PointCloud; labels : (E,) uint8 (1 signal, 2 noise) per event;
    theta1, theta2 : (K,) rad; counts : dict of headline numbers; truth : dict
    of truth comparisons (None without truth); timings : s per stage.
    """

    cloud: PointCloud
    labels: np.ndarray
    theta1: np.ndarray
    theta2: np.ndarray
    counts: dict
    truth: dict | None
    timings: dict = field(default_factory=dict)
    source: str = ""


# --------------------------------------------------------------------------
# stage 1


@dataclass(frozen=True, slots=True)
class ShotDirections:
    """The beam of every shot of a two-axis recording (K shots).

    theta1, theta2 : (K,) float64 rad, the mirror angles; direction : (K, 3) float64,
    unit beam directions in the receiver frame (NaN rows where unknown); valid : (K,)
    bool, whether the shot's angles are known.
    """

    theta1: np.ndarray
    theta2: np.ndarray
    direction: np.ndarray
    valid: np.ndarray


def shot_directions(rec: Recording2D, system: System | None = None) -> ShotDirections:
    """The :class:`ShotDirections` of the recording's shots (``system``: default the
    recording's)."""
    system = rec.system if system is None else system
    require_two_axis(system)
    th1, th2, valid = scan_angles_2d(rec.shot_time, rec.zero_crossings, rec.rising,
                                     rec.monitor2, system.scanner)
    d = np.full((th1.size, 3), np.nan)
    if np.any(valid):
        d[valid] = scan_direction_2d(th1[valid], th2[valid], system.scanner)
    return ShotDirections(th1, th2, d, valid)


# --------------------------------------------------------------------------
# stage 2


def _mobius_interval(A, B, C, D, lo, hi, s0, s1):
    """s-interval within [s0, s1] where lo <= (A + sB)/(C + sD) <= hi (C + sD > 0 there)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        g0 = (A + s0 * B) / (C + s0 * D)
        g1 = (A + s1 * B) / (C + s1 * D)
        inc = g1 >= g0

        def inv(a):
            return (a * C - A) / (B - a * D)

        # increasing: [inv(lo) or s0, inv(hi) or s1]; decreasing: [inv(hi) or s0, inv(lo) or s1]
        a_lo = np.where(inc, lo, hi)
        a_hi = np.where(inc, hi, lo)
        g_start = np.where(inc, g0, -g0)
        g_end = np.where(inc, g1, -g1)
        b_start = np.where(inc, a_lo, -a_lo)
        b_end = np.where(inc, a_hi, -a_hi)
        s_lo = np.where(b_start > g_start, inv(a_lo), s0)
        s_hi = np.where(b_end < g_end, inv(a_hi), s1)
        empty = (b_start > g_end) | (b_end < g_start)
    s_lo = np.clip(s_lo, s0, s1)
    s_hi = np.clip(s_hi, s0, s1)
    return np.where(empty, np.nan, s_lo), np.where(empty, np.nan, s_hi)


def path_length_interval(system: System, d_scan, pixels_uv, r_min: float, r_max: float,
                         margin_px: float):
    """Path lengths L = |x − p| + |x| of beam points that image within ``margin_px``
    of the pixel centres, for target ranges in [r_min, r_max].

    d_scan : (N, 3) unit beam directions; pixels_uv : (N, 2) px (column, row).
    Returns ``(L_lo, L_hi)`` (N,) m; NaN where no beam point images there.
    Exact for a distortion-free receiver (the box ``|u − c| ≤ m``, ``|v − r| ≤ m``
    is tested in normalised coordinates); with distortion the pixel centre is
    undistorted and the margin scaled by 1/f (first order).
    """
    rc = system.receiver
    K = rc.camera_matrix
    p = np.asarray(system.scanner.position, dtype=np.float64)
    d = np.asarray(d_scan, dtype=np.float64)
    xy = normalized_coordinates(pixels_uv, K, rc.dist_coeffs)
    mx, my = margin_px / K[0, 0], margin_px / K[1, 1]
    pd = d @ p
    pp = float(p @ p)
    with np.errstate(invalid="ignore"):
        s0 = -pd + np.sqrt(np.maximum(pd * pd - pp + r_min ** 2, 0.0))
        s1 = -pd + np.sqrt(np.maximum(pd * pd - pp + r_max ** 2, 0.0))
    # the part of the segment in front of the camera (z > 1 mm)
    with np.errstate(invalid="ignore", divide="ignore"):
        s_front = np.where(d[:, 2] > 0, (1e-3 - p[2]) / d[:, 2], np.inf)
        s_back = np.where(d[:, 2] < 0, (1e-3 - p[2]) / d[:, 2], np.inf)
    s0 = np.maximum(s0, np.where(d[:, 2] > 0, s_front, s0))
    s1 = np.minimum(s1, np.where(d[:, 2] < 0, s_back, s1))
    ok = s1 > s0
    C, D = p[2], d[:, 2]
    a0, a1 = _mobius_interval(p[0], d[:, 0], C, D, xy[:, 0] - mx, xy[:, 0] + mx, s0, s1)
    b0, b1 = _mobius_interval(p[1], d[:, 1], C, D, xy[:, 1] - my, xy[:, 1] + my, s0, s1)
    lo = np.maximum(a0, b0)
    hi = np.minimum(a1, b1)
    good = ok & (hi >= lo)

    def L_of(s):
        return s + np.linalg.norm(p + s[:, None] * d, axis=1)

    with np.errstate(invalid="ignore"):
        L_lo = np.where(good, L_of(np.where(good, lo, 0.0)), np.nan)
        L_hi = np.where(good, L_of(np.where(good, hi, 0.0)), np.nan)
    return L_lo, L_hi


def event_path_lengths(system: System, codes) -> np.ndarray:
    """L = c · ((N − ½)·bin_width − offset), (E,) m (FORMAT v1 TDC convention)."""
    t = system.tdc
    return system.speed_of_light * ((np.asarray(codes, np.float64) - 0.5) * t.bin_width
                                    - t.offset)


def classify_events(system: System, d_scan_shot, event_shot, event_pixel, event_code,
                    r_min: float, r_max: float, settings: Settings2D) -> np.ndarray:
    """Label each detection: 1 signal (consistent with its shot's beam), 2 noise.

    d_scan_shot : (K, 3) beam directions (NaN: unknown angle → noise).
    event_shot, event_pixel : (E,) int; event_code : (E,) uint16.
    Returns (E,) uint8.
    """
    w = system.receiver.image_size[0]
    es = np.asarray(event_shot, np.int64)
    ep = np.asarray(event_pixel, np.int64)
    uv = np.stack([ep % w, ep // w], axis=1).astype(np.float64)
    L = event_path_lengths(system, event_code)
    d = d_scan_shot[es]
    known = np.all(np.isfinite(d), axis=1)
    L_lo = np.full(es.shape, np.nan)
    L_hi = np.full(es.shape, np.nan)
    if np.any(known):
        L_lo[known], L_hi[known] = path_length_interval(system, d[known], uv[known], r_min,
                                                        r_max, settings.margin_px)
    sl = system.speed_of_light * timing_sigma(system, settings.timing_jitter)
    k = settings.k_sigma * sl
    with np.errstate(invalid="ignore"):
        sig = (L >= L_lo - k) & (L <= L_hi + k)
    return np.where(sig, 1, 2).astype(np.uint8)


# --------------------------------------------------------------------------
# stages 3-5


def pixel_histograms(n_pixels: int, n_bins: int, event_pixel, event_code, mask) -> np.ndarray:
    """(n_pixels, n_bins) int32: selected events per pixel and code (code 1 → column 0)."""
    ep = np.asarray(event_pixel, np.int64)[mask]
    ec = np.asarray(event_code, np.int64)[mask] - 1
    h = np.bincount(ep * n_bins + ec, minlength=n_pixels * n_bins)
    return h.reshape(n_pixels, n_bins).astype(np.int32)


@dataclass
class PixelPeaks:
    """One peak per pixel that has one: (P,) arrays.

    pixel : flat index; code : mean TDC code of its detections (float);
    counts : signal detections in the window; background : expected background
    detections in the window; L : mean path length, m.
    """

    pixel: np.ndarray
    code: np.ndarray
    counts: np.ndarray
    background: np.ndarray
    L: np.ndarray


def find_pixel_peaks(system: System, hist_signal: np.ndarray, exposure: np.ndarray,
                     noise_rate: float, settings: Settings2D) -> PixelPeaks:
    """The strongest window of each pixel's signal histogram, if significant.

    hist_signal : (P, n_bins) int32; exposure : (P,) shots in which each
    pixel was read; noise_rate : probability per read slot and TDC bin of a
    background detection.  Window: ±``window_sigma`` timing σ.
    """
    tdc = system.tdc
    st = timing_sigma(system, settings.timing_jitter)
    half = max(1, int(math.ceil(settings.window_sigma * st / tdc.bin_width)))
    width = 2 * half + 1
    nb = hist_signal.shape[1]
    cand = np.flatnonzero(hist_signal.sum(axis=1) >= settings.min_counts)
    hs = hist_signal[cand]
    csum = np.concatenate([np.zeros((cand.size, 1), np.int64),
                           np.cumsum(hs, axis=1, dtype=np.int64)], axis=1)
    lo = np.clip(np.arange(nb) - half, 0, nb)
    hi = np.clip(np.arange(nb) + half + 1, 0, nb)
    win = csum[:, hi] - csum[:, lo]
    best = np.argmax(win, axis=1) if cand.size else np.zeros(0, np.int64)
    n = win[np.arange(cand.size), best]
    bg_all = np.asarray(exposure, float) * noise_rate * width
    bg = bg_all[cand]
    thr = np.maximum(settings.min_counts, poisson.isf(settings.false_alarm, bg) + 1)
    keep = n >= thr
    pix = cand[keep]
    codes = np.arange(1, nb + 1, dtype=np.float64)
    mean_code = np.empty(pix.size)
    counts = np.empty(pix.size, np.int64)
    for j, (row, b) in enumerate(zip(hs[keep], best[keep])):
        # re-centre the window on the mean twice (truncated mean)
        c = float(b + 1)
        for _ in range(2):
            a0 = max(0, int(round(c)) - 1 - half)
            a1 = min(nb, int(round(c)) + half)
            h = row[a0:a1]
            tot = h.sum()
            if tot == 0:
                break
            c = float(h @ codes[a0:a1]) / tot
        mean_code[j] = c
        counts[j] = int(row[max(0, int(round(c)) - 1 - half):min(nb, int(round(c)) + half)].sum())
    ok = counts >= thr[keep]  # still significant after re-centring
    pix, mean_code, counts, bgk = pix[ok], mean_code[ok], counts[ok], bg[keep][ok]
    L = event_path_lengths(system, mean_code)
    return PixelPeaks(pix, mean_code, counts, bgk, L)


def cloud_from_peaks(system: System, peaks: PixelPeaks, settings: Settings2D,
                     sigma_extra=None) -> PointCloud:
    """Points of the pixel peaks with their 3 × 3 covariances → PointCloud.

    Attributes: counts, pixel (column), row, range, sigma_r, sigma_phi (FORMAT v1),
    sigma_x, sigma_y, sigma_z, code.
    """
    w = system.receiver.image_size[0]
    u = (peaks.pixel % w).astype(np.float64)
    v = (peaks.pixel // w).astype(np.float64)
    n = np.maximum(peaks.counts, 1)
    sl = system.speed_of_light * timing_sigma(system, settings.timing_jitter)
    pts = np.zeros((u.size, 3))
    cov = np.zeros((u.size, 3, 3))
    if u.size:
        # inputs (u, v, L, θ1, θ2): pixel extent 1/√12 px, σ_L of the mean of n
        # detections; the angles do not enter the pixel-ray point
        pts, J = jacobian_2d(pixel_point_2d, system, u, v, peaks.L, 0.0, 0.0)
        var_L = (sl / np.sqrt(n)) ** 2
        if sigma_extra is not None:
            var_L = var_L + np.asarray(sigma_extra, float) ** 2
        var = np.stack([np.full(u.size, 1.0 / 12.0), np.full(u.size, 1.0 / 12.0),
                        var_L, np.zeros(u.size), np.zeros(u.size)], axis=1)
        cov = np.einsum("nik,nk,njk->nij", J, var, J)
    good = np.all(np.isfinite(pts), axis=1)
    pts, cov = pts[good], cov[good]
    pol = polar_from_cartesian(pts, cov)
    r, sr, sphi = pol.r, pol.sigma_r, pol.sigma_phi
    sxyz = np.sqrt(np.maximum(np.diagonal(cov, axis1=1, axis2=2), 0.0))
    attrs = {
        "counts": peaks.counts[good].astype(np.int32),
        "pixel": (peaks.pixel[good] % w).astype(np.int32),
        "row": (peaks.pixel[good] // w).astype(np.int32),
        "range": r, "sigma_r": sr, "sigma_phi": sphi,
        "sigma_x": sxyz[:, 0], "sigma_y": sxyz[:, 1], "sigma_z": sxyz[:, 2],
        "code": peaks.code[good],
    }
    return PointCloud(pts, attrs)


# --------------------------------------------------------------------------
# the whole run


@dataclass(frozen=True)
class ReadGate:
    """What a two-axis recording read.

    Attributes
    ----------
    gate : the recomputed readout gate of a gated recording, None where every
        pixel was read.
    exposure : (W·H,) int64, shots each pixel was read.
    slots : int, pixel-slots read in all.
    model_gate : the gate the pile-up model uses (the band of the scan where
        every pixel was read).
    """

    gate: object
    exposure: np.ndarray
    slots: int
    model_gate: object


def read_gate(rec: Recording2D, system: System, sd: ShotDirections, r_min: float,
              r_max: float) -> ReadGate:
    """The pixel-slots a recording read (:class:`ReadGate`): a gated recording's gate
    recomputed from its monitors (every detection must lie in it: monitors and gate
    agree, docs/reliability.md), else every pixel of every shot."""
    w, h = system.receiver.image_size
    if rec.readout["mode"] == "gated":
        nominal = sd if system is rec.system else shot_directions(rec, rec.system)
        gate = recompute_gate(rec, rec.system, nominal.direction)
        check_gate(rec, nominal.direction, nominal.valid, gate)
        return ReadGate(gate, gate.exposure(), int(gate.pixels.size), gate)
    # every pixel read: the band is needed only for the pile-up model
    model_gate = gate_pixels(system, sd.direction,
                             GateSpec(r_min, r_max, gate_half_width(system)))
    return ReadGate(None, np.full(w * h, rec.n_shots, np.int64), rec.n_shots * w * h,
                    model_gate)


def process_recording_2d(recording: Recording2D | str | os.PathLike,
                         system: System | None = None,
                         settings: Settings2D | None = None) -> Result2D:
    """Run the two-axis pipeline on a recording (object or path).

    system : process with this System (e.g. calibrated; default the recording's).
    Returns :class:`Result2D`.  Shots of unknown angle are left out (their
    detections are labelled noise).
    """
    timings = {}
    t0 = time.perf_counter()
    rec = recording if isinstance(recording, Recording2D) else read_recording_2d(recording)
    system = rec.system if system is None else system
    settings = Settings2D() if settings is None else settings
    if tuple(system.receiver.image_size) != tuple(rec.system.receiver.image_size):
        raise FormatError(f"expected image_size {rec.system.receiver.image_size} like the "
                          f"recording, found {system.receiver.image_size}", "--system",
                          "receiver.image_size")
    check_codes_fit(rec.event_code, system.tdc.n_bins, rec.source, "/events/code",
                    rec.system.tdc.n_bins)
    timings["read"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    sd = shot_directions(rec, system)
    th1, th2, d, valid = sd.theta1, sd.theta2, sd.direction, sd.valid
    timings["angles"] = time.perf_counter() - t0

    r_min = settings.r_min or rec.readout.get("r_min", 0.3)
    r_max = settings.r_max or rec.readout.get("r_max", 30.0)
    w, h = system.receiver.image_size
    t0 = time.perf_counter()
    rg = read_gate(rec, system, sd, r_min, r_max)
    gate, exposure, slots, model_gate = rg.gate, rg.exposure, rg.slots, rg.model_gate
    timings["gate"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    labels = classify_events(system, d, rec.event_shot, rec.event_pixel, rec.event_code,
                             r_min, r_max, settings)
    timings["classify"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    nb = system.tdc.n_bins
    hist = pixel_histograms(w * h, nb, rec.event_pixel, rec.event_code, labels == 1)
    n_noise = int(np.count_nonzero(labels == 2))
    noise_rate = n_noise / max(1, slots) / nb  # per read slot and bin
    peaks = find_pixel_peaks(system, hist, exposure, noise_rate, settings)
    sigma_extra = None
    if settings.pileup_correction and peaks.pixel.size:
        L_corr, sigma_extra, _ = pileup_correction(system, peaks, model_gate, d,
                                                   settings.timing_jitter)
        peaks = replace(peaks, L=L_corr)
    cloud = cloud_from_peaks(system, peaks, settings, sigma_extra)
    timings["peaks+cloud"] = time.perf_counter() - t0

    counts = {"shots": rec.n_shots, "shots_unknown_angle": int(np.count_nonzero(~valid)),
              "slots_read": slots, "read_fraction": slots / max(1, rec.n_shots * w * h),
              "events": rec.n_events, "signal": int(np.count_nonzero(labels == 1)),
              "noise": n_noise, "peaks": int(peaks.pixel.size), "points": len(cloud)}
    if gate is not None and int(gate.counts().sum()) != int(rec.read_count.sum()):
        counts["gate_mismatch"] = int(gate.counts().sum()) - int(rec.read_count.sum())
    return Result2D(cloud, labels, th1, th2, counts, _truth_2d(rec, labels), timings,
                    rec.source)


def _truth_2d(rec: Recording2D, labels) -> dict | None:
    """Recall and noise rejection of ``labels`` against the recording's
    ``/truth/label`` (None without truth)."""
    if "label" not in rec.truth:
        return None
    tl = np.asarray(rec.truth["label"])
    ts = tl == 1
    return {"true_signal": int(ts.sum()), "true_background": int((tl == 2).sum()),
            "recall": float(np.mean(labels[ts] == 1)) if ts.any() else float("nan"),
            "noise_rejection": (float(np.mean(labels[tl == 2] == 2)) if (tl == 2).any()
                                else float("nan"))}
