"""Scores of a processed simulated recording against its truth and scene.

The figures the README and ``mems-stereo demo`` quote: signal recall and
noise rejection against ``/truth/label``, the median range error of the
cloud's points against the true scene, and the coverage of the illuminated
pixels.  The same definitions as ``benchmarks/bench_pipeline.py``.
"""

from __future__ import annotations

import numpy as np

from mems_stereo.sim.motion import surface_distance_at, true_hits_at

#: m: the point error is evaluated for true surfaces within this range
MAX_TRUE_RANGE = 6.0


def true_ranges(scene, points) -> np.ndarray:
    """(N,) float64 m: range of the scene's first surface on the ray from the
    origin (receiver projection centre) through each point; inf where none."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if not p.shape[0]:
        return np.zeros(0)
    d = p / np.linalg.norm(p, axis=1, keepdims=True)
    return scene.cast(np.zeros(3), d).t


def cloud_scores(cloud, scene, illuminated, max_range: float = MAX_TRUE_RANGE) -> dict:
    """Point error and coverage of a peak cloud.

    cloud : :class:`~mems_stereo.pipeline.cloud.PointCloud` with ``row``, ``pixel``, ``range``.
    scene : :class:`~mems_stereo.sim.scene.Scene` (the truth).
    illuminated : (H, W) bool, pixels with at least one true laser return.

    Returns a dict: ``median_error`` (m, median |range − true range| over
    points whose true surface is within ``max_range``), ``p90_error`` (m),
    ``near`` (points counted), ``points``, ``illuminated``, ``covered``
    (illuminated pixels with a point) and ``coverage`` (covered / illuminated).
    """
    r_true = true_ranges(scene, cloud.points)
    near = np.isfinite(r_true) & (r_true <= max_range)
    has_pt = np.zeros(np.shape(illuminated), bool)
    if len(cloud):
        has_pt[cloud["row"], cloud["pixel"]] = True
    e = np.abs(cloud["range"] - r_true)[near] if len(cloud) else np.zeros(0)
    n_ill = int(np.sum(illuminated))
    covered = int(np.sum(illuminated & has_pt))
    return {"median_error": float(np.median(e)) if e.size else float("nan"),
            "p90_error": float(np.percentile(e, 90)) if e.size else float("nan"),
            "near": int(near.sum()), "points": len(cloud), "illuminated": n_ill,
            "covered": covered, "coverage": covered / n_ill if n_ill else float("nan")}


def score_result(result, truth_label, scene) -> dict:
    """All figures of one processed recording.

    result : :class:`~mems_stereo.pipeline.run.ProcessResult` of a recording with truth.
    truth_label : (K, H, W) uint8 ``/truth/label`` of that recording.
    scene : the scene it was simulated from.

    Returns :func:`cloud_scores` plus ``recall`` and ``noise_rejection``.
    """
    illum = np.any(np.asarray(truth_label) == 1, axis=0)
    out = cloud_scores(result.cloud, scene, illum)
    tr = result.truth or {}
    out["recall"] = float(tr.get("recall", float("nan")))
    out["noise_rejection"] = float(tr.get("noise_rejection", float("nan")))
    return out


def score_result_2d(result, recording, scene) -> dict:
    """All figures of one processed two-axis recording, defined as :func:`score_result`'s.

    result : :class:`~mems_stereo.pipeline.twoaxis.Result2D` of ``recording``.
    recording : :class:`~mems_stereo.io.recording2d.Recording2D` with its per-event
        ``/truth/label`` (E,) uint8 (1 laser return, 2 background).
    scene : the scene it was simulated from.

    A pixel is illuminated when at least one of its recorded detections is a
    laser return.  Returns :func:`cloud_scores` plus ``recall`` and
    ``noise_rejection`` (``result.truth``).
    """
    w, h = recording.system.receiver.image_size
    signal = np.asarray(recording.event_pixel)[np.asarray(recording.truth["label"]) == 1]
    illum = np.bincount(signal, minlength=w * h).reshape(h, w) > 0
    out = cloud_scores(result.cloud, scene, illum)
    tr = result.truth or {}
    out["recall"] = float(tr.get("recall", float("nan")))
    out["noise_rejection"] = float(tr.get("noise_rejection", float("nan")))
    return out


#: m: a point farther than max(3σ_r, this) from every true surface is false
FALSE_MIN = 0.1


def frame_scores(cloud, scene, lit) -> dict:
    """Each point of a frame scored against the scene at the point's own time ``t``.

    cloud : :class:`~mems_stereo.pipeline.cloud.PointCloud` with ``row``, ``pixel``,
    ``range``, ``sigma_r`` and ``t`` (s; a frame's cloud).  scene : a
    :class:`~mems_stereo.sim.scene.Scene`, moving or not (:mod:`mems_stereo.sim.motion`).
    lit : (H, W) bool, pixels with a true laser return among the frame's shots.

    Returns a dict of (N,) arrays ``error`` (m: range − the true surface's range on the
    ray through the point, capped at twice the point's distance to the nearest surface,
    as benchmarks/bench_scenarios.py), ``sigma`` (σ_r), ``object`` (the true surface's
    object, −1 none), ``false`` (bool: farther than max(3σ_r, :data:`FALSE_MIN`) from
    every surface), and ``coverage`` (lit pixels with a point that is not false / lit
    pixels), ``lit`` (their number), ``covered`` ((H, W) bool: the pixels with a point
    that is not false).
    """
    t = cloud["t"] if len(cloud) else np.zeros(0)
    hits = true_hits_at(scene, cloud.points, t)
    near = surface_distance_at(scene, cloud.points, t)
    err = (cloud["range"] - hits.range) if len(cloud) else np.zeros(0)
    with np.errstate(invalid="ignore"):
        err = np.sign(err) * np.minimum(np.abs(err), 2.0 * near)
    sig = cloud["sigma_r"] if len(cloud) else np.zeros(0)
    false = ~(near <= np.maximum(3.0 * sig, FALSE_MIN))
    good = np.zeros(np.shape(lit), bool)
    if len(cloud):
        good[cloud["row"][~false], cloud["pixel"][~false]] = True
    n_lit = int(np.sum(lit))
    return {"error": err, "sigma": sig, "object": hits.object, "false": false,
            "coverage": float(np.sum(good & lit) / n_lit) if n_lit else float("nan"),
            "lit": n_lit, "covered": good}
