"""A built wheel carries the samples: after installing it into a new environment,
``print(ms.process_recording(ms.data.path('room.h5')))`` works from any folder.

Slow (builds a wheel: ~20 s, and pip fetches the build backend): marked ``stress``, run
with ``pytest -m stress``.  The environment is a
new venv with the wheel installed ``--no-deps``; the dependencies come from this
interpreter's site-packages through a ``.pth`` line (as /work/mkwt.sh does), so the
package itself is the wheel's copy, not the source tree.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _pip() -> list[str]:
    if subprocess.run([sys.executable, "-m", "pip", "--version"], capture_output=True).returncode:
        found = shutil.which("pip3") or shutil.which("pip")  # a venv made --without-pip
        if not found:
            pytest.skip("no pip to build the wheel with")
        return [found]
    return [sys.executable, "-m", "pip"]


@pytest.mark.slow
@pytest.mark.stress  # 11 CPU s (pip builds the wheel): with the stress runs (pytest -m stress)
def test_wheel_carries_the_samples(tmp_path):
    wheels = tmp_path / "dist"
    p = subprocess.run([*_pip(), "wheel", "--no-deps", "-q", "-w",
                        str(wheels), str(ROOT)], capture_output=True, text=True)
    if p.returncode and ("connection" in p.stderr.lower() or "network" in p.stderr.lower()):
        pytest.skip("pip could not fetch the build backend (no network)")
    assert p.returncode == 0, p.stderr[-2000:]
    (whl,) = wheels.glob("mems_stereo-*.whl")
    import zipfile

    names = zipfile.ZipFile(whl).namelist()  # the browser viewer's page (live --view browser)
    assert {f"mems_stereo/viz/web/live.{x}" for x in ("html", "js", "css")} <= set(names)
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    py = venv / "bin" / "python"
    subprocess.run([*_pip(), "--python", str(py), "install", "-q",
                    "--no-deps", str(whl)], check=True)
    sp_new = subprocess.run([str(py), "-c", "import site; print(site.getsitepackages()[0])"],
                            capture_output=True, text=True, check=True).stdout.strip()
    import h5py
    import numpy
    import open3d

    # the folders the dependencies come from (not this environment's editable finder)
    deps = sorted({str(Path(m.__file__).parents[1]) for m in (numpy, h5py, open3d)})
    Path(sp_new, "zz_deps.pth").write_text("\n".join(deps) + "\n")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    code = ("import mems_stereo as ms; print(ms.data.root()); "
            "print(ms.process_recording(ms.data.path('room.h5')))")
    out = subprocess.run([str(py), "-c", code], cwd=elsewhere, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    root, res = out.stdout.splitlines()[:2]
    assert root.startswith(sp_new) and root.endswith("mems_stereo/data/samples")
    assert res.startswith("<ProcessResult ") and "800 shots" in res
    # the command line of the wheel finds them too
    cli = subprocess.run([str(venv / "bin" / "mems-stereo"), "samples", "--list"],
                         cwd=elsewhere, capture_output=True, text=True)
    assert cli.returncode == 0 and "room.h5" in cli.stdout and sp_new in cli.stdout
