"""What each command writes: command and option → the suffixes it accepts → their writer.

One table, :data:`WRITES`, read by the help texts (:func:`suffix_help`), by the
checks before any work (:func:`mems_stereo.cli._pathcheck.check_outputs`
refuses any other suffix, naming the option and the suffixes it accepts) and
by tests/test_cli_outputs.py, which writes every suffix through every command
and reads the file back with its own library.  A folder output (``samples``,
``demo``, ``process`` with several recordings) has no suffix.
"""

from __future__ import annotations

from dataclasses import dataclass

_CLOUD = "mems_stereo.viz.export:write_cloud"
_FIGURE = "mems_stereo.viz.plots:_save"
CLOUD_SUFFIXES = (".ply", ".pcd", ".las", ".laz", ".mcap", ".db3")
PLOT_SUFFIXES = (".png", ".pdf", ".svg")
#: ``process --frame-rate/--frame-shots -o``: a ROS 2 bag of frames
#: (mems_stereo.viz.export_frames.FrameBagSink), else a folder of one file per frame in
#: one of :data:`FRAME_FORMATS` (FrameFolderSink, ``--frame-format``)
FRAME_BAG_SUFFIXES = (".mcap", ".db3")
FRAME_FORMATS = ("ply", "pcd", "las", "laz")


@dataclass(frozen=True)
class Written:
    """The files one output option writes: suffix → writer (``module:function``)."""

    writers: dict
    #: a folder is written (no suffix); with ``writers`` too: a file for one input
    #: (``process -o``), a folder of ``<name>.ply`` for several
    folder: bool = False

    @property
    def suffixes(self) -> tuple:
        return tuple(self.writers)


def _same(suffixes, writer: str) -> dict:
    return dict.fromkeys(suffixes, writer)


#: (command, option's argument name) → what it writes; ``plot`` by figure
WRITES: dict[tuple[str, str], Written] = {
    ("info", "plot"): Written(_same(PLOT_SUFFIXES, _FIGURE)),
    ("simulate", "output"): Written(_same((".h5",), "mems_stereo.sim:write_simulation")),
    ("process", "output"): Written(_same(CLOUD_SUFFIXES, _CLOUD), folder=True),
    ("process", "labels"): Written(_same((".h5",), "mems_stereo.pipeline.run:process_recording")),
    ("process", "histograms"): Written(_same((".h5",),
                                             "mems_stereo.io.histograms:write_histograms")),
    ("calibrate", "output"): Written({
        ".json": "mems_stereo.model.system:save_system",
        **_same((".yml", ".yaml", ".xml"), "mems_stereo.calib.opencv_io:write_opencv_system")}),
    ("calibrate", "report"): Written({
        ".pdf": "mems_stereo.viz.calib_report:write_calibration_report",
        ".json": "mems_stereo.cli.calibrate:_write_report"}),
    ("import", "output"): Written({".h5": "mems_stereo.io.tttr:events_to_recording",
                                   ".npz": "mems_stereo.io.tttr:events_to_timetags"}),
    ("samples", "output"): Written({}, folder=True),
    ("export", "output"): Written(_same(CLOUD_SUFFIXES, _CLOUD)),
    ("render", "output"): Written(_same((".png",), "mems_stereo.viz.render:render_cloud")),
    ("plot acquisition", "output"): Written(_same(PLOT_SUFFIXES, _FIGURE)),
    ("plot histograms", "output"): Written(_same(PLOT_SUFFIXES, _FIGURE)),
    ("plot cloud", "output"): Written(_same(PLOT_SUFFIXES, _FIGURE)),
    ("demo", "output"): Written({}, folder=True),
    # a bag of frames, or a folder of frames (DIR/) written as they come
    ("live", "output"): Written(
        _same(FRAME_BAG_SUFFIXES, "mems_stereo.viz.export_frames:FrameBagSink"), folder=True),
}


def suffixes(command: str, option: str) -> tuple:
    """The suffixes ``command``'s option ``option`` writes (lower case, with the dot)."""
    return WRITES[(command, option)].suffixes


def suffix_help(command: str, option: str) -> str:
    """The suffixes as the help texts list them: ``.ply, .pcd, .las``."""
    return ", ".join(suffixes(command, option))


PARENTS_HELP = ("create the missing folders of the output paths (as mkdir -p); without it a "
                "missing folder is refused")


def frames_to_folder(args) -> bool:
    """Whether ``process``'s ``-o`` receives a folder of frames: frames asked for
    (``--frame-rate``/``--frame-shots``) and the output ends in a slash or is a folder."""
    import os

    if getattr(args, "frame_rate", None) is None and getattr(args, "frame_shots", None) is None:
        return False
    out = str(getattr(args, "output", "") or "")
    return out.endswith(("/", os.sep)) or os.path.isdir(out)
