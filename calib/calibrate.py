"""Calibrate a system from flat-target recordings: classify → fit → reclassify → refit.

The classifier (:mod:`mems_stereo.pipeline.intervals`, the pipeline's) needs a system to
tell signal from noise; a miscalibrated one rejects true returns at the edges
of its bounds.  So the detections are classified with the nominal system,
the fit (:func:`mems_stereo.calib.fit.fit_detections`) estimates a better one, and the
recordings are classified again with it, until the estimates stop moving
(change < 0.1 σ) or ``n_iter`` rounds are done.
"""

from __future__ import annotations

import math
import os
import warnings

import numpy as np
from mems_stereo.calib.detections import detections_from_labels
from mems_stereo.calib.fit import CalibrationResult, fit_detections, format_report

from mems_stereo.io.recording import Recording, read_recording
from mems_stereo.model.scanner import phase_from_zero_crossings, scan_angle_from_phase
from mems_stereo.model.system import System, resolve_system
from mems_stereo.pipeline.intervals import interval_table
from mems_stereo.pipeline.pass1 import classify_and_accumulate


def _as_recording(r) -> Recording:
    if isinstance(r, Recording):
        return r
    return read_recording(r, truth=False)


def calibrate_system(recordings, system: System | str | os.PathLike | None = None, *,
                     fix=(), free=None, target_distances=None, distance_std=1e-3,
                     distance_kind: str = "axis", confidence: float = 0.997, n_iter: int = 3,
                     on_unobservable: str = "raise", progress=None,
                     **fit_kwargs) -> CalibrationResult:
    """Estimate the system from recordings of a flat target at several poses.

    Parameters
    ----------
    recordings : Recordings or paths of FORMAT v1 HDF5 files, one per target pose.
    system : nominal System, preset name or JSON path (default: the first
        recording's ``/system``).
    fix, free : see :func:`mems_stereo.calib.fit.fit_detections` (names of
        :data:`mems_stereo.calib.model.SYSTEM_PARAMS`).
    target_distances : per recording, the measured distance (m) of its target
        from the receiver's projection centre along the optical axis
        (``distance_kind="axis"``, see :func:`read_target_distances`), or
        None where unknown.
    distance_std : σ of a measured distance, m (scalar or one per recording).
    distance_kind : "axis" or "normal" (:func:`mems_stereo.calib.fit.known_distance_model`).
    confidence : of the classifier's consistency test.
    n_iter : classify/fit rounds (at least 1).
    on_unobservable : "raise" or "warn".
    progress : optional callable(str) for status lines.
    fit_kwargs : passed to :func:`mems_stereo.calib.fit.fit_detections`.

    Returns
    -------
    :class:`~mems_stereo.calib.fit.CalibrationResult`; ``result.system`` carries the
    ``calibration`` block, ``result.extra["classification"]`` the signal
    counts of each round.
    """
    recs = [_as_recording(r) for r in recordings]
    if not recs:
        raise ValueError("recordings: expected at least one recording")
    nominal = recs[0].system if system is None else resolve_system(system)
    phases = [phase_from_zero_crossings(r.shot_time, r.zero_crossings, r.rising) for r in recs]
    current = nominal
    result = None
    history = []
    for it in range(max(1, int(n_iter))):
        targets = []
        counts = []
        # the compiled interval-table classifier of the pipeline (labels identical
        # to mems_stereo.pipeline.consistency.classify_bins on angles snapped to 50 µrad)
        table = interval_table(current, confidence)
        for r, (ph, ok) in zip(recs, phases):
            theta = scan_angle_from_phase(ph, current.scanner)
            labels = classify_and_accumulate(r.bins, np.where(ok, theta, 0.0), ok, table,
                                             current.tdc.n_bins)[0]
            targets.append(detections_from_labels(ph, ok, r.bins, labels, source=r.source))
            counts.append(targets[-1].n_detections)
        history.append(counts)
        if progress:
            progress(f"round {it + 1}: signal detections per recording {counts}")
        start = {n: current.get_param(n) for n in (result.names if result else [])}
        with warnings.catch_warnings():
            if it > 0:  # said once, in the first round
                warnings.simplefilter("ignore")
            new = fit_detections(targets, nominal, fix=fix, free=free,
                                 known_distances=target_distances, distance_std=distance_std,
                                 distance_kind=distance_kind,
                                 on_unobservable=on_unobservable, initial_values=start,
                                 **fit_kwargs)
        # report against the nominal start, not this round's start
        new.initial = {n: nominal.get_param(n) for n in new.names}
        moved = (max(abs(new.values[n] - result.values[n]) / max(new.std[n], 1e-300)
                     for n in new.names) if result is not None else np.inf)
        result = new
        current = new.system
        if moved < 0.1:
            break
    result.system = result.system.replace(calibration=result.calibration_dict())
    result.extra["classification"] = history
    result.extra["rounds"] = len(history)
    result.report = format_report(result)
    return result


DISTANCES_FORMAT = "mems-stereo/target-distances"


def read_target_distances(path, recordings, default_std: float | None = None):
    """Measured target distances of the given recordings from a JSON file.

    The file (``samples/calib_distances.json`` is an example)::

        {"format": "mems-stereo/target-distances", "version": 1,
         "kind": "axis", "std": 0.002,
         "targets": [{"recording": "calib_1.5m.h5", "distance": 1.494}, ...]}

    ``kind`` "axis": distance (m) from the receiver's projection centre to
    the target along the receiver's optical axis (camera z); "normal": the
    target plane's perpendicular distance.  ``std`` (m): σ of a measurement
    (a target entry may give its own ``std``).  Entries are matched to the
    recordings by file name (``recording``, without directories), so the
    file works from any working directory.

    Parameters
    ----------
    path : the JSON file.
    recordings : paths (or Recordings with ``source``) in the order given to
        :func:`calibrate_system`.
    default_std : σ (m) where the file gives none (default 0.001).

    Returns
    -------
    (distances, stds, kind): lists with one entry per recording (None / the
    default σ where the file has no entry), and the file's ``kind``.

    Raises
    ------
    FormatError : not such a file, a bad field, or no recording matched.
    """
    from pathlib import Path

    from mems_stereo.errors import FormatError
    from mems_stereo.util.jsonfile import read_json_file

    src = str(path)
    doc = read_json_file(path)
    if not isinstance(doc, dict) or doc.get("format") != DISTANCES_FORMAT:
        raise FormatError(f"expected format {DISTANCES_FORMAT!r}, found "
                          f"{doc.get('format') if isinstance(doc, dict) else type(doc).__name__!r}",
                          src, "format")
    kind = doc.get("kind", "axis")
    if kind not in ("axis", "normal"):
        raise FormatError(f"expected 'axis' or 'normal', found {kind!r}", src, "kind")
    std0 = doc.get("std", 1e-3 if default_std is None else default_std)
    entries = doc.get("targets")
    if not isinstance(entries, list):
        raise FormatError("expected a list of {recording, distance[, std]}", src, "targets")
    table = {}
    for i, e in enumerate(entries):
        fld = f"targets[{i}]"
        if not isinstance(e, dict) or "recording" not in e or "distance" not in e:
            raise FormatError("expected an object with 'recording' and 'distance'", src, fld)
        d, sd = e["distance"], e.get("std", std0)
        for name, v in (("distance", d), ("std", sd)):
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise FormatError(f"expected a positive number (m), found {v!r}", src,
                                  f"{fld}.{name}")
        table[Path(str(e["recording"])).name] = (float(d), float(sd))
    names = [Path(getattr(r, "source", r) if isinstance(r, Recording) else r).name
             for r in recordings]
    dists = [table.get(n, (None, None))[0] for n in names]
    stds = [table.get(n, (None, float(std0)))[1] for n in names]
    if all(d is None for d in dists):
        raise FormatError(f"expected an entry for at least one of the recordings {names}, "
                          f"found entries for {sorted(table)}", src, "targets")
    return dists, stds, kind
