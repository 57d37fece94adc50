"""Declarative shape and dtype checks for the top of public functions (kornia style).

::

    pts = check_shape(points, ("N", 3), "points")          # (N, 3) float64
    K = check_shape(camera_matrix, (3, 3), "camera_matrix")
    d = check_shape(dirs, ("...", 3), "directions")        # any leading axes

A dimension is an integer (exact size), a letter (any size, the same letter
must have the same size in one call when ``sizes`` is shared) or ``"..."``
(any number of leading axes, first entry only).  Every failure is a
:class:`~mems_stereo.errors.ShapeError` naming the argument, the expected and
the found shape.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mems_stereo.errors import ShapeError


def _fmt(shape: Sequence) -> str:
    inner = ", ".join(str(s) for s in shape)
    return f"({inner},)" if len(shape) == 1 else f"({inner})"


def check_shape(x, shape: Sequence, name: str, *, dtype=np.float64, finite: bool = False,
                sizes: dict | None = None) -> np.ndarray:
    """``x`` as an array of ``dtype`` (None: keep) whose shape matches ``shape``.

    ``sizes`` : dict shared between calls to tie named dimensions together
    (``{"N": 5}`` after the first call).  ``finite`` : refuse NaN/inf.
    """
    try:
        a = np.asarray(x) if dtype is None else np.asarray(x, dtype=dtype)
    except (TypeError, ValueError):
        raise ShapeError(f"{name}: expected numbers of shape {_fmt(shape)}, found "
                         f"{type(x).__name__}") from None
    spec = list(shape)
    lead = bool(spec) and spec[0] == "..."
    if lead:
        spec = spec[1:]
    found = a.shape[a.ndim - len(spec):] if lead else a.shape
    if (a.ndim < len(spec)) if lead else (a.ndim != len(spec)):
        raise ShapeError(f"{name}: expected shape {_fmt(shape)}, found {a.shape}")
    sizes = {} if sizes is None else sizes
    for want, n in zip(spec, found):
        if isinstance(want, str):
            if sizes.setdefault(want, n) != n:
                raise ShapeError(f"{name}: expected shape {_fmt(shape)} with {want} = "
                                 f"{sizes[want]}, found {a.shape}")
        elif want != n:
            raise ShapeError(f"{name}: expected shape {_fmt(shape)}, found {a.shape}")
    if finite and a.dtype.kind in "fc" and not np.all(np.isfinite(a)):
        raise ShapeError(f"{name}: expected finite values, found NaN or inf")
    return a


def check_dtype(x, kinds: str, name: str, expected: str) -> np.ndarray:
    """``x`` as an array whose dtype kind is one of ``kinds`` (``"iu"``, ``"f"``)."""
    a = np.asarray(x)
    if a.dtype.kind not in kinds:
        raise ShapeError(f"{name}: expected {expected}, found dtype {a.dtype}")
    return a
