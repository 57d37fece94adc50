"""The calibration problem: recordings reduced for the fit, the parameter layout,
and the exact first-photon likelihood of every (shot, pixel) cell near the beam's image.

Data (:class:`WallData`, one per recording = one flat wall): the monitor phase
of each shot, the raw TDC codes, and each pixel's background rate measured
from the late part of the TDC window (where no wall return can be).

Model of one cell (shot k, pixel c) of wall j.  The pixel records its first
photon from the TDC start (τ = 0) on; photons arrive as a Poisson process of
intensity ``I(t) = λ_c + m·φ((t − τ_k)/σ)/σ`` with λ_c the pixel's background
rate (fixed: measured), ``τ_k = L_k/c + offset`` the return's centre
(:func:`mems_stereo.calib.model.beam_hits`), σ the pulse's, and
``m = μ_k · f_c(u_k, s_j)`` the signal photons that reach pixel c: μ_k the
whole spot's (``μ_j·g_k/ḡ_j``, g the Lambertian factor cos θ_e·cos θ_r/R²),
``f_c`` the share of a Gaussian spot of σ ``s_j`` pixels centred on the
beam's image ``u_k`` that falls on pixel c.  Over the analysed window
[0, T_j] the log-likelihood of the cell is

* fired at t ≤ T_j: ``log I(t) − ∫₀ᵗ I``;
* not fired by T_j: ``−∫₀^{T_j} I``,

which is exact for a first-photon SPAD: the first-photon bias (early for a
strong return, late where the TDC start cuts the pulse), background that
fires first, and returns split over two pixels all follow from it; nothing is
picked per shot.  The nuisances μ_j and s_j are fixed by the data through the
same likelihood (the share of cells that fire, and the share that fire on two
pixels); λ_c is not fitted at all.  Cells are the pixels within ``radius`` of
the predicted image, fixed during one solver run (:mod:`.association`).

Frames and units: receiver camera frame, metres, radians, seconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from mems_stereo.calib.model import (
    HARDWARE_PARAMS,
    PARAM_SCALE,
    PULSE_PARAMS,
    SYSTEM_PARAMS,
    beam_hits,
    plane_normal,
)
from scipy.special import ndtr

from mems_stereo.model.system import System
from mems_stereo.physics.pulse import emg_pdf

#: solver units of the wall parameters (PARAM_SCALE has the system's)
WALL_SCALE = {"alpha": 1e-3, "beta": 1e-3, "dist": 1e-3, "logmu": 0.01, "logspot": 0.01}
#: spot σ is kept within these bounds, pixels
SPOT_MIN, SPOT_MAX = 0.12, 6.0


def spot_px(logspot: float) -> float:
    """The wall's spot σ (px) from its log, clipped to [SPOT_MIN, SPOT_MAX]; any
    ``logspot`` a trial step or a failed fit holds gives a size, never an overflow."""
    return min(max(math.exp(min(logspot, 700.0)), SPOT_MIN), SPOT_MAX)
_SQ2PI = math.sqrt(2.0 * math.pi)


@dataclass
class WallData:
    """One recording of a flat wall, reduced for the fit.

    phase : (K,) float64 rad, monitor phase of each usable shot.
    bins : (K, H, W) uint16 TDC codes of those shots (0: no detection).
    background : (H, W) float64 Hz, each pixel's background rate (late window).
    bin_width : s.  source : str, for messages.
    shot_time : (K,) s, zero_crossings : (Z,) s, rising : (Z,) bool — the monitor's
    record, kept so that the phase follows a fitted trajectory or edge delay
    (None: the phase is fixed).
    code_centres : (n_bins,) s, each code's centre from the TDC's code widths
    (:func:`mems_stereo.model.tdc.code_centres`; index code − 1), or None: the
    ideal ``(N − ½)·bin_width``.
    """

    phase: np.ndarray
    bins: np.ndarray
    background: np.ndarray
    bin_width: float
    source: str = "<memory>"
    shot_time: np.ndarray | None = None
    zero_crossings: np.ndarray | None = None
    rising: np.ndarray | None = None
    code_centres: np.ndarray | None = None

    @property
    def n_shots(self) -> int:
        return int(self.phase.shape[0])


class Layout:
    """Parameter vector ↔ named values: free system parameters, then per wall
    (α, [β,] D, log μ, log s).  The solver works in units of :data:`PARAM_SCALE`
    / :data:`WALL_SCALE` around a reference point."""

    def __init__(self, names, n_walls: int, two_d: bool):
        self.names = ([n for n in SYSTEM_PARAMS if n in names]
                      + [n for n in HARDWARE_PARAMS if n in names]
                      + [n for n in PULSE_PARAMS if n in names])
        self.T = int(n_walls)
        self.two_d = bool(two_d)
        self.wall_names = (["alpha", "beta", "dist", "logmu", "logspot"] if two_d
                           else ["alpha", "dist", "logmu", "logspot"])
        self.n_sys = len(self.names)
        self.n_wall = len(self.wall_names)
        self.size = self.n_sys + self.T * self.n_wall
        self.scales = np.array([PARAM_SCALE[n] for n in self.names]
                               + [WALL_SCALE[p] for _ in range(self.T) for p in self.wall_names])

    @property
    def labels(self) -> list:
        return self.names + [f"{p}[{j}]" for j in range(self.T) for p in self.wall_names]

    def wall_slice(self, j: int) -> slice:
        a = self.n_sys + j * self.n_wall
        return slice(a, a + self.n_wall)

    def pack(self, values: dict, walls: np.ndarray) -> np.ndarray:
        """SI values (dict) and walls (T, 5: α, β, D, log μ, log s) → x (SI)."""
        x = [values[n] for n in self.names]
        cols = [0, 1, 2, 3, 4] if self.two_d else [0, 2, 3, 4]
        for j in range(self.T):
            x += list(walls[j, cols])
        return np.asarray(x, dtype=np.float64)

    def unpack(self, x):
        """x (SI) → (values dict, walls (T, 5))."""
        x = np.asarray(x, dtype=np.float64)
        values = {n: float(x[i]) for i, n in enumerate(self.names)}
        walls = np.zeros((self.T, 5))
        cols = [0, 1, 2, 3, 4] if self.two_d else [0, 2, 3, 4]
        for j in range(self.T):
            walls[j, cols] = x[self.wall_slice(j)]
        return values, walls


def lambert(point: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """(N,) relative Lambertian signal cos θ_e·cos θ_r / R² of hits ``point`` (N, 3)."""
    r2 = np.einsum("ij,ij->i", point, point)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.abs(point @ normal) * point[:, 2] / (r2 * r2)


def shot_model(system: System, values: dict, wall: np.ndarray, phase: np.ndarray):
    """Per-shot predictions for one wall: τ (s), u, v (pixels), log g, ok.

    ``wall`` : (5,) α, β, D, log μ, log s.  Returns (N, 4) [τ, u, v, log g] and
    (N,) bool.
    """
    normal = plane_normal(wall[0], wall[1])
    h = beam_hits(system, values, phase, normal, wall[2])
    off = values["tdc_offset"] if "tdc_offset" in values else system.tdc.offset
    tau = h.path / system.speed_of_light + off
    g = lambert(h.point, normal)
    with np.errstate(invalid="ignore", divide="ignore"):
        lg = np.log(g)
    out = np.stack([tau, h.pixel[:, 0], h.pixel[:, 1], lg], axis=1)
    ok = h.ok & np.all(np.isfinite(out), axis=1)
    return out, ok


@dataclass
class Cells:
    """The analysed cells of one wall (fixed during a solver run).

    shot : (N,) int64 index into the wall's shots; col, row : (N,) float64 pixel;
    t : (N,) s, time of the pixel's first detection, NaN when it did not fire by
    ``t_max``; lam : (N,) Hz, background rate; t_max : s; shots : (S,) int64
    the shots analysed; log_gref : float, reference log g of the wall (μ_j is
    the whole spot's mean signal at g = exp(log_gref)).
    """

    shot: np.ndarray
    col: np.ndarray
    row: np.ndarray
    t: np.ndarray
    lam: np.ndarray
    t_max: float
    shots: np.ndarray
    log_gref: float


def spot_share(c, u, s):
    """Share of a Gaussian spot (centre u, σ s pixels) on pixel c, and its
    derivatives by u and by log s."""
    a = (c + 0.5 - u) / s
    b = (c - 0.5 - u) / s
    pa = np.exp(-0.5 * a * a) / _SQ2PI
    pb = np.exp(-0.5 * b * b) / _SQ2PI
    f = ndtr(a) - ndtr(b)
    return f, -(pa - pb) / s, -(a * pa - b * pb)


def cell_terms(cells: Cells, pred: np.ndarray, logmu: float, logspot: float, sigma: float,
               two_d: bool, pitch_ratio: float = 1.0, pulse=None):
    """Log-likelihood of each cell and its derivatives.

    pred : (N, 4) per-cell [τ, u, v, log g] (already indexed by ``cells.shot``).
    pulse : None (the Gaussian pulse of σ ``sigma``) or (w, τ_d): the ex-gaussian
        pulse (1 − w)·N(0, σ) + w·EMG(σ, τ_d) (:func:`shaped_terms`).
    Returns ``ll`` (N,) and ``d`` (N, 5): ∂ℓ/∂[τ, u, v, log μ_k, log s]; with
    ``pulse`` (N, 7), columns 5, 6 ∂ℓ/∂w and ∂ℓ/∂τ_d.
    """
    tau, u, v, lg = pred[:, 0], pred[:, 1], pred[:, 2], pred[:, 3]
    s = spot_px(logspot)
    mu = np.exp(logmu + lg - cells.log_gref)
    f, fu, fs = spot_share(cells.col, u, s)
    if two_d:
        sr = s * pitch_ratio
        fr, fv, frs = spot_share(cells.row, v, sr)
        share = f * fr
        dshare_u, dshare_v = fu * fr, f * fv
        dshare_s = fs * fr + f * frs
    else:
        share = f
        dshare_u, dshare_v, dshare_s = fu, np.zeros_like(fu), fs
    m = mu * share
    if pulse is not None:
        st = shaped_terms(cells, tau, m, sigma, pulse)
        d = np.empty((tau.size, 7))
        d[:, 5:] = st.dpulse
        return st.ll, _cell_derivatives(d, st.dtau, st.dm, mu, m,
                                        (dshare_u, dshare_v, dshare_s), s)
    z0 = -tau / sigma
    fired = np.isfinite(cells.t)
    t_end = np.where(fired, cells.t, cells.t_max)
    z = (t_end - tau) / sigma
    phz = np.exp(-0.5 * z * z) / _SQ2PI
    ph0 = np.exp(-0.5 * z0 * z0) / _SQ2PI
    dG = ndtr(z) - ndtr(z0)
    # ∫ signal intensity from 0 to t_end, and its derivatives
    ll = -m * dG
    dll_dm = -dG
    dll_dtau = m * (phz - ph0) / sigma
    # the fired cells: + log I(t)
    lam = cells.lam
    sig_int = m * phz / sigma
    inten = np.where(fired, lam + sig_int, 1.0)
    inten = np.maximum(inten, 1e-300)
    ll = ll + np.where(fired, np.log(inten), 0.0)
    dll_dm = dll_dm + np.where(fired, (phz / sigma) / inten, 0.0)
    dll_dtau = dll_dtau + np.where(fired, m * z * phz / (sigma * sigma) / inten, 0.0)
    d = np.empty((tau.size, 5))
    return ll, _cell_derivatives(d, dll_dtau, dll_dm, mu, m, (dshare_u, dshare_v, dshare_s), s)


def _cell_derivatives(d, dll_dtau, dll_dm, mu, m, dshare, s):
    """``d``'s first five columns ∂ℓ/∂[τ, u, v, log μ_k, log s] (in place; returned)."""
    dshare_u, dshare_v, dshare_s = dshare
    d[:, 0] = dll_dtau
    d[:, 1] = dll_dm * mu * dshare_u
    d[:, 2] = dll_dm * mu * dshare_v
    d[:, 3] = dll_dm * m
    d[:, 4] = dll_dm * mu * dshare_s * (1.0 if SPOT_MIN < s < SPOT_MAX else 0.0)
    return d


@dataclass(frozen=True)
class PulseAt:
    """The ex-gaussian pulse at delays x (arrays like x): ``cdf``, ``pdf`` (1/s),
    ``slope`` (the density's derivative, 1/s²), ``cdf_w`` and ``pdf_w`` (the CDF's
    and the density's derivatives by the tail share w)."""

    cdf: np.ndarray
    pdf: np.ndarray
    slope: np.ndarray
    cdf_w: np.ndarray
    pdf_w: np.ndarray


def pulse_at(x, sigma: float, w: float, tau_d: float) -> PulseAt:
    """The ex-gaussian pulse (1 − w)·N(0, σ) + w·EMG(σ, τ_d) at delays ``x`` (s)."""
    phi = np.exp(-0.5 * (x / sigma) ** 2) / (sigma * _SQ2PI)
    big = ndtr(x / sigma)
    e_pdf = emg_pdf(x, sigma, tau_d)
    e_cdf = big - tau_d * e_pdf
    # EMG' = (φ_σ − EMG)/τ_d (the derivative of a convolution with the exponential)
    return PulseAt((1.0 - w) * big + w * e_cdf, (1.0 - w) * phi + w * e_pdf,
                   (1.0 - w) * (-x / (sigma * sigma)) * phi + w * (phi - e_pdf) / tau_d,
                   e_cdf - big, e_pdf - phi)


def _shaped_ll(cells: Cells, tau, m, sigma: float, w: float, tau_d: float):
    """ℓ per cell with the ex-gaussian pulse, and the pieces of its derivatives:
    (ℓ (N,), dict of (N,) arrays)."""
    fired = np.isfinite(cells.t)
    p1 = pulse_at(np.where(fired, cells.t, cells.t_max) - tau, sigma, w, tau_d)
    p0 = pulse_at(-tau, sigma, w, tau_d)
    inten = np.maximum(np.where(fired, cells.lam + m * p1.pdf, 1.0), 1e-300)
    ll = -m * (p1.cdf - p0.cdf) + np.where(fired, np.log(inten), 0.0)
    return ll, {"fired": fired, "inten": inten, "dF": p1.cdf - p0.cdf, "f1": p1.pdf,
                "f0": p0.pdf, "slope": p1.slope, "dFw": p1.cdf_w - p0.cdf_w, "fw1": p1.pdf_w}


@dataclass(frozen=True)
class ShapedTerms:
    """:func:`shaped_terms`' result: ``ll`` (N,), ``dm`` ∂ℓ/∂m (N,), ``dtau``
    ∂ℓ/∂τ (N,) 1/s, ``dpulse`` (N, 2) ∂ℓ/∂[w, τ_d]."""

    ll: np.ndarray
    dm: np.ndarray
    dtau: np.ndarray
    dpulse: np.ndarray


def shaped_terms(cells: Cells, tau, m, sigma: float, pulse) -> ShapedTerms:
    """The first-photon likelihood of :func:`cell_terms` with the ex-gaussian pulse
    ``pulse`` = (w, τ_d) (σ ``sigma`` of the core; delay 0 is the core's peak):
    intensity ``λ + m·f(t − τ)``, ``f = (1 − w)·N(0, σ) + w·EMG(σ, τ_d)``
    (:func:`mems_stereo.physics.pulse.emg_pdf`); ∂ℓ/∂τ_d by central differences.
    ℓ is −∞ outside 0 ≤ w < 1, τ_d > 0 (the solver's steps stay inside)."""
    w, tau_d = float(pulse[0]), float(pulse[1])
    if not (0.0 <= w < 1.0 and tau_d > 0.0):
        z = np.zeros_like(tau)
        return ShapedTerms(np.full_like(tau, -np.inf), z, z, np.zeros((tau.size, 2)))
    ll, q = _shaped_ll(cells, tau, m, sigma, w, tau_d)
    fired, inten = q["fired"], q["inten"]
    dll_dm = -q["dF"] + np.where(fired, q["f1"] / inten, 0.0)
    dll_dtau = m * (q["f1"] - q["f0"]) - np.where(fired, m * q["slope"] / inten, 0.0)
    dp = np.empty((tau.size, 2))
    dp[:, 0] = -m * q["dFw"] + np.where(fired, m * q["fw1"] / inten, 0.0)
    h = 1e-4 * tau_d
    dp[:, 1] = (_shaped_ll(cells, tau, m, sigma, w, tau_d + h)[0]
                - _shaped_ll(cells, tau, m, sigma, w, tau_d - h)[0]) / (2.0 * h)
    return ShapedTerms(ll, dll_dm, dll_dtau, dp)


class Problem:
    """Total log-likelihood, its score and information over all walls.

    Parameters
    ----------
    walls : list of :class:`WallData`.
    system : the nominal system (fixed parts; reference values).
    layout : :class:`Layout`.
    sigma : pulse σ, s (with jitter).
    priors : list of (j, kind, distance m, σ m) measured distances.
    """

    def __init__(self, walls, system: System, layout: Layout, sigma: float, priors=()):
        self.walls = list(walls)
        self.system = system
        self.layout = layout
        self.sigma = float(sigma)
        self.priors = list(priors)
        self.cells: list = [None] * layout.T
        pitch = np.asarray(system.receiver.pixel_pitch, dtype=np.float64)
        self.pitch_ratio = float(pitch[0] / pitch[1])
        off = system.tdc.pixel_offsets
        #: (H·W,) s, each pixel's TDC start delay added to its cells' τ (None: none)
        self.pixel_offsets = None if off is None else np.asarray(off, dtype=np.float64)
        self._hw_phase = any(n in HARDWARE_PARAMS for n in layout.names) or bool(
            system.scanner.harmonics or system.scanner.monitor is not None)
        ps = system.laser.pulse_shape
        #: the system's ex-gaussian tail (w, τ_d) used where the fit does not free it
        self.pulse_fixed = ((float(ps.tail_fraction), float(ps.tail_decay))
                            if ps is not None and ps.model == "ex-gaussian"
                            and ps.tail_fraction > 0 and ps.tail_decay > 0 else None)
        #: s, the tail's decay where the layout frees only its share (the score test's)
        self.tail_decay = 1e-9

    def pulse(self, values: dict):
        """The pulse of the time likelihood: None (Gaussian of σ :attr:`sigma`) or the
        ex-gaussian tail (w, τ_d) of ``values`` (the fit's ``pulse_tail_*``) or the system."""
        if not any(n in values for n in PULSE_PARAMS):
            return self.pulse_fixed
        w0, t0 = self.pulse_fixed if self.pulse_fixed is not None else (0.0, self.tail_decay)
        return (values.get("pulse_tail_fraction", w0), values.get("pulse_tail_decay", t0))

    def phase(self, values: dict, j: int, shots=None) -> np.ndarray:
        """Monitor phase of wall j's shots (all, or ``shots``): recorded, or from the
        monitor's record with the trajectory and edge delays of ``values`` and the
        system (:func:`mems_stereo.model.scanner.phase_from_zero_crossings`)."""
        w = self.walls[j]
        if not self._hw_phase or w.shot_time is None:
            return w.phase if shots is None else w.phase[shots]
        from mems_stereo.model.scanner import phase_from_zero_crossings

        hw = {n: v for n, v in values.items() if n in HARDWARE_PARAMS}
        sc = self.system.with_params(**hw).scanner
        t = w.shot_time if shots is None else w.shot_time[shots]
        return phase_from_zero_crossings(t, w.zero_crossings, w.rising, sc)[0]

    # ------------------------------------------------------------------ model
    def predictions(self, x, j: int, shots=None, steps: bool = False):
        """Per-shot [τ, u, v, log g] of wall j (and its Jacobian by the wall's
        system + plane parameters when ``steps``): (S, 4), ok (S,), J (S, 4, P)."""
        lay = self.layout
        values, walls = lay.unpack(x)
        ph = self.phase(values, j, shots)
        p0, ok = shot_model(self.system, values, walls[j], ph)
        if not steps:
            return p0, ok, None
        geo = list(range(lay.n_sys)) + [lay.wall_slice(j).start + i
                                         for i, n in enumerate(lay.wall_names)
                                         if n in ("alpha", "beta", "dist")]
        J = np.zeros((ph.size, 4, len(geo)))
        for q, i in enumerate(geo):  # forward differences (the model is smooth)
            if i < lay.n_sys and lay.names[i] in PULSE_PARAMS:
                continue  # the pulse does not move the beam: its scores are the cells'
            h = 1e-3 * lay.scales[i]
            xp = x.copy()
            xp[i] += h
            vp, wp = lay.unpack(xp)
            moves_phase = i < lay.n_sys and lay.names[i] in HARDWARE_PARAMS
            php = self.phase(vp, j, shots) if moves_phase else ph
            pp, _ = shot_model(self.system, vp, wp[j], php)
            J[:, :, q] = (pp - p0) / h
        J[~np.isfinite(J)] = 0.0
        return p0, ok, (J, geo)

    def wall_terms(self, x, j: int, grad: bool = False):
        """ℓ per cell of wall j; with ``grad`` also the cell scores (N, P_j) and the
        parameter indices they belong to."""
        c = self.cells[j]
        lay = self.layout
        values, walls = lay.unpack(x)
        pred, ok, jac = self.predictions(x, j, c.shots, steps=grad)
        pos = np.searchsorted(c.shots, c.shot)
        pc = pred[pos]
        good = ok[pos]
        pc = np.where(good[:, None], pc, [0.0, -1e6, -1e6, 0.0])
        if self.pixel_offsets is not None:
            W = self.system.receiver.width
            pc[:, 0] += self.pixel_offsets[(c.row * W + c.col).astype(np.int64)]
        ll, d = cell_terms(c, pc, walls[j, 3], walls[j, 4], self.sigma, lay.two_d,
                           self.pitch_ratio, self.pulse(values))
        if not grad:
            return ll, None, None
        J, geo = jac
        Jc = J[pos]  # (N, 4, G)
        d = np.where(good[:, None], d, 0.0)
        # τ, u, v and log g chain through the geometry; log μ and log s directly
        sc = np.einsum("nk,nkg->ng", d[:, [0, 1, 2, 3]], Jc)
        for k, n in enumerate(PULSE_PARAMS):  # the pulse's own scores (geo[i] = i)
            if n in lay.names:
                sc[:, lay.names.index(n)] += d[:, 5 + k]
        ws = lay.wall_slice(j)
        idx = geo + [ws.start + lay.wall_names.index("logmu"),
                     ws.start + lay.wall_names.index("logspot")]
        S = np.concatenate([sc, d[:, 3:4], d[:, 4:5]], axis=1)
        return ll, S, idx

    def prior_terms(self, x):
        """Log-prior of the measured distances, its gradient and Gauss-Newton information."""
        lay = self.layout
        _, walls = lay.unpack(x)
        lp = 0.0
        g = np.zeros(lay.size)
        H = np.zeros((lay.size, lay.size))
        for j, kind, d, sd in self.priors:
            ws = lay.wall_slice(j)
            jac = np.zeros(lay.size)
            val = distance_model(walls[j], kind)
            for i, n in enumerate(lay.wall_names):
                if n in ("alpha", "beta", "dist"):
                    wp = walls[j].copy()
                    h = 1e-6
                    col = {"alpha": 0, "beta": 1, "dist": 2}[n]
                    wp[col] += h
                    jac[ws.start + i] = (distance_model(wp, kind) - val) / h
            r = (val - d) / sd
            lp -= 0.5 * r * r
            g -= r / sd * jac
            H += np.outer(jac, jac) / (sd * sd)
        return lp, g, H

    def loglik(self, x) -> float:
        tot = sum(float(np.sum(self.wall_terms(x, j)[0])) for j in range(self.layout.T))
        return tot + self.prior_terms(x)[0]

    def score(self, x):
        """(total ℓ, gradient (P,), OPG information (P, P)) in SI units."""
        lay = self.layout
        g = np.zeros(lay.size)
        H = np.zeros((lay.size, lay.size))
        tot = 0.0
        for j in range(lay.T):
            ll, S, idx = self.wall_terms(x, j, grad=True)
            tot += float(np.sum(ll))
            g[idx] += S.sum(axis=0)
            H[np.ix_(idx, idx)] += S.T @ S
        lp, gp, Hp = self.prior_terms(x)
        return tot + lp, g + gp, H + Hp


def distance_model(wall, kind: str = "axis") -> float:
    """The distance a user measures from wall parameters (α, β, D, ...), m:
    "axis" D / n_z (along the optical axis), "normal" D."""
    if kind == "normal":
        return float(wall[2])
    return float(wall[2] / plane_normal(wall[0], wall[1])[2])
