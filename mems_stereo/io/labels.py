"""Event labels (FORMAT v1): the label values and the labels file writer.
"""

from __future__ import annotations

import os
from pathlib import Path

import h5py
import numpy as np

from mems_stereo.errors import ShapeError
from mems_stereo.util.atomic import atomic_output

#: Label values of FORMAT v1 event labels.
LABEL_NONE, LABEL_SIGNAL, LABEL_NOISE = 0, 1, 2


def write_labels(path: str | os.PathLike, label, theta) -> Path:
    """Write event labels (FORMAT v1 outputs): ``/label`` uint8 [K,H,W], ``/theta`` [K]."""
    lab = np.asarray(label, dtype=np.uint8)
    th = np.asarray(theta, dtype=np.float64)
    if lab.ndim != 3 or th.shape != (lab.shape[0],):
        raise ShapeError(f"labels: expected (K, H, W) and (K,), found {lab.shape}, {th.shape}")
    with atomic_output(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["format"] = "mems-stereo/labels"
        f.attrs["version"] = 1
        f.create_dataset("label", data=lab, compression="gzip")
        f.create_dataset("theta", data=th)
    return Path(path)
