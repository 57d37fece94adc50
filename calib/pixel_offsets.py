"""Per-pixel TDC offsets from the wall cells: score test, one-step estimates, shrinkage.

A pixel's TDC start delay ``δ_p`` adds to the return time τ of each of its cells
(:mod:`mems_stereo.calib.problem`).  At the fitted point (all ``δ_p = 0``, their common
part held by ``tdc_offset``):

* each pixel's **score** ``g_p = Σ ∂ℓ/∂τ`` over its cells and its **expected (Fisher)
  information** ``I_p = Σ F_ττ``, per cell that of the first-photon law,
  ``F_ττ = ∫₀^T (∂_τ I(t))² / I(t) · S(t) dt`` with ``I(t) = λ + m·f(t − τ)`` the
  cell's photon intensity and ``S(t) = exp(−∫₀ᵗ I)`` the chance that it has not
  fired by t (:func:`mems_stereo.calib.expected_info.cell_fisher`)
  — not the outer product of the cell scores: a pixel has a few detections
  (3 fired cells per pixel is typical of the calibration family), and
  ``g_p / √(Σ s_c²)`` then is a self-normalised sum, skewed and bounded by
  ``√n`` (±1 for one detection), which biased the estimates (pull mean −0.5) and
  doubled the test statistic under no offsets;
* the joint **score test** ``LM = Σ g_p²/I_p − (Σ g_p)²/Σ I_p``, χ² with G − 1 dof
  (G pixels with information; the common part is ``tdc_offset``'s);
* the **one-step estimate** ``d_p = g_p / I_p`` (σ ``I_p^{-½}``; the offsets, at most a
  few hundred ps, are far below the pulse σ, where the log-likelihood is quadratic),
  its information-weighted mean removed;
* the offsets' **spread** σ_o (their σ over pixels) by maximum marginal likelihood,
  ``d_p ~ N(0, 1/I_p + σ_o²)``, and each pixel's posterior mean and σ under that
  normal population (empirical Bayes, Efron & Morris 1975, JASA 70, 311):
  ``d_p·σ_o²/(σ_o² + 1/I_p)`` and ``(I_p + 1/σ_o²)^{-½}``.  A pixel with a handful
  of detections (σ of its own estimate ≈ the pulse σ, several ns) is thus not
  given an offset of nanoseconds; a pixel no cell informs gets the population's
  value 0 with σ σ_o — no made-up value, and no σ of 0.

The pixel offsets are observable only when their spread is not small against
``σ_pulse/√n_p`` (n_p low-pile-up detections of a pixel): with a 6.3 ns pulse,
300 ps offsets need ≈ 150 detections per pixel before the test sees them.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from mems_stereo.calib.expected_info import cell_fisher
from mems_stereo.calib.hardware_fit import ALPHA_SELECT, TermTest
from mems_stereo.calib.problem import cell_terms, spot_px, spot_share
from scipy import optimize, stats


@dataclass(frozen=True)
class PixelOffsets:
    """Per-pixel TDC offsets (see the module); arrays (H·W,), row-major pixels.

    value, std : s, the written offsets (posterior means, their weighted mean 0)
        and their σ (the spread σ_o where no cell informs the pixel).
    test : :class:`~mems_stereo.calib.hardware_fit.TermTest` "pixel offsets".
    covered : bool, pixels with information.
    estimate, estimate_std : s, the one-step estimates ``d_p`` and their σ
        ``I_p^{-½}`` (0 and inf where not covered).
    spread : s, σ_o.
    """

    value: np.ndarray
    std: np.ndarray
    test: TermTest
    covered: np.ndarray
    estimate: np.ndarray
    estimate_std: np.ndarray
    spread: float


def cell_signal(cells, pred: np.ndarray, logmu: float, logspot: float, two_d: bool,
                pitch_ratio: float = 1.0) -> np.ndarray:
    """Expected signal photons m (N,) of each cell, as in
    :func:`~mems_stereo.calib.problem.cell_terms`: the spot's photons at the
    cell's shot times the share of the Gaussian spot on its pixel.
    ``pred`` : (N, 4) per-cell [τ, u, v, log g]."""
    s = spot_px(logspot)
    share = spot_share(cells.col, pred[:, 1], s)[0]
    if two_d:
        share = share * spot_share(cells.row, pred[:, 2], s * pitch_ratio)[0]
    return np.exp(logmu + pred[:, 3] - cells.log_gref) * share


def pixel_scores(prob, x) -> tuple:
    """Each pixel's time score ``g_p`` (1/s) and expected information ``I_p`` (1/s²)
    at the fitted ``x`` of ``prob`` (:class:`~mems_stereo.calib.problem.Problem`
    with its cells): ((H·W,), (H·W,))."""
    lay = prob.layout
    values, walls = lay.unpack(x)
    W, H = prob.system.receiver.width, prob.system.receiver.height
    g, info = np.zeros(W * H), np.zeros(W * H)
    pulse = prob.pulse(values)
    for j in range(lay.T):
        c = prob.cells[j]
        pred, ok, _ = prob.predictions(x, j, c.shots)
        pos = np.searchsorted(c.shots, c.shot)
        good = ok[pos]
        pc = np.where(good[:, None], pred[pos], [0.0, -1e6, -1e6, 0.0])
        pix = (c.row * W + c.col).astype(np.int64)
        if prob.pixel_offsets is not None:
            pc[:, 0] += prob.pixel_offsets[pix]
        _, d = cell_terms(c, pc, walls[j, 3], walls[j, 4], prob.sigma, lay.two_d,
                          prob.pitch_ratio, pulse)
        m = np.where(good, cell_signal(c, pc, walls[j, 3], walls[j, 4], lay.two_d,
                                       prob.pitch_ratio), 0.0)
        g += np.bincount(pix, np.where(good, d[:, 0], 0.0), W * H)
        info += np.bincount(pix, cell_fisher(pc[:, 0], m, c.lam, c.t_max, prob.sigma,
                                             pulse)[:, 0], W * H)
    return g, info


def offset_spread(est: np.ndarray, var: np.ndarray, upper: float) -> float:
    """σ_o ≥ 0 maximising ``Σ log N(est; 0, var + σ_o²)`` (s; at most ``upper``)."""
    if est.size < 2:
        return 0.0

    def nll(s):
        v = var + s * s
        return float(np.sum(np.log(v) + est * est / v))

    r = optimize.minimize_scalar(nll, bounds=(0.0, upper), method="bounded",
                                 options={"xatol": 1e-4 * upper})
    return float(r.x) if nll(r.x) < nll(0.0) else 0.0


def pixel_offsets(prob, x, alpha: float = ALPHA_SELECT) -> PixelOffsets:
    """The per-pixel TDC offsets at the fitted ``x`` of ``prob`` and their joint score
    test (see the module)."""
    g, info = pixel_scores(prob, x)
    cov = info > 0
    isum = float(info[cov].sum())
    mean = float(g[cov].sum() / isum) if isum > 0 else 0.0
    lm = float(np.sum(g[cov] ** 2 / info[cov]) - isum * mean * mean) if isum > 0 else 0.0
    dof = max(int(cov.sum()) - 1, 1)
    p = float(stats.chi2.sf(lm, dof))
    est = np.where(cov, g / np.where(cov, info, 1.0) - mean, 0.0)
    var = np.where(cov, 1.0 / np.where(cov, info, 1.0), np.inf)
    spread = offset_spread(est[cov], var[cov], 3.0 * prob.sigma)
    if spread > 0:
        value = np.where(cov, est * spread ** 2 / (spread ** 2 + var), 0.0)
        std = 1.0 / np.sqrt(np.where(cov, info, 0.0) + 1.0 / spread ** 2)
        wsum = float(np.sum(1.0 / std[cov] ** 2))
        value = np.where(cov, value - float(np.sum(value[cov] / std[cov] ** 2)) / wsum, 0.0)
    else:
        value, std = np.zeros_like(est), np.zeros_like(est)
    return PixelOffsets(value, std, TermTest("pixel offsets", (), lm, dof, p, p < alpha),
                        cov, est, np.sqrt(var), spread)


def with_pixel_offsets(system, offsets: PixelOffsets):
    """``system`` with the per-pixel offsets (added to any it has) and their σ."""
    tdc = system.tdc
    base = (np.zeros(offsets.value.size) if tdc.pixel_offsets is None
            else np.asarray(tdc.pixel_offsets, dtype=np.float64))
    return system.replace(tdc=replace(tdc, pixel_offsets=base + offsets.value,
                                      pixel_offsets_std=np.asarray(offsets.std, np.float64)))
