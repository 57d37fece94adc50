"""The statistics of an import's first seconds and the verdicts on its mapping.

:func:`analyse_import` imports the first ``seconds`` of an event stream into
a temporary recording (removed afterwards), counts the events by kind and
channel, measures how the detections fit the scan geometry under the map as
written, with the monitor's polarity inverted and with the columns reversed
(McNemar's paired counts, as :mod:`mems_stereo.cli._crosscheck` does for a
recording's polarity), and hands the statistics to the pure checks of
:mod:`mems_stereo.io.import_checks`.
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from mems_stereo.errors import FormatError
from mems_stereo.io import hdf5 as h5
from mems_stereo.io.import_checks import (
    CAUSE_IMPORT,
    ImportSample,
    PairedEvidence,
    Verdict,
    count_events,
    first_seconds,
    import_verdicts,
    map_verdicts,
)
from mems_stereo.io.recording import read_header
from mems_stereo.io.tttr import StreamInfo, events_to_recording
from mems_stereo.io.tttr_map import TttrMap
from mems_stereo.model.system import System

#: at most this many shot × pixel values enter the geometric evidence (memory bound)
EVIDENCE_VALUES = 1 << 22
#: interval tables by system (JSON), for repeated imports in one process
_TABLES: dict = {}


@dataclass(frozen=True)
class ImportAnalysis:
    """sample : the statistics (None when the first seconds do not import);
    verdicts : refusals first, then warnings; error : the conversion's error when the
    first seconds do not import, naming the input file (or the map for its fields)."""

    sample: ImportSample | None
    verdicts: list
    error: FormatError | None = None

    @property
    def refusals(self) -> list:
        return [v for v in self.verdicts if v.refuse]

    @property
    def warnings(self) -> list:
        return [v for v in self.verdicts if not v.refuse]


def _map_field(e: FormatError) -> str:
    """The map field behind an error of the conversion."""
    f = str(e.field or "")
    if f.startswith("/scanner"):
        return "zero_crossings"
    if f.startswith("/shots"):
        return "shot_clock"
    return f or "pixels"


def _named_error(e: FormatError, sample_path: Path, source: str,
                 map_source: str) -> FormatError:
    """A conversion error named against the input file or the map, never against the
    temporary recording."""
    if e.source is None and str(e.field or "").startswith("pixels"):
        return FormatError(e.reason, map_source, e.field)
    if e.source is not None and Path(e.source) == sample_path:
        # found while the recording was assembled: the input (or its mapping) is at fault
        return FormatError(f"the recording built from it with {map_source} is invalid: "
                           f"{e.field}: {e.reason}", source)
    return e


def analyse_import(open_blocks: Callable[[], Iterable], info: StreamInfo, m: TttrMap,
                   system: System, seconds: float, source: str = "",
                   map_source: str = "the map") -> ImportAnalysis:
    """Import the first ``seconds`` of a stream to a temporary file; its statistics
    and the verdicts of :func:`mems_stereo.io.import_checks.import_verdicts`.

    The map's ``shots`` selection is not applied (photons before ``shots.first``
    are skipped on purpose, not lost to a wiring fault).  A stream whose first
    seconds do not convert (no shots, fewer than two zero
    crossings, ...) gives the conversion's error as a refusal (cause
    ``not importable``) besides the map's own verdicts.  The geometric
    evidence (polarity, column order) is measured only when no cheaper check
    refuses the map.
    """
    blocks = first_seconds(open_blocks, info, seconds)
    events = count_events(blocks())
    # the wiring is checked on every shot of the first seconds: ``shots`` only selects
    m_s = replace(m, n_shots=None, first_shot=0)
    with tempfile.TemporaryDirectory(prefix="mems-stereo-import-") as d:
        path = Path(d) / "first_seconds.h5"
        try:
            stats = events_to_recording(blocks, info, m_s, system, path, compression=None,
                                        source=source)
            with h5.open_h5(path) as f:
                t = h5.read(h5.dataset(f, "/shots/time", str(path)), str(path))
                zc = h5.read(h5.dataset(f, "/scanner/zero_crossings", str(path)), str(path))
            sample = ImportSample(
                seconds, int(t.size), float(t[-1] - t[0]) if t.size else 0.0, info.sync_rate,
                system.laser.f_rep, int(zc.size), float(zc[-1] - zc[0]), system.scanner.f_mech,
                stats, events, info.micro_unit, system.tdc.bin_width, mode=info.mode,
                macro_unit=info.macro_unit)
            verdicts = import_verdicts(sample, m)
            if not any(v.refuse for v in verdicts):  # the geometric evidence where needed
                polarity, reversed_cols = wiring_evidence(path)
                sample = replace(sample, polarity=polarity, reversed_columns=reversed_cols)
                verdicts = import_verdicts(sample, m)
        except FormatError as e:
            return ImportAnalysis(None, map_verdicts(m) + [
                Verdict(True, _map_field(e), CAUSE_IMPORT, e.reason)],
                _named_error(e, path, source, map_source))
    return ImportAnalysis(sample, verdicts)


def _shots_read(valid: np.ndarray, per_shot: int) -> np.ndarray:
    """Shots of known angle, evenly thinned to :data:`EVIDENCE_VALUES` values."""
    idx = np.flatnonzero(valid)
    cap = max(1, EVIDENCE_VALUES // max(per_shot, 1))
    if idx.size > cap:
        idx = idx[np.linspace(0, idx.size - 1, cap).astype(np.int64)]
    return idx


def _table(system: System):
    """The run's interval table of ``system`` (default settings): kept for the
    process's next import of the same system, rows shared through the disk cache."""
    from mems_stereo.model.system import system_to_json
    from mems_stereo.pipeline.intervals import IntervalTable
    from mems_stereo.pipeline.settings import Settings

    key = system_to_json(system)
    if key not in _TABLES:
        if len(_TABLES) >= 4:
            _TABLES.pop(next(iter(_TABLES)))
        table = IntervalTable.for_settings(system, Settings())
        table.load_cache()
        _TABLES[key] = table
    return _TABLES[key]


def wiring_evidence(path) -> tuple[PairedEvidence | None, PairedEvidence | None]:
    """Paired evidence of a (one-axis) recording's detections: the monitor's polarity
    inverted, and the columns in reverse order, each against the data as recorded.

    A detection counts where its code lies inside the interval the run accepts
    for its pixel and scan angle (the default consistency settings).  Returns
    ``(polarity, reversed_columns)``; None where no shot has a known angle.
    """
    from mems_stereo.pipeline.angles import shot_angles

    head = read_header(path)
    s = head.system
    K, H, W = head.shape
    theta, valid = shot_angles(head, s)
    idx = _shots_read(valid, H * W)
    if idx.size == 0:
        return None, None
    runs = np.split(idx, np.flatnonzero(np.diff(idx) != 1) + 1)  # consecutive shots
    with h5.open_h5(path) as f:
        ds = h5.dataset(f, "/shots/bins", str(path))
        b = np.concatenate([h5.read(ds, str(path), slice(int(r[0]), int(r[-1]) + 1))
                            for r in runs]).astype(np.int64)
    th = theta[idx]
    table = _table(s)
    inside = {}
    for name, angle in (("as mapped", th), ("inverted", 2 * s.scanner.theta0 - th)):
        rows = table.rows(angle, np.ones(angle.shape, bool))
        table.ensure(rows)
        on = (rows >= 0)[:, None]
        lo = np.where(on, table.lo[rows].astype(np.int64), 1).reshape(-1, H, W)
        hi = np.where(on, table.hi[rows].astype(np.int64), 0).reshape(-1, H, W)
        inside[name] = (b > 0) & (b >= lo) & (b <= hi)
        if name == "as mapped":
            rb = b[:, :, ::-1]
            inside["reversed"] = (rb > 0) & (rb >= lo) & (rb <= hi)
    table.save_cache()
    base = inside["as mapped"]

    def paired(alt):
        return PairedEvidence(int((base & ~alt).sum()), int((alt & ~base).sum()))

    return paired(inside["inverted"]), paired(inside["reversed"])
