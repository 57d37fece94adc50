"""Stage 1 of a run: the scan angle θ of every shot, from the recording's
zero crossings (:func:`mems_stereo.model.scanner.scan_angles`), in blocks.
"""

from __future__ import annotations

import numpy as np

from mems_stereo.model.scanner import scan_angles
from mems_stereo.model.system import System


def shot_angles(header, system: System, block: int = 1 << 20):
    """(theta, valid) of every shot of a recording header, from its zero crossings.

    Computed in blocks of shots so the temporaries stay small for long recordings.
    """
    t = header.shot_time
    theta = np.empty(t.shape, np.float64)
    valid = np.empty(t.shape, bool)
    for a in range(0, t.size, block):
        theta[a:a + block], valid[a:a + block] = scan_angles(
            t[a:a + block], header.zero_crossings, header.rising, system.scanner)
    return theta, valid
