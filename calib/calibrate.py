"""Calibrate a system from flat-target recordings: classify → fit → reclassify → refit.

The classifier (:func:`mems_stereo.classify.classify_bins`) needs a system to
tell signal from noise; a miscalibrated one rejects true returns at the edges
of its bounds.  So the detections are classified with the nominal system,
the fit (:func:`calib.fit.fit_detections`) estimates a better one, and the
recordings are classified again with it, until the estimates stop moving
(change < 0.1 σ) or ``n_iter`` rounds are done.
"""

from __future__ import annotations

import os
import warnings

import numpy as np

from mems_stereo.classify import classify_bins
from mems_stereo.recording import Recording, read_recording
from mems_stereo.scanner import phase_from_zero_crossings, scan_angle_from_phase
from mems_stereo.system import System, resolve_system

from .detections import detections_from_labels
from .fit import CalibrationResult, fit_detections, format_report


def _as_recording(r) -> Recording:
    if isinstance(r, Recording):
        return r
    return read_recording(r, truth=False)


def calibrate_system(recordings, system: System | str | os.PathLike | None = None, *,
                     fix=(), free=None, target_distances=None, distance_std: float = 1e-3,
                     confidence: float = 0.997, n_iter: int = 3,
                     on_unobservable: str = "raise", progress=None,
                     **fit_kwargs) -> CalibrationResult:
    """Estimate the system from recordings of a flat target at several poses.

    Parameters
    ----------
    recordings : Recordings or paths of FORMAT v1 HDF5 files, one per target pose.
    system : nominal System, preset name or JSON path (default: the first
        recording's ``/system``).
    fix, free : see :func:`calib.fit.fit_detections` (names of
        :data:`calib.model.SYSTEM_PARAMS`).
    target_distances : per recording, the known distance (m) of its target
        plane from the receiver's projection centre, or None where unknown.
    distance_std : σ of a known distance, m.
    confidence : of the classifier's consistency test.
    n_iter : classify/fit rounds (at least 1).
    on_unobservable : "raise" or "warn".
    progress : optional callable(str) for status lines.
    fit_kwargs : passed to :func:`calib.fit.fit_detections`.

    Returns
    -------
    :class:`~calib.fit.CalibrationResult`; ``result.system`` carries the
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
        for r, (ph, ok) in zip(recs, phases):
            theta = scan_angle_from_phase(ph, current.scanner)
            labels = classify_bins(current, r.bins, theta, ok, confidence)
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
