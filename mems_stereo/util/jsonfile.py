"""Field-by-field validation of JSON-like input, with messages that name the field.

Shared by the system description (:mod:`mems_stereo.model.system`) and the
simulator's scene files (:mod:`mems_stereo.sim.scene`): every failure is a
:class:`~mems_stereo.errors.FormatError` carrying the file, the dotted field
and what was expected and found, e.g.
``scene.json: objects[2].radius: expected a positive number, found -1``.
"""

from __future__ import annotations

import difflib
import json
import math
import numbers
from dataclasses import dataclass
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


# --------------------------------------------------------------------------
# declared schemas: one mechanism for every JSON file kind the package reads


@dataclass(frozen=True)
class Field:
    """The declared spec of one member of a JSON object.

    Attributes
    ----------
    type : JSON type(s), ``"|"``-separated: ``number``, ``integer``, ``string``,
        ``boolean``, ``array``, ``object``, ``null``.
    required : the member must be present.
    unit : SI unit (``""``: none; for the documentation).
    doc : one line for the documentation.
    const : the only value accepted (``format``, ``version``).
    fields : the members of an object value (checked strictly, recursively).
    items : the spec of each element of an array value.
    values : the spec of each member of an object whose keys are free (names).
    variants : ``(key, {value: fields})``: an object whose members depend on
        its ``key`` member (the scene's object ``type``).
    expect : what a wrong type is told it should be (default from ``type``),
        e.g. "a positive number" where the reader will also check the sign.
    """

    type: str
    required: bool = False
    unit: str = ""
    doc: str = ""
    const: Any = None
    fields: dict | None = None
    items: Field | None = None
    values: Field | None = None
    variants: tuple | None = None
    expect: str = ""


_TYPE_WORDS = {"number": "a number", "integer": "an integer", "string": "a string",
               "boolean": "true or false", "array": "a list", "object": "an object",
               "null": "null"}


def _is_type(v: Any, t: str) -> bool:
    if t == "number":
        return isinstance(v, numbers.Real) and not isinstance(v, bool)
    if t == "integer":
        return isinstance(v, numbers.Integral) and not isinstance(v, bool)
    if t == "string":
        return isinstance(v, str)
    if t == "boolean":
        return isinstance(v, bool)
    if t == "array":
        return isinstance(v, (list, tuple, np.ndarray))
    if t == "object":
        return isinstance(v, dict)
    return v is None  # "null"


def edit_distance(a: str, b: str, limit: int | None = None) -> int:
    """Optimal-string-alignment distance: insertions, deletions, substitutions and
    transpositions of neighbours each count 1.

    With ``limit`` only the band ``|i − j| <= limit`` is computed and any distance
    above ``limit`` is returned as ``limit + 1`` (exact up to ``limit``; a typo
    check needs no more).
    """
    big = len(a) + len(b) + 1
    band = big if limit is None else limit
    if abs(len(a) - len(b)) > band:
        return band + 1
    prev2: list[int] = []
    prev = [j if j <= band else big for j in range(len(b) + 1)]
    for i, ca in enumerate(a, 1):
        lo, hi = max(1, i - band), min(len(b), i + band)
        cur = [big] * (len(b) + 1)
        cur[0] = i if i <= band else big
        for j in range(lo, hi + 1):
            cb = b[j - 1]
            v = min(prev[j] + 1, cur[j - 1] + 1, prev[j - 1] + (ca != cb))
            if i > 1 and j > 1 and ca == b[j - 2] and a[i - 2] == cb:
                v = min(v, prev2[j - 2] + 1)
            cur[j] = v
        if limit is not None and min(cur[max(0, lo - 1):hi + 1]) > limit:
            return limit + 1
        prev2, prev = prev, cur
    return prev[-1] if limit is None else min(prev[-1], limit + 1)


def closest_key(key: str, known) -> str | None:
    """The known key nearest ``key`` (a typo of it), or None when none is near."""
    key = str(key)
    low = key.lower()
    best, best_d = None, None
    for k in known:
        limit = max(1, min(len(k), len(key)) // 4)
        if abs(len(k) - len(key)) > limit:  # the distance is at least the length change
            continue
        d = edit_distance(low, k.lower(), limit)
        if d <= limit and (best_d is None or d < best_d):
            best, best_d = k, d
    if best is None:
        close = difflib.get_close_matches(key, list(known), n=1, cutoff=0.75)
        best = close[0] if close else None
    return best


def _join(prefix: str, key: str) -> str:
    return f"{prefix}.{key}" if prefix else key


def check_schema(d: Any, fields: dict, ck: FieldChecker, prefix: str = "") -> None:
    """Validate the object ``d`` against declared ``fields`` (:class:`Field`), strictly.

    In this order: ``const`` members (``format``, ``version``: a file of
    another kind is named as such); missing required members (naming a
    present unknown key that is a near miss); unknown members (refused with
    the closest known key); the type of every member, recursively.  Value
    ranges, shapes and cross-field rules stay with each reader.
    """
    if not isinstance(d, dict):
        raise ck.fail(prefix or "(top level)", f"expected an object, found {shown(d)}")
    for name, f in fields.items():
        if f.const is not None and name in d and not (
                d[name] == f.const and type(d[name]) is type(f.const)):
            raise ck.fail(_join(prefix, name), f"expected {f.const!r}, found {shown(d[name])}")
    unknown = [k for k in d if k not in fields]
    for name, f in fields.items():
        if f.required and name not in d:
            near = [k for k in unknown if closest_key(k, [name]) == name]
            hint = f"; found {near[0]} — did you mean {name}?" if near else ""
            raise ck.fail(_join(prefix, name), f"required field is missing{hint}")
    for k in unknown:
        near = closest_key(k, fields)
        hint = (f"did you mean {near}?" if near
                else f"expected one of {', '.join(fields)}")
        raise ck.fail(_join(prefix, str(k)), f"unknown field; {hint}")
    for name, v in d.items():
        check_value(v, fields[name], ck, _join(prefix, name))


def check_value(v: Any, f: Field, ck: FieldChecker, fld: str) -> None:
    """Check one value against its :class:`Field` (type, then members or items)."""
    types = f.type.split("|")
    if not any(_is_type(v, t) for t in types):
        want = f.expect or " or ".join(_TYPE_WORDS[t] for t in types)
        raise ck.fail(fld, f"expected {want}{f' ({f.unit})' if f.unit else ''}, found {shown(v)}")
    if isinstance(v, dict):
        if f.variants is not None:
            key, table = f.variants
            kind = v.get(key)
            if isinstance(kind, str) and kind in table:
                check_schema(v, table[kind], ck, fld)
            elif key in v:
                raise ck.fail(f"{fld}.{key}", f"expected one of {', '.join(table)}, "
                                              f"found {shown(kind)}")
            else:
                union: dict = {}
                for members in table.values():
                    union.update(members)
                check_schema(v, union, ck, fld)
        elif f.fields is not None:
            check_schema(v, f.fields, ck, fld)
        elif f.values is not None:
            for k, x in v.items():
                check_value(x, f.values, ck, f"{fld}.{k}")
    elif f.items is not None and isinstance(v, (list, tuple)):
        for i, x in enumerate(v):
            check_value(x, f.items, ck, f"{fld}[{i}]")
