"""The first-photon correction of each peak's time of flight.

A SPAD records a shot's first photon only, so the ToF mean of a strong
return is early (pile-up) and one at the TDC start late.  Given the valid
shots per scan-angle step, :func:`first_photon_correction` estimates each
peak's signal photons per shot from which shots of its band fired
(:func:`mems_stereo.physics.first_photon.first_photon_delay`) and removes
that delay from the peak's ToF mean, with its uncertainty and the model's
own systematic allowance.  ``acc`` is the
:class:`~mems_stereo.pipeline.peak_accumulator.PeakAccumulator` whose sums are used.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mems_stereo.geometry.triangulation import path_length_of_point
from mems_stereo.geometry.uncertainty import spreads_for
from mems_stereo.model.hardware import pulse_mean_delay
from mems_stereo.physics.first_photon import (
    MU_GRID,
    MU_MAX,
    OUTLIER_PROBABILITY,
    ShapeExcess,
    band_log_miss_rows,
    first_photon_delay,
    first_photon_table,
    posterior_delay,
)
from mems_stereo.physics.first_photon_band_kernel import (
    band_figures,
    band_likelihood_moments,
)
from mems_stereo.physics.first_photon_band_kernel import kernels as band_kernels
from mems_stereo.physics.pulse import pulse_shape_of
from mems_stereo.physics.spot import spot_fraction, step_directions
from mems_stereo.pipeline.classify_kernel import compiles

#: peaks per block of the first-photon correction (by peak index; see
#: :func:`first_photon_correction`): a split of the peaks at multiples of it
#: gives the same bits as the whole
FP_BLOCK = 16
#: relative systematic uncertainty of the first-photon delay the correction removes
MODEL_DELAY_FRACTION = 0.15
#: factor by which the spot model may misjudge a peak's signal level μ0 (a surface
#: whose range or reflectance changes across the band, a spot clipped at a
#: silhouette): the delay's change over μ0/F … μ0·F is a systematic term of its σ
#: (:func:`first_photon_correction`)
MU_MODEL_FACTOR = 2.0
#: systematic uncertainty of a saturated return's arrival (the pulse's leading edge), in
#: pulse σ, scaled by the square of the detection probability with the spot centred
SATURATED_EDGE_SIGMA = 0.2
#: share of the μ0 grid's top (:data:`~mems_stereo.physics.first_photon.MU_MAX`) above
#: which a peak's posterior mean μ0 is pinned at the grid's top
MU_PINNED_FRACTION = 0.5
#: a pinned peak whose inliers outnumber the firings the spot model predicts with this
#: many times the grid's top μ0 is one the model does not explain
#: (:func:`first_photon_correction`): its mean angle keeps the scatter's spread
MU_BEYOND_GRID = 10.0
#: fewest valid shots per sampled angle step (mean over a peak's band, steps with
#: shots) for the binomial variance of its mean angle (:func:`angle_binomial_factor`)
BINOMIAL_MIN_SHOTS = 2.0


def correcting(acc) -> bool:
    """Whether the first-photon correction applies to the accumulator's peaks (the
    correction is on, the valid shots per step are known and a peak has a band)."""
    return (acc.first_photon and acc.shots_per_step is not None
            and bool(np.any(acc.band[1] >= acc.band[0])))

@dataclass(frozen=True, slots=True)
class BandSteps:
    """The angle steps around the inlier bands of Q' peaks (:func:`band_steps`).

    steps : (Q', B) int64, the steps (B the widest band of these peaks).
    shots : (Q', B) float64, the valid shots counted at each (0 outside the band).
    spot : (Q', B) float64, the spot's share of the pixel at each step (target at the
        peak's centre range; 0 where no shot counts).
    spot_full : (Q', B) float64, the spot's share at every step of the widened band
        (the profile whatever the shots), or None unless asked for.
    """

    steps: np.ndarray
    shots: np.ndarray
    spot: np.ndarray
    spot_full: np.ndarray | None = None


@dataclass(frozen=True, slots=True)
class FirstPhotonCorrection:
    """The first-photon correction of Q peaks (:func:`first_photon_correction`).

    delay : (Q,) float64 s, the delay removed from the ToF mean (NaN: not corrected).
    mu : (Q,) float64, posterior mean signal photons per shot μ0 (NaN: not corrected).
    sigma_L : (Q,) float64 m, the delay's σ as path length (systematic).
    angle_binomial : (Q,) float64 in [0, 1], the binomial factor of the mean angle's
        variance (:func:`angle_binomial_factor`).
    angle_bias : (Q,) float64 rad, the mean angle's expected bias (:func:`mean_angle_bias`).
    tof : ``(x (Q, 3) m, C (Q, 3, 3) m²)`` the ToF mean corrected.
    """

    delay: np.ndarray
    mu: np.ndarray
    sigma_L: np.ndarray
    angle_binomial: np.ndarray
    angle_bias: np.ndarray
    tof: tuple[np.ndarray, np.ndarray]


def _padded_band(acc, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(centre, a, b)``, each (Q',): the peaks ``q``'s centre range (1 where unknown)
    and their inlier band widened by its width plus 8 steps on each side, steps a..b
    (empty, a = 0 and b = −1, where the band is)."""
    lo, hi = acc.band[0][q], acc.band[1][q]
    has = hi >= lo
    pad = np.where(has, hi - lo + 8, 0)
    return (np.nan_to_num(acc.centre[q], nan=1.0), np.where(has, lo - pad, 0),
            np.where(has, hi + pad, -1))


def band_steps(acc, q=None, max_steps: int = 2048, full: bool = False) -> BandSteps:
    """The steps around the inlier band of each peak ``q`` ((Q',) int, default all;
    the band widened by its width plus 8 steps on each side), the valid shots of
    each and the spot share of the pixel at each step (:class:`BandSteps`; with
    ``full`` also its ``spot_full``)."""
    q = np.arange(acc.Q) if q is None else np.asarray(q, np.int64)
    centre, a, b = _padded_band(acc, q)
    B = int(min(max_steps, max(1, (b - a + 1).max())))
    steps = a[:, None] + np.arange(B)[None, :]
    S = acc.shots_per_step.size
    shots = acc.shots_per_step[np.clip(steps, 0, S - 1)]
    # steps that count: in the band, on the table, with valid shots (a frame's shots
    # visit a share of the scan's steps: the others count none, whatever the code)
    inside = (steps <= b[:, None]) & (steps >= 0) & (steps < S) & (shots > 0)
    if acc.step_window is not None:  # only where pass 2 counted detections
        inside &= ((steps >= acc.step_window[0][q, None])
                   & (steps <= acc.step_window[1][q, None]))
    if acc.accept is not None:  # only where the classifier accepts the return's code
        qi, bi = np.nonzero(inside)
        inside[qi, bi] = acc.accept(steps[qi, bi][:, None], centre[qi], q[qi])[:, 0]
    n = np.where(inside, shots, 0)
    in_band = (steps >= a[:, None]) & (steps <= b[:, None])
    # the spot's share where it is read (each entry its own: the same numbers)
    qi, bi = np.nonzero(in_band if full else n > 0)
    t0, dt = acc.step_grid
    f = np.zeros(steps.shape)
    f[qi, bi] = spot_fraction(acc.system, acc.rows[q[qi]], acc.cols[q[qi]],
                              t0 + steps[qi, bi] * dt, centre[qi], acc.spot_sigma,
                              directions=step_directions(acc.system.scanner, t0, dt,
                                                         steps[qi, bi]))
    if full:
        return BandSteps(steps, n.astype(np.float64), np.where(n > 0, f, 0.0),
                         np.where(in_band, f, 0.0))
    return BandSteps(steps, n.astype(np.float64), np.where(n > 0, f, 0.0))


@dataclass(frozen=True, slots=True)
class BlockBands:
    """:func:`band_steps` (``full=True``) of consecutive blocks of peaks, computed at once
    (:func:`block_band_steps`).

    blocks : list of ``(a, b, BandSteps)``, the rows ``a:b`` of the peaks given and
        their :class:`BandSteps` (the same arrays, bit for bit, as ``band_steps`` of
        those peaks alone).
    log_miss : (Q', J) float64, ``Σ_b n_b·ln(1 − P(inlier))`` of each peak's band
        (:func:`~mems_stereo.physics.first_photon.band_log_miss` of its block's arrays),
        or None where not asked for.
    flat : the same entries row after row (:class:`BandEntries`).
    """

    blocks: list
    log_miss: np.ndarray | None
    flat: BandEntries


@dataclass(frozen=True, slots=True)
class BandEntries:
    """The entries of :class:`BlockBands`' blocks laid end to end, row-major.

    starts : (Q' + 1,) int64, row r's entries are ``starts[r]:starts[r + 1]``.
    steps, shots, spot, spot_full : (N,) the rows of :class:`BandSteps`' fields
        (float64, but the int64 steps).
    """

    starts: np.ndarray
    steps: np.ndarray
    shots: np.ndarray
    spot: np.ndarray
    spot_full: np.ndarray


def block_band_steps(acc, q, cut, max_steps: int = 2048, log_miss: bool = True) -> BlockBands:
    """:func:`band_steps` (``full=True``) of the peaks ``q[cut[i]:cut[i + 1]]`` for each
    block i (``cut`` (K + 1,) increasing row boundaries into ``q`` (Q',) int), each block
    its own band width B as there, the elementwise work done once for all blocks: the
    blocks' (rows, B) grids laid end to end, row-major, are one flat list of entries,
    and the classifier's acceptance and the spot shares are evaluated on it with the
    scan directions' products ``d·p`` of each block apart
    (:func:`~mems_stereo.physics.spot.segment_dot`): the same bits as one call per
    block, with a tenth of the calls."""
    q = np.asarray(q, np.int64)
    centre, a, b = _padded_band(acc, q)
    span = b - a + 1
    spans = [(int(r0), int(r1)) for r0, r1 in zip(cut[:-1], cut[1:]) if r1 > r0]
    widths = np.array([min(max_steps, max(1, int(span[r0:r1].max()))) for r0, r1 in spans],
                      np.int64)
    rows_per = np.array([r1 - r0 for r0, r1 in spans], np.int64)
    row_w = np.repeat(widths, rows_per)  # each row's B
    ri = np.repeat(np.arange(row_w.size), row_w)  # flat entry -> row (of the kept rows)
    row_start = np.cumsum(row_w) - row_w
    steps = a[ri] + (np.arange(ri.size) - row_start[ri])
    S = acc.shots_per_step.size
    shots = acc.shots_per_step[np.clip(steps, 0, S - 1)]
    inside = (steps <= b[ri]) & (steps >= 0) & (steps < S) & (shots > 0)
    if acc.step_window is not None:
        inside &= (steps >= acc.step_window[0][q][ri]) & (steps <= acc.step_window[1][q][ri])
    ends = np.concatenate([[0], np.cumsum(widths * rows_per)])  # each block's entries
    if acc.accept is not None:
        sel = np.flatnonzero(inside)
        inside[sel] = acc.accept(steps[sel][:, None], centre[ri[sel]], q[ri[sel]],
                                 cuts=np.searchsorted(sel, ends))[:, 0]
    n = np.where(inside, shots, 0)
    in_band = (steps >= a[ri]) & (steps <= b[ri])
    sel = np.flatnonzero(in_band)
    t0, dt = acc.step_grid
    f = np.zeros(steps.shape)
    f[sel] = spot_fraction(acc.system, acc.rows[q[ri[sel]]], acc.cols[q[ri[sel]]],
                           t0 + steps[sel] * dt, centre[ri[sel]], acc.spot_sigma,
                           cuts=np.searchsorted(sel, ends),
                           directions=step_directions(acc.system.scanner, t0, dt,
                                                      steps[sel]))
    nf = n.astype(np.float64)
    f_band = np.where(n > 0, f, 0.0)
    f_full = np.where(in_band, f, 0.0)
    lm = None
    if log_miss:
        hit = np.flatnonzero(n)
        lm = band_log_miss_rows(row_w.size, ri[hit], nf[hit], f_band[hit])
    out = []
    for (c0, c1), B, e0, e1 in zip(spans, widths, ends[:-1], ends[1:]):
        shape = (c1 - c0, int(B))
        out.append((c0, c1, BandSteps(*(x[e0:e1].reshape(shape)
                                        for x in (steps, nf, f_band, f_full)))))
    flat = BandEntries(np.concatenate([[0], np.cumsum(row_w)]), steps, nf, f_band, f_full)
    return BlockBands(out, lm, flat)


def mean_angle_bias(steps, n_band, f_band, f_full, mu) -> np.ndarray:
    """(Q,) steps: the expected offset of a peak's mean firing angle from the
    angle at which the spot is centred on its pixel.

    The stereo is taken at the detections' mean angle, whose expectation is
    ``Σ N_s p_s θ_s / Σ N_s p_s`` (N_s the valid shots counted at step s,
    ``p_s = 1 − exp(−μ0 f_s)``): where the shots are not spread evenly over
    the footprint — near the scan's turning points, where the mirror slows and
    the shots bunch, or where the band or the accepted codes cut the profile —
    it moves towards the denser side, while the spot is centred where the
    firing profile ``1 − exp(−μ0 f)`` of the unmasked share ``f_full`` has its
    centroid.  The difference is what :class:`PeakAccumulator` removes from the
    mean angle.  ``steps``, ``n_band``,
    ``f_band``, ``f_full`` (Q, B) as :func:`band_steps` (``full=True``); ``mu`` (Q,).
    0 where undefined.
    """
    mu = np.asarray(mu, np.float64)[:, None]
    p = -np.expm1(-mu * f_band)
    pf = -np.expm1(-mu * f_full)
    w = n_band * p
    with np.errstate(invalid="ignore", divide="ignore"):
        em = np.sum(w * steps, axis=1) / np.sum(w, axis=1)
        tc = np.sum(pf * steps, axis=1) / np.sum(pf, axis=1)
    b = em - tc
    return np.where(np.isfinite(b), b, 0.0)

def angle_binomial_factor(steps, n_band, f_band, mu, theta_bar) -> np.ndarray:
    """(Q,) in [0, 1]: the variance of a peak's mean scan angle given its shots,
    against the Poisson variance its scatter (the Birge-scaled spread) stands for.

    θ̄ = Σ k_s θ_s / Σ k_s, k_s the firings of the N_s shots at step s.  As
    independent draws of an angle (Poisson, what the detections' scatter about
    their mean estimates): ``Σ N_s p_s (θ_s − θ̄)²``; given the shots, k_s is
    binomial: ``Σ N_s p_s (1 − p_s)(θ_s − θ̄)²`` (both over K²): a saturated step
    (every shot fires) adds nothing.  ``p_s = 1 − exp(−μ0 f_s)`` (μ0 the
    posterior mean signal photons per shot, f_s the spot's share of the pixel;
    :func:`band_steps`).  Only where the scan revisits its sampled angles with
    at least :data:`BINOMIAL_MIN_SHOTS` shots each on average: with one shot per
    sampled angle, which angles the shots sample is itself the randomness, and
    μ0 (saturated or not) is not identified by the firings.  Otherwise 1.
    ``steps``, ``n_band``, ``f_band`` (Q, B); ``mu``, ``theta_bar`` (Q,), θ̄ in steps.
    """
    p = -np.expm1(-np.asarray(mu, np.float64)[:, None] * f_band)
    dev2 = (steps - np.asarray(theta_bar, np.float64)[:, None]) ** 2
    w = n_band * p * dev2
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.sum(w * (1.0 - p), axis=1) / np.sum(w, axis=1)
        dense = np.sum(n_band, axis=1) / np.sum(n_band > 0, axis=1) >= BINOMIAL_MIN_SHOTS
    return np.where(np.isfinite(r) & dense, np.clip(r, 0.0, 1.0), 1.0)


def first_photon_correction(acc, fused_point, tof) -> FirstPhotonCorrection:
    """The first-photon correction of the accumulator's peaks (see
    :class:`~mems_stereo.pipeline.peak_accumulator.PeakAccumulator`): ``fused_point``
    (Q, 3) m the peak-level fused point (the pulse's centre), ``tof`` ``(x, C)`` the
    uncorrected ToF mean; returns the delays, μ0, the mean angle's figures and the
    corrected ToF mean (:class:`FirstPhotonCorrection`)."""
    s = acc.system
    sp = spreads_for(s) if acc.spreads is None else acc.spreads
    sigma = math.hypot(sp.sigma_t_pulse, sp.sigma_t_jitter)
    out = {"delay": np.full(acc.Q, np.nan), "mu": np.full(acc.Q, np.nan),
           "sigma_L": np.zeros(acc.Q), "angle_binomial": np.ones(acc.Q),
           "angle_bias": np.zeros(acc.Q)}
    # pulse centre from the fused point (stereo-dominated near the TDC start)
    tau = path_length_of_point(fused_point, s.scanner.position) / s.speed_of_light
    tau = tau + s.tdc.offset + pulse_mean_delay(s.laser)  # the pulse's mean (0: Gaussian)
    ok = (acc.band[1] >= acc.band[0]) & np.isfinite(tau) & np.isfinite(acc.centre)
    if sigma <= 0 or not np.any(ok):
        return FirstPhotonCorrection(**out, tof=tof)
    idx = np.flatnonzero(ok)
    t0, dt = acc.step_grid
    with np.errstate(invalid="ignore", divide="ignore"):
        theta_bar = (acc.sums.theta / acc.sums.n - t0) / dt  # the inliers' mean step
    fig = _band_figures(acc, idx, tau, sigma, theta_bar)
    d, sd, var, mu, ab, bias, sm = (fig[k] for k in ("d", "sd", "var", "mu", "ab", "bias",
                                                       "sm"))
    c = s.speed_of_light
    dL = np.zeros(acc.Q)
    dvar = np.zeros(acc.Q)
    # background that fires the pixel first removes the late part of the
    # pulse: the recorded returns' density is the pulse's times exp(−λt),
    # a further shift of −λσ² (exact for a Gaussian pulse)
    d = with_pulse_shape(acc, sp, d - acc.rate_hz[idx] * sigma * sigma, mu, idx, tau[idx])
    dL[ok] = -c * d  # path length to add: the arrivals were early by d
    dvar[ok] = c * c * (var - sigma * sigma)  # first-photon timing variance replaces σ²
    # the model's own systematic uncertainty (pulse shape, spot profile, the
    # signal level's posterior): a share of the correction it applies
    # and, as the return saturates (nearly every shot fires with the spot on the
    # pixel), the arrival is the pulse's leading edge, whose shape the Gaussian
    # model does not know: up to SATURATED_EDGE_SIGMA pulse σ
    sat = -np.expm1(-mu)
    sd = np.hypot(np.hypot(sd, sm), np.hypot(MODEL_DELAY_FRACTION * d,
                                             SATURATED_EDGE_SIGMA * sigma * sat ** 2))
    out["delay"][ok], out["mu"][ok], out["sigma_L"][ok] = d, mu, c * sd
    out["angle_binomial"][ok] = ab
    out["angle_bias"][ok] = bias * dt  # rad
    D, G = acc.sums.tof.dL()
    x, C = tof
    return FirstPhotonCorrection(**out, tof=(x + D * dL[:, None], C + G * dvar[:, None, None]))


def _band_figures(acc, idx, tau, sigma: float, theta_bar) -> dict:
    """The figures of the peaks ``idx`` (Q',) from their bands: ``{name: (Q',) float64}``
    for ``d``, ``sd``, ``var``, ``mu``, ``sm`` (:func:`first_photon_delay`, s, s, s², μ0,
    s), ``ab`` (:func:`angle_binomial_factor`, 1 where :func:`_beyond_model`) and
    ``bias`` (:func:`mean_angle_bias`, steps); ``tau`` (Q,) s the pulses' centres,
    ``theta_bar`` (Q,) the inliers' mean steps.  In a frame's passes
    (:func:`~mems_stereo.pipeline.classify_kernel.compiled_blocks`) by two compiled
    loops over the bands (:func:`_compiled_band_figures`)."""
    # blocks of FP_BLOCK peaks by peak index ((FP_BLOCK, J, B) temporaries), each with
    # its own band width B: a peak's result depends on its block alone, so the
    # fusion of the peaks split at multiples of FP_BLOCK (the Dask runner) is
    # identical to the whole
    cut = np.searchsorted(idx, np.arange(0, acc.Q + FP_BLOCK, FP_BLOCK))
    kern = band_kernels() if compiles(0, 1) else None
    bands = block_band_steps(acc, idx, cut, log_miss=kern is None)
    if kern is not None:
        return _compiled_band_figures(acc, idx, bands, tau, sigma, theta_bar, kern)
    fig = {k: np.empty(idx.size) for k in ("d", "sd", "var", "mu", "ab", "bias", "sm")}
    log_lik = acc.sums.loglik[idx] + bands.log_miss
    for a, b, band in bands.blocks:
        q = idx[a:b]
        steps, n_band, f_band, f_full = band.steps, band.shots, band.spot, band.spot_full
        mu = fig["mu"][a:b]
        (fig["d"][a:b], fig["sd"][a:b], fig["var"][a:b], mu[:],
         fig["sm"][a:b]) = first_photon_delay(log_lik[a:b], f_band, n_band, tau[q], sigma,
                                              mu_factor=MU_MODEL_FACTOR)
        ab = angle_binomial_factor(steps, n_band, f_band, mu, theta_bar[q])
        # the binomial variance rests on the model's firing probabilities: where the
        # model does not explain the firings the mean angle keeps its scatter's spread
        fig["ab"][a:b] = np.where(_beyond_model(acc, q, n_band, f_band, mu), 1.0, ab)
        fig["bias"][a:b] = mean_angle_bias(steps, n_band, f_band, f_full, mu)
    return fig


def _compiled_band_figures(acc, idx, bands: BlockBands, tau, sigma: float, theta_bar,
                           kern) -> dict:
    """:func:`_band_figures` by the compiled loops of
    :mod:`~mems_stereo.physics.first_photon_band_kernel` (``kern``) over the bands laid
    end to end (``bands.flat``): the same numbers but for the order of the sums (and
    ``ln(1 − P)``'s closed form).  Each row's loops are its own, and the posterior is
    taken per block of ``bands`` (its μ0 mean a matrix product, whose rounding may
    follow the rows around): the peaks split at multiples of FP_BLOCK give the whole's
    bits, as the NumPy form does."""
    flat = bands.flat
    lmiss, dj, vj = band_likelihood_moments(kern[0], flat.starts, flat.shots, flat.spot,
                                            MU_GRID, OUTLIER_PROBABILITY, -tau[idx] / sigma,
                                            first_photon_table())
    ll = acc.sums.loglik[idx] + lmiss
    fig = {k: np.empty(idx.size) for k in ("d", "sd", "var", "mu", "sm")}
    for a, b, _ in bands.blocks:
        (fig["d"][a:b], fig["sd"][a:b], fig["var"][a:b], fig["mu"][a:b],
         fig["sm"][a:b]) = posterior_delay(ll[a:b], dj[a:b], vj[a:b], sigma,
                                           mu_factor=MU_MODEL_FACTOR)
    bias, ab, k_top = band_figures(kern[1], flat.starts, flat.steps, flat.shots, flat.spot,
                                   flat.spot_full, fig["mu"], theta_bar[idx],
                                   MU_BEYOND_GRID * MU_MAX, BINOMIAL_MIN_SHOTS)
    beyond = (fig["mu"] >= MU_PINNED_FRACTION * MU_MAX) & (acc.sums.detections[idx] > k_top)
    fig["ab"] = np.where(beyond, 1.0, ab)
    fig["bias"] = bias
    return fig


def with_pulse_shape(acc, spreads, delay, mu, idx, tau):
    """``delay`` (s) of the peaks ``idx`` plus what a non-Gaussian pulse
    (``docs/hardware.md``) adds to the Gaussian model's first-photon delay
    (``delay`` itself for the Gaussian pulse).

    At each step of a peak's band the pixel receives μ_j = μ0·f_j photons; the shape's
    excess delay there (:class:`ShapeExcess`, against the Gaussian of the model's
    σ) is weighted by the detections it expects, n_j·(1 − e^(−μ_j)), as the peak's mean
    weighs its detections.  ``mu`` (Q',) the peaks' μ0; ``tau`` (Q',) s the TDC time of
    their pulse's mean (the window opens at −tau: both pulses are truncated there).
    """
    system = acc.system
    if system.laser.pulse_shape is None:
        return delay
    sigma = math.hypot(spreads.sigma_t_pulse, spreads.sigma_t_jitter)
    excess = ShapeExcess(pulse_shape_of(system.laser, spreads.sigma_t_jitter), sigma)
    out = np.array(delay, dtype=np.float64)
    for a in range(0, idx.size, FP_BLOCK):
        band = band_steps(acc, idx[a:a + FP_BLOCK], full=True)
        mu_j = mu[a:a + FP_BLOCK, None] * band.spot
        wgt = band.shots * -np.expm1(-mu_j)
        start = -tau[a:a + FP_BLOCK, None]
        ex = excess(mu_j, start)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean_ex = np.sum(wgt * np.nan_to_num(ex), axis=1) / np.sum(wgt, axis=1)
        out[a:a + FP_BLOCK] += np.where(np.isfinite(mean_ex), mean_ex,
                                        excess(mu[a:a + FP_BLOCK], start[:, 0]))
    return out


def _beyond_model(acc, q, n_band, f_band, mu):
    """(len(q),) bool: μ0 at the top of its grid, and more firings than even
    MU_BEYOND_GRID times that μ0 would give: they reach further from the pixel than
    the model's spot explains (a surface whose range changes across the band, the
    model taking it constant, e.g. a face seen at grazing incidence; a return truly
    4× the grid's top does not fire that much more)."""
    k_top = np.sum(n_band * -np.expm1(-MU_BEYOND_GRID * MU_MAX * f_band), axis=1)
    return (mu >= MU_PINNED_FRACTION * MU_MAX) & (acc.sums.detections[q] > k_top)
