"""Compiled forms of plain-Python kernels, made only where numba is imported already.

A dense run imports numba for pass 1's kernels; the later stages then use compiled
forms of their loops too. A small recording never imports numba and runs the NumPy
forms, so its start-up stays short.
"""

from __future__ import annotations

import sys

_KERNELS: dict = {}


def compiled_if_loaded(py_func):
    """The numba form of ``py_func`` (``njit(cache=True, nogil=True,
    boundscheck=False)``, made once per function) where numba is imported already,
    else None."""
    if py_func not in _KERNELS:
        if "numba" not in sys.modules:
            return None
        import numba

        _KERNELS[py_func] = numba.njit(cache=True, nogil=True, boundscheck=False)(py_func)
    return _KERNELS[py_func]
