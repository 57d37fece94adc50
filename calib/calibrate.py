"""Calibrate a system from flat-wall recordings (the user's entry points).

* :func:`calibrate_system` — recordings (paths or Recordings) + nominal system →
  :class:`~mems_stereo.calib.result.CalibrationResult`, or a
  :class:`~mems_stereo.calib.result.CalibrationFailure` that tests false and
  has no system;
* :func:`calibrate_scanner_camera` — the same in OpenCV calib3d's terms
  (a :class:`ScannerCameraCalibration`: RMS, system, σ, per target), raising
  on failure;
* :func:`read_target_distances` — measured wall distances from a JSON file.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass

from mems_stereo.calib.association import wall_data
from mems_stereo.calib.fit import fit_walls
from mems_stereo.calib.goodness import judge, name_failure
from mems_stereo.calib.result import CalibrationFailure, CalibrationResult

from mems_stereo.errors import FormatError, MemsStereoError, NotObservableError, OptionError
from mems_stereo.io.recording import Recording, read_recording
from mems_stereo.io.recording_checks import check_codes_fit
from mems_stereo.model.system import System, resolve_system


def _as_recording(r) -> Recording:
    if isinstance(r, Recording):
        return r
    return read_recording(r, truth=False)


def calibrate_system(recordings, system: System | str | os.PathLike | None = None, *,
                     fix=(), free=None, target_distances=None, distance_std=1e-3,
                     distance_kind: str = "axis", on_unobservable: str = "raise",
                     progress=None, model: str = "full",
                     **fit_kwargs) -> CalibrationResult | CalibrationFailure:
    """Estimate the system from recordings of flat walls, one wall per recording.

    Parameters
    ----------
    recordings : Recordings or paths of FORMAT v1 HDF5 files, one per wall pose.
    system : nominal System, preset name or JSON path (default: the first
        recording's ``/system``).  Only its fixed parts and the report's
        "nominal" column come from it: the start values are searched globally.
    fix, free : names of :data:`mems_stereo.calib.model.SYSTEM_PARAMS`.
    target_distances : per recording, the measured distance (m) of its wall
        (``distance_kind``: "axis" from the receiver's projection centre along
        the optical axis, "normal" perpendicular), or None where unknown.
    distance_std : σ of a measured distance, m (scalar or one per recording).
    on_unobservable : "raise" (a failure naming the parameter) or "warn".
    progress : optional callable(str) for status lines.
    model : "full" — the hardware terms the walls call for (trajectory harmonics of
        ``harmonics`` orders, the monitor's edge delay, per-pixel TDC offsets;
        :mod:`mems_stereo.calib.full_model`); "ideal" — today's model only.
    fit_kwargs : ``harmonics`` (orders tested, default 2–5); ``inflate_sigma``
        (default False): when the residuals show structure the model does not
        explain (:mod:`mems_stereo.calib.goodness`), return the result with σ
        inflated to cover it (and a warning) instead of a failure; the rest go to
        :func:`mems_stereo.calib.fit.fit_walls` (``jitter``, ``max_std``).

    Returns
    -------
    CalibrationResult (truthy; ``result.system`` carries the ``calibration``
    block) or CalibrationFailure (falsy; ``failure.reason`` says why, ``kind``
    is "input" or "estimate").

    Raises
    ------
    FormatError, ValueError : unreadable recordings or bad arguments.
    """
    t0 = time.perf_counter()
    recs = [_as_recording(r) for r in recordings]
    if not recs:
        raise ValueError("recordings: expected at least one recording")
    nominal = recs[0].system if system is None else resolve_system(system)
    if distance_kind not in ("axis", "normal"):
        raise ValueError(f"distance_kind: expected 'axis' or 'normal', found {distance_kind!r}")
    priors = []
    if target_distances is not None:
        if len(target_distances) != len(recs):
            raise ValueError(f"target_distances: expected {len(recs)} entries (one per "
                             f"recording), found {len(target_distances)}")
        stds = (list(distance_std) if isinstance(distance_std, (list, tuple))
                else [distance_std] * len(recs))
        for j, (d, sd) in enumerate(zip(target_distances, stds)):
            if d is None or not math.isfinite(d):
                continue
            if not (sd is not None and sd > 0):
                raise ValueError(f"distance_std: expected a positive σ (m), found {sd!r}")
            priors.append((j, distance_kind, float(d), float(sd)))
    walls = []
    for r in recs:
        check_codes_fit(r.bins, nominal.tdc.n_bins, r.source, file_bins=r.system.tdc.n_bins)
        if tuple(r.system.receiver.image_size) != tuple(nominal.receiver.image_size):
            raise FormatError(f"expected image_size {nominal.receiver.image_size} like the "
                              f"nominal system, found {r.system.receiver.image_size}", r.source)
        walls.append(wall_data(r))
        if nominal.tdc.code_widths is not None:  # measured code widths (code-density test)
            from mems_stereo.model.tdc import code_centres

            walls[-1].code_centres = code_centres(nominal.tdc)
    if progress:
        progress(f"read {len(walls)} recording(s), "
                 f"{sum(w.n_shots for w in walls)} shots with a known phase")
    inflate_sigma = bool(fit_kwargs.pop("inflate_sigma", False))
    harmonics = tuple(fit_kwargs.pop("harmonics", (2, 3, 4, 5)))
    if model not in ("ideal", "full"):
        raise OptionError(f"expected 'ideal' or 'full', found {model!r}", field="model")
    out = fit_walls(walls, nominal, free=free, fix=fix, priors=priors,
                    on_unobservable=on_unobservable, progress=progress, **fit_kwargs)
    if not out and model == "ideal":  # refused by another check: name a misfit too
        out = name_failure(out, walls, nominal, priors, fit_kwargs.get("jitter", 50e-12))
    if model == "full":
        from mems_stereo.calib.full_model import add_hardware_terms, rescue

        if not out and out.kind == "estimate":
            out = rescue(out, walls, nominal, priors, tuple(harmonics), progress, **fit_kwargs)
        if out:
            out = add_hardware_terms(out, tuple(harmonics), progress, **fit_kwargs)
    if out:
        out = judge(out, inflate_sigma)
    out.elapsed = time.perf_counter() - t0
    if out:
        from mems_stereo.calib.result import format_report

        out.report = format_report(out)
    return out


@dataclass(frozen=True, slots=True)
class ScannerCameraCalibration:
    """A calibration in OpenCV calib3d's terms (:func:`calibrate_scanner_camera`).

    Attributes
    ----------
    rms : dict {"pixel": px, "time": s}, RMS of the signal-weighted residuals.
    system : the calibrated System.
    std : dict name → σ (SI) of the estimated parameters.
    targets : per wall a dict (source, distance along the optical axis and its
        σ, tilt, signal photons per shot, consistency p-value, ...).
    """

    rms: dict
    system: System
    std: dict
    targets: list


def calibrate_scanner_camera(recordings, system=None, *, target_distances=None,
                             distance_std=1e-3, fix=(), free=None,
                             **kwargs) -> ScannerCameraCalibration:
    """Calibrate in OpenCV calib3d's terms: the RMS, the system, the σ, per target
    (``cv2.stereoCalibrate`` returns the RMS with the estimate), raising on failure.

    Raises
    ------
    NotObservableError : the recordings cannot determine the parameters (the
        failure's reason); MemsStereoError : any other failed estimate.
    """
    out = calibrate_system(recordings, system, target_distances=target_distances,
                           distance_std=distance_std, fix=fix, free=free, **kwargs)
    if not out:
        if out.kind == "input":
            raise NotObservableError(out.reason)
        raise MemsStereoError(out.reason)
    return ScannerCameraCalibration(out.rms, out.system, dict(out.std), list(out.targets))


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
    from mems_stereo.util.jsonfile import FieldChecker, check_schema, read_json_file
    from mems_stereo.util.schemas import DISTANCES_FIELDS

    src = str(path)
    doc = read_json_file(path)
    check_schema(doc, DISTANCES_FIELDS, FieldChecker(src))  # members and types
    if not isinstance(doc, dict) or doc.get("format") != DISTANCES_FORMAT:
        raise FormatError(f"expected format {DISTANCES_FORMAT!r}, found "
                          f"{doc.get('format') if isinstance(doc, dict) else type(doc).__name__!r}",
                          src, "format")
    kind = doc.get("kind", "axis")
    if kind not in ("axis", "normal"):
        raise FormatError(f"expected 'axis' or 'normal', found {kind!r}", src, "kind")
    std0 = doc.get("std", 1e-3 if default_std is None else default_std)
    if not isinstance(std0, (int, float)) or not math.isfinite(std0) or std0 <= 0:
        raise FormatError(f"expected a positive number (m), found {std0!r}", src, "std")
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
