"""Time-tagged event streams (PTU, Photon-HDF5) → FORMAT v1 recordings, through a mapping file.

A TCSPC or time-tagger file holds events, not shots: photons on input
channels, the laser sync (the shot clock), markers.  The mapping JSON
(``mems-stereo/tttr-map``, documented in ``docs/formats.md``) says which
channel is which pixel, what clocks the shots, which events carry the
mirror's zero-crossing monitor and with which polarity, and how a photon's
delay after its shot becomes a TDC code:

.. code-block:: json

    {"format": "mems-stereo/tttr-map", "version": 1,
     "system": "nominal_system.json",
     "pixels": [[0, 0, 0], [1, 1, 0]],
     "shot_clock": {"source": "sync"},
     "zero_crossings": {"source": "marker", "rising_edge": 1, "falling_edge": 2,
                        "polarity": "positive", "delay": 0.0},
     "tdc": {"binning": 1, "delay_bins": 0},
     "photons": "first"}

The TDC bin width always comes from the file header: ``binning`` ×
``MeasDesc_Resolution`` (T3: the dtime bin; T2: the time-tag unit).  A photon
``ticks`` header units after its shot's sync has the code
``N = ticks // binning − delay_bins + 1``; codes outside 1..n_bins are
dropped and counted.  With ``photons = "first"`` (FORMAT v1) each pixel keeps
the earliest photon of each shot; with ``"all"`` every photon goes to the
time-tag layout of :mod:`mems_stereo.pipeline.timetags`
(:func:`events_to_timetags`).

The conversion streams: two passes over the event blocks (pass 1: shot count
and zero crossings, O(Z) memory; pass 2: shots in windows of
``window_shots`` written through :class:`~mems_stereo.io.recording.RecordingWriter`),
so memory does not grow with the file.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, replace

import numpy as np

from mems_stereo.errors import FormatError
from mems_stereo.io.recording import RecordingWriter
from mems_stereo.io.tttr_map import TttrMap
from mems_stereo.model.system import System, system_to_json
from mems_stereo.util.atomic import atomic_output

PHOTON, SYNC, MARKER = 0, 1, 2  # the same codes as mems_stereo.io.ptu


@dataclass(frozen=True)
class StreamInfo:
    """What a converter needs to know about an event stream.

    Attributes
    ----------
    mode : "T2" (macro = absolute time tag) or "T3" (macro = sync count,
        micro = TDC bin).
    macro_unit : s per macro unit (T2 time tag; T3 sync period).
    micro_unit : s per micro unit (T3 dtime bin; T2 = macro_unit).
    sync_rate : Hz, as recorded (0 if unknown).
    """

    mode: str
    macro_unit: float
    micro_unit: float
    sync_rate: float = 0.0


# --------------------------------------------------------------------------- helpers
def _match(m: TttrMap, kind: np.ndarray, channel: np.ndarray, edge: int | None) -> np.ndarray:
    if edge is None:
        return np.zeros(kind.size, bool)
    if m.zc_source == "marker":
        return (kind == MARKER) & ((channel & (1 << (edge - 1))) != 0)
    return (kind == PHOTON) & (channel == edge)


def _is_clock(m: TttrMap, kind, channel) -> np.ndarray:
    if m.clock == "sync":
        return kind == SYNC
    return (kind == PHOTON) & (channel == m.clock_channel)


def bin_width_from_stream(info: StreamInfo, m: TttrMap) -> float:
    """TDC bin width, s: ``binning`` × the header's TDC resolution."""
    return m.binning * info.micro_unit


def system_for_stream(system: System, info: StreamInfo, m: TttrMap) -> System:
    """The nominal system with the TDC bin width from the file header."""
    bw = bin_width_from_stream(info, m)
    return system.replace(tdc=replace(system.tdc, bin_width=bw))


@dataclass
class ImportStats:
    """Counts of a conversion (for the CLI's summary).

    ``out_of_range`` counts the photons whose code falls outside 1..n_bins,
    ``below_codes`` those of them below 1 (the rest are above n_bins).
    """

    n_shots: int = 0
    n_zero_crossings: int = 0
    photons: int = 0
    written: int = 0
    not_first: int = 0
    unmapped: int = 0
    out_of_range: int = 0
    outside_shots: int = 0
    bin_width: float = 0.0
    below_codes: int = 0

    def summary(self) -> str:
        return (f"{self.n_shots} shots, {self.n_zero_crossings} zero crossings, "
                f"{self.photons} photons: {self.written} written, {self.not_first} later "
                f"in their shot, {self.out_of_range} outside codes 1..n_bins, "
                f"{self.unmapped} on unmapped channels, {self.outside_shots} outside the shots")


@dataclass(frozen=True, slots=True)
class StreamScan:
    """What pass 1 over an event stream finds (:func:`scan_stream`).

    Attributes
    ----------
    n_shots : int, shots to convert.
    first_clock : int, the macro time (T2: time tag, T3: sync count) of shot 0's clock.
    zero_crossings : (Z,) float64, s on the recording's clock, increasing.
    rising : (Z,) uint8, 1 where θ_mech crosses zero increasing.
    """

    n_shots: int
    first_clock: int
    zero_crossings: np.ndarray
    rising: np.ndarray


def scan_stream(blocks: Iterable, info: StreamInfo, m: TttrMap, source: str = "") -> StreamScan:
    """Pass 1: the shot count, shot 0's clock and the zero crossings (:class:`StreamScan`).

    ``blocks`` yields EventBlock-like objects (``macro, micro, kind, channel``).
    """
    n_clock = 0
    first_clock = None
    last_macro = -1
    zc_t, zc_r = [], []
    for b in blocks:
        if len(b) == 0:
            continue
        last_macro = max(last_macro, int(b.macro[-1]))
        if info.mode == "T2":
            c = _is_clock(m, b.kind, b.channel)
            n_clock += int(c.sum())
            if first_clock is None and c.any():
                first_clock = int(b.macro[np.argmax(c)])
        for edge, is_rising in ((m.zc_rising_edge, True), (m.zc_falling_edge, False)):
            sel = _match(m, b.kind, b.channel, edge)
            if sel.any():
                if info.mode == "T2":
                    t = b.macro[sel] * info.macro_unit
                else:
                    t = b.macro[sel] * info.macro_unit + (
                        b.micro[sel] * info.micro_unit if m.zc_source == "channel" else 0.0)
                zc_t.append(t - m.zc_delay + m.time_origin)
                zc_r.append(np.full(t.size, is_rising == m.zc_positive))
    if info.mode == "T2":
        if m.clock == "sync" and n_clock == 0:
            raise FormatError("no sync events in the T2 stream; set shot_clock.source to "
                              "'channel' if the laser trigger is on an input", source,
                              "shot_clock")
        avail = n_clock - m.first_shot
        n_shots = avail if m.n_shots is None else min(avail, m.n_shots)
    else:
        if m.clock != "sync":
            raise FormatError("a T3 stream is clocked by its sync; expected shot_clock.source "
                              "= 'sync'", source, "shot_clock")
        n_shots = last_macro + 1 - m.first_shot if m.n_shots is None else m.n_shots
        first_clock = m.first_shot
    if n_shots < 1:
        raise FormatError("no shots in the stream", source, "shot_clock")
    zc = np.concatenate(zc_t) if zc_t else np.zeros(0)
    rising = np.concatenate(zc_r).astype(np.uint8) if zc_r else np.zeros(0, np.uint8)
    order = np.argsort(zc, kind="stable")
    zc, rising = zc[order], rising[order]
    if zc.size < 2:
        raise FormatError(f"expected at least 2 zero-crossing monitor events "
                          f"({m.zc_source} {m.zc_rising_edge}/{m.zc_falling_edge}), found "
                          f"{zc.size}", source, "zero_crossings")
    return StreamScan(n_shots, first_clock, zc, rising)


def _photon_shots(b, info: StreamInfo, m: TttrMap, state: dict):
    """Shot index, ticks after the shot, and time of each event's shot; updates ``state``."""
    if info.mode == "T3":
        return b.macro - m.first_shot, b.micro, None
    c = _is_clock(m, b.kind, b.channel)
    shot = np.cumsum(c) + state["clocks"] - 1 - m.first_shot
    last = np.where(c, b.macro, -1)
    last[0] = max(last[0], state["last_clock"])
    last = np.maximum.accumulate(last)
    state["clocks"] += int(c.sum())
    state["last_clock"] = int(last[-1])
    return shot, b.macro - last, c


def iter_photon_codes(blocks: Iterable, info: StreamInfo, m: TttrMap, lut: np.ndarray,
                      n_shots: int, n_bins: int, stats: ImportStats) -> Iterator[tuple]:
    """Per block: ``(shot, pixel_index, code, clock_shots, clock_times, ticks)``.

    Photons on mapped channels inside the shots with codes 1..n_bins; pixel
    index = row·W + column; clock_shots/times: the T2 shots whose sync is in
    this block and their times in s (None for T3).  ``lut`` : channel → pixel
    index (−1 unmapped), from :func:`pixel_lut`.
    """
    state = {"clocks": 0, "last_clock": -1}
    for b in blocks:
        if len(b) == 0:
            continue
        shot, ticks, c = _photon_shots(b, info, m, state)
        ph = b.kind == PHOTON
        if m.clock == "channel":
            ph &= b.channel != m.clock_channel
        if m.zc_source == "channel":
            for e in (m.zc_rising_edge, m.zc_falling_edge):
                if e is not None:
                    ph &= b.channel != e
        stats.photons += int(ph.sum())
        ch = b.channel.astype(np.int64)
        mapped = ph & (ch < lut.size)
        pix = np.full(ch.size, -1, np.int64)
        pix[mapped] = lut[ch[mapped]]
        stats.unmapped += int((ph & (pix < 0)).sum())
        ok = ph & (pix >= 0)
        inside = ok & (shot >= 0) & (shot < n_shots)
        stats.outside_shots += int((ok & ~inside).sum())
        code = ticks // m.binning - m.delay_bins + 1
        good = inside & (code >= 1) & (code <= n_bins)
        stats.out_of_range += int((inside & ~good).sum())
        stats.below_codes += int((inside & (code < 1)).sum())
        cs = ct = None
        if c is not None:
            sel = c & (shot >= 0) & (shot < n_shots)
            cs, ct = shot[sel], b.macro[sel] * info.macro_unit + m.time_origin
        yield shot[good], pix[good], code[good], cs, ct, ticks[good]


def pixel_lut(m: TttrMap, system: System) -> np.ndarray:
    """Channel → pixel index (row·W + column), −1 for unmapped channels: (C_max + 1,) int64."""
    w, h = system.receiver.image_size
    cols, rows = m.pixels[:, 1], m.pixels[:, 2]
    if np.any(cols >= w) or np.any(rows >= h):
        i = int(np.argmax((cols >= w) | (rows >= h)))
        raise FormatError(f"pixel [{cols[i]}, {rows[i]}] outside the receiver's image size "
                          f"{w}x{h}", field=f"pixels[{i}]")
    lut = np.full(int(m.pixels[:, 0].max()) + 1, -1, np.int64)
    lut[m.pixels[:, 0]] = rows * w + cols
    return lut


def events_to_recording(open_blocks: Callable[[], Iterable], info: StreamInfo, m: TttrMap,
                        system: System, out_path: str | os.PathLike, *,
                        window_shots: int = 8192, compression: str | None = "gzip",
                        source: str = "") -> ImportStats:
    """Convert an event stream to a FORMAT v1 recording (first photon per shot and pixel).

    ``open_blocks()`` returns a fresh iterable of event blocks (called twice:
    one pass for the shot count and zero crossings, one for the photons).
    ``system`` is the nominal system; its TDC bin width is replaced by the
    header's (:func:`system_for_stream`).  Memory: O(window_shots · H · W +
    block + Z).  Returns the counts; raises :class:`FormatError` (and writes
    nothing) when the stream has no shots or fewer than two zero crossings.
    """
    system = system_for_stream(system, info, m)
    stats = ImportStats(bin_width=system.tdc.bin_width)
    scan = scan_stream(open_blocks(), info, m, source)
    n_shots, first_clock, zc, rising = scan.n_shots, scan.first_clock, scan.zero_crossings, \
        scan.rising
    stats.n_shots, stats.n_zero_crossings = n_shots, zc.size
    w, h = system.receiver.image_size
    hw = w * h
    lut = pixel_lut(m, system)
    B = max(1, int(window_shots))
    empty = np.uint16(65535)
    buf = np.full(B * hw, empty, np.uint16)
    tbuf = np.full(B, np.nan)
    base = 0
    n_first = 0

    with RecordingWriter(out_path, system, n_shots, zc, rising, compression=compression,
                         chunk_shots=min(B, 4096)) as wr:

        def flush(upto: int):
            nonlocal base, n_first
            k = min(B, upto - base)
            blk = buf[:k * hw].reshape(k, h, w)
            bins = np.where(blk == empty, 0, blk).astype(np.uint16)
            n_first += int(np.count_nonzero(bins))
            if info.mode == "T3":
                t = (np.arange(base, base + k) + first_clock) * info.macro_unit + m.time_origin
            else:
                t = tbuf[:k].copy()
                if np.isnan(t).any():
                    raise FormatError("a shot without its sync time", source, "shot_clock")
            wr.append(t, bins)
            buf[:] = empty
            tbuf[:] = np.nan
            base += k

        for shot, pix, code, cs, ct, _ in iter_photon_codes(
                open_blocks(), info, m, lut, n_shots, system.tdc.n_bins, stats):
            while True:
                if cs is not None:
                    s_in = cs < base + B
                    tbuf[cs[s_in] - base] = ct[s_in]
                    cs, ct = cs[~s_in], ct[~s_in]
                n_in = int(np.searchsorted(shot, base + B))
                if n_in:
                    idx = (shot[:n_in] - base) * hw + pix[:n_in]
                    np.minimum.at(buf, idx, code[:n_in].astype(np.uint16))
                    stats.written += n_in
                    shot, pix, code = shot[n_in:], pix[n_in:], code[n_in:]
                if shot.size == 0 and (cs is None or cs.size == 0):
                    break
                flush(n_shots)
        while base < n_shots:
            flush(n_shots)
    stats.not_first = stats.written - n_first
    stats.written = n_first
    return stats


def events_to_timetags(open_blocks: Callable[[], Iterable], info: StreamInfo, m: TttrMap,
                       system: System, out_path: str | os.PathLike, *,
                       source: str = "") -> ImportStats:
    """Every photon (not only the first per shot) → the time-tag layout, as ``.npz``.

    Arrays written (CSR by pixel, as ``mems_stereo.io.realdata`` and
    :mod:`mems_stereo.pipeline.timetags` read them): ``timestamps_ps`` (n,)
    int64, delay of the photon after its shot's sync in ps (start of its
    header tick, rounded); ``offsets`` (H·W + 1,) int64; ``shape`` [H, W];
    ``gate_ps`` [0, n_bins · bin_width] in ps; plus per photon ``shot`` (n,)
    int64 and ``code`` (n,) uint16 (the TDC code of the first-photon path),
    and ``shot_time`` (K,) s, ``zero_crossings``, ``rising``, ``system``
    (JSON).  Memory: O(number of photons) (the CSR order needs them all).
    """
    system = system_for_stream(system, info, m)
    stats = ImportStats(bin_width=system.tdc.bin_width)
    scan = scan_stream(open_blocks(), info, m, source)
    n_shots, first_clock, zc, rising = scan.n_shots, scan.first_clock, scan.zero_crossings, \
        scan.rising
    stats.n_shots, stats.n_zero_crossings = n_shots, zc.size
    w, h = system.receiver.image_size
    lut = pixel_lut(m, system)
    unit = info.micro_unit if info.mode == "T3" else info.macro_unit
    parts: dict[str, list] = {"shot": [], "pix": [], "code": [], "ps": [], "cs": [], "ct": []}
    for shot, pix, code, cs, ct, ticks in iter_photon_codes(
            open_blocks(), info, m, lut, n_shots, system.tdc.n_bins, stats):
        parts["shot"].append(shot)
        parts["pix"].append(pix)
        parts["code"].append(code.astype(np.uint16))
        parts["ps"].append(np.rint(ticks * unit * 1e12).astype(np.int64))
        if cs is not None:
            parts["cs"].append(cs)
            parts["ct"].append(ct)
    cat = {k: (np.concatenate(v) if v else np.zeros(0, np.int64)) for k, v in parts.items()}
    order = np.argsort(cat["pix"], kind="stable")
    offsets = np.concatenate([[0], np.cumsum(np.bincount(cat["pix"], minlength=w * h))])
    if info.mode == "T3":
        shot_time = (np.arange(n_shots) + first_clock) * info.macro_unit + m.time_origin
    else:
        shot_time = np.full(n_shots, np.nan)
        shot_time[cat["cs"]] = cat["ct"]
    stats.written = int(cat["pix"].size)
    with atomic_output(out_path) as tmp, open(tmp, "wb") as f:
        np.savez(f, timestamps_ps=cat["ps"][order], offsets=offsets.astype(np.int64),
                 shape=np.array([h, w], np.int64),
                 gate_ps=np.array([0, round(system.tdc.n_bins * system.tdc.bin_width * 1e12)],
                                  np.int64),
                 shot=cat["shot"][order].astype(np.int64), code=cat["code"][order],
                 shot_time=shot_time, zero_crossings=zc, rising=rising,
                 system=np.array(system_to_json(system)))
    return stats
