"""Package hygiene: the core imports light, the code passes the linter, the CLI answers."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_core_and_process_to_ply_load_no_heavy_module(tmp_path):
    """``import mems_stereo, mems_stereo.cli`` loads neither Open3D nor matplotlib, and
    ``mems-stereo process samples/room.h5 -o x.ply`` (the start-up path) then loads
    neither Open3D, matplotlib, Dask nor numba (small recordings run in NumPy), nor the
    simulator; the PLY is written by NumPy.  One interpreter checks both moments."""
    code = ("import sys, mems_stereo, mems_stereo.cli; "
            "bad = [m for m in ('open3d', 'matplotlib') if m in sys.modules]; "
            "assert not bad, ('on import', bad); "
            "from mems_stereo.cli import main; "
            f"rc = main(['-q', 'process', {str(ROOT / 'samples' / 'room.h5')!r}, '-o', "
            f"{str(tmp_path / 'x.ply')!r}]); "
            "bad = [m for m in ('open3d', 'matplotlib', 'dask', 'numba', 'mems_stereo.sim') "
            "if m in sys.modules]; assert rc == 0 and not bad, (rc, bad)")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)
    assert (tmp_path / "x.ply").stat().st_size > 0


def test_ruff_lint_is_clean():
    ruff = shutil.which("ruff") or str(Path(sys.executable).with_name("ruff"))
    if not Path(ruff).exists():
        pytest.fail("ruff is not installed: run scripts/setup.sh (it installs the dev extras)")
    res = subprocess.run([ruff, "check", "mems_stereo", "calib", "viz", "tests", "benchmarks",
                          "samples"], cwd=ROOT, capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr


def test_cli_help_lists_every_command(capsys):
    from mems_stereo.cli import main

    with pytest.raises(SystemExit) as e:
        main(["--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert "info" in out


def test_info_command_prints_statistics(capsys):
    from mems_stereo.cli import main

    assert main(["info", "--shots", "400", "--ratio", "0.0785"]) == 0
    out = capsys.readouterr().out
    assert "mean accumulations per pixel" in out and "theta0 = 0.760419" in out


def test_cli_error_is_one_line_without_traceback(tmp_path, capsys):
    from mems_stereo.cli import main

    bad = tmp_path / "s.json"
    bad.write_text('{"format": "mems-stereo/system", "version": 1}')
    assert main(["info", "--system", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "receiver: required field is missing" in err and "Traceback" not in err
