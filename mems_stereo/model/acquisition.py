"""Acquisition statistics of a resonant scanner sampled by a pulsed laser (Sec. 2.1, Fig. 2).

The laser samples the cosine trajectory once per shot (paper Eq. 1); where
each shot lands on the sensor follows from the scan direction and a target at
a given distance.  The number of shots per pixel is the number of
accumulations of that pixel's histogram.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mems_stereo.model.camera import project_points
from mems_stereo.model.hardware import System
from mems_stereo.model.scanner import scan_direction, theta_mech_samples


@dataclass(frozen=True)
class AcquisitionStats:
    """Distribution of shots over scan angle and over pixels.

    Attributes
    ----------
    theta_mech : (K,) rad, mechanical angle of each shot (Eq. 1).
    pixel : (K,) float64, column where each shot lands (NaN: off the sensor).
    angle_edges : (B+1,) rad; angle_counts : (B,) shots per angle bin.
    pixel_counts : (W,) int64, shots per pixel column (accumulations per histogram).
    mean_accumulations : float, count-weighted mean Σn²/Σn over pixels: the mean
        number of accumulations of the histogram a shot contributes to.
    mean_per_illuminated_pixel : float, mean of n over pixels with n > 0.
    fraction_on_sensor : float, share of shots that land on the sensor.
    """

    theta_mech: np.ndarray
    pixel: np.ndarray
    angle_edges: np.ndarray
    angle_counts: np.ndarray
    pixel_counts: np.ndarray
    mean_accumulations: float
    mean_per_illuminated_pixel: float
    fraction_on_sensor: float


def shot_pixels(system: System, theta, distance: float) -> np.ndarray:
    """Column where the beam at scan angle θ hits a plane z = distance, imaged.

    ``theta`` : (K,) rad.  Returns (K,) float64 column coordinate (NaN when the
    ray misses the plane ahead or lands outside the sensor's width).

    Examples
    --------
    >>> system = ms.preset("burkard2022")
    >>> theta = system.scanner.theta0 + np.array([-0.05, 0.0, 0.05])
    >>> np.round(ms.shot_pixels(system, theta, 2.0), 2)
    array([112.97,  93.03,  73.29])
    """
    d = scan_direction(np.asarray(theta, dtype=np.float64), system.scanner)
    p = np.asarray(system.scanner.position, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (distance - p[2]) / d[:, 2]
    s = np.where(s > 0, s, np.nan)
    pts = p + s[:, None] * d
    px = project_points(pts, system.receiver.camera_matrix, system.receiver.dist_coeffs)
    col = px[:, 0]
    w, h = system.receiver.image_size
    off = (col < -0.5) | (col >= w - 0.5) | (px[:, 1] < -0.5) | (px[:, 1] >= h - 0.5)
    col[off] = np.nan
    return col


def acquisition_statistics(system: System, n_shots: int, distance: float,
                           frequency_ratio: float | None = None, phi0: float = 0.0,
                           n_angle_bins: int = 64) -> AcquisitionStats:
    """Shots over scan angle and over pixels for a flat target at ``distance`` (m).

    ``frequency_ratio`` defaults to f_mech / f_rep of the system.

    Examples
    --------
    >>> stats = ms.acquisition_statistics(ms.preset("burkard2022"), 20000, 2.0)
    >>> stats.pixel_counts.shape, int(stats.pixel_counts.sum()), round(stats.fraction_on_sensor, 3)
    ((192,), 20000, 1.0)
    """
    ratio = frequency_ratio
    if ratio is None:
        ratio = system.scanner.f_mech / system.laser.f_rep
    amp = system.scanner.theta_mech_max
    th = theta_mech_samples(n_shots, ratio, amp, phi0)
    edges = np.linspace(-amp, amp, n_angle_bins + 1)
    angle_counts, _ = np.histogram(th, bins=edges)
    col = shot_pixels(system, system.scanner.theta0 + th, distance)
    on = np.isfinite(col)
    w = system.receiver.width
    pixel_counts = np.bincount(np.rint(col[on]).astype(np.int64), minlength=w)[:w]
    n = pixel_counts.astype(np.float64)
    total = n.sum()
    mean_acc = float((n * n).sum() / total) if total > 0 else 0.0
    lit = n[n > 0]
    return AcquisitionStats(th, col, edges, angle_counts, pixel_counts, mean_acc,
                            float(lit.mean()) if lit.size else 0.0,
                            float(on.mean()) if n_shots else 0.0)
