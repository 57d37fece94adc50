"""Real photon data shipped as ``.npz`` (shared/realdata), validated on read.
"""

from __future__ import annotations

import numpy as np

from mems_stereo.errors import FormatError, ShapeError


def load_realdata_npz(path) -> dict:
    """Read an npz of the real-data layout (``timestamps_ps``, ``offsets``, ``shape``,
    ``gate_ps``) into plain arrays, validating the fields the estimators need."""
    import zipfile

    from mems_stereo.util.paths import require_input_file

    p = require_input_file(path)
    try:
        with np.load(p, allow_pickle=False) as z:
            missing = {"timestamps_ps", "offsets", "shape", "gate_ps"} - set(z.files)
            if missing:
                raise FormatError(f"missing arrays {sorted(missing)}", source=str(path))
            out = {k: z[k] for k in ("timestamps_ps", "offsets", "shape", "gate_ps")}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        if isinstance(e, FormatError):
            raise
        raise FormatError(f"not a readable npz file ({str(e)[:120]})", source=str(path)) \
            from None
    shp = out["shape"]
    if shp.shape != (2,) or shp.dtype.kind not in "iu" or np.any(shp < 1):
        raise ShapeError(f"expected two positive integers, found {shp.tolist()!r}"[:160],
                         source=str(path), field="shape")
    H, W = (int(v) for v in shp)
    if out["offsets"].size != H * W + 1:
        raise FormatError(f"expected {H * W + 1} offsets for shape {H}x{W}, found "
                          f"{out['offsets'].size}", source=str(path), field="offsets")
    return out
