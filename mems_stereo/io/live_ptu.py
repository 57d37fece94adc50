"""A PicoQuant PTU file being written, followed as a live source of shots.

The header is read once (``ptufile``, :func:`mems_stereo.io.ptu.read_ptu_header`); the
32-bit records after it are read as they appear, whole records only (a record half
written is waited for, never read), decoded block by block with the overflow carried,
and turned into shots by the mapping of :mod:`mems_stereo.io.tttr` (the same code
assignment as ``mems-stereo import``: first photon per shot and pixel).  A shot is
complete once a later shot's clock has been read; the zero crossings come from the
mapped monitor events.  The stream ends when the header's record count (when the
writer filled it in) has been read, after ``idle_timeout`` s without a new record, or
at :meth:`~mems_stereo.io.live_sources.LiveSource.stop`.

Record types: T3 of every instrument (decoded by ``ptufile``) and T2 of the HydraHarp
V2 / TimeHarp 260 / MultiHarp / PicoHarp 330 layout (decoded here, as
:mod:`mems_stereo.io.ptu` does, since ``ptufile`` reports a T2 sync as channel 0).
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator

import numpy as np

from mems_stereo.errors import FormatError
from mems_stereo.io.live_sources import LiveSource, ShotRelease
from mems_stereo.io.ptu import MARKER, PHOTON, SYNC, EventBlock, read_ptu_header
from mems_stereo.io.recording import Recording
from mems_stereo.io.tttr import (
    ImportStats,
    StreamInfo,
    iter_photon_codes,
    pixel_lut,
    system_for_stream,
)
from mems_stereo.io.tttr_map import TttrMap
from mems_stereo.model.system import System

POLL_SECONDS = 0.005
#: T2 record types decoded here and their overflow period (HydraHarp V2, TimeHarp 260 N/P,
#: MultiHarp / PicoHarp 330 generic)
T2_WRAP = {0x01010204: 1 << 25, 0x00010205: 1 << 25, 0x00010206: 1 << 25,
           0x00010207: 1 << 25}
#: T3 record types (decoded by ptufile) and their overflow period in syncs
T3_WRAP = {0x00010303: 65536, 0x00010304: 1024, 0x01010304: 1024, 0x00010305: 1024,
           0x00010306: 1024, 0x00010307: 1024}
_EMPTY = np.uint16(65535)


def decode_t2(rec: np.ndarray, carry: int) -> tuple[EventBlock, int]:
    """Generic T2 records → events (overflows consumed) and the overflow count after them."""
    special = (rec >> 31).astype(bool)
    ch = ((rec >> 25) & 63).astype(np.int16)
    tt = (rec & 0x1FFFFFF).astype(np.int64)
    ovf = special & (ch == 63)
    cum = np.cumsum(np.where(ovf, tt, 0)) + carry
    kind = np.where(~special, PHOTON, np.where(ch == 0, SYNC, MARKER)).astype(np.int8)
    keep = ~ovf & (~special | (ch <= 15))
    ev = EventBlock((cum * (1 << 25) + tt)[keep], np.zeros(int(keep.sum()), np.int64),
                    kind[keep], ch[keep])
    return ev, (int(cum[-1]) if cum.size else carry)


class PtuTailSource(LiveSource):
    """Follow a PTU file being written (see the module doc).

    ``m`` : the channel mapping (:func:`mems_stereo.io.tttr_map.load_map`); ``system`` :
    the nominal system (its TDC bin width replaced by the header's).
    """

    def __init__(self, path: str | os.PathLike, m: TttrMap, system: System,
                 idle_timeout: float | None = 10.0, block_records: int = 1 << 16):
        import ptufile

        source = str(path)
        hdr = read_ptu_header(path)
        if hdr.record_type not in T2_WRAP and hdr.record_type not in T3_WRAP:
            raise FormatError(f"record type {hdr.record_type:#x} is not followed live; convert "
                              "it with mems-stereo import", source, "TTResultFormat_TTTRRecType")
        self.info = StreamInfo(hdr.mode, hdr.global_resolution, hdr.resolution, hdr.sync_rate)
        super().__init__(system_for_stream(system, self.info, m), source)
        with ptufile.PtuFile(path) as p:
            self.offset = int(p.record_offset)
        self.path, self.map, self.hdr = path, m, hdr
        self.idle_timeout = idle_timeout
        self.block = max(1, int(block_records))
        self.stats = ImportStats(bin_width=self.system.tdc.bin_width)
        self._last_macro = -1

    def _records(self) -> Iterator[np.ndarray]:
        """Whole 32-bit records as they are written."""
        done, last_new = 0, time.monotonic()
        with open(self.path, "rb") as fh:
            fh.seek(self.offset)
            while not self.stopped:
                avail = (os.path.getsize(self.path) - self.offset) // 4 - done
                if avail > 0:
                    n = min(avail, self.block)
                    rec = np.frombuffer(fh.read(4 * n), "<u4")
                    done += rec.size
                    last_new = time.monotonic()
                    yield rec
                    continue
                if self.hdr.n_records and done >= self.hdr.n_records:
                    self.ended = "finished"
                    return
                if self.idle_timeout is not None and \
                        time.monotonic() - last_new > self.idle_timeout:
                    self.ended = "idle" + self._short(done)
                    return
                self._stop.wait(POLL_SECONDS)
            self.ended = "stopped"

    def _short(self, done: int) -> str:
        """What an idle end left: the header's records not written, a torn last record."""
        torn = (os.path.getsize(self.path) - self.offset) % 4
        what = []
        if self.hdr.n_records and done < self.hdr.n_records:
            what.append(f"{done} of the header's {self.hdr.n_records} records written")
        if torn:
            what.append(f"a torn last record ({torn} bytes) left unread")
        return f" ({'; '.join(what)})" if what else ""

    def _events(self, rel: ShotRelease) -> Iterator[EventBlock]:
        """Decoded blocks; their zero crossings go to ``rel`` on the way."""
        import ptufile

        rt, carry = self.hdr.record_type, 0
        dec = ptufile.PtuFile(self.path) if rt in T3_WRAP else None
        try:
            for rec in self._records():
                if dec is None:
                    ev, carry = decode_t2(rec, carry)
                else:
                    d = dec.decode_records(rec)
                    t = d["time"].astype(np.int64) + carry
                    if t.size:
                        carry = int(t[-1]) // T3_WRAP[rt] * T3_WRAP[rt]
                    chan, mark = d["channel"].astype(np.int16), d["marker"].astype(np.int16)
                    ph = chan >= 0
                    keep = ph | (mark > 0)
                    ev = EventBlock(t[keep], np.where(ph, d["dtime"], 0).astype(np.int64)[keep],
                                    np.where(ph, PHOTON, MARKER).astype(np.int8)[keep],
                                    np.where(ph, chan, mark)[keep])
                if len(ev):
                    self._last_macro = int(ev.macro[-1])
                    self._crossings(ev, rel)
                yield ev
        finally:
            if dec is not None:
                dec.close()

    def _crossings(self, b: EventBlock, rel: ShotRelease) -> None:
        m, info = self.map, self.info
        times, rising = [], []
        for edge, is_rising in ((m.zc_rising_edge, True), (m.zc_falling_edge, False)):
            if edge is None:
                continue
            if m.zc_source == "marker":
                sel = (b.kind == MARKER) & ((b.channel & (1 << (edge - 1))) != 0)
            else:
                sel = (b.kind == PHOTON) & (b.channel == edge)
            t = b.macro[sel] * info.macro_unit
            if info.mode == "T3" and m.zc_source == "channel":
                t = t + b.micro[sel] * info.micro_unit
            times.append(t - m.zc_delay + m.time_origin)
            rising.append(np.full(t.size, is_rising == m.zc_positive))
        t, r = np.concatenate(times), np.concatenate(rising).astype(np.uint8)
        order = np.argsort(t, kind="stable")
        rel.add(zc=t[order], rising=r[order])

    def chunks(self) -> Iterator[Recording]:
        rel = ShotRelease(self.system, self.source)
        asm = _ShotAssembly(self.system, self.info, self.map)
        n_shots = self.map.n_shots if self.map.n_shots is not None else 1 << 62
        lut = pixel_lut(self.map, self.system)
        for shot, pix, code, cs, ct, _ in iter_photon_codes(
                self._events(rel), self.info, self.map, lut, n_shots, self.system.tdc.n_bins,
                self.stats):
            asm.add(shot, pix, code, cs, ct)
            upto = (self._last_macro - self.map.first_shot if self.info.mode == "T3"
                    else asm.clocks - 1)  # shots before the last clock read are complete
            got = asm.release(upto)
            if got is not None:
                rel.add(times=got[0], bins=got[1])
            out = rel.take()
            if out is not None:
                yield self.chunk(*out)
        got = asm.release(asm.top + 1)
        if got is not None:
            rel.add(times=got[0], bins=got[1])
        out = rel.take(final=self.ended != "stopped")
        if out is not None:
            yield self.chunk(*out)


class _ShotAssembly:
    """First photon per shot and pixel over a sliding window of shots (as the import)."""

    def __init__(self, system: System, info: StreamInfo, m: TttrMap):
        self.hw = system.receiver.width * system.receiver.height
        self.shape = (system.receiver.height, system.receiver.width)
        self.info, self.map = info, m
        self.base, self.top, self.clocks = 0, -1, 0
        self.buf = np.full((0, self.hw), _EMPTY, np.uint16)
        self.times = np.zeros(0)

    def _grow(self, upto: int) -> None:
        need = upto - self.base + 1 - self.buf.shape[0]
        if need > 0:
            self.buf = np.concatenate([self.buf, np.full((need, self.hw), _EMPTY, np.uint16)])
            self.times = np.concatenate([self.times, np.full(need, np.nan)])

    def add(self, shot, pix, code, cs, ct) -> None:
        if cs is not None and cs.size:
            self._grow(int(cs.max()))
            self.times[cs - self.base] = ct
            self.clocks = max(self.clocks, int(cs.max()) + 1)
            self.top = max(self.top, int(cs.max()))
        if shot.size:
            self._grow(int(shot.max()))
            self.top = max(self.top, int(shot.max()))
            np.minimum.at(self.buf.reshape(-1), (shot - self.base) * self.hw + pix,
                          code.astype(np.uint16))

    def release(self, upto: int):
        """``(times, bins)`` of the shots ``base … upto − 1`` (complete), or None."""
        k = min(upto, self.top + 1) - self.base
        if k <= 0:
            return None
        if self.info.mode == "T3":
            idx = np.arange(self.base, self.base + k) + self.map.first_shot
            t = idx * self.info.macro_unit + self.map.time_origin
        else:
            t = self.times[:k].copy()
            if np.isnan(t).any():
                raise FormatError("a shot without its sync time", field="shot_clock")
        bins = np.where(self.buf[:k] == _EMPTY, 0, self.buf[:k]).reshape((k, *self.shape))
        self.buf, self.times = self.buf[k:], self.times[k:]
        self.base += k
        return t, bins.astype(np.uint16)
