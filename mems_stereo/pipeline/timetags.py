"""Time-tagged photon input (TCSPC): histograms, timing spread, signal and background.

Systems with a free-running or time-tagging detector give, per pixel, the
arrival time of every detected photon instead of one TDC code per shot.  This
module forms the same per-pixel histograms from such time tags, measures the
system's timing spread (laser pulse ⊗ detector jitter) from the data, and
estimates the mean number of signal photons per pixel and the
signal-to-background ratio — for data with about one signal photon per pixel
among ten background photons, where a single pixel's histogram cannot tell
its return from the background and photons of a spatial neighbourhood must be
pooled.  Method, settings and the real-data result: ``docs/histograms.md``.

Input layout (CSR, as ``/work/shared/realdata``): ``timestamps`` (n,) the
arrival times, pixel by pixel in row-major order; ``offsets`` (P + 1,) int
with the photons of pixel i in ``timestamps[offsets[i]:offsets[i+1]]``.  Times
are in any one unit (s, or integer ps as in the real data); every time
argument is in the same unit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mems_stereo.errors import FormatError


# --------------------------------------------------------------------------- layout
def pixel_of_photon(offsets) -> np.ndarray:
    """Pixel index of each photon from CSR ``offsets`` (P + 1,): (n,) int64.

    Raises :class:`FormatError` unless offsets start at 0 and never decrease.
    """
    o = np.asarray(offsets)
    if o.ndim != 1 or o.size < 1 or not np.issubdtype(o.dtype, np.integer):
        raise FormatError(f"expected (P + 1,) integer offsets, found {o.dtype} {o.shape}",
                          field="offsets")
    if o[0] != 0 or np.any(np.diff(o) < 0):
        raise FormatError("offsets must start at 0 and never decrease", field="offsets")
    return np.repeat(np.arange(o.size - 1, dtype=np.int64), np.diff(o))


def _check(timestamps, offsets):
    t = np.asarray(timestamps)
    if t.ndim != 1:
        raise FormatError(f"expected (n,) timestamps, found shape {t.shape}", field="timestamps")
    pix = pixel_of_photon(offsets)
    if pix.size != t.size:
        raise FormatError(f"offsets[-1] = {pix.size} but there are {t.size} timestamps",
                          field="offsets")
    return t, pix


def histogram_from_timetags(timestamps, offsets, bin_width, t_min, t_max) -> np.ndarray:
    """Per-pixel histograms of photon arrival times.

    Parameters
    ----------
    timestamps : (n,) arrival times (CSR order, see module doc).
    offsets : (P + 1,) int.
    bin_width, t_min, t_max : same unit as ``timestamps``; bin k covers
        ``[t_min + k·bin_width, t_min + (k+1)·bin_width)`` for
        ``k < ceil((t_max − t_min) / bin_width)``.  Photons outside
        ``[t_min, t_max)`` are dropped.

    Returns
    -------
    (P, n_bins) int64 counts (reshape to (H, W, n_bins) for a raster).  Index
    j corresponds to TDC code j + 1 of :mod:`mems_stereo.pipeline.histograms`, so its
    functions apply unchanged (without pile-up: ``n_shots`` = ∞).
    """
    t, pix = _check(timestamps, offsets)
    if not bin_width > 0 or not t_max > t_min:
        raise FormatError(f"need bin_width > 0 and t_max > t_min, found {bin_width}, "
                          f"[{t_min}, {t_max})", field="bin_width")
    n_bins = int(np.ceil((t_max - t_min) / bin_width - 1e-9))
    P = int(np.asarray(offsets).size - 1)
    tt = t.astype(np.float64)
    k = np.floor((tt - t_min) / bin_width).astype(np.int64)
    ok = (tt >= t_min) & (tt < t_max) & (k < n_bins)
    idx = pix[ok] * n_bins + k[ok]
    return np.bincount(idx, minlength=P * n_bins).reshape(P, n_bins).astype(np.int64)


def _box(a: np.ndarray, radius: int) -> np.ndarray:
    """Sum over the (2r+1)² spatial neighbourhood of (H, W, ...) arrays (zeros beyond edges)."""
    if radius == 0:
        return a.astype(np.float64)
    r = int(radius)
    pad = [(r + 1, r), (r + 1, r)] + [(0, 0)] * (a.ndim - 2)
    c = np.pad(a.astype(np.float64), pad).cumsum(0).cumsum(1)
    s = 2 * r + 1
    return c[s:, s:] - c[:-s, s:] - c[s:, :-s] + c[:-s, :-s]


# --------------------------------------------------------------------------- timing spread
@dataclass(frozen=True)
class TimingSpread:
    """Timing response measured from the data (laser pulse ⊗ jitter ⊗ local depth spread).

    Attributes
    ----------
    sigma, fwhm : Gaussian fit to the stacked return, time unit of the input.
    lead, tail : the return's excess holds 99 % of its photons after
        ``−lead`` and 99 % before ``+tail`` (relative to the local centre).
    edges, counts : the stacked profile, (B+1,) and (B,).
    mu : mean of the Gaussian fit relative to the local centre (the centre
        of a signal window, :func:`window_counts_from_timetags`).
    """

    sigma: float
    fwhm: float
    lead: float
    tail: float
    edges: np.ndarray
    counts: np.ndarray
    mu: float = 0.0


def local_return_centres(timestamps, offsets, shape, t_min, t_max, coarse_bin,
                         radius: int = 2):
    """Each pixel's return time seen by its neighbours, and how clear that return is.

    The centre is found from the (2·radius+1)² box *without* the pixel itself,
    so the pixel's own photons do not select themselves by their own
    fluctuation: the peak of the pooled histogram in bins of ``coarse_bin``,
    refined by the count-weighted centroid of the peak bin and its two
    neighbours.

    Returns
    -------
    centre : (H, W) float64, time unit of the input (``t_min`` where the box
        holds no photon).
    height : (H, W) float64, pooled counts in the peak bin.
    """
    t, _ = _check(timestamps, offsets)
    H, W = (int(v) for v in shape)
    hist = histogram_from_timetags(t, offsets, coarse_bin, t_min, t_max).reshape(H, W, -1)
    pooled = _box(hist, radius) - hist
    pk = pooled.argmax(axis=-1)
    nb = hist.shape[-1]
    j3 = np.clip(pk[..., None] + np.arange(-1, 2), 0, nb - 1)
    w3 = np.take_along_axis(pooled, j3, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        cen = (w3 * (j3 + 0.5)).sum(-1) / w3.sum(-1)
    centre = t_min + np.nan_to_num(cen, nan=0.0) * coarse_bin
    return centre, pooled.max(axis=-1)


def estimate_timing_spread(timestamps, offsets, shape, t_min, t_max, coarse_bin,
                           radius: int = 2, span=None, resolution=None) -> TimingSpread:
    """Measure the return's timing spread by stacking photons on their local centre.

    For every pixel the centre of the return is found from its neighbours
    only (:func:`local_return_centres`).  The pixel's photons relative to
    that centre, over the brighter half of the pixels, give a peak on a flat
    background; a Gaussian plus constant fit gives μ, σ and the FWHM, the
    cumulative background-subtracted excess gives ``lead`` and ``tail``.

    ``shape`` : (H, W); ``coarse_bin`` : a first guess of the return's width
    (the bin of the pooled search), e.g. the published jitter; ``span`` :
    half-range of the stacked profile (default 15·coarse_bin); ``resolution``
    : its bin (default coarse_bin / 20).
    """
    from scipy.optimize import curve_fit

    t, pix = _check(timestamps, offsets)
    centre, height = local_return_centres(t, offsets, shape, t_min, t_max, coarse_bin, radius)
    bright = (height > np.median(height)).ravel()
    span = 15.0 * coarse_bin if span is None else float(span)
    res = coarse_bin / 20.0 if resolution is None else float(resolution)
    rel = t.astype(np.float64) - centre.ravel()[pix]
    rel = rel[bright[pix]]
    edges = np.arange(-span, span + res / 2, res)
    counts, _ = np.histogram(rel, edges)
    x = 0.5 * (edges[1:] + edges[:-1])
    c0 = float(np.median(counts))

    def model(x, a, m, s, c):
        return a * np.exp(-0.5 * ((x - m) / s) ** 2) + c

    p, _ = curve_fit(model, x, counts, p0=[counts.max() - c0, 0.0, coarse_bin / 2, c0])
    sigma = abs(float(p[2]))
    excess = counts - p[3]                       # signed: noise cancels in the sums
    excess[np.abs(x - p[1]) > span / 2] = 0.0    # far wings: background only
    cum = np.cumsum(excess) / excess.sum()
    lead = -float(x[np.argmax(cum >= 0.01)])
    tail = float(x[np.argmax(cum >= 0.99)])
    return TimingSpread(sigma, 2.0 * np.sqrt(2.0 * np.log(2.0)) * sigma, lead, tail,
                        edges, counts, float(p[1]))


# --------------------------------------------------------------------------- signal / background
@dataclass(frozen=True)
class TimetagEstimate:
    """Signal and background from time tags.

    Attributes
    ----------
    signal : (H, W) float64, estimated signal photons per pixel (unbiased, may
        be negative for a pixel without return).
    background_rate : (H, W) float64, background photons per time unit.
    mean_signal : float, mean signal photons per pixel (Σ signal / P).
    sbr : float, Σ signal / Σ background within the window.
    mean_signal_std, sbr_std : float, standard deviations from counting
        statistics of the background estimate.
    free_fraction : float, share of (pixel, bin) cells used for the background.
    bin_width, n_total : the analysis bin and the photons in the window.
    """

    signal: np.ndarray
    background_rate: np.ndarray
    mean_signal: float
    sbr: float
    mean_signal_std: float
    sbr_std: float
    free_fraction: float
    bin_width: float
    n_total: int


def _outside_spans(det: np.ndarray, span_radius: int, g_pre: int, g_post: int,
                   p_false_alarm: float, n_iter: int) -> np.ndarray:
    """(H, W, nb) bool: the bins outside every return span (step 3 of
    :func:`signal_background_from_timetags`).

    ``det`` : (H, W, nb) box-summed counts of the other colour's pixels.  A
    bin is a return where it exceeds the Poisson ``p_false_alarm`` quantile
    of the level of the free bins (re-estimated ``n_iter`` times); the span
    runs from the first return − ``g_pre`` bins to the last + ``g_post``,
    widened over ``span_radius`` pixels.
    """
    from scipy.ndimage import maximum_filter, minimum_filter
    from scipy.stats import poisson

    nb = det.shape[-1]
    j = np.arange(nb)
    free = np.ones(det.shape, dtype=bool)
    for _ in range(int(n_iter)):
        mu = (det * free).sum(-1) / np.maximum(free.sum(-1), 1)
        sig = det > poisson.isf(p_false_alarm, mu)[..., None]
        has = sig.any(-1)
        first = np.where(has, sig.argmax(-1), nb)
        last = np.where(has, nb - 1 - sig[..., ::-1].argmax(-1), -1)
        if span_radius > 0:
            first = minimum_filter(first, size=2 * span_radius + 1, mode="nearest")
            last = maximum_filter(last, size=2 * span_radius + 1, mode="nearest")
        free = ~((j >= (first - g_pre)[..., None]) & (j <= (last + g_post)[..., None]))
    return free


def _pooled_rate(hist: np.ndarray, free: np.ndarray, mine: np.ndarray, radius: int,
                 bw: float):
    """Background rate from the free bins of the ``mine`` pixels, pooled over boxes
    of (2·radius+1)² pixels (step 4).

    Returns ``(rate (H, W) per time unit, cells (H, W) free bins pooled,
    own_free (H, W) free-bin counts of each pixel of this colour)``.
    """
    m = mine[..., None]
    own_free = (hist * free * m).sum(-1)
    # the box sum is linear: sum over the bins first, then over the box
    cnt = _box(own_free, radius)
    cells = _box((free & m).sum(-1).astype(np.float64), radius)
    with np.errstate(invalid="ignore", divide="ignore"):
        rate = cnt / (cells * bw)
    return rate, cells, own_free


@dataclass(frozen=True, slots=True)
class SpanSearch:
    """How :func:`signal_background_from_timetags` finds the returns' spans.

    radius : pixels, the (2·radius+1)² box of other-colour pixels searched for returns;
    span_radius : pixels over which a span is widened (None: ``radius``);
    background_radius : pixels, the box the background rate is pooled over;
    p_false_alarm : per bin and box, the Poisson level of a return; n_iter : times
    the background level is re-estimated from the bins outside the spans.
    """

    radius: int = 3
    span_radius: int | None = None
    background_radius: int = 3
    p_false_alarm: float = 1e-4
    n_iter: int = 3


def signal_background_from_timetags(timestamps, offsets, shape, t_min, t_max, bin_width,
                                    lead, tail,
                                    search: SpanSearch | None = None) -> TimetagEstimate:
    """Mean signal photons per pixel and signal-to-background ratio from time tags.

    Model: per pixel a background uniform in time (rate b_i) plus returns at
    unknown times.  Signal = photons in the window − b_i · window.  b_i is
    estimated where no return can be: outside the *span* of the returns of
    the pixel's neighbourhood.

    1. Histograms in bins of ``bin_width`` (the return's FWHM).
    2. Cross-fitting on a checkerboard: the returns near a pixel of one colour
       are found from the pixels of the other colour only, so the choice of
       background bins is independent of the photons then counted in them
       (no selection bias; a missed return can only lower the signal).
    3. In the (2·radius+1)² box of other-colour pixels a bin is a return
       when its count exceeds the Poisson quantile of the box's background
       level at ``p_false_alarm`` (level re-estimated ``n_iter`` times from
       the bins outside the span).  The span runs from the first return −
       ``lead`` to the last + ``tail``, widened to every pixel within
       ``span_radius`` (default ``radius``): a pixel can see any depth of the
       neighbourhood it was pooled with.
    4. b_i = photons outside the span / time outside the span, pooled over
       the same-colour pixels of the (2·background_radius+1)² box.

    Parameters
    ----------
    timestamps, offsets : CSR time tags; ``shape`` (H, W) with H·W = P.
    t_min, t_max : the window (gate); same unit as timestamps.
    bin_width : analysis bin, about the return's FWHM
        (:func:`estimate_timing_spread`); the window is split into
        ``round((t_max − t_min)/bin_width)`` equal bins.
    lead, tail : guard before the first and after the last return (the
        99 % extent of the measured return, :class:`TimingSpread`).
    search : :class:`SpanSearch` (default: its defaults): ``radius``,
        ``span_radius``, ``background_radius`` (pixels) and ``p_false_alarm``, per
        bin and box (over B bins a box declares a false return with probability
        about B·p_false_alarm: that costs only variance, never bias).

    Returns
    -------
    :class:`TimetagEstimate`.
    """
    sp = SpanSearch() if search is None else search
    radius, background_radius = sp.radius, sp.background_radius
    t, pix = _check(timestamps, offsets)
    H, W = (int(v) for v in shape)
    if H * W != np.asarray(offsets).size - 1:
        raise FormatError(f"shape {shape} does not hold {np.asarray(offsets).size - 1} pixels",
                          field="shape")
    T = float(t_max - t_min)
    nb = max(1, int(round(T / bin_width)))
    bw = T / nb
    hist = histogram_from_timetags(t, offsets, bw, t_min, t_max).reshape(H, W, nb)
    hist = hist.astype(np.float64)
    n_pix = hist.sum(axis=-1)
    n_total = float(n_pix.sum())
    yy, xx = np.mgrid[:H, :W]
    colour = ((yy + xx) % 2).astype(bool)
    g_pre = int(np.ceil(lead / bw - 1e-9))
    g_post = int(np.ceil(tail / bw - 1e-9))
    R = radius if sp.span_radius is None else int(sp.span_radius)
    rate = np.full((H, W), np.nan)
    used_cells = 0.0
    var_sum = 0.0
    for c in (False, True):
        mine = colour == c
        det = np.rint(_box(hist * (~mine)[..., None], radius))
        free = _outside_spans(det, R, g_pre, g_post, sp.p_false_alarm, sp.n_iter)
        r_c, cells, own_free = _pooled_rate(hist, free, mine, background_radius, bw)
        rate[mine] = r_c[mine]
        used_cells += float((free & mine[..., None]).sum())
        # Var(Σ_i b_i T) for the pixels of this colour: each pooled count enters
        # the rates of the pixels whose box holds it (weights w_k = Σ_i T/cells_i).
        with np.errstate(invalid="ignore", divide="ignore"):
            wgt = _box(np.where(mine & (cells > 0), T / (cells * bw), 0.0), background_radius)
        var_sum += float(np.nansum(wgt ** 2 * own_free))
    # Pixels whose whole pool lies inside spans: the mean rate of the frame.
    lost = ~np.isfinite(rate)
    if lost.any():
        rate[lost] = np.nanmean(rate)
    background = rate * T
    signal = n_pix - background
    S = float(signal.sum())
    B = n_total - S
    s_std = float(np.sqrt(var_sum))
    sbr = S / B if B > 0 else np.inf
    sbr_std = s_std * n_total / B ** 2 if B > 0 else np.nan   # d(S/(N−S))/dS = N/(N−S)²
    P = H * W
    return TimetagEstimate(signal, rate, S / P, sbr, s_std / P, sbr_std,
                           used_cells / (P * nb), bw, int(n_total))


@dataclass(frozen=True)
class WindowCountEstimate:
    """Signal counted as every photon inside a signal window around each return.

    Attributes
    ----------
    signal : (H, W) int64, photons of each pixel inside its window (true
        signal in the window *plus the background that falls in it*).
    centre : (H, W) float64, window centre (local return time + μ), time unit
        of the input.
    window : float, the window's full width (2·half_width).
    mean_signal : float, Σ signal / P.
    sbr : float, Σ signal / (photons in the gate − Σ signal).
    n_total : int, photons in the gate.
    """

    signal: np.ndarray
    centre: np.ndarray
    window: float
    mean_signal: float
    sbr: float
    n_total: int


def window_counts_from_timetags(timestamps, offsets, shape, t_min, t_max, half_width,
                                coarse_bin, offset: float = 0.0,
                                radius: int = 2) -> WindowCountEstimate:
    """Count as signal every photon within ±``half_width`` of each pixel's return.

    The counting convention of photon-counting lidar papers that quote "signal
    photons per pixel" and an SBR from a signal window (e.g. Li et al. 2020):
    signal = photons in the window around the return, background = every
    other photon of the gate.  Unlike :func:`signal_background_from_timetags`
    it does not subtract the background that falls inside the window (about
    rate × window per pixel) and it does not count return photons outside the
    window (tails, further surfaces), so it is a different quantity, not a
    better estimate of the same one.  Its expectation per pixel is
    ``signal inside the window + background rate × window``.

    The window is centred at ``c_i + offset`` where c_i is the return time
    seen by the pixel's neighbours (:func:`local_return_centres`, the pixel
    itself excluded so its own background fluctuations do not move its
    window onto themselves) and ``offset`` the fitted mean of the stacked
    return (:attr:`TimingSpread.mu`).  Set ``half_width`` from the timing
    spread by a stated rule, e.g. 2·σ of :class:`TimingSpread` (95 % of a
    Gaussian return); windows are clipped to the gate.

    Parameters
    ----------
    timestamps, offsets : CSR time tags; ``shape`` (H, W) with H·W = P.
    t_min, t_max : the gate; same unit as timestamps.
    half_width : half the window, > 0.
    coarse_bin, radius : of :func:`local_return_centres` (use the values the
        timing spread was measured with).
    offset : added to each local centre.

    Returns
    -------
    :class:`WindowCountEstimate`.
    """
    t, pix = _check(timestamps, offsets)
    H, W = (int(v) for v in shape)
    if H * W != np.asarray(offsets).size - 1:
        raise FormatError(f"shape {shape} does not hold {np.asarray(offsets).size - 1} pixels",
                          field="shape")
    if not half_width > 0:
        raise FormatError(f"need half_width > 0, found {half_width}", field="half_width")
    centre, _ = local_return_centres(t, offsets, (H, W), t_min, t_max, coarse_bin, radius)
    centre = centre + float(offset)
    tt = t.astype(np.float64)
    in_gate = (tt >= t_min) & (tt < t_max)
    inside = in_gate & (np.abs(tt - centre.ravel()[pix]) <= half_width)
    signal = np.bincount(pix[inside], minlength=H * W).reshape(H, W).astype(np.int64)
    S = int(signal.sum())
    N = int(in_gate.sum())
    sbr = S / (N - S) if N > S else np.inf
    return WindowCountEstimate(signal, centre, 2.0 * float(half_width), S / (H * W), sbr, N)
