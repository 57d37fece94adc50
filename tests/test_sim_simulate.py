"""The simulator end to end: trajectory and zero crossings, truth, determinism, files, CLI."""

from __future__ import annotations

import dataclasses
import importlib.util
import math
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import brentq

from mems_stereo.cli import main
from mems_stereo.io.recording import read_recording
from mems_stereo.model.scanner import scan_angles, scan_direction
from mems_stereo.model.system import burkard2022, load_system, system_to_dict
from mems_stereo.sim import (
    LinkBudget,
    SimulationOptions,
    Trajectory,
    load_scene,
    scene_from_dict,
    simulate,
    write_simulation,
)

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "samples"


@pytest.fixture(scope="module")
def room():
    return load_scene(SAMPLES / "room_scene.json")


def perturbed(sysm):
    return sysm.with_params(baseline_x=-0.121, baseline_z=-0.003,
                            theta0=sysm.scanner.theta0 + 0.004, tdc_offset=1e-9,
                            phase_offset=0.02)


def test_zero_crossings_are_roots_of_the_monitor_signal():
    traj = Trajectory(f_mech=1570.0, phase=0.7, drift=3e-3, t_ref=0.01, theta0=0.76,
                      amplitude=0.2, phase_offset=0.0)
    t, rising = traj.zero_crossings(0.0, 0.05)
    mon = lambda s: math.cos(float(traj.monitor_phase(s)))  # noqa: E731
    half = 0.5 / 1570.0
    for ti, ri in zip(t, rising):
        # an independent root finder on the monitor signal
        root = brentq(mon, ti - 0.3 * half, ti + 0.3 * half, xtol=1e-15)
        assert ti == pytest.approx(root, abs=1e-12)
        slope = -math.sin(float(traj.monitor_phase(ti)))
        assert (slope > 0) == bool(ri)
    assert np.all(np.diff(rising.astype(int)) != 0)  # alternating
    # drift: half periods shrink as the frequency grows
    assert np.diff(t)[-1] < np.diff(t)[0]
    assert t[0] >= 0 and t[-1] <= 0.05 and t.size == pytest.approx(0.05 * 2 * 1570, abs=3)


@pytest.mark.parametrize("drift,jitter,tol", [(0.0, 0.0, 1e-9), (5e-3, 0.0, 1e-6),
                                              (2e-3, 20e-9, 4e-4)])
def test_scan_angle_recovered_from_zero_crossings(room, drift, jitter, tol):
    nominal = burkard2022()
    true = perturbed(nominal)
    rec = simulate(nominal, room, 3000, rng=np.random.default_rng(1), true_system=true,
                   options=SimulationOptions(drift=drift, zc_jitter=jitter, start_time=0.25))
    theta, valid = scan_angles(rec.shot_time, rec.zero_crossings, rec.rising, true.scanner)
    assert np.all(valid)
    assert np.max(np.abs(theta - rec.truth["theta"])) < tol
    # the nominal scanner (no phase offset, wrong theta0) is off by mrad
    th_nom, _ = scan_angles(rec.shot_time, rec.zero_crossings, rec.rising, nominal.scanner)
    assert np.max(np.abs(th_nom - rec.truth["theta"])) > 3e-3


def test_truth_geometry_and_time_of_flight(room):
    """Hits lie on the true scan ray; codes of laser returns agree with the path length."""
    nominal = burkard2022()
    true = perturbed(nominal)
    rec = simulate(nominal, room, 4000, rng=np.random.default_rng(2), true_system=true,
                   options=SimulationOptions(link=LinkBudget(peak_power=0.01)),
                   background_hz=0.0, dark_count_hz=0.0)
    x = rec.truth["point"]
    hit = np.isfinite(x[:, 0])
    assert hit.mean() > 0.99
    d = scan_direction(rec.truth["theta"], true.scanner)
    v = x[hit] - true.scanner.position
    s = np.sum(v * d[hit], axis=1)
    assert np.all(s > 0)
    assert np.max(np.linalg.norm(v - s[:, None] * d[hit], axis=1)) < 1e-5
    L = s + np.linalg.norm(x[hit], axis=1)
    np.testing.assert_allclose(rec.truth["path_length"][hit], L, atol=1e-5)
    lab = rec.truth["label"]
    assert np.array_equal(lab > 0, rec.bins > 0)
    k, _, col = np.nonzero(lab == 1)
    t_tof = (rec.bins[lab == 1] - 0.5) * true.tdc.bin_width - true.tdc.offset
    res = t_tof - rec.truth["path_length"][k] / true.speed_of_light
    sigma = true.laser.pulse_fwhm / (2 * math.sqrt(2 * math.log(2)))
    # spread by the pulse (and biased early by the first-photon pile-up, a fraction of a ns)
    assert res.std() == pytest.approx(sigma, rel=0.1)
    assert -1.5e-9 < res.mean() < 0.2e-9
    # with a 20 ps pulse and no jitter only the TDC quantisation is left: |res| <= bin / 2
    short = true.replace(laser=dataclasses.replace(true.laser, pulse_fwhm=20e-12))
    rec2 = simulate(nominal, room, 1000, rng=np.random.default_rng(2), true_system=short,
                    background_hz=0.0, dark_count_hz=0.0,
                    options=SimulationOptions(timing_jitter=0.0,
                                              # same pulse energy as 27 mW x 14.9 ns
                                              link=LinkBudget(peak_power=20.0)))
    k2, _, _ = np.nonzero(rec2.truth["label"] == 1)
    t_tof = (rec2.bins[rec2.truth["label"] == 1] - 0.5) * short.tdc.bin_width - short.tdc.offset
    res = t_tof - rec2.truth["path_length"][k2] / short.speed_of_light
    assert k2.size > 500
    assert np.max(np.abs(res)) < 0.5 * short.tdc.bin_width + 4 * 20e-12
    assert abs(res.mean()) < 30e-12
    # the detecting pixel sees the hit point
    K = true.receiver.camera_matrix
    u = K[0, 0] * x[k, 0] / x[k, 2] + K[0, 2]
    assert np.max(np.abs(col - u)) < 2.5
    assert np.mean(np.abs(col - u) < 1.0) > 0.95


def test_recording_system_is_nominal_and_round_trips(tmp_path, room):
    nominal = burkard2022()
    rec = simulate(nominal, room, 500, rng=np.random.default_rng(3),
                   true_system=perturbed(nominal), options=SimulationOptions(crosstalk=0.05))
    p = write_simulation(tmp_path / "r.h5", rec)
    back = read_recording(p)
    assert system_to_dict(back.system) == system_to_dict(nominal)
    np.testing.assert_array_equal(back.bins, rec.bins)
    np.testing.assert_array_equal(back.shot_time, rec.shot_time)
    np.testing.assert_array_equal(back.zero_crossings, rec.zero_crossings)
    np.testing.assert_array_equal(back.rising, rec.rising)
    for key in ("label", "theta", "point", "object", "path_length", "signal_mean"):
        np.testing.assert_array_equal(back.truth[key], rec.truth[key])
    assert back.bins.dtype == np.uint16 and back.truth["label"].dtype == np.uint8
    assert back.bins.shape == (500, 1, 192)
    assert int(back.bins.max()) <= nominal.tdc.n_bins


def test_deterministic_for_a_seed(room):
    sysm = burkard2022()
    opt = SimulationOptions(crosstalk=0.02)
    a = simulate(sysm, room, 300, rng=np.random.default_rng(7), options=opt)
    b = simulate(sysm, room, 300, rng=np.random.default_rng(7), options=opt)
    c = simulate(sysm, room, 300, rng=np.random.default_rng(8), options=opt)
    np.testing.assert_array_equal(a.bins, b.bins)
    np.testing.assert_array_equal(a.truth["label"], b.truth["label"])
    np.testing.assert_array_equal(a.zero_crossings, b.zero_crossings)
    assert not np.array_equal(a.bins, c.bins)


def test_crosstalk_fires_neighbours():
    sysm = burkard2022()
    wall = scene_from_dict({"objects": [{"type": "plane", "center": [0, 0, 2.0],
                                         "normal": [0, 0, -1], "size": [20, 4],
                                         "reflectivity": 0.5}]})
    opt = SimulationOptions(phase=0.1, link=LinkBudget(peak_power=0.004))
    kw = dict(background_hz=0.0, dark_count_hz=0.0)
    a = simulate(sysm, wall, 3000, rng=np.random.default_rng(5), options=opt, **kw)
    b = simulate(sysm, wall, 3000, rng=np.random.default_rng(5),
                 options=dataclasses.replace(opt, crosstalk=0.5), **kw)
    na, nb = (a.bins > 0).sum(), (b.bins > 0).sum()
    # each detection fires left or right (never up/down on a line sensor) with p = 0.5:
    # about a quarter more detections, minus collisions
    assert 1.15 < nb / na < 1.3
    assert np.all(b.truth["label"][b.bins > 0] == 1)


def test_per_pixel_background_rates():
    sysm = burkard2022()
    nothing = scene_from_dict({"objects": [{"type": "sphere", "center": [0, 0, -3],
                                            "radius": 0.1, "reflectivity": 0.5}]})
    rates = np.where(np.arange(192) < 96, 2e5, 2e6)[None, :]
    rec = simulate(sysm, nothing, 2000, rng=np.random.default_rng(6), background_hz=rates,
                   dark_count_hz=0.0)
    window = sysm.tdc.n_bins * sysm.tdc.bin_width
    frac = (rec.bins > 0).mean(axis=(0, 1))
    for lo, hi, rate in ((0, 96, 2e5), (96, 192, 2e6)):
        p = 1 - math.exp(-rate * window)
        n = 2000 * 96
        assert abs(frac[lo:hi].mean() - p) < 5 * math.sqrt(p * (1 - p) / n)


def test_bad_arguments(room):
    sysm = burkard2022()
    with pytest.raises(ValueError):
        simulate(sysm, room, 0, rng=np.random.default_rng(0))
    with pytest.raises(TypeError):
        simulate(sysm, room, 10, rng=0)
    with pytest.raises(ValueError):
        simulate(sysm, room, 10, rng=np.random.default_rng(0), background_hz=-1.0)


def _make_samples_module():
    spec = importlib.util.spec_from_file_location("make_samples", SAMPLES / "make_samples.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["make_samples"] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def test_samples_regenerate_bit_for_bit(tmp_path):
    ms = _make_samples_module()
    room_sample = next(s for s in ms.SAMPLES if s.name == "room")
    a = read_recording(ms.make_sample(room_sample, tmp_path / "a"))
    b = read_recording(ms.make_sample(room_sample, tmp_path / "b"))
    shipped = read_recording(SAMPLES / "room.h5")
    for rec in (b, shipped):
        np.testing.assert_array_equal(a.bins, rec.bins)
        np.testing.assert_array_equal(a.shot_time, rec.shot_time)
        np.testing.assert_array_equal(a.zero_crossings, rec.zero_crossings)
        np.testing.assert_array_equal(a.truth["label"], rec.truth["label"])
    np.testing.assert_array_equal(a.truth["point"], b.truth["point"])
    # the truth geometry is the float64 ray-plane hit of the triangle Embree picked;
    # only libm/SIMD rounding (≲ 1e-15 m) may differ between CPUs
    np.testing.assert_allclose(a.truth["point"], shipped.truth["point"], rtol=0, atol=1e-9)
    # the calibration samples' true system is the one shipped beside them
    assert system_to_dict(load_system(SAMPLES / "calib_true_system.json")) == \
        system_to_dict(ms.calib_true_system())


def test_shipped_samples_are_valid_and_as_described():
    true = load_system(SAMPLES / "calib_true_system.json")
    expect = {"room": (800, 1e5), "floodlight": (3200, 6e6), "calib_1.5m": (4000, 1e5),
              "calib_2.5m": (4000, 1e5), "calib_4.0m": (4000, 1e5)}
    for name, (k, _) in expect.items():
        p = SAMPLES / f"{name}.h5"
        assert p.stat().st_size < 2.2e6
        rec = read_recording(p)
        assert rec.n_shots == k
        scanner = true.scanner  # every sample: one true system, not the recorded nominal
        th, valid = scan_angles(rec.shot_time, rec.zero_crossings, rec.rising, scanner)
        assert np.all(valid)
        assert np.max(np.abs(th - rec.truth["theta"])) < 5e-4
        sig = (rec.truth["label"] == 1).sum() / k
        assert 0.7 < sig < 2.5  # about one laser-return detection per shot
    nominal = read_recording(SAMPLES / "room.h5").system
    from mems_stereo.model.system import system_to_json

    assert system_to_json(nominal) == system_to_json(read_recording(SAMPLES / "calib_2.5m.h5").system)
    dx = true.scanner.position - nominal.scanner.position
    assert 1e-3 < abs(dx[0]) < 1e-2 and 1e-3 < abs(dx[2]) < 1e-2
    assert 1e-3 < abs(true.scanner.theta0 - nominal.scanner.theta0) < 1e-2
    assert true.tdc.offset - nominal.tdc.offset == pytest.approx(1e-9, abs=0.3e-9)


def test_cli(tmp_path, capsys):
    out = tmp_path / "cli.h5"
    rc = main(["simulate", str(SAMPLES / "room_scene.json"), "-o", str(out), "--shots", "120",
               "--seed", "4", "--background", "2e5"])
    assert rc == 0
    assert "120 shots" in capsys.readouterr().out
    rec = read_recording(out)
    assert rec.n_shots == 120
    again = simulate(burkard2022(), load_scene(SAMPLES / "room_scene.json"), 120,
                     rng=np.random.default_rng(4), background_hz=2e5)
    np.testing.assert_array_equal(rec.bins, again.bins)
    bad = tmp_path / "bad.json"
    bad.write_text('{"objects": [{"type": "sphere", "center": [0, 0, 2], "radius": -1, '
                   '"reflectivity": 0.5}]}')
    rc = main(["simulate", str(bad), "-o", str(tmp_path / "x.h5")])
    assert rc == 2
    err = capsys.readouterr().err
    assert "objects[0].radius: expected a positive number, found -1" in err
    assert not (tmp_path / "x.h5").exists()
