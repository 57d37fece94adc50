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


#: JSON descriptions are small; a larger file is refused before it is read.
MAX_JSON_BYTES = 16 << 20
#: Deepest nesting accepted (FORMAT v1 files nest 4 deep).
MAX_JSON_DEPTH = 64


def _no_duplicates(pairs):
    d = {}
    for k, v in pairs:
        if k in d:
            raise _Duplicate(k)
        d[k] = v
    return d


class _Duplicate(Exception):
    pass


def _bad_constant(name):
    raise _Constant(name)


class _Constant(Exception):
    pass


def _depth(text: str) -> int:
    """Deepest bracket nesting of JSON text (strings skipped), without recursion."""
    depth = best = 0
    in_str = esc = False
    for ch in text:
        if in_str:
            if esc:
                esc = False
            elif ch == "\\":
                esc = True
            elif ch == '"':
                in_str = False
        elif ch == '"':
            in_str = True
        elif ch in "[{":
            depth += 1
            best = max(best, depth)
        elif ch in "]}":
            depth -= 1
    return best


def parse_json(text: str, source: str) -> Any:
    """Parse JSON text; a syntax error names the source, line and column.

    Refused as well, each with a :class:`FormatError` naming the source:
    duplicate keys in one object, the non-standard constants NaN/Infinity,
    nesting deeper than :data:`MAX_JSON_DEPTH` and integers too long to
    convert (Python's 4300-digit limit).
    """
    if _depth(text) > MAX_JSON_DEPTH:
        raise FormatError(f"JSON nested deeper than {MAX_JSON_DEPTH} levels", source=source)
    try:
        return json.loads(text, object_pairs_hook=_no_duplicates, parse_constant=_bad_constant)
    except json.JSONDecodeError as e:
        raise FormatError(f"not valid JSON: {e.msg} (line {e.lineno}, column {e.colno})",
                          source=source) from None
    except _Duplicate as e:
        raise FormatError(f"duplicate key {e.args[0]!r} in one object", source=source) from None
    except _Constant as e:
        raise FormatError(f"not valid JSON: {e.args[0]} is not a JSON number", source=source) \
            from None
    except (ValueError, RecursionError) as e:  # over-long integers, pathological nesting
        raise FormatError(f"not valid JSON: {str(e).splitlines()[0][:120]}", source=source) \
            from None


def read_json_file(path) -> Any:
    """Read and parse a UTF-8 JSON file; errors name the file (and line, column).

    The path must be a regular file (:func:`~mems_stereo.util.paths.require_input_file`)
    of at most :data:`MAX_JSON_BYTES`.
    """
    from mems_stereo.util.paths import require_input_file

    try:
        p = require_input_file(path)
    except FileNotFoundError:
        raise FormatError("cannot read file (file not found)", source=str(path)) from None
    try:
        size = p.stat().st_size
        if size > MAX_JSON_BYTES:
            raise FormatError(f"a JSON description of {size} bytes, above the limit of "
                              f"{MAX_JSON_BYTES} bytes", source=str(p))
        data = p.read_bytes()
    except OSError as e:
        raise FormatError(f"cannot read file ({e.strerror})", source=str(p)) from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        if data[:8] == b"\x89HDF\r\n\x1a\n":
            raise FormatError("expected a JSON text file, found binary data (an HDF5 file)",
                              source=str(p)) from None
        raise FormatError(f"not UTF-8 text (byte {e.start}: {e.reason}); JSON files must be "
                          "UTF-8", source=str(p)) from None
    if text.startswith("\ufeff"):
        text = text[1:]
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
