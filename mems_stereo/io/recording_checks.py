"""Validation of HDF5 recordings of FORMAT v1: the attributes, ``/system``, the shot
times, the zero crossings and ``/truth``; shared by the one-axis recordings
(:mod:`mems_stereo.io.recording`) and the two-axis ones
(:mod:`mems_stereo.io.recording2d`).

Errors are :class:`~mems_stereo.errors.FormatError` naming the file, the
dataset and what was wrong.
"""

from __future__ import annotations

from dataclasses import dataclass

import h5py
import numpy as np

from mems_stereo.errors import FormatError
from mems_stereo.io import hdf5 as h5
from mems_stereo.model.scanner import crossing_phases, validate_zero_crossings
from mems_stereo.model.system import System, system_from_json
from mems_stereo.util.limits import check_allocation

FORMAT_NAME = "mems-stereo/recording"
FORMAT_VERSION = 1

#: Accepted deviation of the mirror frequency implied by the zero crossings
#: (median over the recording) from the system's ``scanner.f_mech``.
CROSSING_FREQUENCY_TOLERANCE = 0.25


@dataclass
class RecordingHeader:
    """Everything of a recording except the bins: for streaming."""

    system: System
    shot_time: np.ndarray
    zero_crossings: np.ndarray
    rising: np.ndarray
    shape: tuple
    source: str


def _check_dtype(ds, kinds: str, expected: str, source: str, path: str):
    if ds.dtype.kind not in kinds:
        raise FormatError(f"expected {expected}, found dtype {ds.dtype}", source, path)


def validate_header(f: h5py.File, source: str, scan_axes: int = 1) -> System:
    """Check the file attributes and ``/system``; return the recorded System.

    ``scan_axes`` : 1 (FORMAT v1; the attribute absent or 1) or 2 (the
    two-axis extension, :mod:`mems_stereo.io.recording2d`; the attribute 2).
    """
    h5.require_format(f, FORMAT_NAME, FORMAT_VERSION, source)
    if "scan_axes" in f.attrs or scan_axes != 1:  # the two-axis extension (formats.md §5)
        try:
            axes = h5.attr_int(f, "scan_axes", source)
        except FormatError:
            axes = -1
        axes = 1 if axes is None else axes
        if axes != scan_axes and scan_axes == 1 and axes == 2:
            raise FormatError("a two-axis recording (scan_axes = 2): read it with "
                              "mems_stereo.io.recording2d.read_recording_2d", source,
                              "attrs/scan_axes")
        if axes != scan_axes:
            raise FormatError(f"expected attribute scan_axes = {scan_axes}, found "
                              f"{h5.shown_attr(f, 'scan_axes')}", source, "attrs/scan_axes")
    ds = h5.dataset(f, "/system", source)
    if ds.shape != () or ds.dtype.kind not in "OSU":
        raise FormatError(f"expected a scalar JSON string, found {ds.dtype} {ds.shape}", source,
                          "/system")
    raw = h5.read(ds, source)
    if isinstance(raw, bytes):
        try:
            raw = raw.decode("utf-8")
        except UnicodeDecodeError:
            raise FormatError("expected UTF-8 JSON text, found undecodable bytes", source,
                              "/system") from None
    if not isinstance(raw, str):
        raise FormatError(f"expected a JSON string, found {type(raw).__name__}", source,
                          "/system")
    return system_from_json(raw, source=f"{source}:/system")


def check_crossing_frequency(zc: np.ndarray, rising: np.ndarray, f_mech: float,
                             source: str = "", tol: float = CROSSING_FREQUENCY_TOLERANCE,
                             field: str = "/scanner/zero_crossings"):
    """Cross-check the zero crossings against ``f_mech`` (Hz).

    Between crossings the phase advances by π (alternating kinds) or 2π (same
    kind: one was missed); the median frequency this implies must lie within
    ``tol`` of ``f_mech``.  Crossings spaced for another frequency, or all of
    one kind (which doubles the implied frequency), raise FormatError.
    """
    if zc.size < 3:
        return
    f_implied = np.diff(crossing_phases(zc, rising)) / (2 * np.pi * np.diff(zc))
    med = float(np.median(f_implied))
    if not abs(med / f_mech - 1.0) <= tol:
        kinds = "all rising" if rising.all() else ("all falling" if not rising.any() else "")
        raise FormatError(f"the crossings imply a mirror frequency of {med:.6g} Hz, but "
                          f"scanner.f_mech = {f_mech:g} Hz (/system)"
                          + (f"; the crossings are {kinds}" if kinds else ""),
                          source, field)


def read_shot_times(f: h5py.File, source: str) -> np.ndarray:
    """``/shots/time``: (K,) float64 s, finite, strictly increasing (checked in blocks;
    the per-shot arrays of a run are checked against the memory budget first)."""
    t_ds = h5.dataset(f, "/shots/time", source, whole=True)
    if t_ds.dtype != np.float64:
        raise FormatError(f"expected float64 seconds, found dtype {t_ds.dtype}", source,
                          "/shots/time")
    if t_ds.ndim != 1:
        raise FormatError(f"expected shape (K,), found {t_ds.shape}", source, "/shots/time")
    # O(K) arrays of the run (angles, steps, indices): a few float64 per shot
    check_allocation(16 * t_ds.size * 8, f"per-shot arrays of {t_ds.size} shots", source,
                     "/shots/time")
    t = np.asarray(h5.read(t_ds, source), dtype=np.float64)
    block = 1 << 20  # checked in blocks: small temporaries for long recordings
    for a in range(0, t.size, block):
        tb = t[a:a + block + 1]
        if not np.all(np.isfinite(tb)):
            raise FormatError("expected finite times, found NaN or inf", source, "/shots/time")
        bad = np.diff(tb) <= 0
        if bad.any():
            i = a + int(np.argmax(bad))
            raise FormatError(f"expected strictly increasing shot times, found t[{i + 1}] = "
                              f"{float(t[i + 1])!r} <= t[{i}] = {float(t[i])!r}", source,
                              "/shots/time")
    return t


def check_codes_fit(codes: np.ndarray, n_bins: int, source: str, field: str = "/shots/bins",
                    file_bins: int | None = None) -> None:
    """Refuse TDC ``codes`` (a recording's, any shape) above the ``n_bins`` of the system
    used to read them (``file_bins``: the recording's own, named in the message)."""
    top = int(np.max(codes)) if np.size(codes) else 0
    if top > n_bins:
        own = f" (the recording's own system has n_bins = {file_bins})" if file_bins else ""
        raise FormatError(f"expected codes 0..{n_bins} (tdc.n_bins of the system used), "
                          f"found {top}{own}", source, field)


#: accepted ratio of the median shot interval to the laser period 1 / ``laser.f_rep``
#: (either way): one shot per laser period, with jitter, dropped shots and a nominal
#: f_rep that differs from the true one
SHOT_STRIDE_TOLERANCE = 1.5


def check_shot_stride(t: np.ndarray, f_rep: float, source: str) -> None:
    """Refuse shot times whose median interval is not about one laser period
    (``f_rep`` Hz, /system's ``laser.f_rep``; within :data:`SHOT_STRIDE_TOLERANCE`):
    shot times in other units or of a sub-sampled clock would give wrong angles."""
    if t.size < 2:
        return
    stride = float(np.median(np.diff(t[: 1 << 20])))
    ratio = stride * f_rep
    if 1 / SHOT_STRIDE_TOLERANCE <= ratio <= SHOT_STRIDE_TOLERANCE:
        return
    raise FormatError(f"the median shot interval {stride * 1e6:.6g} µs is {ratio:.3g} laser "
                      f"periods (laser.f_rep = {f_rep:g} Hz of /system: "
                      f"{1e6 / f_rep:.6g} µs); expected one shot per laser period",
                      source, "/shots/time")


def read_crossings(f: h5py.File, source: str, f_mech: float, group: str = "/scanner"):
    """``GROUP/zero_crossings`` (float64 s) and ``GROUP/rising`` (0/1) of a resonant
    axis, validated and cross-checked against its ``f_mech`` (Hz); returns
    ``(zc (Z,) float64, rising (Z,) uint8)``."""
    zpath, rpath = f"{group}/zero_crossings", f"{group}/rising"
    zc_ds = h5.dataset(f, zpath, source, whole=True)
    if zc_ds.dtype != np.float64:
        raise FormatError(f"expected float64 seconds, found dtype {zc_ds.dtype}", source, zpath)
    r_ds = h5.dataset(f, rpath, source, whole=True)
    _check_dtype(r_ds, "iub", "uint8 0/1", source, rpath)
    zc, rising = validate_zero_crossings(h5.read(zc_ds, source), h5.read(r_ds, source),
                                         source=source, field=zpath)
    check_crossing_frequency(zc, rising, f_mech, source, field=zpath)
    return zc, rising.astype(np.uint8)


def validate_recording_file(f: h5py.File, source: str, check_codes: bool = True,
                            chunk_shots: int = 4096) -> RecordingHeader:
    """Validate the datasets of an open recording against FORMAT v1.

    Returns its :class:`RecordingHeader` (everything but the bins); ``/shots/bins`` is
    checked for shape and dtype and, if ``check_codes``, streamed to check
    that every code is <= n_bins (memory bounded by ``chunk_shots``).
    """
    system = validate_header(f, source)
    t = read_shot_times(f, source)
    check_shot_stride(t, system.laser.f_rep, source)
    b_ds = h5.dataset(f, "/shots/bins", source)
    w, h = system.receiver.image_size
    if b_ds.ndim != 3 or b_ds.shape[0] != t.size or b_ds.shape[1:] != (h, w):
        raise FormatError(f"expected shape (K, H, W) = ({t.size}, {h}, {w}), found {b_ds.shape}",
                          source, "/shots/bins")
    if b_ds.dtype != np.uint16:
        raise FormatError(f"expected dtype uint16, found {b_ds.dtype}", source, "/shots/bins")
    if check_codes:
        n_bins = system.tdc.n_bins
        for s0 in range(0, t.size, chunk_shots):
            blk = h5.read(b_ds, source, np.s_[s0:s0 + chunk_shots])
            if blk.size and int(blk.max()) > n_bins:
                k = s0 + int(np.argmax(blk.reshape(blk.shape[0], -1).max(axis=1) > n_bins))
                raise FormatError(f"expected codes 0..{n_bins} (n_bins), found "
                                  f"{int(blk.max())} in shot {k}", source, "/shots/bins")
    zc, rising = read_crossings(f, source, system.scanner.f_mech)
    check_truth(f, b_ds, source)
    return RecordingHeader(system, t, zc, rising, tuple(b_ds.shape), source)


def check_truth(f: h5py.File, b_ds: h5py.Dataset, source: str) -> None:
    """``/truth`` is optional, but where ``/truth/label`` exists it must fit the bins."""
    if "truth" not in f:
        return
    if not isinstance(f["truth"], h5py.Group):
        raise FormatError("expected a group, found a dataset", source, "/truth")
    if "label" in f["truth"]:
        lab = h5.dataset(f, "/truth/label", source)
        if lab.shape != b_ds.shape or lab.dtype.kind not in "iu":
            raise FormatError(f"expected integer labels of shape {b_ds.shape} like /shots/bins,"
                              f" found {lab.dtype} {lab.shape}", source, "/truth/label")


#: the label values of ``/truth/label``: 0 none, 1 laser return, 2 background
TRUTH_LABELS = (0, 1, 2)


def check_label_values(lab: np.ndarray, source: str, first: int = 0) -> None:
    """Refuse ``/truth/label`` values other than :data:`TRUTH_LABELS` (``lab``: the
    labels of shots, or events, ``first`` onwards), naming the first bad one."""
    lab = np.asarray(lab)
    if lab.size == 0 or (lab.min() >= 0 and lab.max() <= TRUTH_LABELS[-1]):
        return
    bad = np.flatnonzero((lab.reshape(-1) < 0) | (lab.reshape(-1) > TRUTH_LABELS[-1]))[0]
    where = np.unravel_index(bad, lab.shape)
    index = ", ".join(str(int(i) + (first if k == 0 else 0)) for k, i in enumerate(where))
    raise FormatError(f"expected labels 0 (none), 1 (laser return) or 2 (background), found "
                      f"{lab.reshape(-1)[bad]} at [{index}]", source, "/truth/label")


def read_truth(f: h5py.File, source: str = "", attrs: bool = False) -> dict:
    """The optional ``/truth`` group's datasets (and, with ``attrs``, its scalar
    attributes) as a dict; anything but a group there is ignored (processing
    never reads the truth)."""
    truth = {}
    try:
        g = f["truth"] if "truth" in f else None
    except h5.H5_ERRORS:
        g = None
    if isinstance(g, h5py.Group):
        for k in g:
            if isinstance(g.get(k), h5py.Dataset):
                ds = h5.dataset(f, f"/truth/{k}", source, whole=True)
                truth[k] = h5.read(ds, source)
                if k == "label" and truth[k].dtype.kind in "iu":
                    check_label_values(truth[k], source)
        if attrs:
            try:
                truth.update({k: v for k, v in g.attrs.items()})
            except h5.H5_ERRORS as e:
                raise FormatError(f"cannot read the attributes ({e})", source,
                                  "/truth") from None
    return truth
