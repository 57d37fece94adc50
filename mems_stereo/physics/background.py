"""Background: rate estimates from histograms and the expected background per
TDC bin, per code window and per scan-angle step (Poisson thresholds).
"""

from __future__ import annotations

import functools
import sys

import numpy as np
from scipy.special import pdtrc

from mems_stereo.errors import FormatError
from mems_stereo.util.lazy_numba import compiled_if_loaded, compiled_kernel

#: entries from which :func:`moving_sum` runs its compiled kernel where numba is loaded
COMPILED_SUM_ENTRIES = 4096


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

    Examples
    --------
    >>> rec = ms.read_recording(ms.data.path("room.h5"))
    >>> h = ms.accumulate_histograms(rec.bins, rec.truth["label"], n_bins=4096)
    >>> rate = ms.background_rate_mle(h.noise, h.n_shots, rec.system.tdc.bin_width, raw=h.raw)
    >>> rate.shape, round(float(np.median(rate)) / 1e3)         # kHz
    ((1, 192), 102)
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


def poisson_isf(alpha, mu) -> np.ndarray:
    """Smallest integer k with P(X > k) <= alpha for X ~ Poisson(mu) (vectorised).

    Bisection on ``scipy.special.pdtrc`` (the Poisson upper tail), which keeps
    the heavy ``scipy.stats`` import off the processing path.  Equals
    ``scipy.stats.poisson.isf(alpha, mu)`` (tested).
    """
    a, m = np.broadcast_arrays(np.asarray(alpha, np.float64), np.asarray(mu, np.float64))
    lo = np.full(m.shape, -1.0)  # P(X > lo) > alpha
    hi = np.ceil(m + 40.0 * np.sqrt(m) + 60.0)  # P(X > hi) <= alpha for any alpha > 1e-300
    while np.any(hi - lo > 1):
        mid = np.floor(0.5 * (lo + hi))
        ok = pdtrc(mid, m) <= a
        hi = np.where(ok, mid, hi)
        lo = np.where(ok, lo, mid)
    return hi


def background_rate_from_noise(noise, raw, acceptance, n_valid: int,
                                bin_width: float) -> np.ndarray:
    """ML background rate per pixel from the noise histogram N, pile-up aware.

    As :func:`mems_stereo.physics.background.background_rate_mle` (binomial trials of
    the shots still armed at each bin, ``n_j = n_valid − Σ_{i<j} raw_i``), but
    a shot whose accepted interval holds bin j would have put a background
    photon there into S, not N: such shots are no trials for N at bin j.  With
    ``A_j`` of the ``n_valid`` shots accepting bin j, and arming independent of
    the scan angle, the trials of N are ``n_j·(1 − A_j / n_valid)``; then
    ``λ̂ = −ln(1 − Σ N_j / Σ n_j (1 − A_j/n_valid)) / Δt``.

    Returns (P,) float64 Hz (NaN where no trial is left).
    """


    n_valid = max(int(n_valid), 1)
    sums = _noise_trial_sums(noise, raw, acceptance, n_valid) if bin_width > 0 else None
    if sums is None:  # (and where the input is refused: the reference names why)
        return background_rate_mle(noise, n_valid, bin_width, raw=raw,
                                   trials_factor=1.0 - np.asarray(acceptance) / n_valid)
    k, n = sums
    with np.errstate(divide="ignore", invalid="ignore"):
        p = np.where(n > 0, k / n, np.nan)
        return -np.log1p(-p) / bin_width


def _noise_trial_sums(noise, raw, acceptance, n_valid: int):
    """``(Σ N_j, Σ n_j (1 − A_j/n_valid))`` per pixel, (P,) float64 each, by the compiled
    kernel (:func:`_noise_trials_py`: :func:`background_rate_mle`'s numbers, its sums
    added in NumPy's pairwise order) where numba is loaded and the histograms are
    (P, n_bins) and valid; else None."""
    h, r, a = np.asarray(noise), np.asarray(raw), np.asarray(acceptance)
    kernel = None
    if h.size >= COMPILED_SUM_ENTRIES and "numba" in sys.modules:  # (as compiled_if_loaded)
        kernel = compiled_kernel(_noise_trials_py, {"_pairwise_py": _pairwise_py})
    if kernel is None or h.ndim != 2 or not h.shape == r.shape == a.shape or not h.shape[1]:
        return None
    k, n, ok = kernel(np.ascontiguousarray(h), np.ascontiguousarray(r),
                      np.ascontiguousarray(a), n_valid, pairwise_plan(h.shape[1]))
    return (k, n) if ok else None


@functools.lru_cache(maxsize=16)
def pairwise_plan(n: int) -> np.ndarray:
    """NumPy's pairwise summation of n float64 values (a contiguous reduction) as a
    program for :func:`_pairwise_py`: rows ``(0, first, count)`` push the sum of a block
    of at most 128 values (8 accumulators), rows ``(1, 0, 0)`` replace the top two sums by
    their sum (the left one first); the blocks and joins of its recursion, which splits
    n > 128 values at n/2 rounded down to a multiple of 8."""
    out = []

    def split(lo: int, m: int) -> None:
        if m <= 128:
            out.append((0, lo, m))
            return
        m2 = m // 2
        m2 -= m2 % 8
        split(lo, m2)
        split(lo + m2, m - m2)
        out.append((1, 0, 0))

    split(0, int(n))
    return np.array(out, np.int64)


def _pairwise_py(a, plan):  # pragma: no cover - compiled by numba
    """``a.sum()`` of a float64 vector as NumPy adds it (``plan`` of :func:`pairwise_plan`)."""
    stack = np.empty(plan.shape[0])
    top = 0
    for row in range(plan.shape[0]):
        if plan[row, 0] == 1:
            top -= 1
            stack[top - 1] = stack[top - 1] + stack[top]
            continue
        lo, m = plan[row, 1], plan[row, 2]
        if m < 8:
            res = -0.0
            for i in range(m):
                res += a[lo + i]
        else:
            r = np.empty(8)
            for i in range(8):
                r[i] = a[lo + i]
            i = 8
            while i < m - m % 8:
                for t in range(8):
                    r[t] += a[lo + i + t]
                i += 8
            res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]))
            while i < m:
                res += a[lo + i]
                i += 1
        stack[top] = res
        top += 1
    return 0.0 + stack[0]


def _noise_trials_py(h, r, a, n_valid, plan):  # pragma: no cover - compiled by numba
    """Per row of (P, n_bins) ``h`` (noise), ``r`` (raw), ``a`` (acceptance): Σ h and
    Σ n_j (1 − a_j/n_valid), n_j the shots armed at bin j (:func:`armed_shots`: n_valid
    less the running sum of r before j), each element as :func:`background_rate_mle`
    computes it; ``ok`` False for a negative count or more detections than shots."""
    P, B = h.shape
    k, n = np.empty(P), np.empty(P)
    hf, tr = np.empty(B), np.empty(B)
    nv = np.float64(n_valid)
    for p in range(P):
        c = 0.0
        for j in range(B):
            hj, rj = np.float64(h[p, j]), np.float64(r[p, j])
            if hj < 0 or rj < 0:
                return k, n, False
            c = rj if j == 0 else c + rj  # np.cumsum's running sum
            nj = nv - (c - rj)
            if nj - rj < -1e-9:
                return k, n, False
            hf[j] = hj
            tr[j] = nj * (1.0 - a[p, j] / nv)
        k[p] = _pairwise_py(hf, plan)
        n[p] = _pairwise_py(tr, plan)
    return k, n, True


def expected_background_in_signal(acceptance, rate_hz, bin_width: float) -> np.ndarray:
    """Expected background counts per (pixel, bin) that pass the classifier.

    ``acceptance`` (P, n_bins), ``rate_hz`` (P,).  First-photon statistics: a
    shot's first background photon falls in bin j with q·(1 − q)^(j−1),
    q = 1 − exp(−λ·Δt) (signal photons, rarer, are neglected here).
    """


    return acceptance * expected_background(rate_hz, 1.0, bin_width, acceptance.shape[1])


def expected_background_by_angle(table, n_per_step, rate_hz, pixels=None) -> np.ndarray:
    """Expected background counts that pass the classifier, per pixel and angle step.

    For step s and pixel p, a first background photon lands in the accepted
    interval [lo, hi] with probability ``(1 − q)^(lo−1) − (1 − q)^hi``
    (geometric first-photon law, q = 1 − exp(−λ·Δt)); times the number of
    valid shots at that step.  Returns (P, S) float64.  ``pixels`` : (P,) the
    flat pixels of ``rate_hz`` (default: all of the table's, in order); each
    pixel's row is the same whichever others are computed with it.
    """
    P = table.lo.shape[1] if pixels is None else len(pixels)
    out = np.zeros((P, table.n_steps))
    used = np.flatnonzero(n_per_step)
    if used.size == 0:
        return out
    table.ensure(used)
    lo = table.lo[used] if pixels is None else table.lo[np.ix_(used, pixels)]
    hi = table.hi[used] if pixels is None else table.hi[np.ix_(used, pixels)]
    lo = lo.astype(np.float64)
    hi = hi.astype(np.float64)
    dt = table.system.tdc.bin_width
    a = np.log1p(-np.minimum(-np.expm1(-np.nan_to_num(rate_hz) * dt), 1 - 1e-15))[None, :]
    pacc = np.where(lo <= hi, np.exp((lo - 1.0) * a) - np.exp(hi * a), 0.0)
    out[:, used] = (pacc * n_per_step[used][:, None]).T
    return out


# --------------------------------------------------------------------------- filter, threshold
def moving_sum(hist, width: int) -> np.ndarray:
    """Centred moving sum of ``width`` (odd) bins along the last axis; zeros beyond the ends.

    The differences of the running sum of ``hist`` padded with ``width // 2 + 1`` zeros
    before and ``width // 2`` after; compiled (:func:`_moving_sum_py`, the same running
    additions in the same order: the same numbers) where numba is loaded."""
    width = int(width)
    if width < 1 or width % 2 == 0:
        raise FormatError(f"width must be an odd number >= 1, found {width}", field="width")
    h = np.asarray(hist, dtype=np.float64)
    half = width // 2
    n = h.shape[-1]
    kernel = compiled_if_loaded(_moving_sum_py) if h.size >= COMPILED_SUM_ENTRIES else None
    if kernel is not None and n:
        rows = np.ascontiguousarray(h.reshape(-1, n))
        return kernel(rows, width).reshape(h.shape)
    # the running sum of h padded with half + 1 zeros before and half after, written
    # in place (no padded copy): the same sums, as the zeros add nothing
    c = np.empty(h.shape[:-1] + (n + width,))
    c[..., :half + 1] = 0.0
    np.cumsum(h, axis=-1, out=c[..., half + 1:half + 1 + n])
    c[..., half + 1 + n:] = c[..., half + n:half + n + 1]
    return c[..., width:] - c[..., :-width]


def _moving_sum_py(rows, width):  # pragma: no cover - compiled by numba
    """:func:`moving_sum` of (R, n) float64 rows, loop by loop (the numba kernel): per
    row the running sum ``c`` (``np.cumsum``'s additions, in its order) padded with
    ``half + 1`` zeros before and its last value after, then ``c[i + width] − c[i]``."""
    R, n = rows.shape
    half = width // 2
    out = np.empty((R, n))
    c = np.empty(n + width)
    for r in range(R):
        for i in range(half + 1):
            c[i] = 0.0
        acc = rows[r, 0]
        c[half + 1] = acc
        for i in range(1, n):
            acc = acc + rows[r, i]
            c[half + 1 + i] = acc
        for i in range(half + 1 + n, n + width):
            c[i] = acc
        for i in range(n):
            out[r, i] = c[i + width] - c[i]
    return out
