"""SIGINT, SIGTERM and SIGHUP during a long ``process`` run (a subprocess).

After a signal: exit 128 + signal, one line on stderr saying what was kept,
no ``.part`` file, no partial output (either none of the outputs or, when the
signal came while they were committed or after, all of them and a line
saying so), the input unchanged.  The default suite sends each signal once
at a fixed moment and the three signals at 2 random moments of a run (its
length measured first); the ``stress`` test at 20 random moments.

Two causes of the earlier rare failure of the 20-moment test were found
with these moments: a signal in the first ~0.1 s (before the outputs are
planned) is truthfully reported as "nothing was written", which the test
did not accept; and a signal during the interpreter's shutdown (about
0.5 s after the run) could be dropped, exit 0 (the program now ends with
``os._exit`` after checking for pending signals, ``_signals.exit_now``).
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
            "--chunk-shots", "64", "--parents", "-q"]  # out/ made by the run
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
    assert p.returncode == 128 + sig, (p.returncode, err)
    assert len(lines) == 1 and "Traceback" not in err, err
    assert f"interrupted by {signal.Signals(sig).name}" in lines[0]
    left = sorted(x.name for x in d.rglob("*") if x.is_file() and x.name != "in.h5")
    assert not any(".part" in x for x in left), left
    if "after every output was written" in lines[0]:
        assert sorted(left) == sorted(OUTPUTS), (left, lines[0])
        kind = "all kept"
    else:
        assert left == [], (left, lines[0])
        # before the outputs were planned: "nothing was written"; after: "no output ..."
        assert "no output was written" in lines[0] or "nothing was written" in lines[0], \
            lines[0]
        assert not (d / "out").exists()  # the folder the run created is gone too
        kind = "none kept"
    assert hashlib.sha1((d / "in.h5").read_bytes()).hexdigest() == digest
    return kind


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP])
def test_signal_leaves_nothing(sig, tmp_path):
    # On a fast machine the run can end before the chosen moment (CI once saw
    # that at 1.27 s): the moment is then halved until the signal lands in the run.
    after = 0.3 + random.Random(int(sig)).random()
    for _ in range(8):
        kind = _interrupt(tmp_path, sig, after=after)
        if kind:
            return
        after /= 2
    pytest.fail(f"the run always ended before the signal (last moment {after:.3f} s)")


def _random_moments(tmp_path, n: int, seed: int) -> dict:
    """``n`` signals at random moments of a run whose length T is measured first.

    The moments are uniform on (0, T): the first ~0.1 s (loading, checking
    options, planning), the run, the commit and the exit are all hit;
    moments after the run ended (load varies) are drawn again.
    """
    p = _start(tmp_path)
    _wait_for_handlers(p)
    t0 = time.monotonic()
    p.communicate(timeout=300)
    assert p.returncode == 0
    T = time.monotonic() - t0
    shutil.rmtree(tmp_path / "out")
    print(f"seed {seed}, run of {T:.2f} s")  # shown with a failure
    rng = random.Random(seed)
    kinds: dict = {}
    tries = 0
    while sum(kinds.values()) < n and tries < 2 * n + 10:
        d = tmp_path / f"run{tries}"
        d.mkdir()
        tries += 1
        sig = rng.choice([signal.SIGINT, signal.SIGTERM, signal.SIGHUP])
        kind = _interrupt(d, sig, after=rng.uniform(0.0, T))
        if kind:
            kinds[kind] = kinds.get(kind, 0) + 1
    print(f"\nrun of {T:.2f} s, {n} signals at random moments ({tries} tries): {kinds}")
    assert sum(kinds.values()) == n, (kinds, tries)
    return kinds


@pytest.mark.slow
def test_signals_at_2_random_moments(tmp_path):
    # a new seed each run (printed): the suite's runs together cover more moments.  Two
    # moments (about 4 runs, ~12 CPU s; six cost 28): the 20-moment run is the stress test
    _random_moments(tmp_path, 2, seed=random.SystemRandom().randrange(10**6))


@pytest.mark.stress
def test_signals_at_20_random_moments(tmp_path):
    _random_moments(tmp_path, 20, seed=20)
