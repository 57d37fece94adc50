"""Safe HDF5 input: one way to open and read every HDF5 file the package reads.

* :func:`open_h5` refuses non-regular files (a FIFO would block), turns any
  HDF5 error into a :class:`~mems_stereo.errors.FormatError` naming the file,
  and, unless ``--allow-external`` (:func:`mems_stereo.util.limits.allow_external`),
  refuses external links, soft links that lead nowhere, datasets with external
  raw storage and virtual datasets (:class:`~mems_stereo.errors.UnsafeFileError`):
  a recording must not make the tool read another file of the host.
* :func:`dataset` checks a dataset before it is read: its chunk layout (chunks
  smaller than :data:`MIN_CHUNK_BYTES` on a dataset of many chunks make HDF5
  allocate per chunk and explode memory), its stored bytes against the file's
  real size, and its logical size against the memory budget when it is to be
  read whole (:func:`mems_stereo.util.limits.check_allocation`).
* :func:`read` reads a selection and turns a corrupt chunk (bad deflate
  stream, flipped bits) into a FormatError naming the dataset.
* :func:`attr_int` / :func:`attr_str` parse root attributes without ``int()``
  on arbitrary values.
"""

from __future__ import annotations

import math
import os

import h5py
import numpy as np

from mems_stereo.errors import FormatError, ShapeError, UnsafeFileError
from mems_stereo.util.limits import allow_external, check_allocation
from mems_stereo.util.paths import require_input_file

#: Smallest chunk (bytes) accepted on a dataset of more than :data:`MAX_SMALL_CHUNKS` chunks.
MIN_CHUNK_BYTES = 1024
MAX_SMALL_CHUNKS = 1024
#: Most objects (groups, datasets, links) walked when checking a file's links.
MAX_OBJECTS = 10000

_H5_ERRORS = (OSError, RuntimeError, ValueError, KeyError, TypeError, IndexError)
#: what h5py raises on malformed files (turned into FormatError by this module's callers)
H5_ERRORS = _H5_ERRORS


def _msg(e: BaseException) -> str:
    return (str(e).splitlines() or [type(e).__name__])[0][:160]


def open_h5(path: str | os.PathLike, field: str | None = None) -> h5py.File:
    """Open an HDF5 file read-only after the checks of this module; returns the File."""
    p = require_input_file(path, field)
    source = str(p)
    try:
        f = h5py.File(p, "r")
    except _H5_ERRORS as e:
        raise FormatError(f"cannot open as HDF5 ({_msg(e)})", source, field) from None
    try:
        if not allow_external():
            check_links(f, source)
    except BaseException:
        f.close()
        raise
    return f


def check_links(f: h5py.File, source: str) -> None:
    """Refuse external links, dangling soft links, external storage, virtual datasets."""
    stack = [f]
    seen = 0
    while stack:
        g = stack.pop()
        try:
            names = list(g.keys())
        except _H5_ERRORS as e:
            raise FormatError(f"cannot list the group ({_msg(e)})", source, g.name) from None
        for name in names:
            seen += 1
            if seen > MAX_OBJECTS:
                raise FormatError(f"more than {MAX_OBJECTS} objects (or a cycle of links)",
                                  source)
            full = f"{g.name.rstrip('/')}/{name}"
            try:
                link = g.get(name, getlink=True)
            except _H5_ERRORS as e:
                raise FormatError(f"cannot read the link ({_msg(e)})", source, full) from None
            if isinstance(link, h5py.ExternalLink):
                raise UnsafeFileError(f"external link to {link.filename}:{link.path} refused "
                                      "(--allow-external to follow it)", source, full)
            if isinstance(link, h5py.SoftLink):
                if link.path not in f:
                    raise FormatError(f"soft link to {link.path}, which does not exist",
                                      source, full)
                continue  # its target is checked where it lives
            try:
                obj = g[name]
            except _H5_ERRORS as e:
                raise FormatError(f"cannot open the object ({_msg(e)})", source, full) from None
            if isinstance(obj, h5py.Group):
                stack.append(obj)
            elif isinstance(obj, h5py.Dataset):
                if obj.is_virtual:
                    raise UnsafeFileError("virtual dataset refused: it maps data of other "
                                          "files (--allow-external to follow it)", source, full)
                if obj.external:
                    raise UnsafeFileError(f"external raw storage in {obj.external[0][0]!r} "
                                          "refused (--allow-external to follow it)",
                                          source, full)


def dataset(f: h5py.File, path: str, source: str, *, whole: bool = False) -> h5py.Dataset:
    """The dataset at ``path``, checked (layout, stored size; memory if read ``whole``)."""
    try:
        if path not in f:
            raise FormatError("required dataset is missing", source, path)
        obj = f[path]
    except _H5_ERRORS as e:
        raise FormatError(f"cannot open ({_msg(e)})", source, path) from None
    if not isinstance(obj, h5py.Dataset):
        raise FormatError(f"expected a dataset, found a {type(obj).__name__.lower()}",
                          source, path)
    check_layout(obj, source, path)
    if whole:
        nbytes = obj.size * max(obj.dtype.itemsize, 1) if obj.shape is not None else 0
        check_allocation(nbytes, f"reading {path} {obj.shape} {obj.dtype}", source)
    return obj


def check_layout(ds: h5py.Dataset, source: str, path: str) -> None:
    """Refuse chunk layouts that explode and storage beyond the file's real size."""
    if ds.shape is None:
        raise FormatError("expected data, found an empty (null) dataspace", source, path)
    if ds.chunks:
        chunk_bytes = math.prod(ds.chunks) * ds.dtype.itemsize
        n_chunks = math.prod(-(-n // c) for n, c in zip(ds.shape, ds.chunks))
        if n_chunks > MAX_SMALL_CHUNKS and chunk_bytes < MIN_CHUNK_BYTES:
            raise FormatError(f"chunks of {ds.chunks} ({chunk_bytes} bytes) make {n_chunks} "
                              f"chunks; expected chunks of at least {MIN_CHUNK_BYTES} bytes",
                              source, path)
    try:
        stored = ds.id.get_storage_size()
        real = os.fstat(ds.file.id.get_vfd_handle()).st_size
    except _H5_ERRORS:
        return
    if stored > real:
        raise FormatError(f"claims {stored} bytes of stored data, more than the file's "
                          f"{real} bytes (truncated or forged)", source, path)


def read(ds: h5py.Dataset, source: str, sel=()):
    """``ds[sel]``; a corrupt chunk becomes a FormatError naming the dataset."""
    try:
        return ds[sel]
    except _H5_ERRORS as e:
        raise FormatError(f"cannot read the data ({_msg(e)})", source, ds.name) from None


def require_shape(ds: h5py.Dataset, shape: tuple, source: str, text: str | None = None) -> None:
    """Refuse a dataset whose shape is not ``shape`` (None entries: any)."""
    ok = ds.ndim == len(shape) and all(s is None or s == n for s, n in zip(shape, ds.shape))
    if not ok:
        want = text or "(" + ", ".join("?" if s is None else str(s) for s in shape) + ")"
        raise ShapeError(f"expected shape {want}, found {ds.shape}", source, ds.name)


def _scalar(v):
    a = np.asarray(v)
    if a.shape not in ((), (1,)):
        return None
    return a.reshape(())[()]


_ABSENT = object()


def _root_attr(f: h5py.File, key: str, source: str):
    """Root attribute ``key`` as a scalar, or ``_ABSENT``; read errors become FormatError."""
    try:
        if key not in f.attrs:
            return _ABSENT
        return _scalar(f.attrs[key])
    except _H5_ERRORS as e:
        raise FormatError(f"cannot read the attribute ({_msg(e)})", source,
                          f"attrs/{key}") from None


def attr_int(f: h5py.File, key: str, source: str) -> int | None:
    """Integer root attribute ``key`` (None when absent); anything else is refused."""
    v = _root_attr(f, key, source)
    if v is _ABSENT:
        return None
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)):
        raise FormatError(f"expected an integer, found {v!r}", source, f"attrs/{key}")
    return int(v)


def attr_str(f: h5py.File, key: str, source: str) -> str | None:
    """String root attribute ``key`` (None when absent or not a string)."""
    v = _root_attr(f, key, source)
    if v is _ABSENT:
        return None
    if isinstance(v, bytes):
        try:
            return v.decode("utf-8")
        except UnicodeDecodeError:
            return None
    return v if isinstance(v, str) else None


def shown_attr(f: h5py.File, key: str) -> str:
    """Root attribute ``key`` as shown in an error message (repr, at most 60 characters)."""
    try:
        v = f.attrs[key] if key in f.attrs else None
    except Exception:  # noqa: BLE001 - only for the message
        return "an unreadable value"
    return repr(v)[:60]


def require_format(f: h5py.File, name: str, version: int, source: str) -> None:
    """The root attributes ``format`` = ``name`` and ``version`` = ``version``, or
    :class:`FormatError` naming ``attrs/format`` / ``attrs/version`` and what was found."""
    if attr_str(f, "format", source) != name:
        raise FormatError(f"expected attribute format = {name!r}, found "
                          f"{shown_attr(f, 'format')}", source, "attrs/format")
    try:
        ver = attr_int(f, "version", source)
    except FormatError:
        ver = None
    if ver != version:
        raise FormatError(f"expected attribute version = {version}, found "
                          f"{shown_attr(f, 'version')}", source, "attrs/version")
