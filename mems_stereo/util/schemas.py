"""The declared schema of every JSON file kind the package reads.

One :class:`~mems_stereo.util.jsonfile.Field` per member; every reader calls
:func:`~mems_stereo.util.jsonfile.check_schema` with its kind's fields before
it reads values, so unknown members are refused with the closest known key,
a missing required member names a near-miss key that is present, and types
are checked.  Value ranges, shapes and cross-field rules stay with each
reader.  ``docs/formats.md`` ("Schemas") is generated from these tables
(:func:`schema_markdown`; ``tests/test_json_schemas.py`` compares them).

Kinds (:data:`SCHEMAS`): ``system`` (``mems-stereo/system``), ``tttr-map``
(``mems-stereo/tttr-map``), ``target-distances``
(``mems-stereo/target-distances``) and ``scene`` (``mems-stereo/scene``).  Not a file:
:data:`LIVE_MESSAGE_FIELDS`, the JSON header of a ZeroMQ live message (``mems-stereo/live``,
its table in docs/live.md).
"""

from __future__ import annotations

from mems_stereo.util.jsonfile import Field

__all__ = ["DISTANCES_FIELDS", "LIVE_MESSAGE_FIELDS", "MAP_FIELDS", "SCENE_FIELDS", "SCHEMAS",
           "SYSTEM_FIELDS", "schema_markdown"]

_NUMBERS = "array"  # numbers in nested lists; shapes are checked by the readers


def _positive(unit: str, doc: str, required: bool = True) -> Field:
    """A number the reader requires > 0."""
    return Field("number", required, unit, doc, expect="a positive number")

# ------------------------------------------------------------------ system

AXIS2_FIELDS = {
    "mode": Field("string", True, doc='"resonant" (Lissajous) or "quasistatic" (raster)'),
    "axis": Field(_NUMBERS, True, doc="3 numbers: unit rotation axis a2, world frame, "
                                      "perpendicular to e1 × e2"),
    "theta0": Field("number", True, "rad", "rest angle of axis 2"),
    "f_mech": _positive("Hz", "resonance, or the triangle's repetition rate"),
    "theta_mech_max": _positive("rad", "mechanical amplitude"),
    "phase_offset": Field("number", False, "rad", "lag behind the axis' monitor (default 0)"),
    "gimbal": Field("string", False, doc='"outer2" (default) or "outer1"'),
    "coupling": Field("number", False, "rad/rad", "mechanical crosstalk (default 0)"),
}

_STD = "σ where estimated (default: unknown)"

HARMONIC_FIELDS = {
    "order": Field("integer", True, doc="harmonic order k >= 2 of the scan phase"),
    "amplitude": Field("number", True, "rel.", "A_k relative to theta_mech_max "
                                              "(0.003 = 0.3 %)"),
    "phase": Field("number", False, "rad", "ψ_k of A_k cos(k φ + ψ_k) (default 0)"),
    "amplitude_std": Field("number", False, "rel.", _STD),
    "phase_std": Field("number", False, "rad", _STD),
}

MONITOR_FIELDS = {
    "rising_delay": Field("number", True, "s", "delay of a recorded rising crossing"),
    "falling_delay": Field("number", True, "s", "delay of a recorded falling crossing"),
    "rising_delay_std": Field("number", False, "s", _STD),
    "falling_delay_std": Field("number", False, "s", _STD),
}

PULSE_SHAPE_FIELDS = {
    "model": Field("string", True, doc='"ex-gaussian" (Gaussian core + exponential tail) '
                                       'or "table" (measured response)'),
    "tail_fraction": Field("number", False, doc="ex-gaussian: share w of the tail, [0, 1)"),
    "tail_decay": Field("number", False, "s", "ex-gaussian: tail decay time τ"),
    "tail_fraction_std": Field("number", False, doc=_STD),
    "tail_decay_std": Field("number", False, "s", _STD),
    "times": Field(_NUMBERS, False, "s", "table: increasing sample times (0: the peak)"),
    "power": Field(_NUMBERS, False, doc="table: power at those times (any scale, >= 0)"),
}

_PARAMETER = Field("object", doc="one parameter's estimate", fields={
    "value": Field("number", True, doc="estimate (the parameter's unit)"),
    "std": Field("number|null", True, doc="standard deviation (null: unknown)"),
    "initial": Field("number", True, doc="start value"),
})

CALIBRATION_FIELDS = {
    # written by the line-sensor calibration (calib/result.py)
    "parameters": Field("object", doc="per parameter name: value, std, initial",
                        values=_PARAMETER),
    "rms_pixel": Field("number", False, "px", "RMS pixel residual"),
    "rms_time": Field("number", False, "s", "RMS time residual"),
    "n_detections": Field("integer", doc="detections used"),
    "fixed": Field("array", doc="names of the parameters held fixed", items=Field("string")),
    "unobservable": Field("array", doc="names of the parameters the data cannot determine",
                          items=Field("string")),
    "correlations": Field("object", doc='strong correlations, "a/b": r',
                          values=Field("number", doc="correlation coefficient")),
    "converged": Field("boolean", doc="the fit converged"),
    "covariance": Field("object", doc="covariance of the free parameters", fields={
        "names": Field("array", True, doc="parameter names", items=Field("string")),
        "matrix": Field(_NUMBERS, True, doc="N×N numbers"),
    }),
    "targets": Field("array", doc="the fitted walls", items=Field("object", fields={
        "source": Field("string", True, doc="the recording"),
        "alpha": Field("number", True, "rad", "wall normal, first angle"),
        "beta": Field("number", True, "rad", "wall normal, second angle"),
        "distance": Field("number", True, "m", "wall distance along its normal"),
        "std": Field(_NUMBERS, True, doc="σ of alpha, beta, distance"),
        "distance_axis": Field("number", True, "m", "distance along the optical axis"),
        "distance_axis_std": Field("number", True, "m", "its σ"),
    })),
    # written by the two-axis calibration (calib/twoaxis.py)
    "method": Field("string", doc='"two-axis walls"'),
    "std": Field("object", doc="two-axis: σ per free parameter name",
                 values=Field("number", doc="σ (the parameter's unit)")),
    "rms_px": Field("number", False, "px", "two-axis: RMS pixel residual"),
    "rms_path_m": Field("number", False, "m", "two-axis: RMS path-length residual"),
    "chi2_dof": Field("number", doc="two-axis: χ² per degree of freedom"),
    "n_shots": Field("integer", doc="two-axis: observations used"),
    "walls": Field(_NUMBERS, doc="two-axis: fitted wall planes"),
}

SYSTEM_FIELDS = {
    "format": Field("string", True, doc="the file kind", const="mems-stereo/system"),
    "version": Field("integer", True, doc="format version", const=1),
    "receiver": Field("object", True, doc="the SPAD receiver (camera model)", fields={
        "camera_matrix": Field(_NUMBERS, True, "px", "3×3 OpenCV K [[fx, 0, cx], [0, fy, cy], "
                                                     "[0, 0, 1]]"),
        "dist_coeffs": Field(_NUMBERS, True, doc="4, 5, 8, 12 or 14 OpenCV distortion "
                                                 "coefficients"),
        "image_size": Field("array", True, "px", "[width, height], integers",
                            items=Field("integer")),
        "pixel_pitch": Field(_NUMBERS, True, "m", "2 numbers: pitch in x and y"),
        "spad_diameter": _positive("m", "diameter of one SPAD"),
    }),
    "scanner": Field("object", True, doc="the MEMS mirror (fast axis)", fields={
        "position": Field(_NUMBERS, True, "m", "3 numbers: mirror pivot (the baseline)"),
        "normal_basis": Field(_NUMBERS, True, doc="2×3 numbers: orthonormal [e1, e2]"),
        "laser_direction": Field(_NUMBERS, True, doc="3 numbers: unit beam direction"),
        "theta0": Field("number", True, "rad", "rest angle θ0"),
        "f_mech": _positive("Hz", "mechanical frequency"),
        "theta_mech_max": _positive("rad", "mechanical amplitude"),
        "phase_offset": Field("number", False, "rad", "mirror lag behind the monitor "
                                                      "(default 0)"),
        "axis2": Field("object|null", doc="second axis (two-axis scanners)",
                       fields=AXIS2_FIELDS),
        "harmonics": Field("array", doc="trajectory harmonics (docs/hardware.md; default "
                                        "none: a cosine)", items=Field("object",
                                                                        fields=HARMONIC_FIELDS)),
        "monitor": Field("object", doc="zero-crossing monitor edge delays (docs/hardware.md; "
                                       "default none)", fields=MONITOR_FIELDS),
    }),
    "laser": Field("object", True, doc="the pulsed laser", fields={
        "f_rep": _positive("Hz", "repetition rate"),
        "pulse_fwhm": Field("number", True, "s", "pulse width (FWHM)"),
        "wavelength": _positive("m", "wavelength"),
        "pulse_shape": Field("object", doc="pulse beyond the Gaussian (docs/hardware.md; "
                                           "default the Gaussian)", fields=PULSE_SHAPE_FIELDS),
    }),
    "tdc": Field("object", True, doc="the time-to-digital converter", fields={
        "bin_width": _positive("s", "code width"),
        "n_bins": Field("integer", True, doc="codes (1..65535)"),
        "offset": Field("number", False, "s", "time of code 1's start (default 0)"),
        "pixel_offsets": Field(_NUMBERS, False, "s", "H·W numbers, row-major: each pixel's "
                                                     "TDC start delay (docs/hardware.md)"),
        "pixel_offsets_std": Field(_NUMBERS, False, "s", "H·W numbers: their σ"),
        "code_widths": Field(_NUMBERS, False, "LSB", "n_bins numbers: code widths in units "
                                                     "of bin_width (DNL + 1)"),
        "code_widths_std": Field(_NUMBERS, False, "LSB", "n_bins numbers: their σ"),
    }),
    "speed_of_light": _positive("m/s", "in air"),
    "device_id": Field("string", doc="the hardware's identifier (serial number, asset tag), "
                                     "shown in the calibration report (default: none)"),
    "calibration": Field("object|null", doc="written by mems-stereo calibrate",
                         fields=CALIBRATION_FIELDS),
}

# ------------------------------------------------------------------ TTTR map

MAP_FIELDS = {
    "format": Field("string", True, doc="the file kind", const="mems-stereo/tttr-map"),
    "version": Field("integer", True, doc="format version", const=1),
    "pixels": Field("array", True, doc="[channel, column, row] or {channel, column, row} "
                                       "per pixel",
                    items=Field("array|object", fields={
                        "channel": Field("integer", True, doc="input channel"),
                        "column": Field("integer", True, doc="pixel column"),
                        "row": Field("integer", False, doc="pixel row (default 0)"),
                    })),
    "shot_clock": Field("object", doc="what clocks the shots (default the sync)", fields={
        "source": Field("string", True, doc='"sync" or "channel"'),
        "channel": Field("integer", doc='the clock channel (source "channel")'),
    }),
    "zero_crossings": Field("object", True, doc="the mirror's zero-crossing monitor", fields={
        "source": Field("string", True, doc='"marker" or "channel"'),
        "rising_edge": Field("integer|null", doc="marker 1..4 or channel of rising crossings"),
        "falling_edge": Field("integer|null", doc="marker 1..4 or channel of falling "
                                                  "crossings"),
        "polarity": Field("string", doc='"positive" (default) or "negative"'),
        "delay": Field("number", False, "s", "subtracted from monitor times (default 0)"),
    }),
    "tdc": Field("object", doc="delay to TDC code", fields={
        "binning": Field("integer", doc="ticks per code (default 1)"),
        "delay_bins": Field("integer", doc="codes subtracted (default 0)"),
    }),
    "photons": Field("string", doc='"first" (default) or "all"'),
    "shots": Field("object", doc="which syncs are shots", fields={
        "first": Field("integer", doc="the sync that is shot 0 (default 0)"),
        "count": Field("integer|null", doc="shots (default all)"),
    }),
    "time_origin": Field("number", False, "s", "added to every time written (default 0)"),
    "system": Field("string|object", doc="system file (relative to the map), preset or "
                                         "system object"),
}

# ------------------------------------------------------------------ target distances

DISTANCES_FIELDS = {
    "format": Field("string", True, doc="the file kind", const="mems-stereo/target-distances"),
    "version": Field("integer", True, doc="format version", const=1),
    "kind": Field("string", doc='"axis" (default: along the optical axis) or "normal"'),
    "std": _positive("m", "default σ of a measurement", False),
    "targets": Field("array", True, doc="one entry per recording", items=Field("object", fields={
        "recording": Field("string", True, doc="the recording's file name"),
        "distance": _positive("m", "measured distance"),
        "std": _positive("m", "σ, overrides the file's std", False),
    })),
    "definition": Field("string", doc="free text: how the distances were measured"),
    "std_note": Field("string", doc="free text on std"),
    "measurement_note": Field("string", doc="free text on the measurement"),
}

# ------------------------------------------------------------------ scene

_COMMON = {
    "type": Field("string", True, doc="plane, box, sphere, cylinder or mesh"),
    "reflectivity": Field("number", True, doc="Lambertian albedo in (0, 1]"),
    "name": Field("string", doc="label (default type and index)"),
    "velocity": Field(_NUMBERS, False, "m/s", "3 numbers: velocity, world frame (default "
                                              "0; the pose written is the one at time 0)"),
    "angular_rate": Field(_NUMBERS, False, "rad/s", "3 numbers: rotation vector rate about "
                                                    "the centre (mesh: translation)"),
}
_CENTER = Field(_NUMBERS, True, "m", "3 numbers: centre")
_ROTATION = Field(_NUMBERS, False, "deg", "3 numbers: Euler angles x, y, z")
_OBJECT_VARIANTS = {
    "plane": _COMMON | {"center": _CENTER,
                        "normal": Field(_NUMBERS, True, doc="3 numbers: normal"),
                        "size": Field(_NUMBERS, True, "m", "2 numbers: width, height"),
                        "up": Field(_NUMBERS, False, doc="3 numbers: in-plane up")},
    "box": _COMMON | {"center": _CENTER,
                      "size": Field(_NUMBERS, True, "m", "3 numbers: edge lengths"),
                      "rotation_deg": _ROTATION},
    "sphere": _COMMON | {"center": _CENTER, "radius": _positive("m", "radius")},
    "cylinder": _COMMON | {"center": _CENTER, "radius": _positive("m", "radius"),
                           "height": _positive("m", "height"),
                           "axis": Field(_NUMBERS, False, doc="3 numbers: axis (default y)")},
    "mesh": _COMMON | {"file": Field("string", True, doc="mesh file, relative to the scene"),
                       "scale": _positive("", "scale factor (default 1)", False),
                       "translation": Field(_NUMBERS, False, "m", "3 numbers"),
                       "rotation_deg": _ROTATION},
}

SCENE_FIELDS = {
    "format": Field("string", doc="the file kind", const="mems-stereo/scene"),
    "version": Field("integer", doc="format version", const=1),
    "name": Field("string", doc="the scene's name"),
    "objects": Field("array", True, doc="the objects", items=Field(
        "object", variants=("type", _OBJECT_VARIANTS))),
}

# ------------------------------------------------------------------ live messages
# (a message header, not a file kind: documented in docs/live.md, read by io/live_zmq.py)

LIVE_MESSAGE_FIELDS = {
    "format": Field("string", True, doc="the message kind", const="mems-stereo/live"),
    "version": Field("integer", True, doc="format version", const=1),
    "type": Field("string", True, doc='"system", "shots" or "end" (docs/live.md)'),
    "n_shots": Field("integer", doc="shots k in a shots message (default 0)"),
    "n_zero_crossings": Field("integer", doc="zero crossings z in a shots message (default 0)"),
}

#: file kind → its declared top-level fields
SCHEMAS = {"system": SYSTEM_FIELDS, "tttr-map": MAP_FIELDS,
           "target-distances": DISTANCES_FIELDS, "scene": SCENE_FIELDS}


def _rows(fields: dict, prefix: str):
    for name, f in fields.items():
        path = f"{prefix}{name}"
        yield path, f
        if f.fields is not None:
            yield from _rows(f.fields, f"{path}.")
        if f.values is not None:
            yield f"{path}.<name>", f.values
            if f.values.fields is not None:
                yield from _rows(f.values.fields, f"{path}.<name>.")
        sub = f.items
        if sub is not None and sub.fields is not None:
            yield from _rows(sub.fields, f"{path}[].")
        if sub is not None and sub.variants is not None:
            key, table = sub.variants
            yield from _rows(_COMMON, f"{path}[].")
            for kind, members in table.items():
                yield from _rows({k: v for k, v in members.items() if k not in _COMMON},
                                 f"{path}[{key}={kind}].")


def schema_rows(kind: str) -> list[tuple[str, Field]]:
    """``(dotted path, Field)`` of every member of a kind, in documentation order
    (``[]``: each element of a list; ``<name>``: each member of a name-keyed object;
    ``objects[type=box]``: the members of a scene object of that type)."""
    return list(_rows(SCHEMAS[kind], ""))


def schema_markdown(kind: str) -> str:
    """The Markdown table of a kind's schema (``docs/formats.md``, "Schemas")."""
    lines = ["| field | type | unit | required | meaning |", "| --- | --- | --- | --- | --- |"]
    for path, f in schema_rows(kind):
        typ = f.type.replace("|", " or ").replace("array", "list")
        if f.expect == "a positive number":
            typ += " > 0"
        if f.const is not None:
            typ += f" `{f.const!r}`".replace("'", '"')
        lines.append(f"| `{path}` | {typ} | {f.unit or '—'} | "
                     f"{'yes' if f.required else 'no'} | {f.doc} |")
    return "\n".join(lines) + "\n"
