"""Goodness of fit, named: structure in residuals that the model does not explain.

:func:`structure_tests` tests normalised residuals r (N,) (σ units: the model
says r ~ N(0, 1), independent) for structure along what the hardware model
leaves out, each a block of an additive linear model fitted by exact weighted
least squares (normal equations assembled block by block) and tested by its
extra sum of squares: over the residual mean square (F test), or over the
variance the model gives (χ² test, :class:`Weights`), with the rank the block
adds to the others as its dof:

============== ============================================ ===============================
block          columns                                      looks like
============== ============================================ ===============================
scan phase     cos kφ, sin kφ, k = 2..K                     harmonics of the mirror
scan direction d, d·cos φ (d = ±1 the sweep's direction)    unequal monitor edge delays
pixel          one mean per pixel                           per-pixel TDC offsets
TDC code       one mean per code                            TDC code widths (DNL/INL)
signal level   ℓ, ℓ² (ℓ the standardised log signal)        pulse tail / pile-up
============== ============================================ ===============================

Not tested (nuisance, always fitted): a constant, cos φ and sin φ (what θ0,
the amplitude and the phase offset already absorb), a quadratic in the pixel
and a cubic in the code (smooth trends the geometry absorbs).  A block fails
when its p-value is below ``alpha`` (default :data:`ALPHA` each, so that
five tests on clean residuals refuse ≤ 0.5 %) *and* its structure's RMS is at
least ``min_effect`` σ (large recordings make negligible structure
significant).  Each failure says which effect it looks like and what to do.

Residuals that are scores of rare photons (a cell expecting m ≪ 1 photons: zero
mostly, ~1/√m now and then) are heavy-tailed: their own mean square is mostly
well below 1 (its median far under its mean), so an F test over it refuses
clean residuals many times above its rate; the calibration's tests therefore
take the variance from the model (1 for scores over their expected RMS), keep
pixels and codes of little information out of the group means, and refer each
group block to a χ² scaled for the groups' excess kurtosis (:class:`Weights`).

:func:`stereo_tof_agreement` is processing's test: the paper's
over-determination gives two ranges per point (stereo, time of flight); their
normalised difference ``z = (r_st − r_tof)/√(σ_st² + σ_tof²)`` has RMS ≈ 1 on
hardware the model describes; beyond :data:`AGREEMENT_RMS` the points' σ are
wrong and the structure of z names the effect.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import stats

#: per-test false-alarm probability on clean residuals
ALPHA = 1e-3
#: smallest structure (RMS, σ units) a failing test names
MIN_EFFECT = 0.05
#: harmonics of the scan phase tested: 2..HARMONICS
HARMONICS = 5
#: fewest entries of a pixel / code for its own mean in the test
MIN_GROUP = 5
#: eigenvalues of the scaled normal equations below this share of the largest are
#: directions the design does not span (the rank of a block counts the others)
RANK_TOL = 1e-10
#: RMS of the stereo/ToF normalised difference beyond which processing warns
AGREEMENT_RMS = 1.3

ADVICE = {
    "scan phase": ("residuals follow the scan phase like a {detail}",
                   "calibrate with trajectory harmonics (mems-stereo calibrate --model full)"),
    "scan direction": ("rising and falling sweeps disagree by {detail}",
                       "unequal monitor edge delays: calibrate with edge delays "
                       "(mems-stereo calibrate --model full)"),
    "pixel": ("residuals differ from pixel to pixel ({detail})",
              "per-pixel TDC offsets: calibrate with per-pixel offsets "
              "(mems-stereo calibrate --model full)"),
    "TDC code": ("residuals follow the TDC code ({detail})",
                 "TDC code widths (DNL/INL): estimate them with the code-density test "
                 "(mems_stereo.calib.code_density)"),
    "signal level": ("residuals change with the signal level ({detail})",
                     "a pulse tail or pile-up the model lacks: estimate the pulse shape "
                     "(mems_stereo.calib.pulse_shape)"),
}


@dataclass(frozen=True)
class Finding:
    """One test: ``name`` (a key of :data:`ADVICE`), F ``statistic`` with
    ``dof``, ``p_value``, ``effect`` (RMS of the fitted structure, σ units),
    ``passed``, and ``message`` (what it looks like; what to do) when failed."""

    name: str
    statistic: float
    dof: int
    p_value: float
    effect: float
    passed: bool
    message: str = ""


@dataclass(frozen=True)
class GoodnessReport:
    """The tests run (``findings``), ``n`` residuals and their ``rms`` (σ units)."""

    findings: tuple
    n: int
    rms: float

    @property
    def passed(self) -> bool:
        return all(f.passed for f in self.findings)

    @property
    def failed(self) -> list:
        """The failed findings, largest structure first."""
        return sorted((f for f in self.findings if not f.passed), key=lambda f: -f.effect)

    def lines(self) -> list:
        """One line per failed test (empty when all pass)."""
        return [f.message for f in self.failed]

    def to_dict(self) -> dict:
        return {"n": self.n, "rms": self.rms, "passed": self.passed,
                "tests": [{"name": f.name, "F": f.statistic, "dof": f.dof, "p": f.p_value,
                           "effect": f.effect, "passed": f.passed, "message": f.message}
                          for f in self.findings]}


@dataclass(frozen=True)
class Weights:
    """What the model says of each residual (``weights`` of :func:`structure_tests`).

    info : (N,) float > 0, each residual's expected information, any common scale
        (weighted least squares: the residuals are r_i = y_i·√w_i of working
        responses y_i of variance 1/w_i).
    variance : the residuals' variance where the model fixes it (1.0 for scores over
        their expected RMS): each block's extra sum of squares over it is then χ² with
        the block's dof.  None: estimated from the residuals (F test), which heavy-
        tailed residuals (a few rare large scores carry the mean square) make a noisy
        denominator.
    min_group : smallest total ``info`` of a pixel or code for its own mean in the
        tests; the group's structure is its score sum, near-normal only when the
        group's information is large enough (in the units of ``info``).
    excess : optional (N,) float ≥ 0, each residual's excess kurtosis under the model
        (with ``variance``): a group's score sum then has the excess
        κ_g = Σ w²κ / (Σ w)², each group's square the variance 2 + κ_g instead of 2,
        and a group block is referred to the scaled χ² of the same mean and variance
        (Satterthwaite: c·χ²_{dof/c}, c = 1 + mean κ_g / 2).
    """

    info: np.ndarray
    variance: float | None = None
    min_group: float = MIN_GROUP
    excess: np.ndarray | None = None


def _ordinal(k: int) -> str:
    return {2: "second", 3: "third", 4: "fourth", 5: "fifth", 6: "sixth"}.get(k, f"{k}th")


def _groups(key, min_group, w=None):
    """Group index (N,) of ``key`` for values whose entries' total weight ``w`` (N,)
    (default 1 each: their count) is at least min_group (−1: none)."""
    vals, inv = np.unique(np.asarray(key), return_inverse=True)
    cnt = np.bincount(inv, w, vals.size)
    ok = cnt[inv] >= min_group
    sel = np.flatnonzero(cnt >= min_group)
    remap = np.full(vals.size, -1)
    remap[sel] = np.arange(sel.size)
    return np.where(ok, remap[inv], -1), int(sel.size)


def _standard(v):
    v = np.asarray(v, dtype=np.float64)
    return (v - v.mean()) / (v.std() or 1.0)


class _Blocks:
    """The additive model: dense blocks (name → columns) and group blocks (name →
    (group index, groups)); :meth:`fit` by exact weighted least squares with any block
    left out (normal equations assembled by block, group products by ``bincount``)."""

    def __init__(self, n, sw=None):
        self.n = n
        self.sw = np.ones(n) if sw is None else sw  # √weight of each residual
        self.w = self.sw * self.sw
        self.dense_blocks = {}
        self.group_blocks = {}
        #: (N,) each residual's excess kurtosis (None: 0) and, per group block, c
        self.excess = None
        self.scale_of = {}

    def dense(self, name, cols):
        self.dense_blocks[name] = np.column_stack(cols) * self.sw[:, None]

    def group(self, name, key, min_group):
        g, G = _groups(key, min_group, self.w)
        if G >= 2:
            self.group_blocks[name] = (g, G)
            if self.excess is not None:
                m = g >= 0
                k = np.bincount(g[m], (self.w * self.w * self.excess)[m], G) / np.maximum(
                    np.bincount(g[m], self.w[m], G), 1e-300) ** 2
                self.scale_of[name] = 1.0 + 0.5 * float(np.mean(k))

    @property
    def names(self) -> list:
        return list(self.dense_blocks) + list(self.group_blocks)

    def _cross(self, a, b):
        """X_aᵀ X_b of blocks a and b (columns scaled by √w)."""
        da, db = self.dense_blocks.get(a), self.dense_blocks.get(b)
        if da is not None and db is not None:
            # einsum, not BLAS: N × (≤ 30) products gain nothing from threads
            return np.einsum("ij,ik->jk", da, db)
        if da is None and db is None:
            (ga, Ga), (gb, Gb) = self.group_blocks[a], self.group_blocks[b]
            m = (ga >= 0) & (gb >= 0)
            return np.bincount(ga[m] * Gb + gb[m], self.w[m], Ga * Gb).reshape(Ga, Gb)
        if da is None:
            return self._cross(b, a).T
        g, G = self.group_blocks[b]
        m = g >= 0
        return np.stack([np.bincount(g[m], col, G) for col in (da * self.sw[:, None])[m].T])

    def _rhs(self, k, r):
        if k in self.dense_blocks:
            return np.einsum("ij,i->j", self.dense_blocks[k], r)
        g, G = self.group_blocks[k]
        m = g >= 0
        return np.bincount(g[m], (self.sw * r)[m], G)

    def normal_equations(self, r):
        """(XᵀX, Xᵀr, column slice of each block) over every block."""
        names = self.names
        cross = {(a, b): self._cross(a, b) for i, a in enumerate(names) for b in names[i:]}
        width = {k: cross[(k, k)].shape[0] for k in names}
        start = np.cumsum([0] + [width[k] for k in names])
        sl = {k: slice(int(start[i]), int(start[i + 1])) for i, k in enumerate(names)}
        A = np.zeros((start[-1], start[-1]))
        for (a, b), c in cross.items():
            A[sl[a], sl[b]] = c
            A[sl[b], sl[a]] = c.T
        return A, np.concatenate([self._rhs(k, r) for k in names]), sl

    @staticmethod
    def fit(A, b, rr: float, cols):
        """Least squares on columns ``cols`` of the normal equations (A, b), r·r = rr:
        (RSS, rank, coefficients over ``cols``).  The columns are scaled to unit
        diagonal and solved through their eigen-decomposition; directions below
        ``RANK_TOL`` of the largest eigenvalue (a group block's sum, which is the
        constant) count as absent."""
        As, bs = A[np.ix_(cols, cols)], b[cols]
        d = np.sqrt(np.maximum(np.diag(As), 1e-300))
        lam, V = np.linalg.eigh(As / d[:, None] / d[None, :])
        keep = lam > RANK_TOL * max(float(lam[-1]), 1e-300)
        z = V[:, keep].T @ (bs / d)
        beta = V[:, keep] @ (z / lam[keep])
        return rr - float(z @ (z / lam[keep])), int(keep.sum()), beta / d


def _details(name: str, coef, effect: float, groups: int, scale: float, unit: str) -> str:
    """The words that size a block's structure."""
    if name == "scan phase":
        amp = np.hypot(coef[0::2], coef[1::2])
        i = int(np.argmax(amp))
        return (f"{_ordinal(i + 2)} harmonic of the mirror (amplitude {amp[i] * scale:.3g} "
                f"{unit})")
    if name == "scan direction":
        return f"{2.0 * abs(float(coef[0])) * scale:.3g} {unit}"
    if name in ("pixel", "TDC code"):
        what = "pixels" if name == "pixel" else "codes"
        return f"RMS {effect * scale:.3g} {unit} over {groups} {what}"
    return f"RMS {effect * scale:.3g} {unit}"


def _findings(B: _Blocks, r, tested, variance, opts) -> list:
    """One :class:`Finding` per tested block: its extra sum of squares (the RSS
    without it less the RSS of all blocks) with the rank it adds as dof, over
    ``variance`` (χ²) or the residual mean square (F); ``opts``: (alpha, min_effect,
    scale, unit)."""
    alpha, min_effect, scale, unit = opts
    n = r.size
    A, b, sl = B.normal_equations(r)
    rr = float(r @ r)
    cols = np.arange(A.shape[0])
    rss, rank, beta = B.fit(A, b, rr, cols)
    dof_res = max(n - rank, 1)
    s2 = max(rss, 0.0) / dof_res if variance is None else float(variance)
    findings = []
    for k in tested:
        rss_k, rank_k, _ = B.fit(A, b, rr, np.concatenate(
            [cols[sl[j]] for j in B.names if j != k]))
        dof = rank - rank_k
        extra = max(rss_k - rss, 0.0)
        F = (extra / max(dof, 1)) / s2 if s2 > 0 else math.inf
        c = B.scale_of.get(k, 1.0)
        if dof <= 0:
            p = 1.0
        elif variance is None:
            p = float(stats.f.sf(F, dof, dof_res))
        else:
            p = float(stats.chi2.sf(F * dof / c, dof / c))
        eff = math.sqrt(extra / max(n, 1))
        ok = not (p < alpha and eff >= min_effect)
        msg = ""
        if not ok:
            what, todo = ADVICE[k]
            groups = B.group_blocks[k][1] if k in B.group_blocks else 0
            detail = _details(k, beta[sl[k]], eff, groups, scale, unit)
            msg = f"{what.format(detail=detail)}: {todo} (p = {p:.1e})"
        findings.append(Finding(k, F, dof, p, eff, ok, msg))
    return findings


def structure_tests(residuals, *, phase=None, direction=None, pixel=None, code=None,
                    signal=None, alpha: float = ALPHA, min_effect: float = MIN_EFFECT,
                    units=(1.0, "σ"), weights=None) -> GoodnessReport:
    """Test residuals for structure the model does not explain (see the module).

    Parameters
    ----------
    residuals : (N,) float64, normalised (σ units); NaN entries are dropped.
    phase : (N,) rad, the scan phase of each residual's shot (monitor phase
        + phase offset: θ = θ0 + A·cos φ); enables the scan-phase test.
    direction : (N,) ±1, the sweep's direction (default ``−sign(sin φ)``
        from ``phase``: +1 while θ rises); enables the scan-direction test.
    pixel, code : (N,) int, the residual's pixel and TDC code.
    signal : (N,) float > 0, the signal level (photons per shot, counts).
    alpha : per-test false-alarm probability; min_effect : σ units.
    units : (scale, unit), the physical size of one σ for the messages (e.g. (0.6, "ns")).
    weights : optional (N,) float > 0, each residual's information (weighted least
        squares: ``residuals`` are then r_i = y_i·√w_i of working responses y_i of
        variance 1/w_i, and every block's columns are scaled by √w_i; a group's
        structure is its information-weighted mean; a pixel or code has its own mean
        when its weights sum to ``MIN_GROUP``), or a :class:`Weights`.  Default:
        equal weights (a group: ``MIN_GROUP`` entries).

    Returns
    -------
    GoodnessReport (one :class:`Finding` per test that had its covariate).
    """
    scale, unit = float(units[0]), str(units[1])
    wt = weights if isinstance(weights, Weights) else Weights(weights)
    r = np.asarray(residuals, dtype=np.float64).ravel()
    keep = np.isfinite(r)
    cov = {k: None if v is None else np.asarray(v).ravel()[keep]
           for k, v in (("phase", phase), ("direction", direction), ("pixel", pixel),
                        ("code", code), ("signal", signal), ("weights", wt.info),
                        ("excess", wt.excess))}
    r = r[keep]
    n = r.size
    sw = cov.pop("weights")
    B = _Blocks(n, None if sw is None else np.sqrt(np.asarray(sw, dtype=np.float64)))
    B.excess = cov.pop("excess")
    base = [np.ones(n)]
    ph = cov["phase"]
    if ph is not None:
        base += [np.cos(ph), np.sin(ph)]
        B.dense("scan phase", [f(k * ph) for k in range(2, HARMONICS + 1)
                               for f in (np.cos, np.sin)])
        d = cov["direction"] if cov["direction"] is not None else -np.sign(np.sin(ph))
        B.dense("scan direction", [d, d * np.cos(ph)])
    if cov["pixel"] is not None:
        p = _standard(cov["pixel"])
        base += [p, p * p]
        B.group("pixel", cov["pixel"], wt.min_group)
    if cov["code"] is not None:
        c = _standard(cov["code"])
        base += [c, c * c, c ** 3]
        B.group("TDC code", cov["code"], wt.min_group)
    if cov["signal"] is not None:
        ls = _standard(np.log(np.maximum(np.asarray(cov["signal"], dtype=np.float64), 1e-300)))
        B.dense("signal level", [ls, ls * ls])
    tested = B.names
    B.dense("nuisance", base)
    findings = _findings(B, r, tested, wt.variance, (alpha, min_effect, scale, unit))
    rms = float(np.sqrt(np.mean(r * r))) if n else math.nan
    return GoodnessReport(tuple(findings), n, rms)


@dataclass(frozen=True)
class Agreement:
    """Processing's stereo/ToF agreement: ``rms`` of z over ``n`` points,
    ``bias`` (mean z), the structure ``report``, and ``warnings`` (lines)."""

    rms: float
    bias: float
    n: int
    report: GoodnessReport | None
    warnings: tuple


def stereo_tof_agreement(cloud, *, min_points: int = 50, alpha: float = ALPHA,
                         rms_limit: float = AGREEMENT_RMS) -> Agreement:
    """The RMS of the normalised stereo − ToF range difference of a cloud's points,
    and its structure against pixel, TDC code and signal counts.

    ``cloud`` : :class:`~mems_stereo.pipeline.cloud.PointCloud` with the attributes
    ``range_stereo``, ``sigma_r_stereo``, ``range_tof``, ``sigma_r_tof`` (processing's;
    others are skipped: no points, no warning).  Warns (lines in ``warnings``)
    when the RMS exceeds ``rms_limit`` or a structure test fails.
    """
    a = cloud.attributes
    need = ("range_stereo", "sigma_r_stereo", "range_tof", "sigma_r_tof")
    if not all(k in a for k in need) or len(cloud) < min_points:
        return Agreement(math.nan, math.nan, 0, None, ())
    with np.errstate(invalid="ignore", divide="ignore"):
        z = (a["range_stereo"] - a["range_tof"]) / np.hypot(a["sigma_r_stereo"],
                                                             a["sigma_r_tof"])
    ok = np.isfinite(z)
    z = z[ok]
    if z.size < min_points:
        return Agreement(math.nan, math.nan, 0, None, ())
    rms = float(np.sqrt(np.mean(z * z)))
    rep = structure_tests(z, pixel=a["pixel"][ok] if "pixel" in a else None,
                          code=np.rint(a["code"][ok]).astype(np.int64) if "code" in a else None,
                          signal=a["counts"][ok] if "counts" in a else None, alpha=alpha)
    warns = []
    if rms > rms_limit:
        bias = float(np.mean(z))
        warns.append(f"stereo and time-of-flight ranges disagree: RMS {rms:.2f} σ of their "
                     f"difference (mean {bias:+.2f} σ; expected ≈ 1): the points' σ are too "
                     f"small for this hardware")
    warns += rep.lines()
    return Agreement(rms, float(np.mean(z)), int(z.size), rep, tuple(warns))
