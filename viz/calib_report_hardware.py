"""The calibration report's hardware page: what the hardware model's terms do to the fit.

:func:`hardware_page` adds one page to a calibration report (PDF, matplotlib ``Figure``,
no pyplot state) for a :class:`~mems_stereo.calib.result.CalibrationResult` that
carries its problem (``result.extra``):

* the time-score residuals against the scan phase, per sweep direction, before (the
  hardware terms set to ideal) and after (as fitted) — a mirror harmonic or unequal
  edge delays show as a wave the fitted model flattens;
* the per-pixel TDC offsets with σ (or the pixels' mean residuals when none were
  estimated);
* the score tests of every candidate term and the goodness-of-fit tests;
* optional panels: the TDC's INL from the code-density test
  (:class:`~mems_stereo.calib.code_density.CodeWidths`, ``result.extra["code_widths"]``)
  and the pulse shape against the Gaussian
  (:class:`~mems_stereo.calib.pulse_shape.PulseFit`, ``result.extra["pulse"]``).
"""

from __future__ import annotations

import numpy as np
from mems_stereo.calib.goodness import cell_residuals
from mems_stereo.calib.model import HARDWARE_PARAMS

#: scan-phase bins of the residual curves
PHASE_BINS = 24


def _binned(phase, r, bins=PHASE_BINS):
    """Mean and its σ of r in bins of phase mod 2π: (centres, mean, sem)."""
    ph = np.mod(phase, 2 * np.pi)
    k = np.minimum((ph / (2 * np.pi) * bins).astype(int), bins - 1)
    n = np.bincount(k, None, bins)
    s = np.bincount(k, r, bins)
    s2 = np.bincount(k, r * r, bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        m = s / n
        sem = np.sqrt(np.maximum(s2 / n - m * m, 0.0) / n)
    return (np.arange(bins) + 0.5) * 2 * np.pi / bins, m, sem


def _phase_panel(ax, result) -> None:
    prob, x = result.extra["problem"], result.extra["x"]
    lay = prob.layout
    x0 = x.copy()
    for i, n in enumerate(lay.names):
        if n in HARDWARE_PARAMS:
            x0[i] = 0.0
    for xx, style, label in ((x0, "--", "before (ideal model)"), (x, "-", "after (fitted)")):
        r = cell_residuals(prob, xx)
        d = -np.sign(np.sin(r.phase))
        for sgn, col, name in ((1, "tab:red", "rising"), (-1, "tab:blue", "falling")):
            sel = d == sgn
            c, m, e = _binned(r.phase[sel], r.time[sel])
            ax.errorbar(c, m, yerr=e, fmt=style, color=col, lw=1, capsize=2,
                        label=f"{name} sweep, {label}")
    ax.axhline(0, color="k", lw=0.6)
    ax.set_xlabel("scan phase φ + δ (rad)")
    ax.set_ylabel("mean time score (unit RMS)")
    ax.set_title("residual against scan phase and direction")
    ax.legend(fontsize=6)


def _pixel_panel(ax, result) -> None:
    po = result.extra.get("pixel_offsets")
    if po is None:
        ax.set_axis_off()
        return
    pix = np.flatnonzero(po.covered)
    est = po.test.selected
    val = result.system.tdc.pixel_offsets if est else po.estimate  # not selected: the
    err = po.std if est else po.estimate_std  # one-step estimates and their own σ
    ax.errorbar(pix, np.asarray(val)[pix] * 1e12, yerr=err[pix] * 1e12, fmt=".", ms=3,
                color="tab:green" if est else "0.5", elinewidth=0.5)
    ax.axhline(0, color="k", lw=0.6)
    ax.set_xlabel("pixel")
    ax.set_ylabel("TDC offset (ps)")
    ax.set_title(f"per-pixel TDC offsets ({'estimated' if est else 'not significant: left 0'};"
                 f" score test p = {po.test.p_value:.2g})", fontsize=9)


def _tests_panel(ax, result) -> None:
    ax.set_axis_off()
    lines = ["score tests of the hardware terms (selected: p < 1e-3):"]
    for t in result.extra.get("hardware_tests", []):
        lines.append(f"  {t.name:14s} LM {t.lm:9.1f}  dof {t.dof:3d}  p {t.p_value:8.2g}  "
                     f"{'SELECTED' if t.selected else ''}")
    for title, rep in zip(("time scores", "column scores"), result.extra.get("goodness", ())):
        lines.append(f"goodness of fit, {title}: {'pass' if rep.passed else 'FAIL'}")
        for f in rep.findings:
            lines.append(f"  {f.name:15s} F {f.statistic:7.2f}  p {f.p_value:8.2g}  "
                         f"structure {f.effect:.3f}")
    ax.text(0.0, 1.0, "\n".join(lines), va="top", family="monospace", fontsize=7,
            transform=ax.transAxes)


def inl_panel(ax, widths) -> None:
    """INL (LSB) of each pixel group with its ±σ band."""
    for g in range(widths.width.shape[0]):
        ax.plot(widths.codes, widths.inl[g], lw=0.8, label=f"group {widths.groups[g]}")
        ax.fill_between(widths.codes, widths.inl[g] - widths.inl_sigma[g],
                        widths.inl[g] + widths.inl_sigma[g], alpha=0.2)
    ax.set_xlabel("TDC code")
    ax.set_ylabel("INL (LSB)")
    ax.set_title(f"code density: DNL RMS {widths.rms_dnl():.3f} LSB, "
                 f"≥ {widths.min_counts} counts/code", fontsize=9)


def pulse_panel(ax, fit) -> None:
    """The fitted pulse against the Gaussian-only fit (ns)."""
    s = max(fit.sigma, 1e-12)
    t = np.linspace(fit.shift - 4 * s, fit.shift + 4 * s + 5 * fit.tail_decay, 400)
    ax.plot(t * 1e9, fit.pdf(t) * 1e-9, label="ex-Gaussian (fitted)")
    ax.plot(t * 1e9, fit.pdf(t, gaussian=True) * 1e-9, "--", label="Gaussian")
    ax.set_xlabel("delay (ns)")
    ax.set_ylabel("density (1/ns)")
    ax.set_title(fit.summary()[:90], fontsize=7)
    ax.legend(fontsize=7)


def hardware_page(pdf, result) -> bool:
    """Add the hardware page to ``pdf`` (a ``PdfPages``); False (no page) when the
    result carries no problem (a failure, or a result read back from a file)."""
    extra = getattr(result, "extra", None) or {}
    if "problem" not in extra or "x" not in extra:
        return False
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11.69, 8.27))
    axs = fig.subplots(2, 2)
    _phase_panel(axs[0, 0], result)
    _pixel_panel(axs[0, 1], result)
    _tests_panel(axs[1, 0], result)
    if extra.get("pulse") is not None:
        pulse_panel(axs[1, 1], extra["pulse"])
    elif "code_widths" in extra:
        inl_panel(axs[1, 1], extra["code_widths"])
    else:
        axs[1, 1].set_axis_off()
    fig.suptitle("hardware model: trajectory, monitor edges, pixel offsets, goodness of fit")
    fig.tight_layout()
    pdf.savefig(fig)
    return True
