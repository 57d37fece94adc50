"""Goodness of fit, named: structure in residuals that the model does not explain.

:func:`structure_tests` tests normalised residuals r (N,) (σ units: the model
says r ~ N(0, 1), independent) for structure along what the hardware model
leaves out, each a block of an additive model fitted by backfitting
(Hastie & Tibshirani 1990, §4.3) and tested by its F statistic:

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
#: backfitting sweeps
SWEEPS = 12
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


def _ordinal(k: int) -> str:
    return {2: "second", 3: "third", 4: "fourth", 5: "fifth", 6: "sixth"}.get(k, f"{k}th")


def _groups(key, min_group):
    """Group index (N,) of ``key`` for values with ≥ min_group entries (−1: none)."""
    vals, inv, cnt = np.unique(np.asarray(key), return_inverse=True, return_counts=True)
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
    (group index, groups)); :meth:`fit` by backfitting with any blocks left out."""

    def __init__(self, n, sw=None):
        self.n = n
        self.sw = np.ones(n) if sw is None else sw  # √weight of each residual
        self.w = self.sw * self.sw
        self.dense_blocks = {}
        self.group_blocks = {}

    def dense(self, name, cols):
        self.dense_blocks[name] = np.column_stack(cols) * self.sw[:, None]

    def group(self, name, key, min_group):
        g, G = _groups(key, min_group)
        if G >= 2:
            self.group_blocks[name] = (g, G)

    def dof(self, name) -> int:
        if name in self.dense_blocks:
            return int(self.dense_blocks[name].shape[1])
        return self.group_blocks[name][1] - 1

    @property
    def names(self) -> list:
        return list(self.dense_blocks) + list(self.group_blocks)

    def fit(self, r, drop=None):
        """Backfit without block ``drop``: (RSS, dense coefficients by block name)."""
        names = [k for k in self.dense_blocks if k != drop]
        X = np.column_stack([self.dense_blocks[k] for k in names])
        # einsum, not BLAS: N × (≤ 30) products gain nothing from threads
        gram_inv = np.linalg.pinv(np.einsum("ij,ik->jk", X, X))
        groups = {k: v for k, v in self.group_blocks.items() if k != drop}
        dense_part = np.zeros(self.n)
        parts = {k: np.zeros(self.n) for k in groups}
        res = r.copy()
        for _ in range(SWEEPS if groups else 1):
            res += dense_part
            coef = gram_inv @ np.einsum("ij,i->j", X, res)
            dense_part = np.einsum("ij,j->i", X, coef)
            res -= dense_part
            for k, (g, G) in groups.items():
                res += parts[k]
                m = g >= 0
                s = np.bincount(g[m], (self.sw * res)[m], G) / np.maximum(
                    np.bincount(g[m], self.w[m], G), 1e-300)
                parts[k] = np.where(m, self.sw * s[np.maximum(g, 0)], 0.0)
                res -= parts[k]
        out, i = {}, 0
        for k in names:
            w = self.dense_blocks[k].shape[1]
            out[k] = coef[i:i + w]
            i += w
        return float(res @ res), out


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
        structure is its information-weighted mean).  Default: equal weights.

    Returns
    -------
    GoodnessReport (one :class:`Finding` per test that had its covariate).
    """
    scale, unit = float(units[0]), str(units[1])
    r = np.asarray(residuals, dtype=np.float64).ravel()
    keep = np.isfinite(r)
    cov = {k: None if v is None else np.asarray(v).ravel()[keep]
           for k, v in (("phase", phase), ("direction", direction), ("pixel", pixel),
                        ("code", code), ("signal", signal), ("weights", weights))}
    r = r[keep]
    n = r.size
    sw = cov.pop("weights")
    B = _Blocks(n, None if sw is None else np.sqrt(np.asarray(sw, dtype=np.float64)))
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
        B.group("pixel", cov["pixel"], MIN_GROUP)
    if cov["code"] is not None:
        c = _standard(cov["code"])
        base += [c, c * c, c ** 3]
        B.group("TDC code", cov["code"], MIN_GROUP)
    if cov["signal"] is not None:
        ls = _standard(np.log(np.maximum(np.asarray(cov["signal"], dtype=np.float64), 1e-300)))
        B.dense("signal level", [ls, ls * ls])
    tested = B.names
    B.dense("nuisance", base)
    rss, coef = B.fit(r)
    dof_res = max(n - sum(B.dof(k) for k in B.names), 1)
    s2 = rss / dof_res
    findings = []
    for k in tested:
        dof = B.dof(k)
        extra = max(B.fit(r, drop=k)[0] - rss, 0.0)
        F = (extra / dof) / s2 if s2 > 0 else math.inf
        p = float(stats.f.sf(F, dof, dof_res))
        eff = math.sqrt(extra / max(n, 1))
        ok = not (p < alpha and eff >= min_effect)
        msg = ""
        if not ok:
            what, todo = ADVICE[k]
            groups = B.group_blocks[k][1] if k in B.group_blocks else 0
            detail = _details(k, coef.get(k), eff, groups, scale, unit)
            msg = f"{what.format(detail=detail)}: {todo} (p = {p:.1e})"
        findings.append(Finding(k, F, dof, p, eff, ok, msg))
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
