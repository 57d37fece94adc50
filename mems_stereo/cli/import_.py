"""``mems-stereo import``: a time-tagger file (PicoQuant PTU, Photon-HDF5) → a recording."""

from __future__ import annotations

from pathlib import Path

from mems_stereo.cli._common import Reporter, add_parents_argument
from mems_stereo.errors import FormatError
from mems_stereo.model.system import resolve_system

NAME = "import"
HELP = ("convert a time-tagger file (PicoQuant .ptu T2/T3, Photon-HDF5 .h5/.hdf5) into a "
        "FORMAT v1 recording, through a channel mapping")
EXAMPLE = ["mems-stereo samples -o samples room48.ptu room48_map.json room48_system.json",
           "mems-stereo import samples/room48.ptu --map samples/room48_map.json -o room48.h5"]


def add_arguments(p):
    p.add_argument("input", metavar="FILE", help="PicoQuant .ptu (T2 or T3) or Photon-HDF5 file")
    p.add_argument("--map", required=True, metavar="MAP.json",
                   help="channel mapping (format mems-stereo/tttr-map, docs/formats.md)")
    p.add_argument("-o", "--output", required=True,
                   help="recording to write (.h5); with --all-photons the time-tag file (.npz)")
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
    suffix = src.suffix.lower()
    if suffix == ".ptu":
        from mems_stereo.io.ptu import ptu_stream

        info, blocks = ptu_stream(src, args.chunk_records)
    elif suffix in (".h5", ".hdf5", ".hdf"):
        from mems_stereo.io.photon_hdf5 import photon_hdf5_stream

        info, blocks = photon_hdf5_stream(src, args.chunk_records)
    else:
        raise FormatError(f"expected a .ptu or Photon-HDF5 (.h5, .hdf5) file, found suffix "
                          f"{suffix or '(none)'!r}", str(src))
    out = Path(args.output)
    all_photons = args.all_photons or m.photons == "all"
    if all_photons and out.suffix.lower() != ".npz":
        raise FormatError(f"with all photons the output is the time-tag layout: expected "
                          f"a .npz name, found {out.suffix or 'no suffix'!r}", field="--output")
    if not all_photons and out.suffix.lower() == ".npz":
        raise FormatError("a recording is written (HDF5): expected a .h5 name, found '.npz' "
                          "(the time-tag layout of --all-photons)", field="--output")
    rep.detail(f"{src}: {info.mode}, time unit {info.macro_unit:.6g} s, TDC unit "
               f"{info.micro_unit:.6g} s, bin width {m.binning * info.micro_unit:.6g} s")
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
