"""Each peak's stereo and time-of-flight means, and the cloud made of them.

:class:`PeakMeans` holds what
:meth:`~mems_stereo.pipeline.peak_accumulator.PeakAccumulator.peak_means` gives for
Q peaks (each row its peak's own; blocks of peaks join with
:meth:`PeakMeans.concat`); :meth:`PeakMeans.cloud` marks the depth edges (which
look at a peak's row neighbours), fuses each peak's two means along the ray
(:func:`fuse_along_ray`) and assembles the :class:`~mems_stereo.pipeline.cloud.PointCloud`
with its attributes.  Units: metres, receiver camera frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr, pdtrc

from mems_stereo.geometry.uncertainty import polar_from_cartesian
from mems_stereo.pipeline.calibration_sigma import calibration_point_covariance
from mems_stereo.pipeline.cloud import PointCloud

#: systematic uncertainty, in pixels, of the stereo of a peak at a depth edge of the cloud
#: (:meth:`PeakMeans._depth_edges`): the pixel sees part of the spot on one
#: surface, its image off the pixel's centre by up to the spot's size
EDGE_PIXEL_SIGMA = 0.25
#: whether the end of a run of points (one row neighbour with a point, the other
#: without) also counts as a depth edge (off: in sparse clouds it flags most points
#: and overstates their σ)
EDGE_RUN_ENDS = False
#: columns on each side in which :meth:`PeakMeans._mixed_pixels` looks for a depth
#: edge's nearest kept neighbour (2: a mixed pixel's other neighbour may have no point)
MIXED_NEIGHBOUR_COLUMNS = 2


def fuse_along_ray(stereo, tof):
    """Peak-level fusion of the stereo and ToF means: ``(x (Q, 3), C (Q, 3, 3), w (Q,))``.

    ``stereo``, ``tof`` : (x (Q, 3), C (Q, 3, 3)) means and covariances (both
    on the scanner ray at the peak's angle).  ``x = w·x_st + (1 − w)·x_tof`` with
    ``w = σ_r,tof² / (σ_r,st² + σ_r,tof²)`` (range variances: inverse-variance
    weights), ``C = w²·C_st + (1 − w)²·C_tof`` (independent given θ: pixel vs
    timing).  One estimate missing (NaN), the other alone.
    """
    xs, Cs = stereo[0], stereo[1]
    xt, Ct = tof[0], tof[1]
    pol = polar_from_cartesian(xs, Cs)
    ss = pol.sigma_r
    pol = polar_from_cartesian(xt, Ct)
    st = pol.sigma_r
    vs, vt = ss ** 2, st ** 2
    ok_s = np.all(np.isfinite(xs), axis=1) & np.isfinite(vs)
    ok_t = np.all(np.isfinite(xt), axis=1) & np.isfinite(vt)
    with np.errstate(invalid="ignore", divide="ignore"):
        w = np.where(vs + vt > 0, vt / (vs + vt), 0.5)
    w = np.where(ok_s & ok_t, w, np.where(ok_s, 1.0, 0.0))
    x = w[:, None] * np.nan_to_num(xs) + (1 - w)[:, None] * np.nan_to_num(xt)
    C = ((w ** 2)[:, None, None] * np.nan_to_num(Cs)
         + ((1 - w) ** 2)[:, None, None] * np.nan_to_num(Ct))
    bad = ~(ok_s | ok_t)
    x[bad] = np.nan
    C[bad] = np.nan
    return x, C, w


@dataclass(frozen=True, slots=True, eq=False)
class PeakMeans:
    """What :meth:`PeakAccumulator.peak_means` gives for Q peaks (each row its peak's
    own), and the cloud from it.

    system : the system; k : the inlier bound in σ (from the confidence).
    rows, cols : (Q,) int64 pixels; peak_code : (Q,) float64 the detector's peak code
    or None.
    stereo, tof : (x (Q, 3) m, C (Q, 3, 3) m²) means with every term of their σ;
    n, detections, window, code : (Q,) float64 sums of the inliers (see
    :class:`~mems_stereo.pipeline.sums.PeakSums`); birge : (Q,) reduced χ²
    scale; range_per_px : (Q, 3) m per pixel at the mean angle (None: no peak
    had a mean angle); delay, mu : (Q,) first-photon delay (s) and μ0 (None:
    not corrected).  Means of consecutive blocks of peaks join with
    :meth:`concat` (the Dask runner fuses blocks on its workers and the client
    makes the cloud of the whole).
    """

    system: object
    k: float
    rows: np.ndarray
    cols: np.ndarray
    peak_code: np.ndarray | None
    stereo: tuple[np.ndarray, np.ndarray]
    tof: tuple[np.ndarray, np.ndarray]
    n: np.ndarray
    detections: np.ndarray
    window: np.ndarray
    code: np.ndarray
    birge: np.ndarray
    range_per_px: np.ndarray | None
    delay: np.ndarray | None
    mu: np.ndarray | None

    @property
    def Q(self) -> int:
        """The number of peaks."""
        return self.rows.size

    @classmethod
    def concat(cls, parts) -> PeakMeans:
        """The means of consecutive blocks of peaks as one: a block without
        ``range_per_px`` (no mean angle) gets zeros, as the whole run gives such
        peaks, and one without first-photon figures (no band) NaN."""
        parts = list(parts)
        p0 = parts[0]

        def cat(get):
            return np.concatenate([get(p) for p in parts])

        def opt(name, fill):
            if all(getattr(p, name) is None for p in parts):
                return None
            return cat(lambda p: getattr(p, name) if getattr(p, name) is not None
                       else fill(p))

        codes = [p.peak_code for p in parts]
        return cls(p0.system, p0.k, cat(lambda p: p.rows), cat(lambda p: p.cols),
                   None if any(c is None for c in codes) else np.concatenate(codes),
                   (cat(lambda p: p.stereo[0]), cat(lambda p: p.stereo[1])),
                   (cat(lambda p: p.tof[0]), cat(lambda p: p.tof[1])),
                   cat(lambda p: p.n), cat(lambda p: p.detections), cat(lambda p: p.window),
                   cat(lambda p: p.code), cat(lambda p: p.birge),
                   opt("range_per_px", lambda p: np.zeros((p.Q, 3))),
                   opt("delay", lambda p: np.full(p.Q, np.nan)),
                   opt("mu", lambda p: np.full(p.Q, np.nan)))

    def _kept(self, min_counts: int, x_fused) -> np.ndarray:
        """(Q,) bool: the peaks that give a point, before depth edges and ``own``."""
        n = self.n
        # the detections (not their background-subtracted sum: 3 detections over an
        # expected background of 0.01 are 3 detections) set the fewest counts
        keep = ((self.detections >= max(1, int(min_counts))) & (n > 0)
                & np.all(np.isfinite(x_fused), axis=1))
        # the means are ratios over the inliers' background-subtracted count n: where
        # their detections are not significant against the background subtracted
        # from them (Poisson, at the peak's own confidence 2·Φ(−k)), n is consistent
        # with zero and the mean with anything — a failed estimate, not a point
        b_in = np.maximum(self.detections - n, 0.0)
        with np.errstate(invalid="ignore"):
            p_in = pdtrc(np.maximum(self.detections - 1.0, 0.0), np.maximum(b_in, 1e-300))
        keep &= p_in < 2.0 * ndtr(-self.k)
        return keep

    def cloud(self, min_counts: int = 1, own=None) -> PointCloud:
        """The cloud (see :meth:`PeakAccumulator.cloud`): the depth edges, the
        fused point and the attributes of every kept peak."""
        n = self.n
        mean = {"stereo": self.stereo, "tof": self.tof}
        mean["fused"] = fuse_along_ray(mean["stereo"], mean["tof"])
        birge = self.birge
        fp = None if self.delay is None else {"delay": self.delay, "mu": self.mu}
        keep = self._kept(min_counts, mean["fused"][0])
        edge = self._depth_edges(mean["fused"][0], mean["fused"][1], keep)
        if self.range_per_px is not None and np.any(edge):
            J = self.range_per_px[edge]
            x, C = mean["stereo"]
            C = C.copy()
            C[edge] += EDGE_PIXEL_SIGMA ** 2 * J[:, :, None] * J[:, None, :]
            mean["stereo"] = (x, C)
            mean["fused"] = fuse_along_ray(mean["stereo"], mean["tof"])
        w_mean = mean["fused"][2]
        xf, Cf = mean["fused"][:2]
        mixed = self._mixed_pixels(xf, Cf, keep, edge)
        if np.any(mixed > 0):  # along the ray: the range between the two surfaces
            with np.errstate(invalid="ignore", divide="ignore"):
                u = xf / np.linalg.norm(xf, axis=1, keepdims=True)
            Cf = Cf + np.nan_to_num((mixed ** 2)[:, None, None] * u[:, :, None] * u[:, None, :])
        # the calibration's parameter errors, shared by all the peak's detections: once
        c_cal = calibration_point_covariance(self.system, np.where(keep[:, None], xf, np.nan),
                                             self.rows, self.cols, w_mean,
                                             self.detections)
        if c_cal is not None:
            Cf = Cf + c_cal
        pol = polar_from_cartesian(xf, Cf)
        r, sr, sphi = pol.r, pol.sigma_r, pol.sigma_phi
        pol = polar_from_cartesian(*mean["stereo"])
        r_st, sr_st = pol.r, pol.sigma_r
        pol = polar_from_cartesian(*mean["tof"])
        r_tf, sr_tf = pol.r, pol.sigma_r
        sx = np.sqrt(np.maximum(np.diagonal(Cf, axis1=1, axis2=2), 0.0))
        with np.errstate(invalid="ignore", divide="ignore"):
            code_mean = self.code / n
        attrs = {
            "counts": np.rint(n).astype(np.int32), "pixel": self.cols.astype(np.int32),
            "row": self.rows.astype(np.int32),
            "code": self.peak_code if self.peak_code is not None else code_mean,
            "range": r, "sigma_r": sr, "sigma_phi": sphi,
            "sigma_x": sx[:, 0], "sigma_y": sx[:, 1], "sigma_z": sx[:, 2],
            "range_stereo": r_st, "sigma_r_stereo": sr_st, "range_tof": r_tf,
            "sigma_r_tof": sr_tf, "weight_stereo": w_mean, "scatter_ratio": np.sqrt(birge),
            "counts_window": np.rint(self.window).astype(np.int32),
        }
        if fp is not None:
            attrs["tof_delay"] = fp["delay"]
            attrs["signal_photons"] = fp["mu"]
        # how far the stereo and time-of-flight ranges of the peak disagree, in σ of
        # their difference (see :func:`consistent_points`)
        with np.errstate(invalid="ignore", divide="ignore"):
            attrs["stereo_tof_z"] = np.abs(r_st - r_tf) / np.sqrt(sr_st ** 2 + sr_tf ** 2)
        if own is not None:
            q = np.arange(self.Q)
            keep = keep & (q >= own[0]) & (q < own[1])
        return PointCloud(xf, attrs).select(keep)

    def _mixed_pixels(self, x, C, keep, edge) -> np.ndarray:
        """(Q,) float64 m: the range uncertainty of a mixed pixel, 0 elsewhere.

        A peak at a depth edge (``edge``, :meth:`_depth_edges`) whose range lies
        between those of its nearest kept neighbours in the row (within
        :data:`MIXED_NEIGHBOUR_COLUMNS` columns on each side), beyond k·σ of the
        difference from both, agrees with neither surface: its pixel (or the spot)
        straddles the silhouette and its range is a blend of the two — a "flying
        pixel".  Which surface the ray meets is not
        known: its distance to the nearer neighbour's range is its uncertainty.
        ``x`` (Q, 3), ``C`` (Q, 3, 3) the fused points; ``keep`` (Q,) those that
        become points.
        """
        Q = self.Q
        out = np.zeros(Q)
        cand = np.flatnonzero(edge & keep)
        if cand.size == 0:
            return out
        pol = polar_from_cartesian(x, C)
        r, sr = pol.r, pol.sigma_r
        W = self.system.receiver.width
        pad = MIXED_NEIGHBOUR_COLUMNS
        at = np.full((int(self.rows.max()) + 1, W + 2 * pad), -1, np.int64)
        kept = np.flatnonzero(keep)
        at[self.rows[kept], self.cols[kept] + pad] = kept
        gaps = []
        for dc in (-1, 1):  # the nearest kept neighbour on each side
            j = np.full(cand.size, -1, np.int64)
            for off in range(MIXED_NEIGHBOUR_COLUMNS, 0, -1):
                jo = at[self.rows[cand], self.cols[cand] + pad + dc * off]
                j = np.where(jo >= 0, jo, j)
            has = j >= 0
            jj = np.where(has, j, 0)
            with np.errstate(invalid="ignore"):
                D = np.where(has, r[jj] - r[cand], np.nan)
                far = np.abs(D) > self.k * np.hypot(sr[cand], sr[jj])
            gaps.append(np.where(far, D, np.nan))
        with np.errstate(invalid="ignore"):
            between = (gaps[0] * gaps[1]) < 0  # (NaN: no neighbour, or one agrees)
        out[cand[between]] = np.minimum(np.abs(gaps[0]), np.abs(gaps[1]))[between]
        return out

    def _depth_edges(self, x, C, keep) -> np.ndarray:
        """(Q,) bool: peaks at a depth edge of the cloud (see :data:`EDGE_PIXEL_SIGMA`).

        Two kept peaks next to each other in a row (columns i, j = i ± 1) are
        across a depth edge (an object's silhouette, a shadow) when their range
        step ``D = r_j − r_i`` exceeds k·σ_D (σ_D of the step) *and* is not the
        local slope of a surface: the two steps behind i (columns i ∓ 2 … i) or the
        two beyond j (j … j ± 2) are not both within k·σ_D of it — three equal
        steps in a row are a surface, one or two a silhouette (a pixel whose spot
        straddles a box and the wall behind it lies halfway between them, its two
        steps equal).
        A surface inclined to the rays steps by about the same amount from column
        to column (5 mm per column at 0.6 m and 60°, several σ of a dense near
        peak): tested against zero alone, every point of it would be an edge and
        carry the edge allowance, many times its error.  With :data:`EDGE_RUN_ENDS`,
        one neighbour holding a point and the other none (the end of a run of points)
        also counts.  ``x`` (Q, 3), ``C``
        (Q, 3, 3) the points; ``keep`` (Q,) those that become points.
        """
        Q = self.Q
        edge = np.zeros(Q, bool)
        if Q == 0 or not np.any(keep):
            return edge
        pol = polar_from_cartesian(x, C)
        r, sr = pol.r, pol.sigma_r
        H = int(self.rows.max()) + 1
        W = self.system.receiver.width
        pad = 3
        at = np.full((H, W + 2 * pad), -1, np.int64)  # padded: columns < 0 and ≥ W are empty
        idx = np.flatnonzero(keep)
        at[self.rows[idx], self.cols[idx] + pad] = idx
        present = []
        k = self.k

        def nb(off):  # (index of the kept peak at column + off or 0, whether there is one)
            j = at[self.rows[idx], self.cols[idx] + pad + off]
            return np.where(j >= 0, j, 0), j >= 0

        def step(a, b):  # (r_b − r_a, its σ)
            return r[b] - r[a], np.hypot(sr[a], sr[b])

        with np.errstate(invalid="ignore"):
            for dc in (-1, 1):
                j, has = nb(dc)
                D, sD = step(idx, j)
                jump = has & (np.abs(D) > k * sD)
                # a surface's slope: the two steps behind i (columns i − 2dc … i) or
                # the two beyond j (i + dc … i + 3dc) both within k·σ_D of D
                for offs in ((-2 * dc, -dc, 0), (dc, 2 * dc, 3 * dc)):
                    (p0, h0), (p1, h1), (p2, h2) = (
                        nb(o) if o else (idx, np.ones(idx.size, bool)) for o in offs)
                    slope = h0 & h1 & h2
                    for a, b in ((p0, p1), (p1, p2)):
                        slope &= np.abs(D - step(a, b)[0]) <= k * sD
                    jump &= ~slope
                edge[idx[jump]] = True
                inside = (self.cols[idx] + dc >= 0) & (self.cols[idx] + dc < W)
                present.append(has | ~inside)  # the sensor's border is not an edge
        if EDGE_RUN_ENDS:
            edge[idx[present[0] ^ present[1]]] = True
        return edge
