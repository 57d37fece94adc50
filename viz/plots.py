"""Figures of the paper with matplotlib (Agg, no display), written atomically.

* :func:`plot_acquisition`  – Fig. 2: shots over scan angle, accumulations per pixel
* :func:`plot_histograms`   – Figs. 8, 9a/b: raw, signal, noise histograms, pixel × TDC code
* :func:`plot_peaks`        – Fig. 9c/d: filtered histogram, threshold, detected peaks
* :func:`plot_uncertainty_bounds` – Fig. 5: covariance ellipses in the x–z plane
* :func:`plot_calibration_residuals` – residuals of a calibration fit
* :func:`plot_cloud_topview` – x–z scatter of a point cloud coloured by an attribute

Figures are built on :class:`matplotlib.figure.Figure` with the Agg canvas (no
pyplot state), so they work in threads and without a display.  The output
format follows the extension: ``.png`` (default), ``.pdf`` or ``.svg``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import LogNorm, Normalize
from matplotlib.figure import Figure
from matplotlib.patches import Ellipse

from mems_stereo.errors import FormatError
from mems_stereo.util.atomic import atomic_output

_FORMATS = (".png", ".pdf", ".svg")


def _check_path(path) -> Path:
    path = Path(path)
    if path.suffix.lower() not in _FORMATS:
        raise FormatError(f"expected a {', '.join(_FORMATS)} output, found {path.suffix!r}",
                          source=str(path))
    return path


def _figure(width: float, height: float) -> Figure:
    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Figure, path: Path, dpi: int = 120) -> Path:
    with atomic_output(path) as tmp:
        fig.savefig(tmp, format=path.suffix.lower()[1:], dpi=dpi)
    return path


# ------------------------------------------------------------------ Fig. 2

def plot_acquisition(stats, path: str | os.PathLike, title: str | None = None) -> Path:
    """Fig. 2: distribution of shots over the mechanical scan angle and over pixels.

    ``stats``: :class:`mems_stereo.model.acquisition.AcquisitionStats` (angle_edges
    (B+1,) rad, angle_counts (B,), pixel_counts (W,) shots per pixel column,
    mean_accumulations, mean_per_illuminated_pixel).  Returns the path.
    """
    path = _check_path(path)
    edges = np.degrees(np.asarray(stats.angle_edges, dtype=np.float64))
    counts = np.asarray(stats.angle_counts)
    px = np.asarray(stats.pixel_counts)
    fig = _figure(10, 4)
    a, b = fig.subplots(1, 2)
    a.stairs(counts, edges, fill=True, color="tab:blue", alpha=0.8)
    a.set_xlabel("mechanical scan angle θ_mech (deg)")
    a.set_ylabel("shots per angle bin")
    a.set_title("shots over scan angle")
    cols = np.arange(px.size)
    b.bar(cols, px, width=1.0, color="tab:orange", edgecolor="none")
    b.axhline(stats.mean_per_illuminated_pixel, color="k", ls="--",
              label=f"mean over lit pixels {stats.mean_per_illuminated_pixel:.2f}")
    b.axhline(stats.mean_accumulations, color="tab:red", ls=":",
              label=f"count-weighted mean {stats.mean_accumulations:.2f}")
    b.set_xlabel("pixel column")
    b.set_ylabel("accumulations (shots per pixel)")
    b.set_xlim(-0.5, px.size - 0.5)
    b.set_title(f"accumulations per pixel ({stats.fraction_on_sensor * 100:.1f} % on sensor)")
    b.legend(loc="upper right", fontsize="small")
    if title:
        fig.suptitle(title)
    return _save(fig, path)


# ------------------------------------------------------------ Figs. 8 and 9

def _as_pixel_bin(name: str, a, row: int | None) -> np.ndarray:
    """(W, n_bins) from (W, n_bins) or (H, W, n_bins) (one row, or the sum over rows)."""
    a = np.asarray(a)
    if a.ndim == 3:
        if row is None:
            a = a.sum(axis=0)
        else:
            if not 0 <= row < a.shape[0]:
                raise FormatError(f"row {row} outside 0..{a.shape[0] - 1}", field=name)
            a = a[row]
    if a.ndim != 2:
        raise FormatError(f"expected shape (W, n_bins) or (H, W, n_bins), found {a.shape}",
                          field=name)
    return a


def _image(ax, img, norm, cmap="viridis"):
    w, nb = img.shape
    data = np.ma.masked_less_equal(img, 0) if isinstance(norm, LogNorm) else img
    return ax.imshow(data, aspect="auto", origin="lower", interpolation="nearest", norm=norm,
                     cmap=cmap, extent=(0.5, nb + 0.5, -0.5, w - 0.5))


def plot_histograms(raw, signal, noise, path: str | os.PathLike, max_code: int | None = None,
                    title: str | None = None, log: bool = True, row: int | None = None) -> Path:
    """Figs. 8 and 9a/b: raw, signal and noise histograms as pixel × TDC code images.

    ``raw``, ``signal``, ``noise``: counts, each (W, n_bins) or (H, W, n_bins)
    (the rows summed, or ``row`` picked); bin b holds TDC code b + 1.
    ``max_code``: show codes 1..max_code only (the paper shows 256).  ``log``:
    logarithmic colour scale shared by the three panels (zero counts blank).
    Returns the path.
    """
    path = _check_path(path)
    imgs = [_as_pixel_bin(n, a, row) for n, a in
            zip(("raw", "signal", "noise"), (raw, signal, noise))]
    if len({i.shape for i in imgs}) != 1:
        raise FormatError(f"raw, signal and noise must have one shape, found "
                          f"{[i.shape for i in imgs]}")
    if max_code is not None:
        if max_code < 1:
            raise FormatError(f"max_code must be >= 1, found {max_code}", field="max_code")
        imgs = [i[:, :max_code] for i in imgs]
    top = max(float(i.max()) if i.size else 0.0 for i in imgs)
    norm = LogNorm(vmin=1, vmax=max(top, 1.0)) if log else Normalize(vmin=0, vmax=max(top, 1))
    fig = _figure(15, 4.5)
    axes = fig.subplots(1, 3, sharey=True)
    for ax, img, name in zip(axes, imgs, ("raw", "signal", "noise")):
        im = _image(ax, img, norm)
        ax.set_title(f"{name} ({int(img.sum())} counts)")
        ax.set_xlabel("TDC code")
    axes[0].set_ylabel("pixel column")
    fig.colorbar(im, ax=list(axes), label="counts" + (" (log)" if log else ""))
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def plot_peaks(filtered, threshold, peaks, path: str | os.PathLike,
               max_code: int | None = None, title: str | None = None) -> Path:
    """Fig. 9c/d: filtered signal histogram, and what passes the threshold with the peaks.

    ``filtered``: (W, n_bins) float, filtered histogram per pixel.
    ``threshold``: scalar, (W,) per pixel, or (W, n_bins).
    ``peaks``: (M, 2) int (pixel, bin index) of detected peaks, or a boolean
    (W, n_bins) mask.  Returns the path.
    """
    path = _check_path(path)
    f = np.asarray(filtered, dtype=np.float64)
    if f.ndim != 2:
        raise FormatError(f"expected filtered shape (W, n_bins), found {f.shape}", field="filtered")
    th = np.asarray(threshold, dtype=np.float64)
    if th.ndim == 1:
        th = th[:, None]
    try:
        above = f > np.broadcast_to(th, f.shape)
    except ValueError:
        raise FormatError(f"threshold shape {th.shape} does not fit filtered {f.shape}",
                          field="threshold") from None
    pk = np.asarray(peaks)
    if pk.dtype == np.bool_:
        if pk.shape != f.shape:
            raise FormatError(f"peak mask shape {pk.shape}, expected {f.shape}", field="peaks")
        pk = np.argwhere(pk)
    pk = pk.reshape(-1, 2)
    if max_code is not None:
        f, above = f[:, :max_code], above[:, :max_code]
        pk = pk[pk[:, 1] < max_code]
    fig = _figure(11, 4.5)
    a, b = fig.subplots(1, 2, sharey=True)
    im = _image(a, f, Normalize(vmin=min(0.0, float(f.min()) if f.size else 0.0),
                                vmax=max(float(f.max()) if f.size else 1.0, 1e-12)))
    fig.colorbar(im, ax=a, label="filtered counts")
    a.set_title("filtered signal histogram")
    _image(b, np.where(above, f, 0.0), Normalize(vmin=0, vmax=max(float(f.max()), 1e-12)),
           cmap="Greys")
    b.scatter(pk[:, 1] + 1, pk[:, 0], s=18, facecolors="none", edgecolors="tab:red",
              label=f"{len(pk)} peaks")
    b.set_title("above threshold and detected peaks")
    b.legend(loc="upper right", fontsize="small")
    for ax in (a, b):
        ax.set_xlabel("TDC code")
    a.set_ylabel("pixel column")
    if title:
        fig.suptitle(title)
    return _save(fig, path)


# ------------------------------------------------------------------ Fig. 5

def ellipse_params(cov, n_sigma: float = 1.0) -> tuple[float, float, float]:
    """Full width, full height (same unit as √cov) and angle (deg) of an n-σ ellipse.

    ``cov``: (2, 2) covariance.  Width is along the major axis; the angle is
    measured from the first coordinate axis towards the second.
    """
    c = np.asarray(cov, dtype=np.float64).reshape(2, 2)
    w, v = np.linalg.eigh((c + c.T) / 2)
    w = np.clip(w, 0.0, None)
    major = v[:, 1]
    return (2 * n_sigma * float(np.sqrt(w[1])), 2 * n_sigma * float(np.sqrt(w[0])),
            float(np.degrees(np.arctan2(major[1], major[0]))))


def plot_uncertainty_bounds(means, covariances, path: str | os.PathLike,
                            n_sigma=(1.0,), samples=None, labels=None,
                            title: str | None = None, scale: float = 1.0) -> Path:
    """Fig. 5: uncertainty ellipses of points in the x–z plane.

    ``means``: (M, 2) float64, (x, z) in m; ``covariances``: (M, 2, 2) m².
    ``n_sigma``: the ellipses drawn per point (1, 2, 3 σ ...).  ``samples``:
    optional (M, S, 2) or (S, 2) Monte-Carlo points to overlay.  ``labels``:
    optional M strings.  ``scale``: enlarge the ellipses for visibility (the
    legend says so).  Returns the path.
    """
    path = _check_path(path)
    mu = np.asarray(means, dtype=np.float64).reshape(-1, 2)
    cov = np.asarray(covariances, dtype=np.float64)
    if cov.shape != (mu.shape[0], 2, 2):
        raise FormatError(f"expected covariances of shape ({mu.shape[0]}, 2, 2), found "
                          f"{cov.shape}", field="covariances")
    fig = _figure(7, 6)
    ax = fig.subplots()
    if samples is not None:
        s = np.asarray(samples, dtype=np.float64).reshape(-1, 2)
        ax.scatter(s[:, 0], s[:, 1], s=1, color="0.6", alpha=0.5, label="samples")
    ax.scatter(mu[:, 0], mu[:, 1], s=6, color="k", zorder=3, label="points")
    styles = ["-", "--", ":", "-."]
    for j, ns in enumerate(np.atleast_1d(n_sigma)):
        for i in range(mu.shape[0]):
            w, h, ang = ellipse_params(cov[i], float(ns))
            ax.add_patch(Ellipse(tuple(mu[i]), w * scale, h * scale, angle=ang, fill=False,
                                 ls=styles[j % 4], color=f"C{i % 10}",
                                 label=(f"{ns:g} σ" + (f" (×{scale:g})" if scale != 1 else "")
                                        if i == 0 else None)))
    if labels is not None:
        for (x, z), lab in zip(mu, labels):
            ax.annotate(str(lab), (x, z), fontsize="x-small", xytext=(3, 3),
                        textcoords="offset points")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("z (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.legend(loc="best", fontsize="small")
    ax.set_title(title or "propagated uncertainty in the x–z plane")
    return _save(fig, path)


# ------------------------------------------------------ calibration, clouds

def plot_calibration_residuals(residuals, path: str | os.PathLike, title: str | None = None,
                               unit: str = "") -> Path:
    """Residuals of a calibration fit: per observation, and their histogram.

    ``residuals``: a dict name → array (any shape, flattened), or one array.
    Each row of the figure shows one entry with its RMS.  Returns the path.
    """
    path = _check_path(path)
    if not isinstance(residuals, dict):
        residuals = {"residual": residuals}
    if not residuals:
        raise FormatError("no residuals to plot", field="residuals")
    items = [(k, np.asarray(v, dtype=np.float64).ravel()) for k, v in residuals.items()]
    fig = _figure(10, 2.6 * len(items) + 0.6)
    axes = np.atleast_2d(fig.subplots(len(items), 2, squeeze=False))
    for (name, r), (a, b) in zip(items, axes):
        fin = r[np.isfinite(r)]
        rms = float(np.sqrt(np.mean(fin**2))) if fin.size else float("nan")
        a.plot(np.arange(r.size), r, ".", ms=3)
        a.axhline(0.0, color="k", lw=0.8)
        a.set_title(f"{name}: RMS {rms:.4g}{(' ' + unit) if unit else ''}, n = {r.size}")
        a.set_xlabel("observation")
        a.set_ylabel(f"residual{f' ({unit})' if unit else ''}")
        if fin.size:
            b.hist(fin, bins=min(50, max(5, fin.size // 5)), color="tab:gray")
        b.set_xlabel(f"residual{f' ({unit})' if unit else ''}")
        b.set_ylabel("count")
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def plot_cloud_topview(cloud, path: str | os.PathLike, color_by: str = "range",
                       title: str | None = None, point_size: float = 2.0) -> Path:
    """Bird's-eye view of a point cloud: x–z scatter (m) coloured by an attribute.

    ``cloud``: :class:`mems_stereo.pipeline.cloud.PointCloud`; ``color_by`` an attribute
    or x/y/z.  The receiver (projection centre) is marked at the origin.
    """
    path = _check_path(path)
    axes_idx = {"x": 0, "y": 1, "z": 2}
    if color_by in cloud.attributes:
        c = np.asarray(cloud.attributes[color_by], dtype=np.float64)
    elif color_by in axes_idx:
        c = cloud.points[:, axes_idx[color_by]]
    else:
        raise FormatError(f"cannot colour by {color_by!r}: expected one of "
                          f"{sorted(set(cloud.attributes) | set(axes_idx))}", field="color_by")
    fig = _figure(7, 6)
    ax = fig.subplots()
    sc = ax.scatter(cloud.points[:, 0], cloud.points[:, 2], c=c, s=point_size, cmap="turbo",
                    linewidths=0)
    fig.colorbar(sc, ax=ax, label=color_by)
    ax.plot([0], [0], marker="^", color="k", ms=8, ls="none", label="receiver")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("z (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(loc="upper right", fontsize="small")
    ax.set_title(title or f"top view, {len(cloud)} points")
    return _save(fig, path)
