"""Resource and safety limits of one run: the memory budget and external data.

Readers check every size they derive from a file against the file's real size
and against the memory budget *before* allocating (:func:`check_allocation`),
so that a small file claiming huge arrays fails at once with a
:class:`~mems_stereo.errors.ResourceError` instead of exhausting memory.

The budget defaults to half of the machine's physical memory; the command
line sets it with ``--max-memory`` (``4G``, ``512M``, bytes) through
:func:`limits`, as it sets ``--allow-external`` (follow HDF5 external
storage, external links and virtual datasets, and scene meshes outside the
scene's folder: refused by default).
"""

from __future__ import annotations

import contextlib
import math
import os
import re
from collections.abc import Iterator

from mems_stereo.errors import OptionError, ResourceError

_state: dict = {"max_memory": None, "allow_external": False}
_UNITS = {"": 1, "B": 1, "K": 1 << 10, "M": 1 << 20, "G": 1 << 30, "T": 1 << 40}


def physical_memory() -> int:
    """Bytes of physical memory (8 GiB when the system does not tell)."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 8 << 30


def max_memory() -> int:
    """The memory budget of the run, bytes (default: half the physical memory)."""
    m = _state["max_memory"]
    return int(m) if m is not None else physical_memory() // 2


def allow_external() -> bool:
    """Whether data outside the input files may be followed (``--allow-external``)."""
    return bool(_state["allow_external"])


def parse_size(text: str, option: str = "--max-memory") -> int:
    """Bytes of a size such as ``4G``, ``512M``, ``1.5G``, ``1000000`` (binary units)."""
    m = re.fullmatch(r"\s*([0-9]+(?:\.[0-9]*)?)\s*([KMGT]?)(?:i?B)?\s*", str(text), re.I)
    if not m:
        raise OptionError(f"expected a size such as 4G, 512M or a number of bytes, found "
                          f"{text!r}", field=option)
    v = float(m.group(1)) * _UNITS[m.group(2).upper()]
    if not math.isfinite(v) or v < 1 << 20:
        raise OptionError(f"expected at least 1M, found {text!r}", field=option)
    return int(v)


@contextlib.contextmanager
def limits(max_memory: int | None = None, allow_external: bool | None = None) -> Iterator[None]:
    """Set the memory budget and the external-data switch inside a ``with`` block."""
    old = dict(_state)
    if max_memory is not None:
        _state["max_memory"] = int(max_memory)
    if allow_external is not None:
        _state["allow_external"] = bool(allow_external)
    try:
        yield
    finally:
        _state.update(old)


def fmt_bytes(n: float) -> str:
    """``1.3 GiB``-style text of a byte count."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(n) < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} TiB"  # pragma: no cover


def check_allocation(nbytes: float, what: str, source: str | None = None,
                     field: str | None = None) -> None:
    """Refuse an allocation of ``nbytes`` above the memory budget.

    ``what`` says what would be allocated ("the histograms (H, W, n_bins)").
    """
    budget = max_memory()
    if not nbytes <= budget:
        prefix = ": ".join(str(p) for p in (source, field) if p)
        raise ResourceError(f"{prefix + ': ' if prefix else ''}{what} would need "
                            f"{fmt_bytes(nbytes)}, above the memory budget of "
                            f"{fmt_bytes(budget)} (--max-memory)")
