"""SIGINT, SIGTERM and SIGHUP during a long ``process`` run (a subprocess).

After a signal: exit 128 + signal, one line on stderr saying what was kept,
no ``.part`` file, no partial output (either none of the outputs or, when the
signal came while they were committed, all of them and a line saying so),
the input unchanged.  The fast test sends each signal once; the slow one at
20 random moments.
"""

from __future__ import annotations

import hashlib
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.skipif(not Path("/proc/self/status").exists(),
                                reason="needs /proc to see when the handlers are installed")

SAMPLES = Path(__file__).resolve().parents[1] / "samples"
OUTPUTS = ("o.ply", "l.h5", "h.h5")


def _start(d: Path):
    shutil.copy(SAMPLES / "floodlight.h5", d / "in.h5")
    argv = [sys.executable, "-c", "import sys; from mems_stereo.cli import main; "
            "sys.exit(main())", "process", str(d / "in.h5"), "-o", str(d / "out/o.ply"),
            "--labels", str(d / "out/l.h5"), "--histograms", str(d / "out/h.h5"),
            "--chunk-shots", "64", "-q"]
    return subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for_handlers(p, timeout=60.0):
    """Wait until the child catches SIGHUP and SIGTERM (/proc/PID/status SigCgt).

    Before that, Python is still importing the package and a signal ends the
    process by its default action (nothing has been written then); the
    random moments are counted from here.
    """
    status = Path(f"/proc/{p.pid}/status")
    want = (1 << (signal.SIGHUP - 1)) | (1 << (signal.SIGTERM - 1))
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end and p.poll() is None:
        for line in status.read_text().splitlines():
            if line.startswith("SigCgt:") and int(line.split()[1], 16) & want == want:
                return
        time.sleep(0.005)
    raise AssertionError("the child never installed its signal handlers")


def _interrupt(d: Path, sig: int, after: float):
    digest = hashlib.sha1((SAMPLES / "floodlight.h5").read_bytes()).hexdigest()
    p = _start(d)
    _wait_for_handlers(p)
    time.sleep(after)
    if p.poll() is not None:  # finished before the moment: not an interrupt
        p.communicate()
        shutil.rmtree(d)
        d.mkdir()
        return False
    p.send_signal(sig)
    out, err = p.communicate(timeout=120)
    lines = err.strip().splitlines()
    if p.returncode == -sig and not err:
        # the signal came while Python was exiting after a finished run (it restores the
        # default actions then): every output is there, complete
        left = sorted(x.relative_to(d).as_posix() for x in d.rglob("*") if x.is_file())
        assert left == sorted(["in.h5", *(f"out/{o}" for o in OUTPUTS)]), left
        return True
    assert p.returncode == 128 + sig, (p.returncode, err)
    assert len(lines) == 1 and "Traceback" not in err, err
    assert f"interrupted by {signal.Signals(sig).name}" in lines[0]
    left = sorted(x.name for x in d.rglob("*") if x.is_file() and x.name != "in.h5")
    assert not any(".part" in x for x in left), left
    if "after every output was written" in lines[0]:
        assert sorted(left) == sorted(OUTPUTS)
    else:
        assert left == [], left
        assert "no output was written" in lines[0]
        assert not (d / "out").exists()  # the folder the run created is gone too
    assert hashlib.sha1((d / "in.h5").read_bytes()).hexdigest() == digest
    return True


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP])
def test_signal_leaves_nothing(sig, tmp_path):
    assert _interrupt(tmp_path, sig, after=0.3 + random.Random(int(sig)).random())


@pytest.mark.stress
def test_signals_at_20_random_moments(tmp_path):
    p = _start(tmp_path)
    _wait_for_handlers(p)
    t0 = time.monotonic()
    p.communicate(timeout=300)
    assert p.returncode == 0
    T = time.monotonic() - t0
    shutil.rmtree(tmp_path / "out")
    rng = random.Random(20)
    done = tries = 0
    while done < 20 and tries < 40:  # moments after the run ended (load varies) do not count
        d = tmp_path / f"run{tries}"
        d.mkdir()
        tries += 1
        sig = rng.choice([signal.SIGINT, signal.SIGTERM, signal.SIGHUP])
        done += _interrupt(d, sig, after=rng.uniform(0.05, 0.95 * T))
    assert done == 20
