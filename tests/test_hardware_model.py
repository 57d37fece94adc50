"""The hardware model (docs/hardware.md): JSON members, closed forms against numerics,
the ideal case bit for bit, and an imperfect recording processed with the full model."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import brentq

from mems_stereo.errors import FormatError
from mems_stereo.model.hardware import Harmonic, MonitorEdges
from mems_stereo.model.scanner import PHASE_FALLING, scan_angles
from mems_stereo.model.system import (
    burkard2022,
    load_system,
    system_from_dict,
    system_from_json,
    system_to_dict,
    system_to_json,
)
from mems_stereo.model.tdc import (
    code_centres,
    code_of_time,
    detection_codes,
    detection_path_length,
    path_length_from_codes,
)
from mems_stereo.model.trajectory import trajectory_shape, zero_crossing_phases
from mems_stereo.physics.first_photon import (
    ShapeExcess,
    first_photon_mean_delay,
    first_photon_mean_truncated,
)
from mems_stereo.physics.pulse import (
    PulseShape,
    emg_cdf,
    emg_pdf,
    ex_gaussian_shape,
    pulse_shape_of,
    pulse_sigma_of,
)
from mems_stereo.sim import Imperfections, Trajectory, monitor_zero_crossings
from mems_stereo.sim.imperfections import tdc_codes

SAMPLES = Path(__file__).resolve().parents[1] / "samples"


def full_system(seed: int = 3):
    return Imperfections.typical().apply(burkard2022(), np.random.default_rng(seed))


def test_json_round_trip_with_every_member():
    s = full_system()
    d = system_to_dict(s)
    d["scanner"]["harmonics"][0].update(amplitude_std=1e-4, phase_std=0.05)
    d["scanner"]["monitor"]["rising_delay_std"] = 5e-9
    d["tdc"]["pixel_offsets_std"] = [1e-11] * 192
    back = system_from_json(json.dumps(d), "x.json")
    assert system_to_dict(back) == d
    assert back.scanner.harmonics[0].amplitude_std == 1e-4
    assert back.scanner.monitor == MonitorEdges(300e-9, 100e-9, 5e-9, None)
    assert back.laser.pulse_shape.tail_fraction == 0.2 and not back.ideal_hardware
    np.testing.assert_array_equal(back.tdc.code_widths, s.tdc.code_widths)


def test_table_pulse_round_trip_and_bad_members_refused():
    d = system_to_dict(burkard2022())
    d["laser"]["pulse_shape"] = {"model": "table", "times": [-1e-8, 0.0, 2e-8],
                                 "power": [0.0, 1.0, 0.0]}
    assert system_to_dict(system_from_dict(d)) == d
    bad = [("scanner", "harmonics", [{"order": 1, "amplitude": 0.01}], "order"),
           ("scanner", "harmonics", [{"order": 3, "amplitud": 0.01}], "amplitud"),
           ("tdc", "code_widths", [1.0] * 10, "code_widths"),
           ("tdc", "pixel_offsets", [0.0] * 191, "pixel_offsets"),
           ("laser", "pulse_shape", {"model": "ex-gaussian", "tail_fraction": 1.2,
                                     "tail_decay": 1e-9}, "tail_fraction")]
    for part, key, value, word in bad:
        e = system_to_dict(burkard2022())
        e[part][key] = value
        with pytest.raises(FormatError, match=word):
            system_from_dict(e, "s.json")


def test_version1_file_means_what_it_meant():
    path = SAMPLES / "nominal_system.json"
    s = load_system(path)
    assert s.ideal_hardware and s.scanner.harmonics == () and s.tdc.pixel_offsets is None
    assert system_to_dict(s) == json.loads(path.read_text())
    codes = np.arange(0, 4097)
    # the ideal path is the FORMAT v1 rule, bit for bit
    np.testing.assert_array_equal(detection_path_length(codes, s, np.zeros(codes.size, int)),
                                  path_length_from_codes(codes, s.tdc, s.speed_of_light))
    t = np.linspace(1e-4, 2e-3, 50)
    zc = np.arange(0.0, 3e-3, 1 / (2 * s.scanner.f_mech))
    rising = np.arange(zc.size) % 2
    th, _ = scan_angles(t, zc, rising, s.scanner)
    np.testing.assert_array_equal(
        th, s.scanner.theta0 + s.scanner.theta_mech_max * np.cos(
            np.interp(t, zc, PHASE_FALLING + math.pi * np.arange(zc.size))
            + s.scanner.phase_offset))


def test_zero_crossing_phases_are_the_trajectory_roots():
    hs = (Harmonic(2, 0.01, 0.4), Harmonic(3, 0.008, -1.0), Harmonic(5, 0.005, 2.0))
    pf, pr = zero_crossing_phases(hs)
    for got, a, b in ((pf, 1.0, 2.0), (pr, 4.0, 5.5)):
        root = brentq(lambda p: float(trajectory_shape(p, hs)), a, b, xtol=1e-15)
        assert got == pytest.approx(root, abs=1e-12)
    assert zero_crossing_phases(()) == (0.5 * math.pi, 1.5 * math.pi)


def test_harmonic_trajectory_and_edge_delays_recovered_from_the_monitor():
    sc = full_system().scanner
    sc = sc.__class__(**{**sc.__dict__, "harmonics": (Harmonic(2, 0.006, 0.3),
                                                       Harmonic(3, 0.003, 1.1))})
    traj = Trajectory.from_scanner(sc, phase=0.7, drift=0.0)
    t = np.linspace(0.0, 4e-3, 400)
    zc, rising = monitor_zero_crossings(traj, t, np.random.default_rng(0), jitter=0.0)
    # the monitor's recorded times: the true crossings plus the edges' delays
    true_zc = np.array([brentq(lambda x: float(trajectory_shape(traj.monitor_phase(x), sc.harmonics)),
                               z - 2e-5, z + 2e-5, xtol=1e-16)
                        for z in zc - np.where(rising == 1, 300e-9, 100e-9)])
    np.testing.assert_allclose(zc - np.where(rising == 1, 300e-9, 100e-9), true_zc, atol=1e-12)
    th, ok = scan_angles(t, zc, rising, sc)
    assert ok.all()
    np.testing.assert_allclose(th, traj.theta(t), atol=1e-9)
    ideal = sc.__class__(**{**sc.__dict__, "harmonics": (), "monitor": None})
    th0, _ = scan_angles(t, zc, rising, ideal)
    assert np.max(np.abs(th0 - traj.theta(t))) > 1e-4  # what the ideal model misses


def test_two_axis_fast_axis_follows_its_harmonics_and_edges():
    from dataclasses import replace

    from mems_stereo.model.presets import lissajous64
    from mems_stereo.model.scanner2d import Axis2Monitor, scan_angles_2d

    s = lissajous64()
    sc = replace(s.scanner, harmonics=(Harmonic(3, 0.004, 0.5),),
                 monitor=MonitorEdges(250e-9, 50e-9))
    a2 = sc.axis2
    t = np.arange(2000) / s.laser.f_rep
    rng = np.random.default_rng(4)
    tr1 = Trajectory.from_scanner(sc, phase=0.3)
    zc, ri = monitor_zero_crossings(tr1, t, rng, 0.0)
    tr2 = Trajectory(a2.f_mech, 1.1, 0.0, 0.0, a2.theta0, a2.theta_mech_max, 0.0)
    z2, r2 = monitor_zero_crossings(tr2, t, rng, 0.0)
    th1, _, valid = scan_angles_2d(t, zc, ri, Axis2Monitor(zero_crossings=z2, rising=r2), sc)
    assert valid.all()
    np.testing.assert_allclose(th1, tr1.theta(t), atol=1e-9)


def test_ex_gaussian_first_photon_mean_against_monte_carlo():
    sig, w, tau, mu = 2e-9, 0.3, 3e-9, 2.5
    shape = ex_gaussian_shape(sig, w, tau)
    rng = np.random.default_rng(7)
    n = rng.poisson(mu, 100_000)
    n = n[n > 0]
    k = int(n.sum())
    d = rng.normal(0, sig, k) + np.where(rng.random(k) < w, rng.exponential(tau, k), 0.0)
    first = np.minimum.reduceat(d, np.concatenate([[0], np.cumsum(n)[:-1]]))
    mc = first.mean()
    se = first.std() / math.sqrt(first.size)
    assert first_photon_mean_delay(mu, shape) == pytest.approx(mc, abs=4 * se + 2e-12)
    assert first_photon_mean_delay(1e-12, shape) == pytest.approx(w * tau, rel=1e-4)
    # the TDC window opening at −1 ns: photons before it are lost
    d2 = np.where(d >= -1e-9, d, np.inf)
    first2 = np.minimum.reduceat(d2, np.concatenate([[0], np.cumsum(n)[:-1]]))
    first2 = first2[np.isfinite(first2)]
    se2 = first2.std() / math.sqrt(first2.size)
    got = first_photon_mean_truncated(np.array([mu]), np.array([-1e-9]), shape)[0, 0]
    assert got == pytest.approx(first2.mean(), abs=4 * se2 + 2e-12)
    # the Gaussian model plus the shape's excess is the shape's first-photon mean
    mean_g = first_photon_mean_truncated(np.array([mu]), np.array([-1e-9 - w * tau]),
                                         PulseShape.gaussian(2.3548200450309493 * 3e-9))
    ex = ShapeExcess(shape, 3e-9)(mu, -1e-9 - w * tau)
    assert mean_g[0, 0] + ex == pytest.approx(got - w * tau, abs=0.01 * 3e-9)  # table interp.
    lz = full_system().laser
    samples = (rng.normal(0, lz.pulse_fwhm / 2.3548200450309493, 200_000)
               + np.where(rng.random(200_000) < 0.2, rng.exponential(2e-9, 200_000), 0.0))
    assert pulse_sigma_of(lz) == pytest.approx(samples.std(), rel=0.01)
    g = pulse_shape_of(burkard2022().laser, 5e-11)  # no model: exactly today's Gaussian
    np.testing.assert_array_equal(g.cdf, PulseShape.gaussian(14.9e-9, 5e-11).cdf)


def test_emg_density_is_the_convolution_of_gaussian_and_exponential():
    sig, tau, dt = 1.5e-9, 4e-9, 1e-11
    t = np.arange(-1.5e-8, 5e-8, dt)
    gauss = np.exp(-0.5 * (t / sig) ** 2) / (sig * math.sqrt(2 * math.pi))
    expo = np.where(t >= 0, np.exp(-np.clip(t, 0, None) / tau) / tau, 0.0)
    shift = int(round(-t[0] / dt))  # the kernel's t = 0 is index ``shift``
    expo[shift] *= 0.5  # trapezoidal weight at the exponential's step
    conv = np.convolve(gauss, expo, mode="full")[:t.size] * dt
    ref = conv[shift:]
    got = emg_pdf(t[:ref.size], sig, tau)
    assert np.max(np.abs(got - ref)) < 1e-4 * got.max()
    cdf = emg_cdf(t, sig, tau)
    np.testing.assert_allclose(np.diff(cdf) / dt, emg_pdf(t[:-1] + dt / 2, sig, tau),
                               atol=1e-4 * got.max())


def test_code_widths_give_cumulative_centres_and_codes():
    s = full_system()
    tdc = s.tdc
    w = tdc.code_widths
    centres = np.empty(w.size)
    acc = 0.0
    for i, wi in enumerate(w):  # direct cumulative sum, one code at a time
        centres[i] = (acc + 0.5 * wi) * tdc.bin_width
        acc += wi
    np.testing.assert_allclose(code_centres(tdc), centres, rtol=1e-12, atol=1e-18)
    np.testing.assert_array_equal(code_of_time(centres, tdc), np.arange(1, w.size + 1))
    # the code density: uniform times fill codes in proportion to their widths
    t = np.random.default_rng(1).uniform(0, 64 * tdc.bin_width * 0.999, 400_000)
    h = np.bincount(tdc_codes(t, tdc), minlength=66)[1:64]
    np.testing.assert_allclose(h / h.mean(), w[:63] / w[:63].mean(), atol=0.05)


def test_code_time_with_pixel_offsets_and_its_inverse():
    s = full_system()
    codes = np.array([1, 17, 800, 4096])
    pix = np.array([0, 5, 100, 191])
    L = detection_path_length(codes, s, pix)
    t = code_centres(s.tdc)[codes - 1] - s.tdc.offset - s.tdc.pixel_offsets[pix] - 0.2 * 2e-9
    np.testing.assert_allclose(L, s.speed_of_light * t, rtol=1e-12)
    np.testing.assert_allclose(detection_codes(L, s, pix), codes, atol=1e-9)
    assert np.isnan(detection_path_length(np.array([0]), s, np.array([3]))[0])


def test_named_parameters_of_the_model():
    s = burkard2022().with_params(harmonic3_cos=0.002, harmonic3_sin=-0.001,
                                  edge_rising_delay=2e-7, pulse_tail_fraction=0.1,
                                  pulse_tail_decay=1e-9, pixel_offset_4=3e-11)
    h = s.scanner.harmonics[0]
    assert (h.order, h.amplitude) == (3, pytest.approx(math.hypot(0.002, 0.001)))
    phi = np.linspace(0, 7, 11)
    np.testing.assert_allclose(trajectory_shape(phi, (h,)) - np.cos(phi),
                               0.002 * np.cos(3 * phi) - 0.001 * np.sin(3 * phi), atol=1e-15)
    for name, value in (("harmonic3_cos", 0.002), ("harmonic3_sin", -0.001),
                        ("edge_rising_delay", 2e-7), ("edge_falling_delay", 0.0),
                        ("pulse_tail_decay", 1e-9), ("pixel_offset_4", 3e-11)):
        assert s.get_param(name) == pytest.approx(value, abs=1e-18)
    assert system_from_json(system_to_json(s)).get_param("harmonic3_sin") == pytest.approx(-0.001)


def test_imperfect_recording_processed_with_the_full_model_is_as_good_as_ideal():
    from mems_stereo.pipeline.angles import shot_angles
    from mems_stereo.pipeline.run import process_recording
    from mems_stereo.sim import SimulationOptions, load_scene, simulate
    from mems_stereo.sim.score import score_result

    scene = load_scene(SAMPLES / "room_scene.json")
    nominal = burkard2022()
    imperfect = Imperfections.typical().apply(nominal, np.random.default_rng(5))
    errors = {}
    for name, true in (("ideal", nominal), ("full", imperfect)):
        rec = simulate(nominal, scene, 500, rng=np.random.default_rng(1),
                       true_system=true, options=SimulationOptions(phase=0.3))
        sc = score_result(process_recording(rec, system=true), rec.truth["label"], scene)
        errors[name] = sc["median_error"]
        assert sc["recall"] > 0.97 and sc["points"] > 50
    # the exact model undoes the imperfections (same scene, seed and shots)
    assert errors["full"] <= 1.3 * errors["ideal"] + 0.003
    # stage 1 of the run: the shots' angles are the true ones with the full model
    # to the monitor's 20 ns jitter (θ_max·ω·20 ns ≈ 4e-5 rad), not with the cosine
    th_full, ok = shot_angles(rec, imperfect)  # a Recording has the header's arrays
    th_cos, _ = shot_angles(rec, nominal)
    assert ok.all()
    e_full = np.abs(th_full - rec.truth["theta"])
    e_cos = np.abs(th_cos - rec.truth["theta"])
    assert np.median(e_full) < 2e-5 and e_full.max() < 1.5e-4
    assert np.median(e_cos) > 5 * np.median(e_full) and e_cos.max() > 5e-4


@pytest.mark.stress
def test_simulated_background_fills_codes_by_their_widths():
    """The simulator's code-density signature (floodlight, 1000 shots, ~10 s): the first
    background photon's code N has P ∝ exp(−λ e_{N−1}) − exp(−λ e_N) with the DNL's
    edges e (χ²/dof ≈ 1), not with equal widths."""
    from mems_stereo.model.tdc import code_edges
    from mems_stereo.sim import load_scene, simulate

    nom = burkard2022()
    true = Imperfections(dnl_periodic=0.15).apply(nom, np.random.default_rng(2))
    rec = simulate(nom, load_scene(SAMPLES / "room_scene.json"), 1000,
                   rng=np.random.default_rng(3), background_hz=6e6, true_system=true)
    b = rec.bins[rec.truth["label"] == 2].astype(np.int64)
    h = np.bincount(b, minlength=4097)[1:301]
    lam = 6e6 + 1e3  # background + dark counts
    chi2 = []
    for tdc in (true.tdc, nom.tdc):
        e = code_edges(tdc)
        p = np.exp(-lam * e[:-1]) - np.exp(-lam * e[1:])
        ex = p[:300] / p.sum() * b.size
        chi2.append(np.sum((h - ex) ** 2 / ex) / 300)
    assert chi2[0] < 1.3 < 2.0 < chi2[1]


def test_tabulated_pulse_moments_and_code_time():
    from dataclasses import replace

    from mems_stereo.model.hardware import PulseModel, pulse_mean_delay

    sig, shift = 2e-9, 0.7e-9
    t = np.linspace(-15e-9, 15e-9, 3001)
    laser = replace(burkard2022().laser, pulse_shape=PulseModel(
        "table", times=t, power=np.exp(-0.5 * ((t - shift) / sig) ** 2)))
    assert pulse_mean_delay(laser) == pytest.approx(shift, rel=1e-6)
    assert pulse_sigma_of(laser) == pytest.approx(sig, rel=1e-4)
    s = burkard2022().replace(laser=laser)
    L = detection_path_length(np.array([100]), s)
    L0 = path_length_from_codes(np.array([100]), s.tdc, s.speed_of_light)
    assert L[0] == pytest.approx(L0[0] - s.speed_of_light * shift, abs=1e-9)
