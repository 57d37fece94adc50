"""Real photon data (K11 building at 21 km, Li et al. 2020): signal and SBR from time tags.

Skipped where the data are absent.  Looks in $MEMS_STEREO_REALDATA, then
``<repo>/../shared/realdata``.  Published: mean detected signal photons per
pixel 1.242, signal-to-background ratio 0.1455 in the 200 ns window.  Two
definitions are computed (docs/histograms.md): the background-subtracted
signal, and the window count (every photon within a signal window around the
return).  Print the figures with
``.venv/bin/python -m pytest tests/test_realdata.py -p no:dash -q -s``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from mems_stereo.io.realdata import load_realdata_npz
from mems_stereo.pipeline.timetags import (
    estimate_timing_spread,
    signal_background_from_timetags,
    window_counts_from_timetags,
)

PUBLISHED_SIGNAL = 1.242
PUBLISHED_SBR = 0.1455
AUTHORS_JITTER_PS = 1000.0   # "the whole system jitter is 1ns": σ of their temporal kernel


def realdata_dir() -> Path:
    env = os.environ.get("MEMS_STEREO_REALDATA")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[1].parent / "shared" / "realdata"


@pytest.fixture(scope="module")
def k11():
    path = realdata_dir() / "k11_21km_night.npz"
    if not path.is_file():
        pytest.skip(f"real data not found at {path}")
    return load_realdata_npz(path)


@pytest.fixture(scope="module")
def result(k11):
    t, o = k11["timestamps_ps"], k11["offsets"]
    shape = tuple(int(v) for v in k11["shape"])
    g0, g1 = (int(v) for v in k11["gate_ps"])
    # first guess of the return's width: the authors' 1 ns system jitter
    spread = estimate_timing_spread(t, o, shape, g0, g1, coarse_bin=1000.0)
    est = signal_background_from_timetags(t, o, shape, g0, g1, spread.fwhm, spread.lead,
                                          spread.tail)
    return spread, est


def test_layout(k11):
    assert k11["offsets"][-1] == k11["timestamps_ps"].size == 640952
    g0, g1 = k11["gate_ps"]
    assert k11["timestamps_ps"].min() >= g0 and k11["timestamps_ps"].max() < g1


def test_timing_spread_is_physical(result):
    spread, _ = result
    # sub-ns jitter of an InGaAs SPAD + ns-class pulse: FWHM between 0.5 and 2 ns
    assert 500 < spread.fwhm < 2000
    assert spread.tail > spread.lead > 0


def test_signal_and_sbr_against_published(result):
    _, est = result
    print(f"mean signal/pixel {est.mean_signal:.4f} ± {est.mean_signal_std:.4f} "
          f"(published {PUBLISHED_SIGNAL}); SBR {est.sbr:.4f} ± {est.sbr_std:.4f} "
          f"(published {PUBLISHED_SBR})")
    # Statistical precision of our estimate: about 1 %.
    assert est.mean_signal_std / est.mean_signal < 0.02
    # The background-subtracted estimator lands 6-8 % below the published figures
    # (docs/histograms.md: the published "background" is 0.7 % below the background level
    # of every signal-free part of the gate, as a window-count convention would make it);
    # it does not meet the 5 % goal of issue 4.  Bound what we do get:
    assert abs(est.mean_signal / PUBLISHED_SIGNAL - 1) < 0.10
    assert abs(est.sbr / PUBLISHED_SBR - 1) < 0.10
    # internal consistency: SBR = S / (N − S)
    S = est.mean_signal * est.signal.size
    assert est.sbr == pytest.approx(S / (est.n_total - S))
    assert np.isclose(est.signal.sum(), S)


def _window(k11, spread, half_width):
    t, o = k11["timestamps_ps"], k11["offsets"]
    shape = tuple(int(v) for v in k11["shape"])
    g0, g1 = (int(v) for v in k11["gate_ps"])
    return window_counts_from_timetags(t, o, shape, g0, g1, half_width, 1000.0,
                                       offset=spread.mu)


def _report(name, w):
    print(f"{name}: window {w.window / 1000:.2f} ns, mean signal/pixel {w.mean_signal:.4f} "
          f"({w.mean_signal / PUBLISHED_SIGNAL - 1:+.1%}), SBR {w.sbr:.4f} "
          f"({w.sbr / PUBLISHED_SBR - 1:+.1%})")


def test_window_count_prestated_rule(k11, result):
    """Rule stated before computing it: window ±2σ of the measured timing spread.

    It does NOT meet the 5 % goal (−12 %): the window holds only ~87 % of the
    background-subtracted signal (long tail, faint further surfaces) while it
    adds the background inside it.  Bound what we get and check the split.
    """
    spread, est = result
    w = _window(k11, spread, 2 * spread.sigma)
    _report("window count, ±2σ measured", w)
    assert abs(w.mean_signal / PUBLISHED_SIGNAL - 1) < 0.15
    assert abs(w.sbr / PUBLISHED_SBR - 1) < 0.15
    # count = signal in the window + background in the window: the signal part
    # can be at most the whole background-subtracted signal
    in_window = w.mean_signal - (est.background_rate * w.window).mean()
    assert 0.8 * est.mean_signal < in_window < est.mean_signal + 3 * est.mean_signal_std


def test_window_count_grows_at_the_background_rate(k11, result):
    """Beyond the return (6 → 10 ns) the count grows by the background rate × width."""
    spread, est = result
    w6, w10 = _window(k11, spread, 3000.0), _window(k11, spread, 5000.0)
    slope = (w10.mean_signal - w6.mean_signal) / (w10.window - w6.window)
    assert slope == pytest.approx(est.background_rate.mean(), rel=0.15)


def test_window_count_with_the_authors_jitter(k11, result):
    """The same ±2σ rule with the authors' stated σ = 1 ns (their code's temporal kernel).

    Listed before computing as a sensitivity variant, not as the primary rule;
    it lands within 1 % of both published figures.  This pins the finding; it
    does not by itself show that the authors used this window
    (docs/histograms.md).
    """
    spread, _ = result
    w = _window(k11, spread, 2 * AUTHORS_JITTER_PS)
    _report("window count, ±2 × 1 ns (authors' jitter)", w)
    assert abs(w.mean_signal / PUBLISHED_SIGNAL - 1) < 0.05
    assert abs(w.sbr / PUBLISHED_SBR - 1) < 0.05
