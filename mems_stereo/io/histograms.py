"""Histogram files (HDF5): raw, signal and noise TDC histograms per pixel.

Format ``"mems-stereo/histograms"`` version 1 (docs/visualisation.md):

============================ ====================== ===============================
path                         type, shape            meaning
============================ ====================== ===============================
attrs ``format``/``version`` str, int               ``"mems-stereo/histograms"``, 1
``/raw``                     int32 (H, W, n_bins)   counts of every detection per TDC
                                                    code (bin b holds code b + 1)
``/signal``                  int32 (H, W, n_bins)   counts of detections classified signal
``/noise``                   int32 (H, W, n_bins)   counts of detections classified noise
other root attrs             scalars / str          free metadata (``bin_width`` in s,
                                                    ``source`` recording, ...)
============================ ====================== ===============================

All three datasets have the same shape; (W, n_bins) input is stored as
(1, W, n_bins).  Writes are atomic.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mems_stereo.errors import FormatError, ShapeError
from mems_stereo.util.atomic import atomic_output

FORMAT_NAME = "mems-stereo/histograms"
FORMAT_VERSION = 1
DATASETS = ("raw", "signal", "noise")


@dataclass(frozen=True, slots=True)
class Histograms:
    """The contents of a histogram file (:func:`read_histograms`).

    Attributes
    ----------
    raw : (H, W, n_bins) int32, counts of every detection per TDC code (bin b
        holds code b + 1).
    signal : (H, W, n_bins) int32, counts of the detections classified signal.
    noise : (H, W, n_bins) int32, counts of the detections classified noise.
    attrs : the file's other root attributes (``bin_width`` in s, ``source``, ...).
    """

    raw: np.ndarray
    signal: np.ndarray
    noise: np.ndarray
    attrs: dict = field(default_factory=dict)


def _as_hwb(name: str, a, source: str) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim == 2:
        a = a[None]
    if a.ndim != 3:
        raise ShapeError(f"expected shape (H, W, n_bins) or (W, n_bins), found {a.shape}",
                         source=source, field=f"/{name}")
    if not (np.issubdtype(a.dtype, np.integer) or a.dtype == np.bool_):
        raise FormatError(f"expected integer counts, found dtype {a.dtype}",
                          source=source, field=f"/{name}")
    if a.size and (a.min() < 0 or a.max() > np.iinfo(np.int32).max):
        raise FormatError("counts must lie in 0..2**31-1", source=source, field=f"/{name}")
    return a.astype(np.int32)


def write_histograms(path: str | os.PathLike, raw, signal, noise,
                     attrs: dict | None = None) -> Path:
    """Write raw/signal/noise count histograms, each (H, W, n_bins) or (W, n_bins) int.

    ``attrs``: extra root attributes (numbers or strings), e.g. ``bin_width`` (s).
    Returns the path.
    """
    import h5py

    path = Path(path)
    arrays = {n: _as_hwb(n, a, str(path)) for n, a in zip(DATASETS, (raw, signal, noise))}
    shapes = {a.shape for a in arrays.values()}
    if len(shapes) != 1:
        raise ShapeError(f"raw, signal and noise must have one shape, found "
                          f"{[a.shape for a in arrays.values()]}", source=str(path))
    with atomic_output(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["format"] = FORMAT_NAME
        f.attrs["version"] = FORMAT_VERSION
        for k, v in (attrs or {}).items():
            if k in ("format", "version"):
                continue
            f.attrs[k] = v
        for n, a in arrays.items():
            f.create_dataset(n, data=a, compression="gzip", compression_opts=4, shuffle=True)
    return path


def read_histograms(path: str | os.PathLike) -> Histograms:
    """Read a histogram file: :class:`Histograms` of (H, W, n_bins) int32 arrays.

    Raises FileNotFoundError when missing and FormatError naming the dataset
    when the file does not follow the format.
    """
    from mems_stereo.io import hdf5 as h5

    path = Path(path)
    source = str(path)
    with h5.open_h5(path) as f:
        h5.require_format(f, FORMAT_NAME, FORMAT_VERSION, source)
        out = []
        for n in DATASETS:
            ds = h5.dataset(f, f"/{n}", source, whole=True)
            if ds.ndim not in (2, 3):
                raise ShapeError(f"expected shape (H, W, n_bins) or (W, n_bins), found "
                                 f"{ds.shape}", source, f"/{n}")
            out.append(_as_hwb(n, h5.read(ds, source), source))
        attrs = {}
        for k in f.attrs:
            if k in ("format", "version"):
                continue
            v = h5.attr_str(f, k, source)
            attrs[k] = v if v is not None else f.attrs[k]
    if len({a.shape for a in out}) != 1:
        raise ShapeError(f"raw, signal and noise must have one shape, found "
                         f"{[a.shape for a in out]}", source=source)
    return Histograms(out[0], out[1], out[2], attrs)
