"""Sanity of an import: what a correct channel mapping must give, checked on its statistics.

A mapping file (``mems-stereo/tttr-map``) that is valid JSON can still be
wired wrong: the laser trigger one input off, pixels shifted, the wrong TDC
binning, the monitor's markers swapped.  Such a map converts without an
error into a recording that looks plausible and is wrong.  The functions here
look at what the import of the first seconds of a stream gives
(:class:`ImportSample`) and return :class:`Verdict`\\ s: each names the map
field at fault, a short cause (one of the ``CAUSE_*`` strings) and the fix;
a *refusal* stops the import (``mems-stereo import`` exits 2), a *warning*
is printed.  The functions are pure: the statistics are gathered by the
command (``mems_stereo.cli._import_sanity``).

=========================  ===============================================  ==========
cause                      when                                             verdict
=========================  ===============================================  ==========
clock on a pixel input     ``shot_clock.channel`` (or a monitor channel)    refuse
                           is also an input of ``pixels``
monitor edges on one       ``rising_edge`` = ``falling_edge``               refuse
input
shot rate                  shots per second off the header's sync rate      refuse >10 %
                           (or the system's ``laser.f_rep``)                warn >2 %
zero-crossing rate         crossings per second off 2 f_mech (f_mech        refuse >25 %
                           when one edge is wired)                          warn >10 %
monitor edge silent        a wired edge has no events                       refuse
monitor quantised          the monitor on a T3 marker (sync-period times)   warn
few photons kept           < 50 % of the photons reach a shot and code      refuse
                           (reasons counted; the commonest is named)
pixels shifted             photons on unmapped inputs, or mapped inputs     warn
                           without photons
binning                    binning × header resolution ≠ the system's bin   warn
                           width, which a whole binning would give
polarity inverted          detections fit the mirrored scan angle (z ≥ 5;   refuse
                           3 ≤ z < 5: warn)
columns reversed           detections fit the columns in reverse order      refuse
=========================  ===============================================  ==========
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field

import numpy as np

from mems_stereo.io.recording_checks import CROSSING_FREQUENCY_TOLERANCE
from mems_stereo.io.tttr import MARKER, PHOTON, SYNC, ImportStats, StreamInfo
from mems_stereo.io.tttr_map import TttrMap

CAUSE_CLOCK_ON_PIXEL = "clock on a pixel input"
CAUSE_SAME_EDGE = "monitor edges on one input"
CAUSE_SHOT_RATE = "shot rate"
CAUSE_ZC_RATE = "zero-crossing rate"
CAUSE_EDGE_SILENT = "monitor edge silent"
CAUSE_FEW_KEPT = "few photons kept"
CAUSE_PIXELS_SHIFTED = "pixels shifted"
CAUSE_BINNING = "binning"
CAUSE_POLARITY = "polarity inverted"
CAUSE_REVERSED = "columns reversed"
CAUSE_IMPORT = "not importable"
CAUSE_T3_MARKER = "monitor quantised"

#: below this share of photons kept (reaching a shot and a code 1..n_bins) an import is refused
KEPT_MIN = 0.5
#: relative deviation of the shot rate from the sync rate: refused beyond, warned beyond
SHOT_RATE_REFUSE, SHOT_RATE_WARN = 0.10, 0.02
#: relative deviation of the zero-crossing rate from 2 f_mech: refused beyond (the
#: recording reader's own tolerance on the crossings' frequency), warned beyond
ZC_RATE_REFUSE, ZC_RATE_WARN = CROSSING_FREQUENCY_TOLERANCE, 0.10
#: z of the paired evidence (polarity, column order) from which a verdict is refused / warned
EVIDENCE_REFUSE_Z, EVIDENCE_WARN_Z = 5.0, 3.0
#: an input counts as carrying photons from this share of the median mapped input's count
ACTIVE_SHARE = 0.1
#: a T3 marker's quantisation (the sync period) above this share of the mirror period is warned
T3_MARKER_SHARE = 0.01
#: shifts of the pixels' inputs tried to explain active unmapped / silent mapped inputs
MAX_SHIFT = 8


@dataclass(frozen=True)
class Verdict:
    """One finding of the checks.

    refuse : True stops the import (exit 2); False is a warning.
    field : the map field at fault (e.g. ``shot_clock.channel``).
    cause : one of the module's ``CAUSE_*`` strings.
    text : what was found and the fix, one line.
    """

    refuse: bool
    field: str
    cause: str
    text: str

    def line(self) -> str:
        """``refused``/``warning``, the cause, the field and the text, one line."""
        kind = "refused" if self.refuse else "warning"
        return f"{kind} ({self.cause}): {self.field}: {self.text}"


@dataclass(frozen=True)
class PairedEvidence:
    """Detections inside the accepted code intervals under the mapping as written only
    (``only_recorded``) and under an alternative only (``only_alternative``)."""

    only_recorded: int
    only_alternative: int

    @property
    def z(self) -> float:
        """McNemar's z, about N(0, 1) when neither fits better; > 0: the alternative fits."""
        n = self.only_recorded + self.only_alternative
        return (self.only_alternative - self.only_recorded) / np.sqrt(n) if n else 0.0


@dataclass(frozen=True)
class EventCounts:
    """Events of a stream by kind.

    photons : input channel → photons on it; markers : marker number (1..4) →
    events carrying it; syncs : sync events (T2).
    """

    photons: dict = field(default_factory=dict)
    markers: dict = field(default_factory=dict)
    syncs: int = 0


@dataclass(frozen=True)
class ImportSample:
    """What the import of a stream's first seconds gives (the checks' input).

    Attributes
    ----------
    seconds : s, the length of stream read.
    n_shots : shots imported; shot_span : s, last minus first shot time.
    sync_rate : Hz, the header's (0 when unknown); f_rep : Hz, the system's laser.
    n_zero_crossings : crossings imported; zc_span : s, last minus first.
    f_mech : Hz, the system's mirror frequency.
    stats : the conversion's counts (photons kept and why not).
    events : the events by kind and channel (:class:`EventCounts`).
    header_bin : s, binning × the header's TDC resolution (the bin imported).
    micro_unit : s, the header's TDC resolution; system_bin : s, the system's bin width.
    polarity, reversed_columns : :class:`PairedEvidence` of the mirrored scan angle
        and of the columns in reverse order, or None when not measured.
    mode : "T2" or "T3"; macro_unit : s, the header's macro time unit (T3: the sync period).
    """

    seconds: float
    n_shots: int
    shot_span: float
    sync_rate: float
    f_rep: float
    n_zero_crossings: int
    zc_span: float
    f_mech: float
    stats: ImportStats
    events: EventCounts
    micro_unit: float
    system_bin: float
    polarity: PairedEvidence | None = None
    reversed_columns: PairedEvidence | None = None
    mode: str = "T2"
    macro_unit: float = 0.0

    @property
    def shots_per_s(self) -> float:
        """Shots per second (NaN with fewer than two shots)."""
        return (self.n_shots - 1) / self.shot_span if self.shot_span > 0 else float("nan")

    @property
    def zc_per_s(self) -> float:
        """Zero crossings per second (NaN with fewer than two)."""
        return ((self.n_zero_crossings - 1) / self.zc_span if self.zc_span > 0
                else float("nan"))

    @property
    def kept(self) -> int:
        """Photons that reached a shot and a code 1..n_bins (written or later in their shot)."""
        s = self.stats
        return s.photons - s.unmapped - s.out_of_range - s.outside_shots


# ------------------------------------------------------------------ reading the first seconds
def first_seconds(open_blocks: Callable[[], Iterable], info: StreamInfo,
                  seconds: float) -> Callable[[], Iterator]:
    """``open_blocks`` cut at ``seconds`` after the stream's first event.

    Event time: macro × ``info.macro_unit`` (T2: the time tag; T3: the sync
    count × the sync period).  Returns a callable giving a fresh iterator.
    """
    def opened():
        t_end = None
        for b in open_blocks():
            if len(b) == 0:
                continue
            t = b.macro * info.macro_unit
            if t_end is None:
                t_end = float(t[0]) + seconds
            n = int(np.searchsorted(t, t_end))
            if n < len(b):
                yield type(b)(b.macro[:n], b.micro[:n], b.kind[:n], b.channel[:n])
                return
            yield b
    return opened


def count_events(blocks: Iterable) -> EventCounts:
    """Photons per input channel, events per marker number (1..4) and syncs."""
    ph = np.zeros(0, np.int64)
    mk = np.zeros(4, np.int64)
    syncs = 0
    for b in blocks:
        if len(b) == 0:
            continue
        ch = b.channel.astype(np.int64)
        c = np.bincount(ch[b.kind == PHOTON], minlength=ph.size)
        ph = c if ph.size == 0 else np.concatenate([ph, np.zeros(c.size - ph.size, np.int64)]) + c
        m = ch[b.kind == MARKER]
        mk += np.array([int(((m >> k) & 1).sum()) for k in range(4)])
        syncs += int((b.kind == SYNC).sum())
    return EventCounts({int(c): int(n) for c, n in enumerate(ph) if n},
                       {k + 1: int(n) for k, n in enumerate(mk) if n}, syncs)


# ------------------------------------------------------------------ the checks
def map_verdicts(m: TttrMap) -> list[Verdict]:
    """Wiring the map itself contradicts: a clock or monitor input that is also a
    pixel's, both monitor edges on one input."""
    out = []
    pixel_of = {int(c): i for i, c in enumerate(m.pixels[:, 0])}
    if m.clock == "channel" and m.clock_channel in pixel_of:
        i = pixel_of[m.clock_channel]
        out.append(Verdict(True, "shot_clock.channel", CAUSE_CLOCK_ON_PIXEL,
                           f"input {m.clock_channel} is the shot clock and also pixels[{i}]'s "
                           f"input: the laser trigger needs an input of its own; set "
                           f"shot_clock.channel to the trigger's input (or source 'sync')"))
    edges = [("rising_edge", m.zc_rising_edge), ("falling_edge", m.zc_falling_edge)]
    if m.zc_source == "channel":
        for name, e in edges:
            if e in pixel_of:
                out.append(Verdict(True, f"zero_crossings.{name}", CAUSE_CLOCK_ON_PIXEL,
                                   f"input {e} is the mirror monitor and also "
                                   f"pixels[{pixel_of[e]}]'s input: set it to the monitor's "
                                   f"input"))
    if m.zc_rising_edge is not None and m.zc_rising_edge == m.zc_falling_edge:
        out.append(Verdict(True, "zero_crossings.falling_edge", CAUSE_SAME_EDGE,
                           f"rising_edge and falling_edge are both {m.zc_source} "
                           f"{m.zc_rising_edge}: set each to the {m.zc_source} of its own "
                           f"edge (or null when an edge is not wired)"))
    return out


def _deviation(found: float, expected: float) -> float:
    return abs(found / expected - 1.0) if expected > 0 and np.isfinite(found) else 0.0


def rate_verdicts(s: ImportSample, m: TttrMap) -> list[Verdict]:
    """Shots per second against the sync rate; zero crossings against 2 f_mech; silent
    monitor edges."""
    out = []
    ref, ref_name = (s.sync_rate, "the header's sync rate") if s.sync_rate > 0 else (
        s.f_rep, "the system's laser.f_rep")
    dev = _deviation(s.shots_per_s, ref)
    if dev > SHOT_RATE_WARN:
        fix = ("the shot clock's input is not the laser trigger: set shot_clock.channel to it"
               if m.clock == "channel" else "check the sync divider and shots.first")
        out.append(Verdict(dev > SHOT_RATE_REFUSE, "shot_clock", CAUSE_SHOT_RATE,
                           f"{s.shots_per_s:.6g} shots/s, {ref_name} is {ref:.6g} Hz "
                           f"({100 * dev:.0f} % off): {fix}"))
    silent = _silent_edges(s, m)
    out += silent
    t3 = _t3_marker(s, m)
    if t3 is not None:
        out.append(t3)
    wired = [e for e in (m.zc_rising_edge, m.zc_falling_edge) if e is not None]
    expected = s.f_mech * (2 if len(wired) == 2 else 1)
    dev = _deviation(s.zc_per_s, expected)
    if dev > ZC_RATE_WARN and not silent:
        out.append(Verdict(dev > ZC_RATE_REFUSE, "zero_crossings", CAUSE_ZC_RATE,
                           f"{s.zc_per_s:.6g} zero crossings/s, expected {expected:.6g} "
                           f"({len(wired)} edge{'s' if len(wired) == 2 else ''} of the "
                           f"system's f_mech = {s.f_mech:.6g} Hz; {100 * dev:.0f} % off): set "
                           f"rising_edge / falling_edge to the monitor's "
                           f"{m.zc_source}s, or use the system of this mirror"))
    return out


def _t3_marker(s: ImportSample, m: TttrMap) -> Verdict | None:
    """A monitor on a T3 marker: its time is the sync count only."""
    share = s.macro_unit * s.f_mech
    if s.mode != "T3" or m.zc_source != "marker" or share <= T3_MARKER_SHARE:
        return None
    return Verdict(False, "zero_crossings.source", CAUSE_T3_MARKER,
                   f"a T3 marker carries only its sync count: the monitor's times are "
                   f"quantised to the sync period {s.macro_unit:.6g} s, {100 * share:.0f} % of "
                   f"the mirror period: wire the monitor to an input (source 'channel') or "
                   f"record T2")


def _silent_edges(s: ImportSample, m: TttrMap) -> list[Verdict]:
    """A wired monitor edge without events while the stream has others."""
    if m.zc_source == "marker":
        seen, what = s.events.markers, "markers"
    else:
        seen, what = s.events.photons, "inputs"
    out = []
    for name, e in (("rising_edge", m.zc_rising_edge), ("falling_edge", m.zc_falling_edge)):
        if e is not None and seen.get(e, 0) == 0:
            others = ", ".join(f"{k}: {n}" for k, n in sorted(seen.items())[:6]) or "none"
            out.append(Verdict(True, f"zero_crossings.{name}", CAUSE_EDGE_SILENT,
                               f"{m.zc_source} {e} has no events in the first "
                               f"{s.seconds:g} s ({what} with events: {others}): set it to "
                               f"the monitor's {m.zc_source} (null when not wired)"))
    return out


def photon_verdicts(s: ImportSample, m: TttrMap) -> list[Verdict]:
    """Photons kept (reasons counted), inputs shifted, binning against the system."""
    out = []
    st = s.stats
    if st.photons and s.kept < KEPT_MIN * st.photons:
        out.append(_few_kept(s, m))
    shifted = _shift_verdict(s, m)
    if shifted is not None:
        out.append(shifted)
    if s.micro_unit > 0 and s.system_bin > 0:
        n = s.system_bin / s.micro_unit
        if abs(n - round(n)) < 1e-6 * n and round(n) != m.binning and round(n) >= 1:
            out.append(Verdict(False, "tdc.binning", CAUSE_BINNING,
                               f"binning {m.binning} × the header's resolution "
                               f"{s.micro_unit:.6g} s gives bins of "
                               f"{m.binning * s.micro_unit:.6g} s, the system's tdc.bin_width "
                               f"is {s.system_bin:.6g} s: set tdc.binning to {round(n)}"))
    return out


def _few_kept(s: ImportSample, m: TttrMap) -> Verdict:
    st = s.stats
    reasons = {"outside codes 1..n_bins": st.out_of_range, "on unmapped inputs": st.unmapped,
               "outside the shots": st.outside_shots}
    top = max(reasons, key=reasons.get)
    counted = ", ".join(f"{n} {k}" for k, n in reasons.items())
    head = f"{s.kept} of {st.photons} photons kept ({100 * s.kept / st.photons:.0f} %; " \
           f"{counted})"
    if _deviation(s.shots_per_s, s.sync_rate or s.f_rep) > SHOT_RATE_REFUSE:
        fld, why = "shot_clock", "the shot clock is not the laser's: photons fall far from a shot"
    elif top == "on unmapped inputs":
        fld, why = "pixels", "the pixels' inputs are wrong (shifted?)"
    elif top == "outside the shots":
        fld, why = "shot_clock", "photons before the first shot clock: the clock is wrong"
    elif st.below_codes * 2 > st.out_of_range:
        fld, why = "tdc.delay_bins", "codes below 1: tdc.delay_bins too large"
    else:
        fld = "tdc.binning"
        n = s.system_bin / s.micro_unit if s.micro_unit > 0 else 0
        why = ("codes beyond n_bins: the binning is too small"
               + (f" (the system's bin width needs binning {round(n)})" if n >= 1 else "")
               + ", or tdc.delay_bins too negative")
    return Verdict(True, fld, CAUSE_FEW_KEPT, f"{head}: {why}")


def _shift_verdict(s: ImportSample, m: TttrMap) -> Verdict | None:
    """Active inputs that are not mapped, or mapped inputs without photons."""
    mapped = {int(c) for c in m.pixels[:, 0]}
    counts = s.events.photons
    skip = {m.clock_channel} if m.clock == "channel" else set()
    if m.zc_source == "channel":
        skip |= {m.zc_rising_edge, m.zc_falling_edge}
    mapped_n = [counts.get(c, 0) for c in mapped]
    level = ACTIVE_SHARE * float(np.median(mapped_n)) if mapped_n else 0.0
    active = {c for c, n in counts.items() if n >= max(level, 20) and c not in skip}
    if max(mapped_n or [0]) < 20:
        return None
    unmapped_active = sorted(active - mapped)
    silent = sorted(c for c in mapped if counts.get(c, 0) < level)
    if not unmapped_active and not silent:
        return None
    best = min(range(-MAX_SHIFT, MAX_SHIFT + 1),
               key=lambda k: (len(active ^ {c + k for c in mapped}), abs(k)))
    parts = []
    if unmapped_active:
        n = sum(counts[c] for c in unmapped_active)
        one = len(unmapped_active) == 1
        parts.append(f"input{'' if one else 's'} {_few(unmapped_active)} carr"
                     f"{'ies' if one else 'y'} {n} photons but no pixel")
    if silent:
        one = len(silent) == 1
        parts.append(f"mapped input{'' if one else 's'} {_few(silent)} ha"
                     f"{'s' if one else 've'} (almost) none")
    if best:
        fix = (f"the pixels' inputs look shifted by {best:+d}: "
               f"{'add' if best > 0 else 'subtract'} {abs(best)} "
               f"{'to' if best > 0 else 'from'} each pixel's channel")
    elif unmapped_active:
        fix = "map those inputs, or check the pixels' channels"
    else:
        fix = "dead pixels, or check the pixels' channels"
    return Verdict(False, "pixels", CAUSE_PIXELS_SHIFTED, "; ".join(parts) + f": {fix}")


def _few(chs: list) -> str:
    return ", ".join(map(str, chs[:6])) + (f" (+{len(chs) - 6} more)" if len(chs) > 6 else "")


def evidence_verdicts(s: ImportSample, m: TttrMap) -> list[Verdict]:
    """The monitor's polarity and the column order, from the detections' fit (the
    better-fitting alternative first).  Where the pixels' inputs look shifted, or
    the monitor is quantised to a T3 sync period, the geometry is off anyway, and
    these are warnings only."""
    out = []
    trusted = _shift_verdict(s, m) is None and _t3_marker(s, m) is None
    ev = s.polarity
    if ev is not None and ev.z >= EVIDENCE_WARN_Z:
        other = "negative" if m.zc_positive else "positive"
        fix = (f"set zero_crossings.polarity to {other!r} (or, if the markers are swapped, "
               f"swap rising_edge and falling_edge)")
        out.append((ev.z, Verdict(trusted and ev.z >= EVIDENCE_REFUSE_Z,
                                  "zero_crossings.polarity", CAUSE_POLARITY,
                                  f"the detections fit the mirrored scan angle: "
                                  f"{ev.only_alternative} only the inverted polarity, "
                                  f"{ev.only_recorded} only the mapped one (z = {ev.z:.1f}): "
                                  f"{fix}")))
    ev = s.reversed_columns
    if ev is not None and ev.z >= EVIDENCE_WARN_Z:
        out.append((ev.z, Verdict(trusted and ev.z >= EVIDENCE_REFUSE_Z, "pixels",
                                  CAUSE_REVERSED,
                                  f"the detections fit the columns in reverse order: "
                                  f"{ev.only_alternative} only reversed, {ev.only_recorded} "
                                  f"only as mapped (z = {ev.z:.1f}): set each pixel's column "
                                  f"to W − 1 − column")))
    return [v for _, v in sorted(out, key=lambda x: -x[0])]


def import_verdicts(s: ImportSample, m: TttrMap) -> list[Verdict]:
    """Every verdict on an import's first seconds, refusals first."""
    v = map_verdicts(m) + rate_verdicts(s, m) + photon_verdicts(s, m) + evidence_verdicts(s, m)
    return sorted(v, key=lambda x: not x.refuse)


def sample_text(s: ImportSample, m: TttrMap) -> list[str]:
    """The statistics of :class:`ImportSample`, as lines for ``import --dry-run``."""
    st = s.stats
    ref = f"header sync rate {s.sync_rate:.6g} Hz" if s.sync_rate > 0 else \
        f"no sync rate in the header; laser.f_rep {s.f_rep:.6g} Hz"
    wired = sum(e is not None for e in (m.zc_rising_edge, m.zc_falling_edge))
    lines = [f"first {s.seconds:g} s read: {s.n_shots} shots over {s.shot_span:.6g} s, "
             f"{s.shots_per_s:.6g} shots/s ({ref})",
             f"zero crossings: {s.n_zero_crossings}, {s.zc_per_s:.6g}/s (expected "
             f"{wired * s.f_mech:.6g}/s: {wired} edge(s) × f_mech {s.f_mech:.6g} Hz)",
             f"photons: {st.photons}, kept {s.kept} ({100 * s.kept / max(st.photons, 1):.1f} %); "
             f"not kept: {st.out_of_range} outside codes 1..n_bins ({st.below_codes} below 1), "
             f"{st.unmapped} on unmapped inputs, {st.outside_shots} outside the shots; "
             f"{st.not_first} later in their shot",
             "photons per input: " + (", ".join(f"{c}: {n}" for c, n in
                                                sorted(s.events.photons.items())) or "none"),
             "events per marker: " + (", ".join(f"{c}: {n}" for c, n in
                                                sorted(s.events.markers.items())) or "none")
             + f"; sync events: {s.events.syncs}"]
    for name, ev in (("polarity", s.polarity), ("column order", s.reversed_columns)):
        if ev is not None:
            lines.append(f"{name}: {ev.only_recorded} detections fit only the map, "
                         f"{ev.only_alternative} only the alternative (z = {ev.z:.1f})")
    return lines
