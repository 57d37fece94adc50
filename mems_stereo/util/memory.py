"""Freed heap memory handed back to the OS between the stages of a run.

NumPy's temporaries below glibc's (growing) mmap threshold come from the heap, and
freed heap pages stay resident: without a trim the peak memory of a run adds each
stage's temporaries to the freed ones of the stage before.  The drivers wrap their
stages with :class:`HeapTrimmer`; the stages themselves know nothing of it.
"""

from __future__ import annotations

import ctypes
import functools
from typing import TypeVar

T = TypeVar("T")


@functools.cache
def _malloc_trim():
    """glibc's ``malloc_trim``, or None where there is none."""
    try:
        return ctypes.CDLL("libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return None


def release_freed_memory() -> bool:
    """Return the heap memory freed so far to the OS (glibc's ``malloc_trim(0)``; a
    no-op where there is none); returns whether it ran.

    One call costs milliseconds, unlike ``MALLOC_TRIM_THRESHOLD_``, which trims at
    every free."""
    trim = _malloc_trim()
    if trim is None:
        return False
    trim(0)
    return True


class HeapTrimmer:
    """Trims the heap after each stage it wraps, where ``enabled`` (large runs: a
    small one has nothing to gain).

    >>> HeapTrimmer(False).after(41) + 1
    42
    """

    __slots__ = ("enabled",)

    def __init__(self, enabled: bool):
        self.enabled = bool(enabled)

    def after(self, result: T) -> T:
        """``result`` (a stage's), the heap trimmed once the stage has returned it."""
        if self.enabled:
            release_freed_memory()
        return result
