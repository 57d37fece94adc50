"""Where a frame removes the expected bias of its peaks' mean scan angles.

A peak's stereo is taken at its detections' mean scan angle less that angle's expected
bias (:func:`~mems_stereo.pipeline.first_photon_correction.mean_angle_bias`: the shots
bunch towards the scan's turning points, the band and the accepted codes cut the
footprint).  A recording processed as one cloud removes it only where it exceeds k of
the mean angle's own σ (:func:`~mems_stereo.pipeline.peak_estimates.peak_means_of`):
below that the correction is within the noise and rests on the
system's geometry.  A frame is not the end of the averaging: the temporal fusion
(:mod:`~mems_stereo.pipeline.temporal`) averages the frames' noise down by √age but not
a bias they share, which is the same in every frame of a static pixel (the frames of a
recording visit the same angles).  At the wall columns next to the turning points of
the paper's system the dwell skew is 2–5 steps (5–15 cm at 6 m), below a frame's σ
(about 20 cm) and far above twenty fused frames' (about 5 cm).  Frames therefore remove
every peak's expected bias: :func:`every_bias_removed` around the frame's processing
(:func:`~mems_stereo.pipeline.frames.frame_cloud`); its residual, the correction's own
allowance, is the fusion's shared error
(:func:`~mems_stereo.pipeline.temporal.shared_errors`).
"""

from __future__ import annotations

import contextvars
from collections.abc import Iterator
from contextlib import contextmanager

_EVERY_BIAS = contextvars.ContextVar("every_bias_removed", default=False)


@contextmanager
def every_bias_removed() -> Iterator[None]:
    """Within the block, the peak means remove every peak's expected mean-angle bias
    (see the module)."""
    token = _EVERY_BIAS.set(True)
    try:
        yield
    finally:
        _EVERY_BIAS.reset(token)


def removing_every_bias() -> bool:
    """Whether the peak means remove every expected mean-angle bias here."""
    return _EVERY_BIAS.get()
