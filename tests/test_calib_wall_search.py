"""The matched-filter pose search over every shot (calib/wall_search.py): its
false-alarm threshold holds on pure background, and it finds walls far too faint
for a phase bin (a calibration whose walls are missed is refused)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from mems_stereo.calib.association import wall_data
from mems_stereo.calib.family import Case, Wall, simulate_case
from mems_stereo.calib.problem import WallData
from mems_stereo.calib.wall_search import FALSE_ALARM, search_pose, threshold

from mems_stereo.model.system import burkard2022
from mems_stereo.physics.pulse import pulse_sigma


@pytest.fixture(scope="module")
def nominal():
    return burkard2022()


def _background_only(rng, nominal, shots, rate):
    """A recording of background alone: each pixel's first photon after the TDC
    start exponential at ``rate`` (Hz), the monitor phase uniform."""
    tdc = nominal.tdc
    W = nominal.receiver.width
    lam = rate * rng.uniform(0.7, 1.3, size=(1, W))
    t = rng.exponential(1.0 / lam, size=(shots, 1, W))
    code = np.floor(t / tdc.bin_width).astype(np.int64) + 1
    bins = np.where(code <= tdc.n_bins, code, 0).astype(np.uint16)
    # the measured rates, as association.background_rates gives them
    from mems_stereo.calib.association import background_rates
    return WallData(rng.uniform(-math.pi, math.pi, shots), bins,
                    background_rates(bins, tdc.bin_width, tdc.n_bins), tdc.bin_width, "bg")


def test_threshold_is_the_bonferroni_quantile():
    assert abs(threshold(1) + __import__("scipy.stats").stats.norm.ppf(FALSE_ALARM)) < 1e-9
    assert 5.3 < threshold(10_000) < 5.8
    assert threshold(100) < threshold(10_000)


@pytest.mark.stress  # 15 s: with the stress runs (pytest -m stress)
def test_background_alone_is_not_a_wall(nominal):
    """Pure background at 10 kHz–6 MHz: the best pose stays below the threshold, and
    the largest significance over the poses is what a maximum over ~10⁴ mostly
    correlated Gaussian tests gives (≤ ~4.5σ), not a heavy tail."""
    rng = np.random.default_rng(5)
    sigma = pulse_sigma(nominal.laser.pulse_fwhm, 50e-12)
    vals = {n: nominal.get_param(n) for n in ("theta0", "tdc_offset", "baseline_x")}
    zs = []
    for shots, rate in [(3000, 1e4), (8000, 3e5), (4000, 2e6), (2500, 6e6)]:
        f = search_pose(_background_only(rng, nominal, shots, rate), nominal, vals, sigma)
        assert f is not None
        zs.append(f.z)
        assert f.z < f.z_needed, (shots, rate, f)
    assert max(zs) < 5.0, zs


@pytest.mark.slow
def test_a_faint_near_wall_is_found_with_the_nominal_system(nominal):
    """0.05 photons per shot at 0.7 m under 2 MHz (the TDC start cuts most of the
    pulse): a few hundred signal counts in 20,000 shots.  The search with the
    nominal system (the truth 8 mrad, 8 mm and 2.5 ns away) finds it above its
    threshold, at a pose near the truth."""
    offsets = {"theta0": 8e-3, "tdc_offset": -2.5e-9, "baseline_x": -8e-3,
               "baseline_z": 5e-3}
    case = Case([Wall(0.7, math.radians(5), 0.0, 0.5, 0.05, 20000, 2e6)], offsets, 11, [0.7])
    w = wall_data(simulate_case(case, nominal)[0])
    sigma = pulse_sigma(nominal.laser.pulse_fwhm, 50e-12)
    vals = {n: nominal.get_param(n) for n in ("theta0", "tdc_offset", "baseline_x")}
    f = search_pose(w, nominal, vals, sigma)
    assert f.z > f.z_needed, f
    assert abs(f.alpha - math.radians(5)) < 0.2 and abs(f.dist - 0.7) < 0.2, f


def test_pose_grid_and_gate_counts_match_the_per_pose_model(nominal):
    """The search's outer grid (beam per phase once, every plane offset of a tilt) gives
    exactly what :func:`beam_hits` gives shot by shot, with harmonics in the mirror's
    motion too, and the gates' background expectation from the per-column tables is
    the closed form ``n·exp(−λ lo DT)·(1 − exp(−λ (hi − lo) DT))`` of each gate."""
    from mems_stereo.calib.model import beam_hits, plane_normal
    from mems_stereo.calib.wall_search import DT, GATE, N_PHASE, PooledRecording, PoseGrid

    rng = np.random.default_rng(3)
    w = _background_only(rng, nominal, 3000, 1e6)
    sigma = pulse_sigma(nominal.laser.pulse_fwhm, 50e-12)
    vals = {"theta0": nominal.get_param("theta0") + 3e-3, "tdc_offset": 1e-9,
            "harmonic3_cos": 4e-3, "harmonic2_sin": -2e-3}
    pr = PooledRecording(w, 120e-9)
    dists = np.array([0.5, 1.3, 4.0, 14.0])
    grid = PoseGrid(nominal, vals, pr.phase)
    for a in (-0.6, 0.7, 0.1):
        u, path = grid.hits(a, dists)
        h = beam_hits(nominal, vals, np.repeat(pr.phase, dists.size), plane_normal(a),
                      np.tile(dists, N_PHASE))
        ref_u = np.where(h.ok, h.pixel[:, 0], np.nan).reshape(N_PHASE, dists.size)
        np.testing.assert_allclose(u, ref_u, rtol=0, atol=1e-9)
        ok = np.isfinite(ref_u)
        np.testing.assert_allclose(path[ok], h.path.reshape(u.shape)[ok], rtol=1e-14)
    u, path = grid.hits(0.1, dists)
    tau = path / nominal.speed_of_light + 1e-9
    n, e, ok = pr.counts(u, tau, sigma)
    assert ok.any() and n[ok].sum() > 0
    ui = np.rint(u[ok]).astype(int)
    lo = np.clip(np.floor((tau[ok] - GATE * sigma) / DT), 0, pr.ntb - 1)
    hi = np.clip(np.ceil((tau[ok] + GATE * sigma) / DT), 0, pr.ntb - 1)
    lam = pr.lam[ui]
    ns = np.broadcast_to(pr.n_shots[:, None], u.shape)[ok]
    want = ns * np.exp(-lam * lo * DT) * -np.expm1(-lam * (hi - lo) * DT)
    np.testing.assert_allclose(e[ok], want, rtol=1e-13)
    b = np.broadcast_to(np.arange(N_PHASE)[:, None], u.shape)[ok]
    want_n = pr.C[b, ui, hi.astype(int)] - pr.C[b, ui, lo.astype(int)]
    np.testing.assert_array_equal(n[ok], want_n)
