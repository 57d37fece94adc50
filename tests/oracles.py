"""Reference implementations kept as test oracles (issue 11): not used by the package.

* :func:`detect_peaks`, :class:`HistogramPeaks`, :func:`peak_centroid` — the
  paper's peak detector on code histograms (local maxima above a threshold)
  and a background-subtracted centroid;
* :func:`find_code_peaks` — the paper's detector on each pixel's signal
  histogram over codes, with the Poisson threshold of
  :mod:`mems_stereo.pipeline.peaks` (the package's one detector is
  :func:`mems_stereo.pipeline.peaks.find_peaks`, in scan angle × code);
* :func:`peak_points` — per-detection fusion of each peak's signal
  detections from the full (K, H, W) bins and labels (the package's one
  fusion is :func:`mems_stereo.pipeline.fusion.points_from_counts`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mems_stereo.errors import FormatError, GeometryError
from mems_stereo.geometry.uncertainty import Spreads, polar_from_cartesian
from mems_stereo.model.system import System
from mems_stereo.physics.background import (
    background_rate_from_noise,
    expected_background_in_signal,
)
from mems_stereo.pipeline.cloud import PointCloud
from mems_stereo.pipeline.detections import detection_points
from mems_stereo.pipeline.peaks import acceptance_counts, strongest_window


# --------------------------------------------------------------------------- peaks
@dataclass(frozen=True)
class HistogramPeaks:
    """Peaks found in a stack of histograms.

    Attributes
    ----------
    index : (M, D) int64, the pixel multi-index of each peak (D = hist.ndim − 1).
    code : (M,) int64, 1-based TDC code of the peak's maximum.
    value : (M,) float64, the (filtered) histogram value at the peak.
    """

    index: np.ndarray
    code: np.ndarray
    value: np.ndarray

    def __len__(self) -> int:
        return int(self.code.size)

    def strongest(self, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
        """Per pixel the strongest peak: ``code`` (shape) int64 (0 = none), ``value`` float64."""
        code = np.zeros(shape, dtype=np.int64)
        value = np.zeros(shape, dtype=np.float64)
        if len(self):
            order = np.argsort(self.value, kind="stable")  # largest written last
            idx = tuple(self.index[order].T)
            code[idx] = self.code[order]
            value[idx] = self.value[order]
        return code, value


def detect_peaks(hist, threshold=0.0, min_separation: int = 1,
                 max_peaks: int | None = None) -> HistogramPeaks:
    """Local maxima above a threshold, at least ``min_separation`` bins apart.

    Parameters
    ----------
    hist : (..., n_bins), usually :func:`moving_average` of a histogram.
    threshold : scalar, (...) or (..., n_bins); a peak needs ``value >
        threshold`` (the paper's fixed threshold is a scalar; the
        background-grounded one comes from :func:`poisson_threshold`).
    min_separation : bins; a peak is the maximum of the centred window of
        ``2·min_separation + 1`` bins (non-maximum suppression), the first
        bin of a flat top wins.
    max_peaks : keep at most this many per pixel, the highest.

    Returns
    -------
    :class:`HistogramPeaks`, sorted by pixel then code.
    """
    from scipy.ndimage import maximum_filter1d

    h = np.asarray(hist, dtype=np.float64)
    if h.ndim < 1:
        raise FormatError(f"expected (..., n_bins), found shape {h.shape}", field="hist")
    n_bins = h.shape[-1]
    sep = int(min_separation)
    if sep < 1:
        raise FormatError(f"min_separation must be >= 1, found {sep}", field="min_separation")
    # Tie-break flat tops towards the first bin with a key below any real difference.
    scale = float(np.nanmax(np.abs(h))) if h.size else 0.0
    eps = (scale + 1.0) * 1e-12
    key = h - eps * np.arange(n_bins)
    mx = maximum_filter1d(key, size=2 * sep + 1, axis=-1, mode="constant", cval=-np.inf)
    thr = np.asarray(threshold, dtype=np.float64)
    if thr.ndim == h.ndim - 1 and thr.ndim > 0:
        thr = thr[..., None]
    is_peak = (key >= mx) & (h > thr) & np.isfinite(h)
    nz = np.nonzero(is_peak)
    index = np.stack(nz[:-1], axis=1).astype(np.int64) if h.ndim > 1 else \
        np.zeros((nz[0].size, 0), dtype=np.int64)
    code = nz[-1].astype(np.int64) + 1
    value = h[nz]
    if max_peaks is not None and code.size:
        pix = np.ravel_multi_index(tuple(index.T), h.shape[:-1]) if h.ndim > 1 else \
            np.zeros(code.size, dtype=np.int64)
        order = np.lexsort((-value, pix))
        rank = np.empty(code.size, dtype=np.int64)
        first = np.r_[True, pix[order][1:] != pix[order][:-1]]
        start = np.maximum.accumulate(np.where(first, np.arange(code.size), 0))
        rank[order] = np.arange(code.size) - start
        keep = rank < int(max_peaks)
        index, code, value = index[keep], code[keep], value[keep]
    return HistogramPeaks(index, code, value)


# --------------------------------------------------------------------------- ranges
def peak_centroid(hist, code, half_width: int, background=None):
    """Background-subtracted centroid of a peak within ±``half_width`` bins.

    Parameters
    ----------
    hist : (..., n_bins) counts (raw or signal histogram, not filtered).
    code : (...) int, 1-based peak code per pixel (0 = no peak → NaN).
    half_width : bins, about the pulse's FWHM in bins (14.9 ns / 312.5 ps ≈ 48
        for the paper's laser), so the window holds the whole return.
    background : (...) or (..., n_bins) expected background counts per bin,
        subtracted (and the difference clipped at 0) before weighting.

    Returns
    -------
    centroid : (...) float64, 1-based fractional code (use it as N in
        :func:`path_length`).
    std : (...) float64, its standard deviation from counting statistics,
        ``√(Σ h_j (j − ĉ)²) / Σ w_j`` (Poisson counts, weights ``w = h − b``).
    signal : (...) float64, background-subtracted counts in the window.
    """
    h = np.asarray(hist, dtype=np.float64)
    c = np.asarray(code, dtype=np.int64)
    n_bins = h.shape[-1]
    if c.shape != h.shape[:-1]:
        raise FormatError(f"code must have shape {h.shape[:-1]}, found {c.shape}", field="code")
    hw = int(half_width)
    offs = np.arange(-hw, hw + 1)
    j = (c[..., None] - 1) + offs                          # 0-based bins of the window
    inside = (j >= 0) & (j < n_bins) & (c[..., None] > 0)
    jj = np.clip(j, 0, n_bins - 1)
    hv = np.take_along_axis(h, jj, axis=-1) * inside
    if background is None:
        bv = 0.0
    else:
        bg = np.asarray(background, dtype=np.float64)
        if bg.ndim == h.ndim:
            bv = np.take_along_axis(np.broadcast_to(bg, h.shape), jj, axis=-1) * inside
        else:
            bv = bg[..., None] * inside
    w = np.clip(hv - bv, 0.0, None)
    sw = w.sum(axis=-1)
    x = jj + 1.0
    with np.errstate(divide="ignore", invalid="ignore"):
        cen = np.where(sw > 0, (w * x).sum(axis=-1) / sw, np.nan)
        var = (hv * (x - cen[..., None]) ** 2).sum(axis=-1) / sw ** 2
    return cen, np.sqrt(var), sw


def find_code_peaks(system: System, signal, noise, theta, valid, settings):
    """The paper's detector: one peak per pixel of the signal histogram over codes.

    Parameters
    ----------
    signal, noise : (H, W, n_bins) counts (index j = code j+1).
    theta, valid : (K,) scan angles and validity of the shots.
    settings : :class:`mems_stereo.pipeline.settings.Settings` (confidence, min_range,
        smoothing_bins, false_alarm, min_counts).

    Returns
    -------
    peaks : dict of (Q,) int64 ``row``, ``col``, ``code``, ``code_lo``,
        ``code_hi``, ``counts`` (signal counts in the window) and float64
        ``background`` (expected background counts in the window).
    background_hz : (H, W) float64 ML background rate per pixel.
    """
    H, W, n_bins = signal.shape
    P = H * W
    bw = system.tdc.bin_width
    S = np.asarray(signal, dtype=np.float64).reshape(P, n_bins)
    N = np.asarray(noise).reshape(P, n_bins)
    n_valid = int(np.count_nonzero(valid))
    raw = S + N
    A = acceptance_counts(system, theta, valid, settings.confidence, settings.min_range)
    rate = background_rate_from_noise(N, raw, A, n_valid, bw)
    width = settings.smoothing_bins
    if width is None:
        width = max(1, int(round(system.laser.pulse_fwhm / bw)))
    width += 1 - width % 2  # odd
    B = expected_background_in_signal(A, np.nan_to_num(rate), bw)
    ws = strongest_window(S, B, width, A > 0, settings)
    j, cnt, mu, keep = ws.j, ws.cnt, ws.mu, ws.keep
    keep &= np.isfinite(rate)
    code = j + 1
    half = max(1, width)
    q = np.flatnonzero(keep)
    peaks = {
        "row": (q // W).astype(np.int64), "col": (q % W).astype(np.int64),
        "code": code[q].astype(np.int64),
        "code_lo": np.maximum(1, code[q] - half).astype(np.int64),
        "code_hi": np.minimum(n_bins, code[q] + half).astype(np.int64),
        "counts": np.rint(cnt[q]).astype(np.int64), "background": mu[q],
        "rate_hz": rate.reshape(-1)[q],
    }
    return peaks, rate.reshape(H, W)



def _group_mean(idx, n, values):
    """Mean of values (M, ...) per group idx (M,) in 0..n-1 -> (n, ...)."""
    cnt = np.bincount(idx, minlength=n).astype(np.float64)
    out = np.zeros((n,) + values.shape[1:])
    np.add.at(out, idx, values)
    with np.errstate(invalid="ignore", divide="ignore"):
        return out / cnt.reshape((-1,) + (1,) * (values.ndim - 1)), cnt


def _group_median(idx, n, values):
    """Median of values (M,) per group idx (M,) in 0..n-1 -> (n,) (NaN for empty groups)."""
    order = np.lexsort((values, idx))
    gi, vs = idx[order], values[order]
    cnt = np.bincount(gi, minlength=n)
    start = np.concatenate([[0], np.cumsum(cnt)[:-1]])
    out = np.full(n, np.nan)
    has = cnt > 0
    a = start[has] + (cnt[has] - 1) // 2
    b = start[has] + cnt[has] // 2
    out[has] = 0.5 * (vs[a] + vs[b])
    return out


def peak_points(system: System, bins, labels, theta, rows, cols, code_lo, code_hi,
                spreads: Spreads | None = None, min_counts: int = 1,
                confidence: float = 0.997) -> PointCloud:
    """One point per peak from its signal detections, with propagated uncertainty.

    Parameters
    ----------
    bins : (K, H, W) uint16 TDC codes; labels : (K, H, W) uint8 (1 = signal).
    theta : (K,) float64 scan angles, rad.
    rows, cols : (P,) int pixel of each peak; code_lo, code_hi : (P,) int, the
        peak's code window (inclusive), e.g. from the peak detector.
    min_counts : peaks with fewer signal detections are dropped.
    confidence : of the in-peak consistency test: a detection whose fused
        range differs from the peak's median fused range by more than
        ``k·sqrt(σ_i² + (σ_tof/√n)²)`` (background that passed the
        classifier inside the window) is left out of the average.

    Returns
    -------
    :class:`~mems_stereo.pipeline.cloud.PointCloud` of the fused points with attributes
    ``counts`` int32, ``pixel`` int32 (column), ``row`` int32, ``code`` (mean
    code), ``range``, ``sigma_r``, ``sigma_phi``, ``sigma_x/y/z`` (fused), and
    per estimate ``range_stereo``, ``sigma_r_stereo``, ``range_tof``,
    ``sigma_r_tof``, ``weight_stereo`` (float64), and ``counts_window``
    int32 (signal-labelled detections in the window before the in-peak test).
    """
    b = np.asarray(bins)
    lab = np.asarray(labels)
    if b.shape != lab.shape or b.ndim != 3:
        raise GeometryError(f"bins, labels: expected equal (K, H, W) shapes, found "
                            f"{b.shape}, {lab.shape}")
    rows = np.asarray(rows, dtype=np.int64).ravel()
    cols = np.asarray(cols, dtype=np.int64).ravel()
    lo = np.asarray(code_lo, dtype=np.int64).ravel()
    hi = np.asarray(code_hi, dtype=np.int64).ravel()
    P = rows.size
    if not (cols.size == lo.size == hi.size == P):
        raise GeometryError("rows, cols, code_lo, code_hi: expected equal lengths")
    # signal detections of each peak's pixel inside its window
    det_k, det_p, det_code = [], [], []
    col_bins = b[:, rows, cols].astype(np.int64)  # (K, P)
    col_lab = lab[:, rows, cols]
    m = (col_lab == 1) & (col_bins >= lo) & (col_bins <= hi) & (col_bins > 0)
    det_k, det_p = np.nonzero(m)
    det_code = col_bins[det_k, det_p]
    dp = detection_points(system, det_k, rows[det_p], cols[det_p], det_code, theta, spreads)
    good = dp.ok.copy()
    from mems_stereo.pipeline.consistency import k_from_confidence

    k = k_from_confidence(confidence)
    pol = polar_from_cartesian(dp.fused, dp.cov_fused)
    r_i, sr_i = pol.r, pol.sigma_r
    pol = polar_from_cartesian(dp.tof, dp.cov_tof)
    srt_i = pol.sigma_r
    idx_all = np.where(good, det_p, P)  # bad detections go to a dummy group
    med = _group_median(idx_all, P + 1, np.where(good, r_i, 0.0))[det_p]
    n_in = np.bincount(idx_all, minlength=P + 1)[det_p].astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        bound = k * np.sqrt(sr_i ** 2 + srt_i ** 2 / np.maximum(n_in, 1.0))
        good &= np.abs(r_i - med) <= bound
    window_counts = np.bincount(det_p, minlength=P)
    gi = det_p[good]
    mean = {}
    for name in ("stereo", "tof", "fused"):
        x, cnt = _group_mean(gi, P, getattr(dp, name)[good])
        C, _ = _group_mean(gi, P, getattr(dp, "cov_" + name)[good])
        with np.errstate(invalid="ignore", divide="ignore"):
            C = C / cnt[:, None, None]
        mean[name] = (x, C)
    code_mean, cnt = _group_mean(gi, P, det_code[good].astype(np.float64))
    w_mean, _ = _group_mean(gi, P, dp.weight_stereo[good])
    keep = cnt >= max(1, int(min_counts))
    xf, Cf = mean["fused"]
    pol = polar_from_cartesian(xf, Cf)
    r, sr, sphi = pol.r, pol.sigma_r, pol.sigma_phi
    pol = polar_from_cartesian(*mean["stereo"])
    r_st, sr_st = pol.r, pol.sigma_r
    pol = polar_from_cartesian(*mean["tof"])
    r_tf, sr_tf = pol.r, pol.sigma_r
    sx = np.sqrt(np.maximum(np.diagonal(Cf, axis1=1, axis2=2), 0.0))
    attrs = {
        "counts": cnt.astype(np.int32), "pixel": cols.astype(np.int32),
        "row": rows.astype(np.int32), "code": code_mean, "range": r, "sigma_r": sr,
        "sigma_phi": sphi, "sigma_x": sx[:, 0], "sigma_y": sx[:, 1], "sigma_z": sx[:, 2],
        "range_stereo": r_st, "sigma_r_stereo": sr_st, "range_tof": r_tf,
        "sigma_r_tof": sr_tf, "weight_stereo": w_mean,
        "counts_window": window_counts.astype(np.int32),
    }
    return PointCloud(xf, attrs).select(keep)
