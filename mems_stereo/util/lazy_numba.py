"""The package's compiled (numba) kernels, made in one place and kept for the process.

Every kernel is a plain-Python function (its name ends in ``_py``) that is also its
reference semantics; its numba form is made here on first use, with numba's disk
cache.  Two ways to ask for it:

* :func:`compiled_kernel` — compile (importing numba) where the caller has decided that
  compiling pays (pass 1 of a large recording);
* :func:`compiled_if_loaded` — only where numba is imported already: a dense run
  imports numba for pass 1's kernels and the later stages then use compiled forms of
  their loops too, while a small recording never imports numba and runs the NumPy
  forms, so its start-up stays short.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Mapping

#: numba options of every kernel
KERNEL_OPTIONS = {"cache": True, "nogil": True, "boundscheck": False}

#: the compiled form of each kernel (None: numba is not installed), by its Python form
_KERNELS: dict = {}


def _compile(py_func, helpers: Mapping[str, Callable]):
    try:
        import numba
    except ImportError:  # pragma: no cover - numba is a declared dependency
        return None
    # a kernel calls its helpers by their global names: numba resolves them when it
    # compiles the kernel, so the names are bound to the helpers' inlined forms first
    for name, helper in helpers.items():
        py_func.__globals__[name] = numba.njit(cache=True, inline="always")(helper)
    return numba.njit(**KERNEL_OPTIONS)(py_func)


def compiled_kernel(py_func, helpers: Mapping[str, Callable] | None = None):
    """The numba form of ``py_func``, compiled (or loaded from numba's disk cache) on
    first use; None where numba is not installed.

    ``helpers`` : ``{global name: Python function}`` that the kernel calls; the name is
    rebound to the helper's compiled form before the kernel compiles."""
    if py_func not in _KERNELS:
        _KERNELS[py_func] = _compile(py_func, helpers or {})
    return _KERNELS[py_func]


def compiled_if_loaded(py_func):
    """The numba form of ``py_func`` where numba is imported already, else None."""
    if py_func not in _KERNELS and "numba" not in sys.modules:
        return None
    return compiled_kernel(py_func)
