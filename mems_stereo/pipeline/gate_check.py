"""A gated two-axis recording's detections against the gate recomputed from its monitors.

A gated recording (docs/formats.md §5, ``/readout attrs mode = "gated"``) was
read, shot by shot, only at the pixels of the epipolar band of the beam's
direction; the band follows from ``/system``, the ``/readout`` parameters and
the scan angles, which the monitors (``/scanner/zero_crossings``,
``/scanner/rising`` and those of ``/scanner/axis2``) give.  Recomputing the
gate with :func:`recompute_gate` must therefore put **every** detection
inside the pixels read in its shot, and give the per-shot pixel counts of
``/readout/count``.  Monitors that do not describe the trajectory the gate
was computed with break this: an inverted zero-crossing polarity mirrors
the scan angle about θ0 (the crossings stay alternating and spaced for
``f_mech``, so the format's checks cannot see it) and leaves only a small share of
the detections inside the recomputed gate.

:func:`gate_evidence` counts the detections inside the recomputed gate (on
all shots, or on a random sample of :data:`SAMPLE_SHOTS` shots, quick on any
recording); :func:`check_gate` refuses a recording with fewer than
:data:`REFUSE_INSIDE` of them inside (naming the monitor whose inverted
polarity explains the detections, where one does) and warns below
:data:`WARN_INSIDE`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from mems_stereo.errors import FormatError
from mems_stereo.geometry.gating import Gate, GateSpec, gate_pixels
from mems_stereo.io.recording2d import Recording2D
from mems_stereo.model.scanner2d import scan_angles_2d, scan_direction_2d
from mems_stereo.model.system import System

#: share of the detections inside the recomputed gate below which a recording is refused
REFUSE_INSIDE = 0.9
#: below this share a warning is given (a recording written by the gate's own
#: function has every detection inside: 1.0)
WARN_INSIDE = 0.999
#: shots sampled by :func:`gate_evidence` when no gate of every shot is given
SAMPLE_SHOTS = 4096

#: the monitors' polarity fields, by the axes inverted
_FIELDS = {(1,): "/scanner/rising", (2,): "/scanner/axis2/rising",
           (1, 2): "/scanner/rising and /scanner/axis2/rising"}


def recompute_gate(rec: Recording2D, system: System, d_scan: np.ndarray) -> Gate:
    """The gate a gated recording was read with, from its /readout parameters.

    d_scan : (K, 3) beam directions of the shots (NaN rows: unknown angle).
    """
    if rec.readout["mode"] != "gated":
        raise FormatError(f"expected a gated readout, found {rec.readout['mode']!r}",
                          rec.source, "/readout attrs/mode")
    spec = GateSpec(rec.readout["r_min"], rec.readout["r_max"], rec.readout["half_width"])
    return gate_pixels(system, d_scan, spec)


def monitor_directions(rec: Recording2D, invert: tuple[int, ...] = ()):
    """Beam directions (K, 3) (NaN rows where unknown) and valid (K,) bool of the
    recording's shots under its own ``/system``, with the zero-crossing polarity
    of the axes in ``invert`` (1: the fast axis, 2: axis 2) inverted."""
    rising = 1 - rec.rising if 1 in invert else rec.rising
    m2 = rec.monitor2
    if 2 in invert and m2.rising is not None:
        m2 = replace(m2, rising=1 - m2.rising)
    sc = rec.system.scanner
    th1, th2, valid = scan_angles_2d(rec.shot_time, rec.zero_crossings, rising, m2, sc)
    d = np.full((th1.size, 3), np.nan)
    if np.any(valid):
        d[valid] = scan_direction_2d(th1[valid], th2[valid], sc)
    return d, valid


@dataclass(frozen=True)
class GateEvidence:
    """Detections of a gated recording against its recomputed gate."""

    shots: int          # shots compared (of known angle)
    events: int         # their detections
    inside: int         # of which inside the recomputed gate
    counts_equal: int   # shots whose recomputed pixel count equals /readout/count

    @property
    def fraction_inside(self) -> float:
        return self.inside / self.events if self.events else 1.0

    def text(self) -> str:
        return (f"{self.inside} of {self.events} detections ({100 * self.fraction_inside:.1f} %) "
                f"lie inside the gate recomputed from the monitors, and {self.counts_equal} of "
                f"{self.shots} shots read the recomputed number of pixels (expected all)")


def gate_evidence(rec: Recording2D, d_scan: np.ndarray, valid: np.ndarray,
                  gate: Gate | None = None, seed: int = 0) -> GateEvidence:
    """Count the detections inside the recomputed gate.

    d_scan : (K, 3) beam directions, valid : (K,) bool (e.g. of :func:`monitor_directions`).
    gate : the recomputed gate of every shot, where already at hand; otherwise
    the gate of a random sample of :data:`SAMPLE_SHOTS` shots of known angle is
    computed.  Detections of shots of unknown angle are left out.
    """
    shots = np.flatnonzero(valid)
    if gate is None and shots.size > SAMPLE_SHOTS:
        shots = np.sort(np.random.default_rng(seed).choice(shots, SAMPLE_SHOTS, replace=False))
    if gate is None:
        gate = recompute_gate(rec, rec.system, d_scan[shots])
        counts = gate.counts()
    else:
        counts = gate.counts()[shots]
    ev_shot = np.asarray(rec.event_shot, np.int64)
    pos = np.minimum(np.searchsorted(shots, ev_shot), max(shots.size - 1, 0))
    mine = (shots[pos] == ev_shot) if shots.size else np.zeros(ev_shot.shape, bool)
    # shot numbers in the gate: positions in ``shots`` for a sampled gate, shot indices otherwise
    g_shot = pos[mine] if gate.n_shots == shots.size else ev_shot[mine]
    inside = gate.contains(g_shot, np.asarray(rec.event_pixel, np.int64)[mine])
    equal = int(np.count_nonzero(counts == np.asarray(rec.read_count)[shots]))
    return GateEvidence(int(shots.size), int(mine.sum()), int(inside.sum()), equal)


def check_gate(rec: Recording2D, d_scan: np.ndarray | None = None,
               valid: np.ndarray | None = None, gate: Gate | None = None,
               warn=None) -> GateEvidence | None:
    """Refuse a gated recording whose detections lie outside its recomputed gate.

    FormatError naming the monitor's polarity field where inverting it puts
    the detections inside, ``/scanner/zero_crossings`` otherwise; ``warn(text)``
    below :data:`WARN_INSIDE`.  Returns the evidence (None for a full readout).
    """
    if rec.readout.get("mode") != "gated":
        return None
    if d_scan is None or valid is None:
        d_scan, valid = monitor_directions(rec)
    ev = gate_evidence(rec, d_scan, valid, gate)
    if ev.fraction_inside >= REFUSE_INSIDE:
        if ev.fraction_inside < WARN_INSIDE and warn is not None:
            warn(f"{rec.source}: /events/pixel: {ev.text()}")
        return ev
    axes = (1, 2) if rec.monitor2.rising is not None else (1,)
    for inv in [(a,) for a in axes] + ([axes] if len(axes) == 2 else []):
        alt = gate_evidence(rec, *monitor_directions(rec, inv))
        if alt.fraction_inside >= REFUSE_INSIDE:
            raise FormatError(f"the zero-crossing polarity looks inverted: {ev.text()}; with "
                              f"it inverted {100 * alt.fraction_inside:.1f} % do",
                              rec.source, _FIELDS[inv])
    raise FormatError(f"the monitors do not describe the trajectory the recording was gated "
                      f"with: {ev.text()}", rec.source, "/scanner/zero_crossings")
