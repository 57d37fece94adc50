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
#: pipeline stages in data-flow order; a stage may import only stages before it
STAGES = ["consistency", "intervals", "settings", "angles", "histograms", "pass1", "peaks",
          "pass2", "matched", "signal_store", "cloud", "detection_kernel", "detections", "sums",
          "peak_means",
          "window_background", "first_photon_correction", "peak_geometry", "fusion", "run",
          "distributed", "timetags", "gate_check", "twoaxis"]


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
        if parts[1:2] != ["pipeline"] or len(parts) < 3:
            continue
        me = STAGES.index(parts[2])
        for imp in _imports(path):
            ip = imp.split(".")
            if ip[:2] == ["mems_stereo", "pipeline"] and len(ip) > 2 and ip[2] != parts[2]:
                if STAGES.index(ip[2]) > me:
                    bad.append(f"{name} imports {imp}")
    assert not bad, "\n".join(bad)


def test_every_pipeline_module_is_a_known_stage():
    stages = {p.stem for p in (ROOT / "mems_stereo" / "pipeline").glob("*.py")} - {"__init__"}
    assert stages == set(STAGES)


def test_old_module_paths_still_import_with_a_warning():
    import importlib
    import warnings

    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        mod = importlib.import_module("mems_stereo.points")
        from mems_stereo.physics.first_photon import first_photon_moments

        assert mod.first_photon_moments is first_photon_moments
    assert any(issubclass(x.category, DeprecationWarning) for x in w)
