"""The processing pipeline, one module per stage, in order:

settings → angles → consistency (the per-detection test) + intervals (the
test compiled per angle step) → pass1 (classify and histogram) → peaks →
pass2 (counts per peak, angle step and code) → fusion (points) → cloud;
block_fusion (the fusion in blocks of peaks); run (process_recording) drives them;
distributed (process_split, process_many) calls them on Dask, with dask_setup,
dask_plan, dask_reduce, dask_tasks and dask_split; timetags is the same stage for TCSPC
time tags.
"""

import importlib

#: public names of the stage modules, importable from ``mems_stereo.pipeline``
#: (loaded on first use, so that importing one stage does not load them all)
_PUBLIC = {
    "Settings": "settings", "DEFAULT_CHUNK_SHOTS": "settings",
    "process_recording": "run", "ProcessResult": "run",
    "truth_scores": "pass1", "shot_angles": "angles", "as_source": "run",
    "RangeAccumulation": "pass1", "accumulate_range": "pass1", "Counts": "pass1",
    "classify_recording": "pass1",
    "PeakCounts": "pass2", "peak_counts_range": "pass2", "points_from_counts": "fusion",
}

__all__ = sorted(_PUBLIC)


def __getattr__(name):
    if name in _PUBLIC:
        return getattr(importlib.import_module(f"{__name__}.{_PUBLIC[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
