"""The gated two-axis recording's detections against its recomputed gate
(mems_stereo.pipeline.gate_check): counted against a plain per-event loop over
the gate's CSR rows, on the samples and with the polarity inverted."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mems_stereo.errors import FormatError
from mems_stereo.io.recording2d import read_recording_2d
from mems_stereo.pipeline.gate_check import (
    SAMPLE_SHOTS,
    check_gate,
    gate_evidence,
    monitor_directions,
    recompute_gate,
)

SAMPLES = Path(__file__).resolve().parents[1] / "samples"


def _plain_count(rec, g, valid):
    """Detections inside the gate ``g`` (the recomputed gate: CSR rows per shot) of every
    shot, one event at a time."""
    inside = events = 0
    for s, p in zip(rec.event_shot[:3000], rec.event_pixel[:3000]):
        if not valid[s]:
            continue
        events += 1
        inside += p in set(g.pixels[g.offsets[s]:g.offsets[s + 1]].tolist())
    return inside, events


@pytest.fixture(scope="module")
def liss():
    return read_recording_2d(SAMPLES / "lissajous64.h5")


@pytest.mark.parametrize("invert", [(), (1,), (2,)])
def test_evidence_matches_a_plain_count(liss, invert):
    rec = replace(liss, event_shot=liss.event_shot[:3000], event_pixel=liss.event_pixel[:3000],
                  event_code=liss.event_code[:3000])
    d, valid = monitor_directions(rec, invert)
    gate = recompute_gate(rec, rec.system, d)  # computed once: both counts read it
    full = gate_evidence(rec, d, valid, gate)
    assert (full.inside, full.events) == _plain_count(rec, gate, valid)
    assert full.shots == int(valid.sum())
    if not invert:
        assert full.inside == full.events and full.counts_equal == full.shots


def test_sampled_evidence_estimates_the_share(liss):
    d, valid = monitor_directions(liss, (1,))
    full = gate_evidence(liss, d, valid, recompute_gate(liss, liss.system, d))
    part = gate_evidence(liss, d, valid)
    assert part.shots == SAMPLE_SHOTS
    p, n = full.fraction_inside, part.events
    assert abs(part.fraction_inside - p) < 5 * np.sqrt(p * (1 - p) / n)


def test_consistent_recording_passes_and_full_readout_is_not_checked(liss):
    ev = check_gate(liss, warn=pytest.fail)
    assert ev.fraction_inside == 1.0
    assert check_gate(replace(liss, readout={"mode": "full"})) is None


def test_detections_moved_off_the_gate_are_refused(liss):
    rng = np.random.default_rng(3)
    w, h = liss.system.receiver.image_size
    moved = replace(liss, event_pixel=rng.integers(0, w * h, liss.n_events))
    with pytest.raises(FormatError, match="/scanner/zero_crossings.*do not describe"):
        check_gate(moved)


def test_a_few_detections_off_the_gate_are_warned_about(liss):
    pix = liss.event_pixel.copy()
    pix[::50] = (pix[::50] + 17) % (64 * 64)
    said = []
    ev = check_gate(replace(liss, event_pixel=pix), warn=said.append)
    assert 0.9 < ev.fraction_inside < 0.999 and len(said) == 1 and "/events/pixel" in said[0]
