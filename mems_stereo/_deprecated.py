"""Deprecated module paths of version 0.1 (flat modules), kept importable.

``import mems_stereo.points`` and ``from mems_stereo.points import X`` still
work: the old module is a thin alias whose attributes come from the modules
that now hold them (see docs/architecture.md), with a DeprecationWarning.
They will be removed in version 0.3.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import warnings

#: old module -> the modules that now hold its names, the main one first
MOVED = {
    "mems_stereo.acquisition": ('mems_stereo.model.acquisition',),
    "mems_stereo.camera": ('mems_stereo.model.camera',),
    "mems_stereo.classify": ('mems_stereo.pipeline.consistency', 'mems_stereo.io.labels'),
    "mems_stereo.cloud": ('mems_stereo.pipeline.cloud',),
    "mems_stereo.distributed": ('mems_stereo.pipeline.distributed',),
    "mems_stereo.epipolar": ('mems_stereo.geometry.epipolar',),
    "mems_stereo.fastpath": (
        "mems_stereo.pipeline.intervals",
        "mems_stereo.pipeline.pass1",
        "mems_stereo.pipeline.pass2",
    ),
    "mems_stereo.histogram": (
        "mems_stereo.pipeline.histograms",
        "mems_stereo.io.labels",
        "mems_stereo.physics.background",
        "mems_stereo.model.tdc",
    ),
    "mems_stereo.histogram_io": ('mems_stereo.io.histograms',),
    "mems_stereo.io_util": ('mems_stereo.util.atomic',),
    "mems_stereo.peaks": ('mems_stereo.pipeline.peaks', 'mems_stereo.physics.background'),
    "mems_stereo.points": (
        "mems_stereo.pipeline.fusion",
        "mems_stereo.pipeline.detections",
        "mems_stereo.pipeline.sums",
        "mems_stereo.physics.first_photon",
        "mems_stereo.physics.spot",
    ),
    "mems_stereo.recording": ('mems_stereo.io.recording', 'mems_stereo.io.labels'),
    "mems_stereo.scanner": ('mems_stereo.model.scanner',),
    "mems_stereo.system": ('mems_stereo.model.system',),
    "mems_stereo.timetags": ('mems_stereo.pipeline.timetags', 'mems_stereo.io.realdata'),
    "mems_stereo.triangulation": ('mems_stereo.geometry.triangulation', 'mems_stereo.model.tdc'),
    "mems_stereo.uncertainty": (
        "mems_stereo.geometry.uncertainty",
        "mems_stereo.physics.pulse",
        "mems_stereo.physics.spot",
    ),
    "mems_stereo.validation": ('mems_stereo.util.jsonfile',),
}


class _AliasFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    def find_spec(self, fullname, path=None, target=None):
        if fullname in MOVED:
            return importlib.util.spec_from_loader(fullname, self)
        return None

    def create_module(self, spec):
        return None

    def exec_module(self, module):
        targets = MOVED[module.__name__]
        warnings.warn(f"{module.__name__} is deprecated: its names moved to "
                      f"{', '.join(targets)}", DeprecationWarning, stacklevel=2)

        def __getattr__(attr):
            for t in targets:
                mod = importlib.import_module(t)
                if hasattr(mod, attr):
                    return getattr(mod, attr)
            raise AttributeError(f"module {module.__name__!r} has no attribute {attr!r}")

        module.__getattr__ = __getattr__
        module.__all__ = []


def install() -> None:
    """Put the alias finder on ``sys.meta_path`` once."""
    if not any(isinstance(f, _AliasFinder) for f in sys.meta_path):
        sys.meta_path.append(_AliasFinder())
