"""Depth edges of the cloud (``PeakMeans._depth_edges``): a silhouette is an edge, a
surface inclined to the rays is not."""

from __future__ import annotations

import numpy as np

from mems_stereo.model.system import burkard2022
from mems_stereo.pipeline.peak_means import PeakMeans


def _row(ranges, sigma):
    """``(PeakMeans, x, C, keep)`` of one row of points at ``ranges`` (m, NaN: no point)
    along +z, σ ``sigma`` in range."""
    r = np.asarray(ranges, np.float64)
    Q = r.size
    x = np.zeros((Q, 3))
    x[:, 2] = np.nan_to_num(r)
    C = np.zeros((Q, 3, 3))
    C[:, 2, 2] = sigma ** 2
    C[:, 0, 0] = C[:, 1, 1] = 1e-12
    one = np.ones(Q)
    pm = PeakMeans(burkard2022(), 2.97, np.zeros(Q, np.int64), np.arange(Q, dtype=np.int64) + 50,
                   None, (x, C), (x, C), one, one, one, np.zeros(Q), one, None, None, None)
    return pm, x, C, np.isfinite(r)


def _edges(ranges, sigma):
    """Edge flags of one row of points (see :func:`_row`)."""
    pm, x, C, keep = _row(ranges, sigma)
    return pm._depth_edges(x, C, keep)


def test_inclined_surface_is_not_an_edge():
    # 5 mm per column at σ 1 mm: every step is 3.5 σ of a step, all equal
    e = _edges(0.6 + 0.005 * np.arange(30), 1e-3)
    assert not e.any()


def test_silhouette_and_straddling_pixel_are_edges():
    r = np.r_[np.full(10, 1.0), np.full(10, 4.0)]
    e = _edges(r, 1e-3)
    assert np.flatnonzero(e).tolist() == [9, 10]
    # a pixel halfway between the box and the wall: its two steps agree with each
    # other, not with the surfaces' (flat) steps around them
    r = np.r_[np.full(10, 1.0), 2.5, np.full(10, 4.0)]
    e = _edges(r, 1e-3)
    assert {9, 10, 11} <= set(np.flatnonzero(e).tolist())
    # an inclined box before a flat wall: the jump is an edge, the slope is not
    r = np.r_[1.0 + 0.01 * np.arange(10), np.full(10, 4.0)]
    assert np.flatnonzero(_edges(r, 1e-3)).tolist() == [9, 10]


def _mixed(ranges, sigma):
    """Mixed-pixel σ (m) of one row of points (see :func:`_row`)."""
    pm, x, C, keep = _row(ranges, sigma)
    return pm._mixed_pixels(x, C, keep, pm._depth_edges(x, C, keep))


def test_flying_pixel_between_two_surfaces_carries_the_gap():
    # a pixel straddling a box at 1 m and the wall at 4 m, at 2.2 m: 1.2 m from the
    # box's range, 1.8 m from the wall's — its σ is the distance to the nearer
    m = _mixed(np.r_[np.full(10, 1.0), 2.2, np.full(10, 4.0)], 1e-3)
    assert np.flatnonzero(m).tolist() == [10]
    assert np.isclose(m[10], 1.2)
    # the neighbour on one side without a point: the next column's is used
    m = _mixed(np.r_[np.full(10, 1.0), np.nan, 3.7, np.full(10, 4.0)], 1e-3)
    assert np.flatnonzero(m).tolist() == [11] and np.isclose(m[11], 0.3)


def test_silhouette_and_slope_are_not_mixed():
    # a plain silhouette (each side's points agree with their own surface), an
    # inclined surface, and a point that agrees with one neighbour within k·σ
    assert not _mixed(np.r_[np.full(10, 1.0), np.full(10, 4.0)], 1e-3).any()
    assert not _mixed(0.6 + 0.005 * np.arange(30), 1e-3).any()
    assert not _mixed(np.r_[np.full(10, 1.0), 1.002, np.full(10, 4.0)], 1e-3).any()
