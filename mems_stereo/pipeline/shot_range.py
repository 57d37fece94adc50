"""A range of a recording's shots and the scan angles they are processed with."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, slots=True)
class ShotRange:
    """Shots ``[start, stop)`` of a recording and their scan angles.

    theta : (n,) float64 rad and valid : (n,) bool, the scan angles of the shots from
    shot ``angle_offset`` on (default 0: the whole recording, indexed by shot);
    start, stop : the range (``stop`` None: to the end of ``theta``).  Pass 1
    (:func:`~mems_stereo.pipeline.pass1.accumulate_range`) and pass 2
    (:func:`~mems_stereo.pipeline.pass2.peak_counts_range`) run over one.
    """

    theta: np.ndarray
    valid: np.ndarray
    start: int = 0
    stop: int | None = None
    angle_offset: int = 0

    @property
    def n_shots(self) -> int:
        """Shots in the range (``stop`` None: those of ``theta`` from ``start`` on)."""
        stop = self.stop if self.stop is not None else (
            self.start + len(self.theta) - self.angle_offset)
        return stop - self.start

    def angles(self, s0: int, s1: int) -> tuple[np.ndarray, np.ndarray]:
        """``(theta, valid)`` of shots ``[s0, s1)`` of the recording."""
        a, b = s0 - self.angle_offset, s1 - self.angle_offset
        return self.theta[a:b], self.valid[a:b]
