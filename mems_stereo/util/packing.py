"""Compact pickling of count arrays between processes (Dask): an array travels as its
non-zero entries where that is smaller than the dense array.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, slots=True)
class SparseArray:
    """An array as its non-zero entries: ``shape``, ``dtype`` (a NumPy dtype string),
    ``indices`` (N,) uint32 flat indices and ``values`` (N,) of that dtype."""

    shape: tuple[int, ...]
    dtype: str
    indices: np.ndarray
    values: np.ndarray

    def dense(self) -> np.ndarray:
        """The array itself."""
        a = np.zeros(int(np.prod(self.shape)), dtype=np.dtype(self.dtype))
        a[self.indices] = self.values
        return a.reshape(self.shape)


def pack_sparse(a: np.ndarray) -> np.ndarray | SparseArray:
    """``a`` as a :class:`SparseArray` where its non-zero entries take fewer bytes than
    ``a`` itself, else ``a``.

    >>> unpack_sparse(pack_sparse(np.array([0, 0, 0, 7, 0, 0]))).tolist()
    [0, 0, 0, 7, 0, 0]
    """
    nz = np.flatnonzero(a)
    if nz.size * (4 + a.itemsize) < a.nbytes and a.size < (1 << 32):
        return SparseArray(a.shape, a.dtype.str, nz.astype(np.uint32), a.ravel()[nz])
    return a


def unpack_sparse(x: np.ndarray | SparseArray) -> np.ndarray:
    """The array that :func:`pack_sparse` packed."""
    return x.dense() if isinstance(x, SparseArray) else x


def pack_histograms(h: dict[str, np.ndarray]) -> dict:
    """``{"raw", "signal", "noise"}`` int64 count histograms compacted for a transfer:
    raw and signal as uint32 where every count fits, each as :func:`pack_sparse`, and no
    noise (raw − signal); any other mapping as it is.  :func:`unpack_histograms`
    reverses it exactly."""
    if set(h) != {"raw", "signal", "noise"}:
        return dict(h)
    out = {}
    for k in ("raw", "signal"):
        a = h[k]
        if a.dtype == np.int64 and a.size and 0 <= a.min() and a.max() < 2 ** 32:
            a = a.astype(np.uint32)
        out[k] = pack_sparse(a)
    out["_packed"] = True
    return out


def unpack_histograms(h: dict) -> dict[str, np.ndarray]:
    """The int64 ``raw``, ``signal`` and ``noise`` histograms of :func:`pack_histograms`."""
    h = dict(h)
    if not h.pop("_packed", False):
        return h
    raw = unpack_sparse(h["raw"]).astype(np.int64)
    sig = unpack_sparse(h["signal"]).astype(np.int64)
    return {"raw": raw, "signal": sig, "noise": raw - sig}
