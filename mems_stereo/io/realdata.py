"""Real photon data shipped as ``.npz`` (shared/realdata), validated on read.
"""

from __future__ import annotations

import numpy as np

from mems_stereo.errors import FormatError


def load_realdata_npz(path) -> dict:
    """Read an npz of the real-data layout (``timestamps_ps``, ``offsets``, ``shape``,
    ``gate_ps``) into plain arrays, validating the fields the estimators need."""
    with np.load(path) as z:
        missing = {"timestamps_ps", "offsets", "shape", "gate_ps"} - set(z.files)
        if missing:
            raise FormatError(f"missing arrays {sorted(missing)}", source=str(path))
        out = {k: z[k] for k in ("timestamps_ps", "offsets", "shape", "gate_ps")}
    H, W = (int(v) for v in out["shape"])
    if out["offsets"].size != H * W + 1:
        raise FormatError(f"expected {H * W + 1} offsets for shape {H}x{W}, found "
                          f"{out['offsets'].size}", source=str(path), field="offsets")
    return out
