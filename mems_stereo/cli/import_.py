"""``mems-stereo import``: a time-tagger file (PicoQuant PTU, Photon-HDF5) → a recording."""

from __future__ import annotations

import sys
from pathlib import Path

from mems_stereo.cli._common import Reporter, add_parents_argument
from mems_stereo.errors import FormatError, OptionError
from mems_stereo.model.system import resolve_system

NAME = "import"
HELP = ("convert a time-tagger file (PicoQuant .ptu T2/T3, Photon-HDF5 .h5/.hdf5) into a "
        "FORMAT v1 recording, through a channel mapping")
EXAMPLE = ["mems-stereo samples -o samples room48.ptu room48_map.json room48_system.json",
           "mems-stereo import samples/room48.ptu --map samples/room48_map.json --dry-run",
           "mems-stereo import samples/room48.ptu --map samples/room48_map.json -o room48.h5"]
#: seconds of the file the checks read (and --dry-run prints) unless --dry-run-seconds
DEFAULT_SECONDS = 2.0


def add_arguments(p):
    p.add_argument("input", metavar="FILE", help="PicoQuant .ptu (T2 or T3) or Photon-HDF5 file")
    p.add_argument("--map", required=True, metavar="MAP.json",
                   help="channel mapping (format mems-stereo/tttr-map, docs/formats.md)")
    p.add_argument("-o", "--output", default=None,
                   help="recording to write (.h5); with --all-photons the time-tag file (.npz); "
                        "required unless --dry-run")
    add_parents_argument(p)
    p.add_argument("--system", default=None,
                   help="nominal system JSON or preset (default: the mapping's 'system')")
    p.add_argument("--all-photons", action="store_true",
                   help="keep every photon, not only the first per shot and pixel: write the "
                        "time-tag layout (.npz) of the TCSPC path instead of a recording")
    p.add_argument("--chunk-records", type=int, default=1 << 21,
                   help="records read per block; memory does not grow with the file "
                        "(default 2097152)")
    p.add_argument("--window-shots", type=int, default=8192,
                   help="shots assembled in memory before they are written (default 8192)")
    p.add_argument("--dry-run", action="store_true",
                   help="read only the first seconds, print their statistics (shots/s against "
                        "the sync rate, photons kept and why not, zero crossings/s against "
                        "2 f_mech, photons per input) and the checks' verdicts; write nothing; "
                        "exit 2 when a check refuses the map.  The same checks run before every "
                        "import: a clock or monitor input that is also a pixel's, the shot and "
                        "zero-crossing rates, under 50 %% of the photons kept, silent monitor "
                        "edges, shifted inputs, the binning against the system's bin width, an "
                        "inverted monitor polarity, reversed columns; a refusal names the map "
                        "field and its fix (exit 2), a warning goes to stderr "
                        "(docs/interchange.md)")
    p.add_argument("--dry-run-seconds", type=float, default=None, metavar="S",
                   help=f"seconds of the file the checks read (default {DEFAULT_SECONDS:g})")


def run(args) -> int:
    from mems_stereo.io.tttr import events_to_recording, events_to_timetags
    from mems_stereo.io.tttr_map import load_map

    rep = Reporter(args)
    src = Path(args.input)
    if not src.exists():
        raise FileNotFoundError(2, "file not found", str(src))
    m = load_map(args.map)
    if args.system is not None:
        system = resolve_system(args.system)
    elif m.system is not None:
        system = m.system
    else:
        raise FormatError("no nominal system: give --system or a 'system' field in the map",
                          args.map, "system")
    info, blocks = open_stream(src, args.chunk_records)
    if args.dry_run_seconds is not None and not args.dry_run_seconds > 0:
        raise OptionError(f"expected seconds > 0, found {args.dry_run_seconds}",
                          field="--dry-run-seconds")
    if args.output is None and not args.dry_run:
        raise OptionError("required unless --dry-run (the recording to write)",
                          field="--output")
    out = Path(args.output or "dry-run.h5")
    all_photons = args.all_photons or m.photons == "all"
    if all_photons and out.suffix.lower() != ".npz":
        raise FormatError(f"with all photons the output is the time-tag layout: expected "
                          f"a .npz name, found {out.suffix or 'no suffix'!r}", field="--output")
    if not all_photons and out.suffix.lower() == ".npz":
        raise FormatError("a recording is written (HDF5): expected a .h5 name, found '.npz' "
                          "(the time-tag layout of --all-photons)", field="--output")
    rep.detail(f"{src}: {info.mode}, time unit {info.macro_unit:.6g} s, TDC unit "
               f"{info.micro_unit:.6g} s, bin width {m.binning * info.micro_unit:.6g} s")
    if check_wiring(args, rep, (info, blocks), m, system):
        return 0
    try:
        if all_photons:
            st = events_to_timetags(blocks, info, m, system, out, source=str(src))
        else:
            st = events_to_recording(blocks, info, m, system, out,
                                     window_shots=args.window_shots, source=str(src))
    except FormatError as e:
        if e.source is None and str(e.field or "").startswith("pixels"):
            raise FormatError(e.reason, str(args.map), e.field) from None
        if e.source is not None and Path(e.source) == out:
            # found while the recording was assembled: the input (or its mapping) is at fault
            raise FormatError(f"the recording built from it with {args.map} is invalid: "
                              f"{e.field}: {e.reason}", str(src)) from None
        raise
    if abs(st.bin_width - system.tdc.bin_width) > 1e-6 * system.tdc.bin_width:
        rep.info(f"note: TDC bin width {st.bin_width:.6g} s from the file header replaces the "
                 f"system's {system.tdc.bin_width:.6g} s")
    rep.info(f"{out}: {st.summary()}")
    return 0


def open_stream(src: Path, chunk_records: int):
    """``(StreamInfo, open_blocks)`` of a PTU or Photon-HDF5 file, by its suffix."""
    suffix = src.suffix.lower()
    if suffix == ".ptu":
        from mems_stereo.io.ptu import ptu_stream

        return ptu_stream(src, chunk_records)
    if suffix in (".h5", ".hdf5", ".hdf"):
        from mems_stereo.io.photon_hdf5 import photon_hdf5_stream

        return photon_hdf5_stream(src, chunk_records)
    raise FormatError(f"expected a .ptu or Photon-HDF5 (.h5, .hdf5) file, found suffix "
                      f"{suffix or '(none)'!r}", str(src))


def check_wiring(args, rep: Reporter, stream, m, system) -> bool:
    """The checks of the first seconds: print the statistics with ``--dry-run``, the
    warnings on stderr; raise the first refusal.  True when the run ends here
    (``--dry-run`` without a refusal)."""
    from mems_stereo.cli._import_sanity import analyse_import
    from mems_stereo.io.import_checks import CAUSE_IMPORT

    info, blocks = stream
    seconds = args.dry_run_seconds or DEFAULT_SECONDS
    res = analyse_import(blocks, info, m, system, seconds, source=str(args.input),
                         map_source=str(args.map))
    if args.dry_run:
        from mems_stereo.io.import_checks import sample_text

        lines = sample_text(res.sample, m) if res.sample is not None else [
            f"first {seconds:g} s: not importable"]
        for line in lines + [v.line() for v in res.verdicts] + [
                "verdict: " + ("refused" if res.refusals else "clean" if not res.verdicts
                               else "warnings")]:
            print(line)
    elif not rep.quiet:
        for v in res.warnings:
            print(f"mems-stereo import: warning: {args.map}: {v.field}: {v.text} ({v.cause})",
                  file=sys.stderr)
    if res.refusals:
        v = res.refusals[0]
        if res.error is not None and v.cause == CAUSE_IMPORT:
            raise res.error
        raise FormatError(f"{v.text} ({v.cause})", str(args.map), v.field)
    return bool(args.dry_run)
