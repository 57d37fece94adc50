"""The package's disk cache: tables that take a noticeable time to compute and
depend only on the package's source and the library versions.

The folder is ``$MEMS_STEREO_CACHE`` (default ``~/.cache/mems-stereo``; ``off``,
``0`` or empty turn the cache off).  Files are written atomically and read
defensively: an unreadable, stale or foreign file is recomputed, never trusted
(keys hash everything the content depends on).
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np


def cache_dir() -> Path | None:
    """Folder of the disk cache (``$MEMS_STEREO_CACHE``, default ``~/.cache/mems-stereo``);
    None when ``MEMS_STEREO_CACHE`` is ``off``, ``0`` or empty."""
    v = os.environ.get("MEMS_STEREO_CACHE")
    if v is None:
        return Path.home() / ".cache" / "mems-stereo"
    if v.strip().lower() in ("", "0", "off", "no", "false"):
        return None
    return Path(v)


def source_key(*parts) -> str:
    """A 32-hex-digit key of ``parts`` (bytes, str, or anything with a stable repr)
    and the NumPy version."""
    h = hashlib.sha256(np.__version__.encode())
    for p in parts:
        h.update(p if isinstance(p, bytes) else (p if isinstance(p, str) else repr(p)).encode())
        h.update(b"\0")
    return h.hexdigest()[:32]


def cached_arrays(name: str, key: str, compute: Callable[[], dict]) -> dict:
    """Arrays ``compute()`` returns (a dict of name → ndarray), from the disk cache
    file ``{name}-{key}.npz`` when it holds them all, else computed and saved
    (best effort: a cache that cannot be written is skipped silently)."""
    d = cache_dir()
    path = None if d is None else d / f"{name}-{key}.npz"
    if path is not None and path.is_file():
        try:
            with np.load(path, allow_pickle=False) as z:
                return {k: z[k] for k in z.files}
        except Exception:  # noqa: BLE001 - an unreadable cache file is recomputed
            pass
    out = compute()
    if path is not None:
        try:
            from mems_stereo.util.atomic import atomic_output

            path.parent.mkdir(parents=True, exist_ok=True)
            with atomic_output(path, suffix=".npz") as tmp, open(tmp, "wb") as f:
                np.savez(f, **out)
        except OSError:
            pass
    return out
