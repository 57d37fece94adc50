"""The pixels where the scan turns (issue 31): a wall seen there gives a point.

The mirror dwells at its turning points, so the pixel whose footprint holds one
collects more returns than any other, all at one edge of its footprint: the stereo
mean (the pixel's centre ray against the beam's mean angle) is off by up to the
spot's reach, while the time of flight is not (each return lies on its own shot's
ray).  Such a peak is kept, marked ``turning``, with a systematic σ on its stereo
(``TURNING_PIXEL_SIGMA`` pixels), so the fused point leans on the time of flight.
"""

from __future__ import annotations

import numpy as np
import pytest

import mems_stereo as ms
from mems_stereo.pipeline.peak_estimates import TURNING_PIXEL_SIGMA
from mems_stereo.pipeline.run import process_recording
from mems_stereo.sim import scene_from_dict, simulate

WALL_Z = 6.0  # m


@pytest.fixture(scope="module")
def wall():
    """(recording, result) of 0.2 s of a wall at 6 m, room light (100 kHz)."""
    system = ms.preset("burkard2022")
    scene = scene_from_dict({"objects": [
        {"type": "plane", "center": [0, 0, WALL_Z], "normal": [0, 0, -1], "size": [14, 4],
         "reflectivity": 0.7}]})
    rec = simulate(system, scene, 4000, rng=np.random.default_rng(31), background_hz=1e5)
    return rec, process_recording(rec)


def _turning_columns(rec) -> list[int]:
    """The columns of the beam's centre at the scan's two extreme angles (the true hits
    of the shots at the smallest and largest true angle, projected)."""
    th = rec.truth["theta"]
    pts = rec.truth["point"][[int(np.argmin(th)), int(np.argmax(th))]]
    rc = rec.system.receiver
    u = ms.project_points(pts, rc.camera_matrix, rc.dist_coeffs)[:, 0]
    return [int(np.rint(x)) for x in u]


def _true_range(rec, cloud) -> np.ndarray:
    """(N,) m: the wall's range along each point's direction from the receiver."""
    x = cloud.points
    return WALL_Z * np.linalg.norm(x, axis=1) / x[:, 2]


def test_the_turning_columns_get_a_point_within_its_sigma(wall):
    """Both turning columns hold the most returns of their neighbourhood (the dwell) and
    each gives a point marked ``turning`` whose error is within 3σ; before, they gave
    none.  The other points are unmarked."""
    rec, res = wall
    returns = np.sum(rec.truth["label"] == 1, axis=0)[0]
    cols = _turning_columns(rec)
    pk = res.peaks
    c = res.cloud
    err = c["range"] - _true_range(rec, c)
    for col in cols:
        near = returns[max(col - 3, 0):col + 4]
        assert returns[col] == near.max() and returns[col] > 50
        i = np.flatnonzero(c["pixel"] == col)
        assert i.size == 1, f"column {col}: no point"
        assert abs(err[i[0]]) <= 3 * c["sigma_r"][i[0]]
        assert pk.turning[np.flatnonzero(pk.col == col)[0]]
    inner = (pk.col > min(cols) + 1) & (pk.col < max(cols) - 1)
    assert not np.any(pk.turning[inner])


def test_the_turning_stereo_carries_its_systematic_sigma(wall):
    """At a turning peak the stereo's σ holds TURNING_PIXEL_SIGMA pixels of range: one
    pixel is dr/du = r·z/(b·f) of range on the pixel's ray (z = b·f/disparity, r ∝ z
    along the ray; b the baseline, f the focal length in pixels; the scanner's rays
    are not rectified, hence the band), far above the stereo's statistical σ at 6 m,
    so the fused point leans on the time of flight."""
    rec, res = wall
    c = res.cloud
    b = abs(rec.system.scanner.position[0])
    f = rec.system.receiver.camera_matrix[0, 0]
    for col in _turning_columns(rec):
        i = np.flatnonzero(c["pixel"] == col)[0]
        r = _true_range(rec, c)[i]
        per_px = r * WALL_Z / (b * f)
        assert 0.8 <= c["sigma_r_stereo"][i] / (TURNING_PIXEL_SIGMA * per_px) <= 1.25
        assert c["weight_stereo"][i] < 0.2
