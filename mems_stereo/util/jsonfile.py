"""Field-by-field validation of JSON-like input, with messages that name the field.

Shared by the system description (:mod:`mems_stereo.model.system`) and the
simulator's scene files (:mod:`mems_stereo.sim.scene`): every failure is a
:class:`~mems_stereo.errors.FormatError` carrying the file, the dotted field
and what was expected and found, e.g.
``scene.json: objects[2].radius: expected a positive number, found -1``.
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np

from mems_stereo.errors import FormatError


def shown(value: Any) -> str:
    """A value as the user wrote it (JSON where possible)."""
    try:
        return json.dumps(value)
    except (TypeError, ValueError):
        return repr(value)


def parse_json(text: str, source: str) -> Any:
    """Parse JSON text; a syntax error names the source, line and column."""
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise FormatError(f"not valid JSON: {e.msg} (line {e.lineno}, column {e.colno})",
                          source=source) from None


def read_json_file(path) -> Any:
    """Read and parse a JSON file; errors name the file (and line, column)."""
    from pathlib import Path

    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as e:
        raise FormatError(f"cannot read file ({e.strerror})", source=str(p)) from None
    except UnicodeDecodeError:
        kind = " (an HDF5 file)" if p.read_bytes()[:8] == b"\x89HDF\r\n\x1a\n" else ""
        raise FormatError(f"expected a JSON text file, found binary data{kind}",
                          source=str(p)) from None
    return parse_json(text, str(p))


def _fmt_shape(shape: tuple) -> str:
    return "(" + ", ".join("D" if s is None else str(s) for s in shape) + ")"


class FieldChecker:
    """Validates values read from one source; ``fail`` builds the error."""

    def __init__(self, source: str):
        self.source = source

    def fail(self, fld: str, msg: str) -> FormatError:
        return FormatError(msg, source=self.source, field=fld)

    def req(self, d: Any, key: str, prefix: str) -> Any:
        """``d[key]``; the field must exist and ``d`` must be an object."""
        if not isinstance(d, dict):
            raise self.fail(prefix or "(top level)",
                            f"expected an object, found {type(d).__name__}")
        if key not in d:
            raise self.fail(f"{prefix}.{key}" if prefix else key, "required field is missing")
        return d[key]

    def number(self, v: Any, fld: str, *, positive: bool = False,
               nonneg: bool = False) -> float:
        """A finite number (optionally > 0 or >= 0)."""
        kind = "positive " if positive else ("non-negative " if nonneg else "")
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise self.fail(fld, f"expected a {kind}number, found {shown(v)}")
        if (positive and v <= 0) or (nonneg and v < 0):
            raise self.fail(fld, f"expected a {kind}number, found {shown(v)}")
        return float(v)

    def array(self, value: Any, fld: str, shape: tuple) -> np.ndarray:
        """Finite float64 numbers of the given shape (None: any length)."""
        try:
            a = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise self.fail(fld, f"expected numbers of shape {_fmt_shape(shape)}, "
                                 f"found {shown(value)}") from None
        if a.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, a.shape)):
            raise self.fail(fld, f"expected shape {_fmt_shape(shape)}, found {a.shape}")
        if not np.all(np.isfinite(a)):
            raise self.fail(fld, "expected finite numbers, found NaN or inf")
        return a
