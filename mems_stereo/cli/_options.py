"""Option checks of every command, declared in one table and run before any work.

Each rule names the option as typed and says what it accepts; a value out of
range, not finite or of the wrong kind is refused with one
:class:`~mems_stereo.errors.OptionError` line such as
``--confidence: expected a number in (0, 1), found 0.0``.  ``--scheduler``
addresses are tried (TCP connect, 3 s) before a run starts.
"""

from __future__ import annotations

import math
import socket
from collections.abc import Callable
from urllib.parse import urlsplit

from mems_stereo.cli._pathcheck import opt, samples_dir
from mems_stereo.errors import OptionError

#: seconds to wait for a Dask scheduler's TCP port before giving up
SCHEDULER_TIMEOUT = 3.0


def _num(v, o: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise OptionError(f"expected a finite number, found {v!r}", field=o)
    return v


def between(lo: float, hi: float, *, lo_open=False, hi_open=False, integer=False) -> Callable:
    """A number in [lo, hi] (``lo_open``/``hi_open``: excluded; ``integer``: whole)."""
    def rule(v, o):
        _num(v, o)
        ok = (v > lo if lo_open else v >= lo) and (v < hi if hi_open else v <= hi)
        if not ok:
            lb, rb = "(" if lo_open else "[", ")" if hi_open else "]"
            kind = "an integer" if integer else "a number"
            raise OptionError(f"expected {kind} in {lb}{lo:g}, {hi:g}{rb}, found {v!r}", field=o)
    return rule


def positive(hi: float = math.inf) -> Callable:
    return between(0.0, hi, lo_open=True)


def count(lo: int = 1, hi: int = 10**9) -> Callable:
    return between(lo, hi, integer=True)


def probability_open() -> Callable:
    return between(0.0, 1.0, lo_open=True, hi_open=True)


def each(rule: Callable, allow_nan: bool = False) -> Callable:
    def r(v, o):
        for x in v:
            if allow_nan and isinstance(x, float) and math.isnan(x):
                continue
            rule(x, o)
    return r


def scheduler(v, o):
    """``local`` or a reachable ``tcp://host:port`` (``host:port``)."""
    if v in ("local",):
        return
    text = v if "://" in v else f"tcp://{v}"
    u = urlsplit(text)
    if u.scheme != "tcp":
        return  # tls://, inproc://, ucx://: left to Dask
    try:
        host, port = u.hostname, u.port
    except ValueError:
        host, port = None, None
    if not host or port is None:
        raise OptionError(f"expected 'local' or tcp://HOST:PORT, found {v!r}", field=o)
    try:
        with socket.create_connection((host, port), timeout=SCHEDULER_TIMEOUT):
            pass
    except OSError as e:
        why = e.strerror or str(e) or type(e).__name__
        raise OptionError(f"cannot reach the Dask scheduler at {text} ({why})",
                          field=o) from None


def calib_names(which: str) -> Callable:
    def rule(v, o):
        from mems_stereo.calib.model import SYSTEM_PARAMS

        for n in v:
            if n not in SYSTEM_PARAMS:
                raise OptionError(f"unknown parameter {n!r}; expected names of "
                                  f"{', '.join(SYSTEM_PARAMS)}", field=o)
    return rule


def sample_folder(v, o):
    """A folder holding the bundled sample recordings (``demo --samples``)."""
    samples_dir(v)


_DIST = each(between(0.0, 1e4, lo_open=True), allow_nan=True)
_ACQ = {"shots": count(1, 10**8), "distance": between(0.0, 1e4, lo_open=True),
        "ratio": between(0.0, 1e3, lo_open=True)}
_RENDER = {"width": count(16, 16384), "height": count(16, 16384),
           "point_size": between(0.0, 1000.0, lo_open=True),
           "vmin": between(-1e300, 1e300), "vmax": between(-1e300, 1e300)}

#: command → {argument name: rule}; None values (option not given) are not checked
RULES: dict[str, dict[str, Callable]] = {
    "info": dict(_ACQ),
    "plot acquisition": dict(_ACQ),
    "simulate": {"shots": count(1, 10**8), "background": between(0.0, 1e10),
                 "dark": between(0.0, 1e10), "seed": count(0, 2**63 - 1),
                 "drift": between(-1.0, 1.0), "crosstalk": between(0.0, 1.0, hi_open=True)},
    "process": {"confidence": probability_open(), "min_range": between(0.0, 1e4, lo_open=True),
                "false_alarm": probability_open(), "chunk_shots": count(1, 10**7),
                "workers": count(1, 1024), "scheduler": scheduler},
    "calibrate": {"confidence": probability_open(), "distance_std": positive(1e3),
                  "target_distance": _DIST, "fix": calib_names("fix"),
                  "free": calib_names("free")},
    "view": {"point_size": between(0.0, 1000.0, lo_open=True)},
    "render": dict(_RENDER),
    "plot histograms": {"max_code": count(1, 65535), "row": count(0, 1 << 20)},
    "demo": {"samples": sample_folder},
    "live": {"frame_shots": count(1, 10**9), "queue_frames": count(1, 1000),
             "idle_timeout": between(0.0, 1e6), "confidence": probability_open(),
             "min_range": between(0.0, 1e4, lo_open=True), "false_alarm": probability_open()},
}


def check_options(command: str, args) -> None:
    """Run the rules of ``command`` on ``args`` and the cross-option checks."""
    for name, rule in RULES.get(command, {}).items():
        v = getattr(args, name, None)
        if v is not None:
            rule(v, opt(name))
    if command == "render" and None not in (args.vmin, args.vmax) and not args.vmin < args.vmax:
        raise OptionError(f"expected --vmin < --vmax, found {args.vmin!r} >= {args.vmax!r}",
                          field="--vmin")
    if command == "calibrate":
        from mems_stereo.calib.model import DEFAULT_FREE

        td = args.target_distance
        if td is not None and len(td) != len(args.recordings):
            raise OptionError(f"expected one distance per recording ({len(args.recordings)}), "
                              f"found {len(td)}", field="--target-distance")
        free = set(DEFAULT_FREE) | set(args.free)
        if free <= set(args.fix):
            raise OptionError("every parameter is fixed; nothing is left to estimate",
                              field="--fix")
        both = sorted(set(args.fix) & set(args.free))
        if both:
            raise OptionError(f"{', '.join(both)} both fixed and free", field="--fix")
