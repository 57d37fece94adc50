"""The pixels where the scan turns (issue 31): a wall seen there gives a point.

The mirror dwells at its turning points, so the pixel whose footprint holds one
collects more returns than any other, all at one edge of its footprint: the stereo
mean (the pixel's centre ray against the beam's mean angle) is off by up to the
spot's reach, while the time of flight is not (each return lies on its own shot's
ray).  Such a peak is kept, marked ``turning``; its footprint's angle is solved from
the mean angle (mems_stereo.pipeline.turning_angle), or where that fails its stereo
carries a systematic σ (``TURNING_PIXEL_SIGMA`` pixels) and the fused point leans on
the time of flight.
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


def test_the_turning_stereo_is_solved_within_its_sigma(wall):
    """Where the beam's centre reaches into the turning pixel, its footprint's angle is
    solved (mems_stereo.pipeline.turning_angle): the stereo lies within 3σ of the wall
    and its σ is a fraction of the pixel of range an unsolved turning peak carries
    (TURNING_PIXEL_SIGMA pixels; one pixel is dr/du = r·z/(b·f) of range on the pixel's
    ray, z = b·f/disparity, r ∝ z along the ray, b the baseline, f the focal length in
    pixels), so the stereo carries a good share of the point (before: the systematic
    pixel, weight < 0.2)."""
    rec, res = wall
    c = res.cloud
    b = abs(rec.system.scanner.position[0])
    f = rec.system.receiver.camera_matrix[0, 0]
    r_true = _true_range(rec, c)
    for col in _turning_columns(rec):
        i = np.flatnonzero(c["pixel"] == col)[0]
        per_px = r_true[i] * WALL_Z / (b * f)
        assert abs(c["range_stereo"][i] - r_true[i]) <= 3 * c["sigma_r_stereo"][i]
        assert c["sigma_r_stereo"][i] < 0.25 * TURNING_PIXEL_SIGMA * per_px
        assert c["weight_stereo"][i] > 0.3


def test_an_unsolved_turning_stereo_carries_the_systematic_pixel(wall, monkeypatch):
    """With no turning angle solved (the smallest slope set above any), the turning
    peaks' stereo σ holds TURNING_PIXEL_SIGMA pixels of range (within the band the
    unrectified scanner rays give) and the point leans on the time of flight."""
    import mems_stereo.pipeline.turning_angle as ta

    monkeypatch.setattr(ta, "TURNING_MIN_SLOPE", 10.0)
    rec, _ = wall
    c = process_recording(rec).cloud
    b = abs(rec.system.scanner.position[0])
    f = rec.system.receiver.camera_matrix[0, 0]
    for col in _turning_columns(rec):
        i = np.flatnonzero(c["pixel"] == col)[0]
        per_px = _true_range(rec, c)[i] * WALL_Z / (b * f)
        assert 0.8 <= c["sigma_r_stereo"][i] / (TURNING_PIXEL_SIGMA * per_px) <= 1.25
        assert c["weight_stereo"][i] < 0.2


def test_a_frame_removes_the_dwell_skew_the_scan_density_predicts(wall):
    """Frames remove every peak's expected mean-angle bias
    (mems_stereo.pipeline.frame_bias), also where the whole recording leaves it in σ as
    below its noise.  Where the two differ, next to the turning columns, the stereo
    moves by the dwell skew that the scan's arcsine angle density predicts for a
    Gaussian footprint (mems_stereo.pipeline.scan_dwell, an independent derivation from
    the mirror's motion, not the shots): within 30 %, one sign on each side of the
    field."""
    from mems_stereo.pipeline.frame_bias import every_bias_removed
    from mems_stereo.pipeline.scan_dwell import DwellSkew

    rec, res = wall
    with every_bias_removed():
        frame = process_recording(rec).cloud
    whole = res.cloud
    assert np.array_equal(frame["pixel"], whole["pixel"])
    moved = whole["range_stereo"] - frame["range_stereo"]
    probe = frame.select(np.ones(len(frame), bool))
    probe.attributes["weight_stereo"] = np.ones(len(frame))
    skew = DwellSkew(rec.system).systematic(probe).sigma_r  # |∂r/∂θ·Δθ|, m
    lo, hi = sorted(_turning_columns(rec))
    col = frame["pixel"]
    for side in ((col > lo) & (col <= lo + 14), (col < hi) & (col >= hi - 14)):
        m = side & (moved != 0) & (skew > 0.02)
        assert m.sum() >= 4
        np.testing.assert_allclose(np.abs(moved[m]), skew[m], rtol=0.3)
        assert np.all(np.sign(moved[m]) == np.sign(moved[m][0]))
