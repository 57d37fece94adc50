"""PicoQuant PTU files (T2 and T3 TTTR records): header, streamed events, a small encoder.

Reading goes through the `ptufile` package: it parses the tag header and
gives the records' offset; the 32-bit records are then read in blocks of
``chunk_records`` records (memory bounded by the block, whatever the file size).  T3 records are
decoded by ``ptufile``; the overflow count is carried from block to block.
T2 records of the HydraHarp / TimeHarp 260 / MultiHarp / PicoHarp 330
layout are decoded here (vectorised NumPy), because ``ptufile`` reports a
T2 *sync* event as channel 0, the same number as a photon on input 1, and
the sync is our shot clock (checked with ptufile 2026.2.6).

Events come out as :class:`EventBlock`\\ s in the file's order:

- T3: ``macro`` = the sync count (the laser shot), ``micro`` = the dtime,
  in units of ``header.resolution`` (the TDC bin width of the file).
- T2: ``macro`` = the time tag in units of ``header.global_resolution``,
  ``micro`` = 0.

``kind`` is :data:`PHOTON`, :data:`SYNC` (T2 only) or :data:`MARKER`;
``channel`` is the 0-based input of a photon (input 1 of the instrument =
channel 0, as ``ptufile`` numbers them) or the marker bit mask (1..15).
Overflow records are consumed and never yielded.

The encoder (:func:`write_ptu`, :func:`encode_t2`, :func:`encode_t3`) writes
the Generic T2/T3 layout (MultiHarp, PicoHarp 330; the same bits as
HydraHarp V2) after PicoQuant's published record description; it exists for
tests and samples, since ``ptufile`` itself writes only T3 image histograms.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mems_stereo.errors import FormatError, OptionError
from mems_stereo.io.tttr import StreamInfo
from mems_stereo.io.tttr_map import TttrMap, map_to_dict
from mems_stereo.util.atomic import atomic_output

PHOTON, SYNC, MARKER = 0, 1, 2

# record types (TTResultFormat_TTTRRecType) and their overflow period, in
# units of the macro time (T3: syncs, T2: global resolution)
_T3_WRAP = {0x00010303: 65536,  # PicoHarp 300 T3
            0x00010304: 1024, 0x01010304: 1024,  # HydraHarp V1, V2 T3
            0x00010305: 1024, 0x00010306: 1024,  # TimeHarp 260 N, P T3
            0x00010307: 1024}  # MultiHarp / PicoHarp 330 (generic) T3
_T2_GENERIC = {0x00010204: 33552000,  # HydraHarp V1 T2 (overflow = one wrap)
               0x01010204: 1 << 25, 0x00010205: 1 << 25, 0x00010206: 1 << 25,
               0x00010207: 1 << 25}  # HydraHarp V2, TimeHarp 260 N/P, generic T2
_T2_PICOHARP = 0x00010203
GENERIC_T2, GENERIC_T3 = 0x00010207, 0x00010307


@dataclass(frozen=True)
class PtuHeader:
    """What the import needs from a PTU header.

    Attributes
    ----------
    mode : "T2" or "T3".
    record_type : TTResultFormat_TTTRRecType (int).
    global_resolution : s; T3: the sync period, T2: the time-tag unit.
    resolution : s; T3: the dtime bin (TDC bin width), T2: as global.
    sync_rate : Hz as recorded at the start (TTResult_SyncRate).
    n_records : number of 32-bit records.
    tags : every header tag (name → value).
    """

    mode: str
    record_type: int
    global_resolution: float
    resolution: float
    sync_rate: float
    n_records: int
    tags: dict = field(default_factory=dict, compare=False, repr=False)


@dataclass
class EventBlock:
    """A block of time-ordered events (overflows consumed).

    macro : (n,) int64 — T3 sync count, or T2 time tag (global resolution).
    micro : (n,) int64 — T3 dtime (header.resolution), T2 zeros.
    kind : (n,) int8 — PHOTON, SYNC or MARKER.
    channel : (n,) int16 — photon input (0-based) or marker bit mask.
    """

    macro: np.ndarray
    micro: np.ndarray
    kind: np.ndarray
    channel: np.ndarray

    def __len__(self) -> int:
        return int(self.macro.size)


def _open(path):
    try:
        import ptufile
    except ImportError as e:  # pragma: no cover - a declared dependency
        raise FormatError("reading PTU files needs the 'ptufile' package "
                          "(pip install ptufile)", str(path)) from e
    from mems_stereo.util.paths import require_input_file

    require_input_file(path, None)  # a FIFO or a folder is refused before the parser sees it
    try:
        return ptufile.PtuFile(path)
    except FileNotFoundError:
        raise
    except Exception as e:  # noqa: BLE001 - the parser fails in many ways on a damaged header
        msg = (str(e).splitlines() or [type(e).__name__])[0][:120]
        raise FormatError(f"not a readable PicoQuant PTU file ({msg})", str(path)) from None


def _header_tag(tags: dict, key: str, default, kind, source: str):
    """Header tag ``key`` as ``kind`` (int or float); a tag of another type or not
    finite is a FormatError naming it."""
    v = tags.get(key, default)
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) \
            or not np.isfinite(v):
        raise FormatError(f"expected a number, found {v!r}"[:120], source, key)
    return kind(v)


def read_ptu_header(path: str | os.PathLike) -> PtuHeader:
    """Read the PTU header; :class:`FormatError` for image-mode-only or unknown records."""
    with _open(path) as p:
        return _header(p, str(path))


def _header(p, source: str) -> PtuHeader:
    try:
        tags = dict(p.tags)
        n_records = int(p.number_records)
    except Exception as e:  # noqa: BLE001 - a damaged header, seen by the parser late
        raise FormatError(f"not a readable PicoQuant PTU file ({type(e).__name__})",
                          source) from None
    rt = _header_tag(tags, "TTResultFormat_TTTRRecType", -1, int, source)
    if rt in _T3_WRAP:
        mode = "T3"
    elif rt in _T2_GENERIC or rt == _T2_PICOHARP:
        mode = "T2"
    else:
        raise FormatError(f"expected a T2 or T3 TTTR record type, found {rt:#x}", source,
                          "TTResultFormat_TTTRRecType")
    bits = _header_tag(tags, "TTResultFormat_BitsPerRecord", 32, int, source)
    if bits not in (0, 32):
        raise FormatError(f"expected 32 bits per record, found {bits}", source,
                          "TTResultFormat_BitsPerRecord")
    glob = _header_tag(tags, "MeasDesc_GlobalResolution", 0.0, float, source)
    res = _header_tag(tags, "MeasDesc_Resolution", 0.0, float, source)
    if not (glob > 0 and res > 0):
        raise FormatError(f"expected positive resolutions, found global {glob}, "
                          f"resolution {res}", source, "MeasDesc_Resolution")
    rate = _header_tag(tags, "TTResult_SyncRate", 0.0, float, source)
    return PtuHeader(mode, rt, glob, res, rate, n_records, tags)


def _decode_t2_generic(rec: np.ndarray, wrap: int, v1: bool,
                       carry: int) -> tuple[EventBlock, int]:
    """Decode HydraHarp/generic T2 records: the photons' and markers'
    :class:`EventBlock` (overflow records dropped) and the overflow count carried
    to the next block."""
    special = (rec >> 31).astype(bool)
    ch = ((rec >> 25) & 63).astype(np.int16)
    tt = (rec & 0x1FFFFFF).astype(np.int64)
    ovf = special & (ch == 63)
    n_ovf = ovf.astype(np.int64) if v1 else np.where(ovf, tt, 0)
    cum = np.cumsum(n_ovf) + carry
    macro = cum * wrap + tt
    kind = np.where(~special, PHOTON, np.where(ch == 0, SYNC, MARKER)).astype(np.int8)
    keep = ~ovf & (~special | (ch <= 15))
    ev = EventBlock(macro[keep], np.zeros(int(keep.sum()), np.int64), kind[keep], ch[keep])
    return ev, (int(cum[-1]) if cum.size else carry)


def iter_ptu_events(path: str | os.PathLike, chunk_records: int = 1 << 21
                    ) -> Iterator[tuple[PtuHeader, EventBlock]]:
    """Yield ``(header, EventBlock)`` for consecutive blocks of ``chunk_records`` records.

    Memory: O(chunk_records) whatever the file size: the records are read
    block by block with ``readinto`` (not memory-mapped, whose pages would
    count as resident memory as the file is swept).
    """
    source = str(path)
    chunk_records = max(1, int(chunk_records))
    with _open(path) as p:
        hdr = _header(p, source)
        offset = int(p.record_offset)
    if hdr.n_records == 0:
        return
    rt = hdr.record_type
    carry = 0  # overflow units (T3: syncs, T2 generic: wraps) before this block
    decoder = None
    if not (hdr.mode == "T2" and rt in _T2_GENERIC):
        decoder = _open(path)  # ptufile decodes T3 and PicoHarp T2 blocks
    buf = np.empty(chunk_records, dtype="<u4")
    try:
        with open(path, "rb") as fh:
            fh.seek(offset)
            left = hdr.n_records
            while left > 0:
                n = fh.readinto(memoryview(buf)[:min(left, chunk_records)]) // 4
                if n == 0:
                    raise FormatError(f"file ends {left} records before the "
                                      f"{hdr.n_records} its header declares", source,
                                      "TTResult_NumberOfRecords")
                left -= n
                blk = buf[:n]
                if decoder is None:
                    ev, carry = _decode_t2_generic(blk, _T2_GENERIC[rt], rt == 0x00010204,
                                                   carry)
                else:
                    d = decoder.decode_records(blk)
                    t = d["time"].astype(np.int64) + carry
                    if hdr.mode == "T3":
                        wrap = _T3_WRAP[rt]
                        micro = d["dtime"].astype(np.int64)
                    else:  # PicoHarp T2: no separate sync events
                        wrap = 210698240
                        micro = np.zeros(t.size, np.int64)
                    chan = d["channel"].astype(np.int16)
                    mark = d["marker"].astype(np.int16)
                    photon = chan >= 0
                    keep = photon | (mark > 0)
                    if t.size:
                        carry = int(t[-1]) // wrap * wrap
                    micro = np.where(photon, micro, 0)  # ptufile gives markers dtime -1
                    ev = EventBlock(t[keep], micro[keep],
                                    np.where(photon, PHOTON, MARKER).astype(np.int8)[keep],
                                    np.where(photon, chan, mark)[keep])
                yield hdr, ev
    finally:
        if decoder is not None:
            decoder.close()


# --------------------------------------------------------------------------- encoder
_TY_EMPTY, _TY_BOOL, _TY_INT, _TY_FLOAT, _TY_ANSI = (0xFFFF0008, 0x00000008, 0x10000008,
                                                     0x20000008, 0x4001FFFF)


def _tag(name: str, value, idx: int = -1) -> bytes:
    ident = name.encode("ascii").ljust(32, b"\0")
    if value is None:
        return ident + struct.pack("<iIq", idx, _TY_EMPTY, 0)
    if isinstance(value, bool):
        return ident + struct.pack("<iIq", idx, _TY_BOOL, int(value))
    if isinstance(value, (int, np.integer)):
        return ident + struct.pack("<iIq", idx, _TY_INT, int(value))
    if isinstance(value, (float, np.floating)):
        return ident + struct.pack("<iId", idx, _TY_FLOAT, float(value))
    b = str(value).encode("utf-8") + b"\0"
    b = b.ljust((len(b) + 7) // 8 * 8, b"\0")
    return ident + struct.pack("<iIq", idx, _TY_ANSI, len(b)) + b


def ptu_header_bytes(mode: str, global_resolution: float, resolution: float,
                     n_records: int, sync_rate: float, comment: str = "") -> bytes:
    """The tag header of a Generic T2/T3 PTU file (magic, version, tags, Header_End)."""
    if mode not in ("T2", "T3"):
        raise OptionError(f"mode: expected 'T2' or 'T3', found {mode!r}")
    tags = [("File_GUID", "{00000000-0000-4000-8000-000000000000}"),
            ("File_Comment", comment),
            ("CreatorSW_Name", "mems-stereo"),
            ("Measurement_Mode", 2 if mode == "T2" else 3),
            ("Measurement_SubMode", 0),
            ("MeasDesc_GlobalResolution", float(global_resolution)),
            ("MeasDesc_Resolution", float(resolution)),
            ("MeasDesc_BinningFactor", 1),
            ("TTResult_SyncRate", int(round(sync_rate))),
            ("TTResult_NumberOfRecords", int(n_records)),
            ("TTResultFormat_TTTRRecType", GENERIC_T2 if mode == "T2" else GENERIC_T3),
            ("TTResultFormat_BitsPerRecord", 32),
            ("HW_InpChannels", 64),
            ("Header_End", None)]
    return b"PQTTTR\0\x001.0.00\0\0" + b"".join(_tag(n, v) for n, v in tags)


def encode_t2(time, kind, channel, prev_wrap: int = 0) -> np.ndarray:
    """Generic T2 records of time-ordered events, overflow records inserted.

    time : (n,) int64 time tags (global resolution), non-decreasing; kind :
    (n,) PHOTON / SYNC / MARKER; channel : (n,) photon input 0..62 or marker
    mask 1..15.  ``prev_wrap`` : the overflow count (``time // 2**25``) of the
    last event already written, to encode a long stream block by block.
    Returns (m,) uint32 records.
    """
    t = np.asarray(time, dtype=np.int64)
    kind = np.asarray(kind)
    ch = np.asarray(channel, dtype=np.int64)
    if t.size and (t[0] < 0 or np.any(np.diff(t) < 0)):
        raise OptionError("time: expected non-negative, non-decreasing time tags")
    if np.any((kind == PHOTON) & ((ch < 0) | (ch > 62))) or np.any(
            (kind == MARKER) & ((ch < 1) | (ch > 15))):
        raise OptionError("channel: photon inputs 0..62, marker masks 1..15 in Generic T2")
    wrap = 1 << 25
    w = t // wrap
    # one overflow record (count = the jump) before each event whose wrap count grew
    jump = np.diff(np.concatenate([[prev_wrap], w]))
    special = kind != PHOTON
    code = np.where(kind == SYNC, 0, ch)
    ev = ((special.astype(np.uint64) << 31) | (code.astype(np.uint64) << 25)
          | (t % wrap).astype(np.uint64)).astype(np.uint32)
    return _interleave_overflows(ev, jump, (1 << 25) - 1)


def encode_t3(nsync, dtime, kind, channel) -> np.ndarray:
    """Generic T3 records: nsync (n,) int64 non-decreasing, dtime (n,) 0..32767,
    kind PHOTON / MARKER (T3 has no sync events), channel as in :func:`encode_t2`."""
    ns = np.asarray(nsync, dtype=np.int64)
    dt = np.asarray(dtime, dtype=np.int64)
    kind = np.asarray(kind)
    ch = np.asarray(channel, dtype=np.int64)
    if ns.size and (ns[0] < 0 or np.any(np.diff(ns) < 0)):
        raise OptionError("nsync: expected non-negative, non-decreasing sync counts")
    if np.any(kind == SYNC):
        raise OptionError("kind: T3 records carry no sync events")
    if np.any((dt < 0) | (dt > 32767)):
        raise OptionError("dtime: expected 0..32767 in Generic T3")
    if np.any((kind == PHOTON) & ((ch < 0) | (ch > 62))) or np.any(
            (kind == MARKER) & ((ch < 1) | (ch > 15))):
        raise OptionError("channel: photon inputs 0..62, marker masks 1..15 in Generic T3")
    w = ns // 1024
    jump = np.diff(np.concatenate([[0], w]))
    special = kind != PHOTON
    ev = ((special.astype(np.uint64) << 31) | (ch.astype(np.uint64) << 25)
          | (np.where(special, 0, dt).astype(np.uint64) << 10)
          | (ns % 1024).astype(np.uint64)).astype(np.uint32)
    return _interleave_overflows(ev, jump, 1023)


def _interleave_overflows(ev: np.ndarray, jump: np.ndarray, max_count: int) -> np.ndarray:
    """Insert overflow records (special, channel 63, count ≤ max_count) before events."""
    n_rec = np.where(jump > 0, -(-jump // max_count), 0)  # records needed per event
    out = np.empty(ev.size + int(n_rec.sum()), dtype=np.uint32)
    pos = np.arange(ev.size) + np.cumsum(n_rec)
    out[pos] = ev
    if n_rec.sum():
        is_ovf = np.ones(out.size, bool)
        is_ovf[pos] = False
        # counts: for each event with a jump, full records of max_count then the remainder
        owner = np.repeat(np.arange(ev.size), n_rec)
        first = np.repeat(np.cumsum(n_rec) - n_rec, n_rec)
        k = np.arange(owner.size) - first
        left = jump[owner] - k * max_count
        cnt = np.minimum(left, max_count).astype(np.uint64)
        out[is_ovf] = ((np.uint64(1) << np.uint64(31)) | (np.uint64(63) << np.uint64(25))
                       | cnt).astype(np.uint32)
    return out


def write_ptu(path: str | os.PathLike, mode: str, records, *, global_resolution: float,
              resolution: float, sync_rate: float, comment: str = "") -> Path:
    """Write a Generic T2/T3 PTU file from encoded records (atomically)."""
    rec = np.asarray(records, dtype="<u4")
    with atomic_output(path) as tmp, open(tmp, "wb") as f:
        f.write(ptu_header_bytes(mode, global_resolution, resolution, rec.size, sync_rate,
                                 comment))
        f.write(rec.tobytes())
    return Path(path)


# --------------------------------------------------------------------------- import glue
def ptu_stream(path: str | os.PathLike, chunk_records: int = 1 << 21):
    """``(StreamInfo, open_blocks)`` of a PTU file for :mod:`mems_stereo.io.tttr`.

    ``open_blocks()`` returns a fresh iterator of :class:`EventBlock`.
    """
    hdr = read_ptu_header(path)
    info = StreamInfo(hdr.mode, hdr.global_resolution, hdr.resolution, hdr.sync_rate)

    def open_blocks():
        return (ev for _, ev in iter_ptu_events(path, chunk_records))

    return info, open_blocks


def recording_to_ptu(recording, path: str | os.PathLike, *, mode: str = "T2",
                     channels=None, zc_markers=(1, 2), t2_ticks_per_bin: int = 64,
                     delay_bins: int = 0) -> dict:
    """Encode a FORMAT v1 recording as a Generic T2 or T3 PTU file (tests, samples).

    Every detection (code N > 0) becomes a photon on the channel of its
    pixel, every shot a sync (T2) or a sync count (T3), every zero crossing a
    marker (``zc_markers`` = (rising, falling) marker numbers, polarity
    positive).  ``channels`` : (H·W,) input per pixel index (default 0..P−1,
    at most 63).  T2: time-tag unit = bin_width / ``t2_ticks_per_bin``, each
    photon at the start of its bin plus ``delay_bins`` bins; shot times must
    be integer multiples of that unit (relative to 0).  T3: sync period =
    1 / f_rep, shot k at sync count round(shot_time / period); zero crossings
    are quantised to the sync period (markers carry no dtime in T3).

    Returns the mapping object (JSON-ready, without ``system``) that imports it.
    """
    sysm = recording.system
    w, h = sysm.receiver.image_size
    P = w * h
    ch_of_pix = np.arange(P) if channels is None else np.asarray(channels, np.int64)
    if ch_of_pix.size != P or ch_of_pix.max() > 62:
        raise OptionError(f"channels: expected {P} inputs 0..62 (one per pixel), found "
                         f"{ch_of_pix.size} up to {ch_of_pix.max()}")
    bins = np.asarray(recording.bins).reshape(recording.n_shots, P)
    k_idx, p_idx = np.nonzero(bins)
    code = bins[k_idx, p_idx].astype(np.int64)
    bw = sysm.tdc.bin_width
    zc = np.asarray(recording.zero_crossings)
    mk = np.where(np.asarray(recording.rising) > 0, 1 << (zc_markers[0] - 1),
                  1 << (zc_markers[1] - 1))
    if mode == "T2":
        tick = bw / t2_ticks_per_bin
        # time zero of the file: a whole number of sync periods before the first event
        period = 1.0 / sysm.laser.f_rep
        origin = float(np.floor(min(zc[0], recording.shot_time[0]) / period) * period)
        st = (np.asarray(recording.shot_time) - origin) / tick
        s_ticks = np.rint(st).astype(np.int64)
        if np.any(np.abs(st - s_ticks) > 1e-3) or s_ticks[0] < 0:
            raise OptionError("shot_time: expected non-negative multiples of the T2 time tag")
        ph_t = s_ticks[k_idx] + (code - 1 + delay_bins) * t2_ticks_per_bin
        z_t = np.rint((zc - origin) / tick).astype(np.int64)
        t = np.concatenate([s_ticks, ph_t, z_t])
        kind = np.concatenate([np.full(s_ticks.size, SYNC), np.full(ph_t.size, PHOTON),
                               np.full(z_t.size, MARKER)]).astype(np.int8)
        ch = np.concatenate([np.zeros(s_ticks.size, np.int64), ch_of_pix[p_idx], mk])
        # syncs first, then photons, then markers at equal times
        order = np.lexsort((kind != SYNC, t))
        rec = encode_t2(t[order], kind[order], ch[order])
        write_ptu(path, "T2", rec, global_resolution=tick, resolution=tick,
                  sync_rate=sysm.laser.f_rep)
        binning = t2_ticks_per_bin
    elif mode == "T3":
        period = 1.0 / sysm.laser.f_rep
        origin = float(np.floor(min(zc[0], recording.shot_time[0]) / period) * period)
        ns = np.rint((np.asarray(recording.shot_time) - origin) / period).astype(np.int64)
        zs = np.floor((zc - origin) / period).astype(np.int64)
        t = np.concatenate([ns[k_idx], zs])
        dt = np.concatenate([code - 1 + delay_bins, np.zeros(zs.size, np.int64)])
        kind = np.concatenate([np.full(k_idx.size, PHOTON), np.full(zs.size, MARKER)])
        ch = np.concatenate([ch_of_pix[p_idx], mk])
        order = np.argsort(t, kind="stable")
        rec = encode_t3(t[order], dt[order], kind[order], ch[order])
        write_ptu(path, "T3", rec, global_resolution=period, resolution=bw,
                  sync_rate=sysm.laser.f_rep)
        binning = 1
    else:
        raise OptionError(f"mode: expected 'T2' or 'T3', found {mode!r}")
    pix_rows = [[int(ch_of_pix[i]), i % w, i // w] for i in range(P)]
    first = 0 if mode == "T2" else int(ns[0])
    m = TttrMap(np.asarray(pix_rows, np.int64), "sync", None, "marker", zc_markers[0],
                zc_markers[1], True, 0.0, binning, delay_bins, "first",
                None if mode == "T2" else int(recording.n_shots), first, origin)
    return map_to_dict(m)
