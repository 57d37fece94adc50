"""TDC code widths from the code-density test on background detections.

Background photons arrive uniformly in time, so the number of background
detections that land in TDC code N is proportional to that code's width
(the code-density or histogram test, IEEE Std 1057 §4.1.6 / 1241 §4.1.1).  A
SPAD pixel records only its *first* photon of a shot, so the raw counts fall
off along the window (a pixel that fired is not armed for the later codes):
the estimator works with the **hazard**, the detections in code N per shot
still armed at N (the Coates correction of first-photon histograms, Coates
1968, Rev. Sci. Instrum. 39, 1751).

Model, per pixel p and code N: ``n_pN ~ Poisson(λ_p · w_N · E_pN)`` with
``E_pN = S_pN − n_pN/2`` the actuarial exposure (S_pN the shots in which pixel
p was armed at the start of code N), λ_p the pixel's background per mean code
width and ``w_N`` the code's width in LSB.  λ and w are fitted jointly by
alternating maximum likelihood (a rank-one Poisson model: pixels with
different background share one set of code widths per group).

Signal is excluded by *windows*: per (shot, pixel) a code interval
``[lo, hi]`` where a return may lie (for instance the consistency test's
accepted interval, :func:`signal_windows`).  Codes inside it are not exposure
and detections inside it are not counted; a pixel that fired inside its
window is no longer armed after it (censored).  What is left is background
alone, whatever the scene.

Outputs: widths ``w_N`` (LSB, mean 1 over the estimated codes of a group),
``DNL_N = w_N − 1``, ``INL_N = Σ_{i≤N} DNL_i`` (LSB, at the upper edge of code
N), each with σ (INL's as a Brownian bridge: the widths' normalisation ties
both ends to 0).

Two estimators (``structured``):

* **plain** (``structured=False``): each code's own Poisson ML width, σ
  ``w/√n`` (2 % RMS needs ≈ 2500 detections per code and group);
* **structured** (default, :func:`structured_widths`): a delay-line TDC's DNL is
  a periodic pattern (the interpolator's, repeated every few codes) plus a small
  random part per code.  The periodic part is fitted over all codes as the
  significant Fourier components of the plain widths (each component's power
  against the noise floor at a family-wise false-alarm rate
  :data:`FOURIER_ALPHA`), then every code's residual from it is shrunk toward
  it by its variance ratio ``τ²/(τ² + v_N)`` (τ² the random part's variance, by
  its posterior over the codes; ``v_N`` the code's Poisson variance): the
  empirical-Bayes (James–Stein) estimator (Morris 1983, J. Am. Stat. Assoc. 78,
  47), its σ including the uncertainty of τ² and of the periodic fit.
  With plentiful counts (v_N ≪ τ²) it tends to the plain estimate; a code whose
  residual is beyond :data:`OUTLIER_Z` σ (a defect the Gaussian random part does
  not describe) keeps its plain estimate and σ.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mems_stereo.errors import ShapeError

#: alternating-ML iterations of :func:`code_widths` (converges to 1e-10 in ~10)
N_ITER = 60
#: family-wise false-alarm probability of a Fourier component of the periodic DNL
FOURIER_ALPHA = 1e-3
#: |residual| / σ beyond which a code keeps its plain estimate (structured estimator)
OUTLIER_Z = 4.0
#: grid points of the posterior of τ² (structured estimator)
TAU_GRID = 161


@dataclass(frozen=True)
class CodeWidths:
    """The code-density estimate.

    codes : (M,) int64 1-based TDC codes estimated.
    groups : (G,) int64 pixel-group labels (one set of widths per group).
    width, width_sigma : (G, M) float64, LSB (mean 1 over ``codes``).
    dnl : (G, M) float64 LSB, ``width − 1``.
    inl, inl_sigma : (G, M) float64 LSB, INL at the upper edge of each code.
    counts : (G, M) int64 background detections per code and group.
    rate : (P,) float64, each pixel's background probability per shot and
        mean-width code (λ_p; Hz = rate / bin_width).
    periodic : (G, M) float64 LSB, the structured estimator's periodic model
        (Fourier part; 1 for the plain estimator).
    random_rms : (G,) float64 LSB, the random part's RMS τ it estimated (nan: plain).
    """

    codes: np.ndarray
    groups: np.ndarray
    width: np.ndarray
    width_sigma: np.ndarray
    dnl: np.ndarray
    inl: np.ndarray
    inl_sigma: np.ndarray
    counts: np.ndarray
    rate: np.ndarray
    periodic: np.ndarray | None = None
    random_rms: np.ndarray | None = None

    @property
    def min_counts(self) -> int:
        """Fewest background detections in any estimated code of any group."""
        return int(self.counts.min()) if self.counts.size else 0

    def rms_dnl(self) -> float:
        """RMS of the DNL over all groups and codes, LSB."""
        return float(np.sqrt(np.mean(self.dnl ** 2)))


def first_photon_tables(codes, n_codes: int, window=None):
    """Background events and at-risk shots per (pixel, code).

    codes : (K, P) integer first-photon codes, 0 = none (1..n_codes).
    window : None or (lo, hi), each broadcastable to (K, P): codes lo..hi of
        that shot and pixel may hold signal (lo > hi: none).
    Returns (events, at_risk), each (P, n_codes + 1) int64 (column 0 unused).
    """
    c = np.asarray(codes).astype(np.int64)
    if c.ndim != 2:
        raise ShapeError(f"codes: expected (shots, pixels), found shape {c.shape}")
    if c.size and (c.min() < 0 or c.max() > n_codes):
        raise ShapeError(f"codes: expected values 0..{n_codes}, found {c.min()}..{c.max()}")
    K, P = c.shape
    M = n_codes + 2
    if window is None:
        lo = np.full_like(c, n_codes + 1)
        hi = np.zeros_like(c)
    else:
        lo = np.broadcast_to(np.asarray(window[0], dtype=np.int64), c.shape)
        hi = np.broadcast_to(np.asarray(window[1], dtype=np.int64), c.shape)
    has_win = lo <= hi
    fired = c > 0
    in_win = fired & has_win & (c >= lo) & (c <= hi)
    event = fired & ~in_win
    # last code at which the pixel was armed and observed for background
    last = np.where(event, c, np.where(in_win, lo - 1, n_codes))
    pix = np.broadcast_to(np.arange(P), c.shape)
    base = pix * M
    surv = np.zeros(P * M, dtype=np.int64)
    np.add.at(surv, (base + np.clip(last, 0, n_codes)).ravel(), 1)
    # at risk at N: last >= N  (reverse cumulative sum per pixel)
    at_risk = np.cumsum(surv.reshape(P, M)[:, ::-1], axis=1)[:, ::-1]
    # minus the window codes of shots still armed there (window wholly before last)
    wsel = has_win & (last >= lo) & ~in_win
    diff = np.zeros(P * M, dtype=np.int64)
    np.add.at(diff, (base + np.clip(lo, 0, n_codes + 1))[wsel], 1)
    np.add.at(diff, (base + np.clip(hi + 1, 0, n_codes + 1))[wsel], -1)
    at_risk = at_risk - np.cumsum(diff.reshape(P, M), axis=1)
    events = np.zeros(P * M, dtype=np.int64)
    np.add.at(events, (base + c)[event], 1)
    return events.reshape(P, M)[:, : n_codes + 1], at_risk[:, : n_codes + 1]


def _fit_group(n, E):
    """Alternating Poisson ML of n (p, m) ~ λ_p·w_m·E (p, m); w normalised to mean 1."""
    lam = n.sum(axis=1) / np.maximum(E.sum(axis=1), 1e-300)
    w = np.ones(n.shape[1])
    for _ in range(N_ITER):
        w = n.sum(axis=0) / np.maximum(lam @ E, 1e-300)
        w = w / w.mean()
        lam = n.sum(axis=1) / np.maximum(E @ w, 1e-300)
    return w, lam


@dataclass(frozen=True)
class Structured:
    """:func:`structured_widths`' estimate of one group (arrays (M,), LSB).

    width, sigma : the shrunk widths and their σ.
    periodic : the Fourier model of the periodic DNL (1 + Σ components).
    random_rms : τ, the random part's RMS; n_components : Fourier terms kept.
    """

    width: np.ndarray
    sigma: np.ndarray
    periodic: np.ndarray
    random_rms: float
    n_components: int


def _periodic_model(r, alpha: float):
    """The significant Fourier components of r (M,): (model (M,), real parameters)."""
    M = r.size
    X = np.fft.rfft(r)
    P = np.abs(X) ** 2
    P[0] = 0.0
    nf = max(P.size - 1, 1)
    sel = np.zeros(P.size, dtype=bool)
    for _ in range(3):  # noise floor from the components not (yet) selected
        rest = P[1:][~sel[1:]]
        if rest.size < 4:
            break
        floor = float(np.mean(rest))
        new = P > floor * math.log(nf / alpha)
        new[0] = False
        if np.array_equal(new, sel):
            break
        sel = new
    return np.fft.irfft(np.where(sel, X, 0.0), n=M), int(2 * sel.sum())


def _tau2_posterior(r, v, k: int, n_grid: int = TAU_GRID):
    """Posterior of τ² (flat prior) for r_N ~ N(0, v_N + τ²): (grid (T,), weights (T,))."""
    mv = float(np.mean(v))
    excess = max(float(np.mean(r * r)) - mv, 0.0)
    sd = math.sqrt(2.0 / max(r.size - k, 1)) * (mv + excess)
    t = np.linspace(0.0, excess + 8.0 * sd, n_grid)
    s = v[None, :] + t[:, None]
    ll = -0.5 * np.sum(np.log(s) + (r * r)[None, :] / s, axis=1)
    p = np.exp(ll - ll.max())
    return t, p / p.sum()


def structured_widths(width, exposure, alpha: float = FOURIER_ALPHA) -> Structured:
    """The empirical-Bayes code widths of one group (module docstring).

    width : (M,) plain widths (LSB, mean 1); exposure : (M,) background
    detections expected per LSB of width (``Σ_p λ_p·E_pN``): a code's Poisson
    variance at its expected count is ``v_N = m_N / exposure_N``.  The periodic
    model m is the Fourier components of ``width − 1`` above ``ln(F/α)`` times the
    noise floor (F frequencies, K real parameters with the mean).  Given τ² each
    code is ``m_N + (1 − B_N)(ŵ_N − m_N)``, ``B_N = v_N/(v_N + τ²)``, with variance
    ``v_N(1 − B_N) + B_N²·(K/M)(v_N + τ²)`` (the second term: the periodic fit's
    own error); both are averaged over the posterior of τ² (flat prior, from the
    codes that are not outliers), so τ² near 0 does not claim more than the
    data show.  Returns :class:`Structured` (τ: the posterior mean's root).
    """
    w = np.asarray(width, dtype=np.float64)
    M = w.size
    dm, k = _periodic_model(w - 1.0, alpha)
    m = 1.0 + dm
    expo = np.maximum(np.asarray(exposure, dtype=np.float64), 1e-300)
    v = np.maximum(m, 0.05) / expo
    r = w - m
    keep = np.ones(M, dtype=bool)
    for _ in range(2):  # τ² from the codes the Gaussian random part describes
        t, p = _tau2_posterior(r[keep], v[keep], k)
        keep = np.abs(r) <= OUTLIER_Z * np.sqrt(v + float(p @ t))
        if keep.sum() <= k + 3:
            keep[:] = True
            break
    lev = (k + 1) / M
    B = v[None, :] / (v[None, :] + t[:, None])                 # (T, M)
    mean = m + (1.0 - B) * r
    var = v * (1.0 - B) + B * B * lev * (v + t[:, None])
    est = p @ mean
    var = p @ var + p @ (mean - est) ** 2
    est = np.where(keep, est, w)
    var = np.where(keep, var, np.maximum(w, 0.05) / expo)
    c = float(np.mean(est))  # widths of mean 1, as the plain ones
    return Structured(est / c, np.sqrt(var) / c, m, math.sqrt(float(p @ t)), k)


def code_widths(codes, n_codes: int, *, window=None, groups=None, first_code: int = 1,
                last_code: int | None = None, structured: bool = True) -> CodeWidths:
    """Code widths, DNL and INL of a TDC from the background detections of a recording.

    Parameters
    ----------
    codes : (K, P) or (K, H, W) integer first-photon TDC codes per shot and
        pixel, 0 = no detection (a recording's ``bins``).
    n_codes : the TDC's codes (``system.tdc.n_bins``).
    window : optional (lo, hi) signal windows broadcastable to ``codes``
        (e.g. :func:`signal_windows`); codes lo..hi are left out per shot and pixel.
    groups : optional (P,) or (H, W) integer pixel groups (pixels behind one
        TDC); default one group.
    first_code, last_code : the codes estimated (default 1..n_codes); the
        widths' mean is 1 over them.
    structured : the structured (empirical-Bayes) estimator (default) or the
        plain per-code estimate (module docstring).

    Returns
    -------
    CodeWidths.  Plain σ are Poisson: a code with n background detections has
    ``σ_w ≈ w/√n`` (2 % RMS needs ≈ 2500 per code and group); the structured
    estimator's are smaller where the random part is small against them.

    Examples
    --------
    >>> rng = np.random.default_rng(1)
    >>> t = rng.exponential(1 / 0.02, size=(4000, 8))      # 2 % per code
    >>> codes = np.where(t < 64, np.floor(t).astype(int) + 1, 0)
    >>> est = code_widths(codes, 64)
    >>> bool(np.all(np.abs(est.dnl) < 5 * est.width_sigma))
    True
    """
    c = np.asarray(codes)
    if c.ndim == 3:
        c = c.reshape(c.shape[0], -1)
        if window is not None:
            window = tuple(np.asarray(w).reshape(np.asarray(w).shape[0], -1)
                           if np.ndim(w) == 3 else w for w in window)
    events, at_risk = first_photon_tables(c, int(n_codes), window)
    return widths_from_tables(events, at_risk, groups=groups, first_code=first_code,
                              last_code=last_code, structured=structured)


def widths_from_tables(events, at_risk, *, groups=None, first_code: int = 1,
                       last_code: int | None = None, structured: bool = True) -> CodeWidths:
    """:func:`code_widths` from the tables of :func:`first_photon_tables`.

    events, at_risk : (P, n_codes + 1) int background detections and armed shots
    per pixel and code (column 0 unused); tables of several recordings of one
    TDC add.  Other parameters and the result as :func:`code_widths`.
    """
    events, at_risk = np.asarray(events), np.asarray(at_risk)
    if events.ndim != 2 or events.shape != at_risk.shape:
        raise ShapeError(f"events, at_risk: expected equal (pixels, codes + 1) tables, "
                         f"found {events.shape} and {at_risk.shape}")
    P = events.shape[0]
    last = int(events.shape[1] - 1 if last_code is None else last_code)
    sel = np.arange(int(first_code), last + 1)
    n = events[:, sel].astype(np.float64)
    E = np.maximum(at_risk[:, sel] - 0.5 * n, 0.0)
    g = np.zeros(P, dtype=np.int64) if groups is None else np.asarray(groups).ravel()
    if g.shape != (P,):
        raise ShapeError(f"groups: expected {P} pixel labels, found shape {g.shape}")
    labels = np.unique(g)
    out = {k: np.zeros((labels.size, sel.size))
           for k in ("w", "sw", "inl", "sinl", "n", "per")}
    tau = np.full(labels.size, np.nan)
    rate = np.zeros(P)
    for i, lab in enumerate(labels):
        m = g == lab
        w, lam = _fit_group(n[m], E[m])
        rate[m] = lam
        cnt = n[m].sum(axis=0)
        expo = np.maximum(lam @ E[m], 1e-300)
        var = np.where(cnt > 0, w * w / np.maximum(cnt, 1.0), 1.0 / expo ** 2)
        out["per"][i] = 1.0
        if structured and sel.size > 8:
            st = structured_widths(w, expo)
            w, var, out["per"][i], tau[i] = st.width, st.sigma ** 2, st.periodic, st.random_rms
        A = np.cumsum(var)
        out["w"][i], out["sw"][i], out["n"][i] = w, np.sqrt(var), cnt
        out["inl"][i] = np.cumsum(w - 1.0)
        out["sinl"][i] = np.sqrt(np.maximum(A * (1.0 - A / A[-1]), 0.0))
    return CodeWidths(sel.astype(np.int64), labels.astype(np.int64), out["w"], out["sw"],
                      out["w"] - 1.0, out["inl"], out["sinl"], out["n"].astype(np.int64), rate,
                      out["per"], tau)


def code_edges(widths, bin_width: float) -> np.ndarray:
    """Times of the code edges, s, from widths (M,) LSB: (M + 1,), 0 at the
    lower edge of the first code (a TDC with equal widths gives k·bin_width)."""
    w = np.asarray(widths, dtype=np.float64)
    return np.concatenate([[0.0], np.cumsum(w)]) * float(bin_width)


def signal_windows(recording, system=None, confidence: float = 0.9999):
    """Per (shot, pixel) the codes where a return may lie: the consistency test's
    accepted interval (:func:`mems_stereo.pipeline.consistency.accepted_code_intervals`)
    at ``confidence``, from the recording's scan angles.

    recording : :class:`~mems_stereo.io.recording.Recording` (line or 2-D sensor);
    system : default the recording's.  Returns (lo, hi), each (K, H, W) int32.
    """
    from mems_stereo.model.scanner import scan_angles
    from mems_stereo.pipeline.consistency import accepted_code_intervals

    sys_ = recording.system if system is None else system
    theta, _ = scan_angles(recording.shot_time, recording.zero_crossings, recording.rising,
                           sys_.scanner)
    return accepted_code_intervals(sys_, theta, confidence)
