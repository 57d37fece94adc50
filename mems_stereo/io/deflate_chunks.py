"""Reading gzip'd HDF5 chunks with libdeflate: the same bytes, faster than zlib.

A dense recording's ``/shots/bins`` is gzip'd (HDF5's deflate filter, zlib
format) in chunks of whole shots; inflating them is most of the cost of
reading the file.  Where the system has libdeflate (``libdeflate.so.0``,
loaded with :mod:`ctypes`; no Python package needed), :func:`chunk_reader`
reads the compressed chunks as stored (``read_direct_chunk``) and inflates
them with ``libdeflate_zlib_decompress`` straight into the output array: the
same bytes (deflate is lossless; tested against h5py), in about half the time.

Only the simple layout is taken this way — chunks that span every dimension
but the first, the deflate filter alone, an integer type in the
machine's byte order; anything else (no libdeflate, other filters, a chunk the filter mask
says was stored raw, a chunk never written, a decompression error) is read
by h5py, as before, so a corrupt chunk still raises h5py's error.
"""

from __future__ import annotations

import ctypes
import ctypes.util

import numpy as np

#: HDF5's identifier of the deflate (gzip) filter
H5Z_FILTER_DEFLATE = 1

_LIB: list = []


def libdeflate():
    """The libdeflate library with its decompressor, or None where it is missing."""
    if not _LIB:
        lib = None
        for name in ("libdeflate.so.0", ctypes.util.find_library("deflate")):
            if not name:
                continue
            try:
                lib = ctypes.CDLL(name)
                lib.libdeflate_alloc_decompressor.restype = ctypes.c_void_p
                lib.libdeflate_alloc_decompressor.argtypes = []
                lib.libdeflate_zlib_decompress.restype = ctypes.c_int
                lib.libdeflate_zlib_decompress.argtypes = [
                    ctypes.c_void_p, ctypes.c_char_p, ctypes.c_size_t, ctypes.c_void_p,
                    ctypes.c_size_t, ctypes.POINTER(ctypes.c_size_t)]
                break
            except (OSError, AttributeError):
                lib = None
        _LIB.append(lib)
    return _LIB[0]


class ChunkReader:
    """Rows ``[s0, s1)`` of a chunked, deflate-only dataset, inflated by libdeflate
    (see the module docstring); build it with :func:`chunk_reader`."""

    def __init__(self, ds, lib):
        self.ds = ds
        self.lib = lib
        self.rows = int(ds.chunks[0])
        self.shape = tuple(ds.shape)
        self.dtype = ds.dtype
        self.row_items = int(np.prod(self.shape[1:], dtype=np.int64))
        self._chunk = np.empty(self.rows * self.row_items, self.dtype)  # edge chunks
        self._got = ctypes.c_size_t()
        # one decompressor per reader: libdeflate's are not shared between threads
        self._dec = lib.libdeflate_alloc_decompressor()
        if not self._dec:  # pragma: no cover - out of memory
            raise MemoryError("libdeflate_alloc_decompressor")

    def _inflate(self, k0: int, out: np.ndarray) -> bool:
        """Chunk from row ``k0`` inflated into ``out`` (contiguous, a whole chunk's
        items); False where h5py must read it instead."""
        try:
            mask, raw = self.ds.id.read_direct_chunk((k0,) + (0,) * (len(self.shape) - 1))
        except Exception:  # noqa: BLE001 - a chunk never written, or unreadable: h5py's turn
            return False
        if mask != 0:  # the filter was skipped for this chunk: stored as is
            return False
        r = self.lib.libdeflate_zlib_decompress(self._dec, raw, len(raw), out.ctypes.data,
                                                out.nbytes, ctypes.byref(self._got))
        return r == 0 and self._got.value == out.nbytes

    def read(self, s0: int, s1: int) -> np.ndarray:
        """``ds[s0:s1]`` (a new array), inflated here where it can, else by h5py."""
        out = np.empty((s1 - s0,) + self.shape[1:], self.dtype)
        flat = out.reshape(-1)
        c = self.rows
        for k0 in range((s0 // c) * c, s1, c):
            a, b = max(s0, k0), min(s1, k0 + c)  # rows of this chunk that are wanted
            if a == k0 and b == k0 + c:  # the whole chunk: straight into the output
                dst = flat[(a - s0) * self.row_items:(b - s0) * self.row_items]
                if self._inflate(k0, dst):
                    continue
            elif self._inflate(k0, self._chunk):
                flat[(a - s0) * self.row_items:(b - s0) * self.row_items] = \
                    self._chunk[(a - k0) * self.row_items:(b - k0) * self.row_items]
                continue
            out[a - s0:b - s0] = self.ds[a:b]
        return out

    def __del__(self):
        dec, self._dec = getattr(self, "_dec", None), None
        if dec and self.lib is not None:
            self.lib.libdeflate_free_decompressor(ctypes.c_void_p(dec))


def chunk_reader(ds) -> ChunkReader | None:
    """A :class:`ChunkReader` of the h5py dataset ``ds`` where libdeflate can inflate
    its chunks (chunks of whole rows, the deflate filter alone, an integer type
    in the machine's byte order), else None (read it with h5py)."""
    lib = libdeflate()
    if lib is None or ds.chunks is None or ds.ndim < 1:
        return None
    if tuple(ds.chunks[1:]) != tuple(ds.shape[1:]):
        return None
    dt = ds.dtype  # the file's type: its bytes are the stored ones where it is native
    if dt.kind not in "ui" or not dt.isnative:
        return None
    plist = ds.id.get_create_plist()
    if plist.get_nfilters() != 1 or plist.get_filter(0)[0] != H5Z_FILTER_DEFLATE:
        return None
    return ChunkReader(ds, lib)
