"""TDC histograms per pixel: formation, background, pile-up, filtering, peaks, ranges.

The stage after classification (paper Sec. 3.2, Figs. 8–9): the TDC codes of
many shots are accumulated per pixel into the raw histogram, and, given the
per-detection labels of :mod:`mems_stereo.classify`, into the signal
histogram S and the noise histogram N.  From N (or from the raw histogram
with the return's window excluded) a maximum-likelihood estimate of the
background rate per pixel that accounts for first-photon pile-up; the
paper's moving-average filter, a threshold and a peak detector; and the
path length of each peak.  Method and derivations: ``docs/histograms.md``.

Conventions (``docs/conventions.md``): TDC code N is 1-based, 0 means no
detection, and histogram index ``j = N − 1``; a detection in code N has
``t_TOF = (N − ½)·bin_width − offset`` and path length ``L = c·t_TOF``
(mirror → target → projection centre).  A SPAD pixel records at most one
photon per shot, its first.  Counts are int64, rates in Hz, times in s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import FormatError

#: Label values of FORMAT v1 event labels.
LABEL_NONE, LABEL_SIGNAL, LABEL_NOISE = 0, 1, 2


# --------------------------------------------------------------------------- formation
@dataclass
class Histograms:
    """Per-pixel TDC histograms of a block of shots.

    Attributes
    ----------
    raw : (H, W, n_bins) int64, every detection; index j counts code j + 1.
    signal : (H, W, n_bins) int64, detections labelled 1 (signal S); zeros
        when no labels were given.
    noise : (H, W, n_bins) int64, detections labelled 2 (noise N); zeros when
        no labels were given.
    n_shots : (H, W) int64, shots in which the pixel was armed (read out):
        the number of trials of the pile-up model (K for a line sensor).

    Histograms of disjoint blocks of shots add (``a + b``): the histogram of
    the whole is the sum of the histograms of its chunks.
    """

    raw: np.ndarray
    signal: np.ndarray
    noise: np.ndarray
    n_shots: np.ndarray

    @property
    def n_bins(self) -> int:
        return int(self.raw.shape[-1])

    def __add__(self, other: Histograms) -> Histograms:
        if not isinstance(other, Histograms):
            return NotImplemented
        if other.raw.shape != self.raw.shape:
            raise FormatError(f"cannot add histograms of shape {self.raw.shape} and "
                              f"{other.raw.shape}", field="histograms")
        return Histograms(self.raw + other.raw, self.signal + other.signal,
                          self.noise + other.noise, self.n_shots + other.n_shots)

    @classmethod
    def zeros(cls, shape: tuple[int, int], n_bins: int) -> Histograms:
        """Empty histograms for an (H, W) sensor: the start of an accumulation."""
        h, w = shape
        z = np.zeros((h, w, n_bins), dtype=np.int64)
        return cls(z, z.copy(), z.copy(), np.zeros((h, w), dtype=np.int64))


def accumulate_histograms(bins, labels=None, n_bins: int = 4096, armed=None) -> Histograms:
    """Histograms of a block of shots (raw, and signal S / noise N from the labels).

    Parameters
    ----------
    bins : (K, H, W) uint16 TDC codes, 0 = no detection, 1..n_bins the bin of
        the first detected photon (``/shots/bins`` of FORMAT v1).
    labels : (K, H, W) uint8 or None; 1 signal, 2 noise, 0 none (or left out:
        a detection labelled 0 counts in ``raw`` only).
    n_bins : number of TDC bins; a code above it raises :class:`FormatError`.
    armed : (K, H, W) bool or None; False where the pixel was not read out in
        that shot (epipolar readout).  Those slots add neither counts nor
        trials.  Default: every pixel armed in every shot.

    Returns
    -------
    :class:`Histograms` with int64 arrays.  One ``np.bincount`` over
    ``(label·P + pixel)·n_bins + code − 1``; a dense 3200 × 192 frame with 4096
    bins takes 0.03–0.4 s (most of it allocating the 3 × 19 MB output).
    """
    b = np.asarray(bins)
    if b.ndim != 3:
        raise FormatError(f"expected (K, H, W) codes, found shape {b.shape}", field="bins")
    if not np.issubdtype(b.dtype, np.integer):
        raise FormatError(f"expected integer codes, found dtype {b.dtype}", field="bins")
    n_bins = int(n_bins)
    if n_bins < 1:
        raise FormatError(f"n_bins must be >= 1, found {n_bins}", field="n_bins")
    K, H, W = b.shape
    P = H * W
    if armed is None:
        n_shots = np.full((H, W), K, dtype=np.int64)
        arm = None
    else:
        arm = np.asarray(armed, dtype=bool)
        if arm.shape != b.shape:
            raise FormatError(f"expected armed of shape {b.shape}, found {arm.shape}",
                              field="armed")
        n_shots = arm.sum(axis=0, dtype=np.int64)
    flat = b.reshape(K, P)
    det = flat > 0
    if arm is not None:
        det &= arm.reshape(K, P)
    shot_idx, pix = np.nonzero(det)
    codes = flat[shot_idx, pix].astype(np.int64)
    if codes.size and (codes.max() > n_bins or codes.min() < 0):
        bad = codes.max() if codes.max() > n_bins else codes.min()
        raise FormatError(f"TDC codes must lie in 0..{n_bins}, found {bad}", field="bins")
    if labels is None:
        cls = np.zeros_like(codes)
    else:
        lab = np.asarray(labels)
        if lab.shape != b.shape:
            raise FormatError(f"expected labels of shape {b.shape}, found {lab.shape}",
                              field="labels")
        cls = lab.reshape(K, P)[shot_idx, pix].astype(np.int64)
        if cls.size and cls.max() > LABEL_NOISE:
            raise FormatError(f"labels must lie in 0..2, found {cls.max()}", field="labels")
    idx = (cls * P + pix) * n_bins + (codes - 1)
    counts = np.bincount(idx, minlength=3 * P * n_bins).reshape(3, H, W, n_bins)
    counts = counts.astype(np.int64, copy=False)
    raw = counts.sum(axis=0)
    return Histograms(raw, counts[LABEL_SIGNAL].copy(), counts[LABEL_NOISE].copy(), n_shots)


# --------------------------------------------------------------------------- pile-up
def _as_hist(hist, name: str = "hist") -> np.ndarray:
    h = np.asarray(hist)
    if h.ndim < 1 or h.shape[-1] < 1:
        raise FormatError(f"expected (..., n_bins) counts, found shape {h.shape}", field=name)
    if np.any(h < 0):
        raise FormatError("counts must be >= 0", field=name)
    return h.astype(np.float64)


def armed_shots(hist, n_shots) -> np.ndarray:
    """Shots still armed at the start of each bin under first-photon detection.

    ``hist`` : (..., n_bins) counts of *all* detections of the pixel (raw);
    ``n_shots`` : (...) or scalar, shots per pixel.  Returns (..., n_bins)
    float64 ``n_j = n_shots − Σ_{i<j} h_i``.  Raises :class:`FormatError`
    when the histogram holds more detections than shots.
    """
    h = _as_hist(hist)
    n = np.asarray(n_shots, dtype=np.float64)[..., None]
    before = np.cumsum(h, axis=-1) - h
    nj = n - before
    if np.any(nj - h < -1e-9):
        raise FormatError("histogram holds more detections than shots (n_shots too small)",
                          field="n_shots")
    return nj


def background_rate_mle(hist, n_shots, bin_width: float, exclude=None, raw=None,
                        return_std: bool = False, trials_factor=None):
    """Maximum-likelihood constant background rate per pixel under first-photon pile-up.

    A pixel records only the first photon of a shot.  With a constant rate λ a
    shot still armed at the start of bin j detects in it with probability
    ``p = 1 − exp(−λ·Δ)``; given the armed count ``n_j = n_shots − Σ_{i<j}
    raw_i`` the counts are independent binomials ``h_j ~ B(n_j, p)``, so the
    log-likelihood over the included bins is ``Σ h_j ln p + (n_j − h_j)
    ln(1 − p)``, maximised at ``p̂ = Σ h_j / Σ n_j`` and (invariance)

        λ̂ = −ln(1 − Σ h_j / Σ n_j) / Δ.

    Excluded bins (the return's window, or where N lacks the detections the
    classifier moved to S) drop out of the sums but still disarm the pixel
    through ``raw``.  Derivation: ``docs/histograms.md``.

    Parameters
    ----------
    hist : (..., n_bins) counts of background detections (the noise histogram
        N, or the raw histogram).
    n_shots : (...) or scalar, shots in which the pixel was armed.
    bin_width : s.
    exclude : (..., n_bins) or (n_bins,) bool, True = bin not used; None = all.
    raw : (..., n_bins) counts of all detections (default ``hist``): what
        disarms the pixel.  Pass the raw histogram when ``hist`` is N.
    return_std : also return the standard deviation from the Fisher
        information, ``σ_p² = p(1−p)/Σn_j``, ``σ_λ = σ_p / ((1−p)Δ)``.
    trials_factor : (..., n_bins) or None, the share of the armed shots that
        were trials for ``hist`` at each bin (e.g. ``1 − A_j/n_shots`` when
        the classifier moved the background of A_j shots at bin j into S).

    Returns
    -------
    rate : (...) float64, Hz.  ``inf`` when every armed trial detected, NaN
    when no bin is included or no trial was armed.  With ``return_std``:
    ``(rate, std)``.
    """
    h = _as_hist(hist)
    r = h if raw is None else _as_hist(raw, "raw")
    if r.shape != h.shape:
        raise FormatError(f"raw must have the shape of hist {h.shape}, found {r.shape}",
                          field="raw")
    if not bin_width > 0:
        raise FormatError(f"bin_width must be > 0 s, found {bin_width}", field="bin_width")
    nj = armed_shots(r, n_shots)
    if trials_factor is not None:
        nj = nj * np.asarray(trials_factor, dtype=np.float64)
    use = np.ones(h.shape, dtype=bool) if exclude is None else ~np.broadcast_to(
        np.asarray(exclude, dtype=bool), h.shape)
    k = np.where(use, h, 0.0).sum(axis=-1)
    n = np.where(use, nj, 0.0).sum(axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        p = np.where(n > 0, k / n, np.nan)
        rate = -np.log1p(-p) / bin_width
        if not return_std:
            return rate
        std = np.sqrt(p * (1.0 - p) / n) / ((1.0 - p) * bin_width)
    return rate, std


def coates_correction(hist, n_shots) -> np.ndarray:
    """Coates' pile-up correction: mean photon number per shot in each bin.

    ``hist`` : (..., n_bins) counts of all detections; ``n_shots`` : (...) or
    scalar.  Returns (..., n_bins) float64 ``μ_j = −ln(1 − h_j / n_j)`` with
    ``n_j`` the armed shots (:func:`armed_shots`) — the bin-wise MLE of the
    photon flux, free of the first-photon bias (D. Coates, J. Phys. E 1, 878,
    1968).  ``inf`` where every armed shot detected, NaN where none was armed.
    Multiply by ``n_shots`` for a pile-up-free histogram on the count scale.
    """
    h = _as_hist(hist)
    nj = armed_shots(h, n_shots)
    with np.errstate(divide="ignore", invalid="ignore"):
        return -np.log1p(-np.where(nj > 0, h / nj, np.nan))


def expected_background(rate, n_shots, bin_width: float, n_bins: int) -> np.ndarray:
    """Expected background counts per bin for a constant rate under pile-up.

    ``rate`` : (...) Hz, ``n_shots`` : (...) or scalar.  Returns (..., n_bins)
    float64 ``n_shots·(1 − p)^j·p`` with ``p = 1 − exp(−rate·Δ)`` (geometric
    first-photon distribution; ignores the disarming by the return, so later
    bins are over- rather than under-estimated: a conservative threshold).
    """
    lam = np.asarray(rate, dtype=np.float64)[..., None]
    n = np.asarray(n_shots, dtype=np.float64)[..., None]
    j = np.arange(int(n_bins), dtype=np.float64)
    x = lam * bin_width
    return n * np.exp(-x * j) * (-np.expm1(-x))


# --------------------------------------------------------------------------- filter, threshold
def moving_sum(hist, width: int) -> np.ndarray:
    """Centred moving sum of ``width`` (odd) bins along the last axis; zeros beyond the ends."""
    width = int(width)
    if width < 1 or width % 2 == 0:
        raise FormatError(f"width must be an odd number >= 1, found {width}", field="width")
    h = np.asarray(hist, dtype=np.float64)
    half = width // 2
    pad = [(0, 0)] * (h.ndim - 1) + [(half + 1, half)]
    c = np.cumsum(np.pad(h, pad), axis=-1)
    return c[..., width:] - c[..., :-width]


def moving_average(hist, width: int) -> np.ndarray:
    """The paper's moving-average filter along the codes (last axis).

    ``hist`` : (..., n_bins); ``width`` : odd number of bins.  Returns (...,
    n_bins) float64, the mean over the bins of a centred window; at the ends
    the mean over the bins that exist (no loss of height at code 1).
    """
    s = moving_sum(hist, width)
    n_bins = np.asarray(hist).shape[-1]
    norm = moving_sum(np.ones(n_bins), width)
    return s / norm


def poisson_threshold(background, width: int, p_false_alarm: float = 1e-3) -> np.ndarray:
    """Threshold on the moving average that background alone exceeds with ``p_false_alarm``.

    ``background`` : (..., n_bins) expected background counts per bin (e.g.
    :func:`expected_background` of the MLE rate: pile-up included).  The sum
    over a window is Poisson with the window's expected sum μ; the threshold
    is the smallest k with P(X > k) ≤ p_false_alarm, divided by the window's
    bin count (so it applies to :func:`moving_average`).  Per bin and pixel;
    the probability is per window position, so over B positions expect about
    ``B·p_false_alarm`` false peaks per pixel.
    """
    from scipy.stats import poisson

    if not 0 < p_false_alarm < 1:
        raise FormatError(f"p_false_alarm must lie in (0, 1), found {p_false_alarm}",
                          field="p_false_alarm")
    b = np.asarray(background, dtype=np.float64)
    mu = moving_sum(b, width)
    norm = moving_sum(np.ones(b.shape[-1]), width)
    return poisson.isf(p_false_alarm, mu) / norm


# --------------------------------------------------------------------------- peaks
@dataclass(frozen=True)
class Peaks:
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
                 max_peaks: int | None = None) -> Peaks:
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
    :class:`Peaks`, sorted by pixel then code.
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
    return Peaks(index, code, value)


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


def path_length(code, bin_width: float, offset: float = 0.0,
                speed_of_light: float = 299704644.5):
    """Path length L = c·((N − ½)·bin_width − offset), m, for (fractional) codes N.

    ``code`` : array of 1-based codes (NaN or 0 → NaN); ``bin_width``,
    ``offset`` : s; ``speed_of_light`` : m/s (in air by default, as the
    system JSON).  L is measured mirror → target → projection centre
    (FORMAT v1); points are :mod:`mems_stereo.points`' job.
    """
    n = np.asarray(code, dtype=np.float64)
    n = np.where(n > 0, n, np.nan)
    return speed_of_light * ((n - 0.5) * bin_width - offset)
