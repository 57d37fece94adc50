"""The package's layers: no module imports a layer (or a pipeline stage) below it.

docs/architecture.md draws the map; this test keeps the tree true to it.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: layers from the bottom up; a module may import only its own layer and those before it
LAYERS = ["errors", "util", "model", "physics", "geometry", "io", "pipeline", "sim", "calib",
          "viz", "cli"]
#: pipeline stages in data-flow order; a stage may import only stages before it.  The
#: orchestration comes last: block_fusion (the fusion in blocks of peaks), run (one
#: process), then the Dask runner's modules, distributed (its face) last of them
STAGES = ["consistency", "intervals", "settings", "frame_bias", "angles", "shot_range", "histograms",
          "classify_kernel", "point_times_kernel", "pass1", "peak_table", "peak_support", "acceptance",
          "step_windows", "peaks", "pass2", "matched_boxes", "matched_grid",
          "matched_best_kernel", "matched_frame_kernel", "matched",
          "signal_store", "cloud",
          "detection_kernel", "detections", "sums", "calibration_sigma", "peak_means",
          "window_background", "first_photon_correction", "peak_geometry",
          "fusion_inputs", "turning_angle", "peak_estimates", "peak_accumulator", "background_entries", "fusion",
          "goodness", "scan_dwell",
          "temporal", "block_fusion", "run", "dask_setup", "dask_plan", "dask_reduce",
          "dask_tasks", "dask_split", "distributed", "frames", "live_queue", "live_warmup",
          "frame_split", "frame_workers", "timetags", "gate_check", "twoaxis_pileup", "twoaxis"]
#: the orchestration modules: they drive the stages and no stage imports them
ORCHESTRATION = ["block_fusion", "run", "dask_setup", "dask_plan", "dask_reduce", "dask_tasks",
                 "dask_split", "distributed", "frames", "live_queue", "live_warmup",
                 "frame_split", "frame_workers"]


def _modules():
    for folder, prefix in ((ROOT / "mems_stereo", "mems_stereo"), (ROOT / "calib", "mems_stereo.calib"),
                           (ROOT / "viz", "mems_stereo.viz")):
        for p in folder.rglob("*.py"):
            rel = p.relative_to(folder).with_suffix("").parts
            name = ".".join((prefix, *rel)).removesuffix(".__init__")
            yield name, p


def _layer(name: str):
    parts = name.split(".")
    return parts[1] if len(parts) > 1 else None


def _imports(path: Path):
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            yield node.module
        elif isinstance(node, ast.Import):
            yield from (a.name for a in node.names)


def test_no_import_goes_up_the_layers():
    bad = []
    for name, path in _modules():
        me = _layer(name)
        if me not in LAYERS:
            continue
        for imp in _imports(path):
            if not imp.startswith("mems_stereo.") or imp.startswith("mems_stereo._"):
                continue
            other = _layer(imp)
            if other in LAYERS and LAYERS.index(other) > LAYERS.index(me):
                bad.append(f"{name} imports {imp}")
    assert not bad, "\n".join(bad)


def test_pipeline_stages_import_only_earlier_stages():
    bad = []
    for name, path in _modules():
        parts = name.split(".")
        if parts[1:2] != ["pipeline"] or len(parts) < 3 or parts[2] not in STAGES:
            continue  # (an unknown module: test_every_pipeline_module_is_a_known_stage)
        me = STAGES.index(parts[2])
        for imp in _imports(path):
            ip = imp.split(".")
            if ip[:2] == ["mems_stereo", "pipeline"] and len(ip) > 2 and ip[2] != parts[2]:
                if ip[2] in STAGES and STAGES.index(ip[2]) > me:  # (unknown: test below)
                    bad.append(f"{name} imports {imp}")
    assert not bad, "\n".join(bad)


def test_every_pipeline_module_is_a_known_stage():
    stages = {p.stem for p in (ROOT / "mems_stereo" / "pipeline").glob("*.py")} - {"__init__"}
    assert stages == set(STAGES)


def test_orchestration_comes_after_every_stage_it_drives():
    """run and the Dask runner sit after the algorithm's stages: no stage imports them."""
    last_stage = max(STAGES.index(s) for s in STAGES
                     if s not in ORCHESTRATION
                     and s not in ("timetags", "gate_check", "twoaxis_pileup", "twoaxis"))
    assert all(STAGES.index(m) > last_stage for m in ORCHESTRATION)
    bad = []
    for name, path in _modules():
        parts = name.split(".")
        if parts[1:2] != ["pipeline"] or len(parts) < 3 or parts[2] in ORCHESTRATION:
            continue
        for imp in _imports(path):
            ip = imp.split(".")
            if ip[:2] == ["mems_stereo", "pipeline"] and len(ip) > 2 and ip[2] in ORCHESTRATION:
                bad.append(f"{name} imports {imp}")
    assert not bad, "\n".join(bad)
