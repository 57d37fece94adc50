"""The calibration's hardware terms (calib/model.py, calib/problem.py, calib/hardware_fit.py):
the forward model against the hardware model's own functions, the score test's
calibration on data the ideal model describes, the per-pixel offsets' one step."""

from __future__ import annotations

import numpy as np
import pytest
from mems_stereo.calib.hardware_fit import candidate_blocks, score_tests
from mems_stereo.calib.model import HARDWARE_PARAMS, beam_hits, harmonic_orders, plane_normal
from mems_stereo.calib.pixel_offsets import pixel_offsets
from mems_stereo.calib.problem import Cells, Layout, Problem, WallData

from mems_stereo.model.scanner import phase_from_zero_crossings, scan_angle_from_phase
from mems_stereo.model.system import burkard2022


def _theta_from_hits(system, values, phase):
    """The scan angle beam_hits used, recovered from its beam direction."""
    h = beam_hits(system, values, phase, plane_normal(0.0), 2.0)
    d = h.point - system.baseline
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ref = beam_hits(system, {}, phase, plane_normal(0.0), 2.0)
    return d, ref


def test_trajectory_matches_the_hardware_model():
    sys0 = burkard2022()
    vals = {"harmonic3_cos": 0.004, "harmonic3_sin": -0.002, "harmonic2_cos": 0.001}
    true = sys0.with_params(**vals)
    phase = np.linspace(0.0, 2 * np.pi, 50)
    th_model = scan_angle_from_phase(phase, true.scanner)  # E's model
    # the same angle through the calibration's forward model: a system with that θ0
    # and no harmonics must give the calibration's direction at every shot
    d_cal = beam_hits(sys0, vals, phase, plane_normal(0.0), 2.0).point - sys0.baseline
    for k in (0, 17, 33):
        one = sys0.with_params(theta0=float(th_model[k]) - sys0.scanner.theta_mech_max
                               * np.cos(phase[k] + sys0.scanner.phase_offset))
        d_ref = beam_hits(one, {}, phase[k:k + 1], plane_normal(0.0), 2.0).point - one.baseline
        np.testing.assert_allclose(d_cal[k], d_ref[0], rtol=1e-9, atol=1e-12)
    # a system that carries the harmonics gives the same as the values
    a = beam_hits(true, {}, phase, plane_normal(0.0), 2.0).point
    np.testing.assert_allclose(a, beam_hits(sys0, vals, phase, plane_normal(0.0), 2.0).point,
                               rtol=1e-12)
    assert harmonic_orders((3,)) == ["harmonic3_cos", "harmonic3_sin"]
    assert set(harmonic_orders((2, 5))) <= set(HARDWARE_PARAMS)


def blank_wall(rng, n_shots=400):
    """A wall of ``n_shots`` shots at random times over 0.2 s of a 1570 Hz scan, no
    detections (one row of 192 pixels): a :class:`WallData` for model-only tests."""
    f = 1570.0
    zc = np.arange(0, 0.2, 0.5 / f) + 1e-4
    rising = (np.arange(zc.size) % 2).astype(bool)
    t = np.sort(rng.uniform(zc[0] + 1e-5, zc[-1] - 1e-5, n_shots))
    ph, _ = phase_from_zero_crossings(t, zc, rising)
    bins = np.zeros((n_shots, 1, 192), dtype=np.uint16)
    return WallData(ph, bins, np.full((1, 192), 1e5), 3.125e-10, "w", t, zc, rising)


def test_phase_follows_the_edge_delay_and_harmonics():
    rng = np.random.default_rng(1)
    w = blank_wall(rng)
    sys0 = burkard2022()
    lay = Layout(["theta0", "edge_rising_delay", "harmonic3_cos"], 1, False)
    assert lay.names == ["theta0", "harmonic3_cos", "edge_rising_delay"]
    prob = Problem([w], sys0, lay, 6e-9)
    vals = {"theta0": 0.7, "edge_rising_delay": 2e-7, "harmonic3_cos": 0.003}
    got = prob.phase(vals, 0)
    sc = sys0.with_params(edge_rising_delay=2e-7, harmonic3_cos=0.003).scanner
    want = phase_from_zero_crossings(w.shot_time, w.zero_crossings, w.rising, sc)[0]
    np.testing.assert_array_equal(got, want)
    # ideal values: the recorded phase, bit for bit
    prob0 = Problem([w], sys0, Layout(["theta0"], 1, False), 6e-9)
    assert prob0.phase({"theta0": 0.7}, 0) is w.phase


def _synthetic_problem(rng, offsets=None, tail=None):
    """A problem whose cells' first photons are drawn from the model itself (``tail``:
    (w, τ_d) of an ex-gaussian pulse)."""
    sys0 = burkard2022()
    w = blank_wall(rng, 6000)
    lay = Layout(["theta0", "tdc_offset"], 1, False)
    prob = Problem([w], sys0, lay, 1e-9)
    wall = np.array([0.0, 0.0, 1.5, np.log(0.3), np.log(0.6)])
    x = lay.pack({"theta0": sys0.scanner.theta0, "tdc_offset": 0.0}, wall[None, :])
    pred, ok, _ = prob.predictions(x, 0)
    shots = np.flatnonzero(ok & (pred[:, 1] > 3) & (pred[:, 1] < 188))
    u = np.rint(pred[shots, 1])
    cols = (u[:, None] + np.arange(-2, 3)[None, :]).ravel()
    sh = np.repeat(shots, 5)
    tau = pred[sh, 0] + (0.0 if offsets is None else offsets[cols.astype(int)])
    share = np.exp(-0.5 * ((cols - pred[sh, 1]) / 0.6) ** 2) * 0.3 / (0.6 * np.sqrt(2 * np.pi))
    n = rng.poisson(share)
    if tail is None:
        t = np.where(n > 0, tau + rng.normal(0.0, 1e-9, sh.size), np.nan)
    else:  # the first of the n photons, each N(0, σ) + (share w) Exp(τ_d)
        a = rng.normal(0.0, 1e-9, (sh.size, 4)) + np.where(
            rng.random((sh.size, 4)) < tail[0], rng.exponential(tail[1], (sh.size, 4)), 0.0)
        a[np.arange(4)[None, :] >= n[:, None]] = np.inf
        t = np.where(n > 0, tau + a.min(axis=1), np.nan)
    lg = float(np.median(pred[shots, 3]))
    prob.cells[0] = Cells(sh, cols, np.zeros_like(cols), t, np.full(sh.size, 1e3), 60e-9,
                          shots, lg)
    return prob, lay.pack({"theta0": sys0.scanner.theta0, "tdc_offset": 0.0},
                          np.array([[0.0, 0.0, 1.5, np.log(0.3), np.log(0.6)]]))


def test_score_tests_and_pixel_offsets():
    rng = np.random.default_rng(2)
    prob, x = _synthetic_problem(rng)
    tests = score_tests(prob, x, candidate_blocks((3,)))
    assert [t.name for t in tests] == ["harmonic 3", "edge delays"]
    assert all(np.isfinite(t.lm) and t.dof in (1, 2) for t in tests)
    po = pixel_offsets(prob, x)
    assert not po.test.selected  # no offsets in the data
    # offsets of 1.5 ns on every other pixel are found, with σ that cover the error
    off = np.zeros(192)
    off[::2] = 1.5e-9
    off -= off.mean()
    prob2, x2 = _synthetic_problem(np.random.default_rng(2), off)
    po2 = pixel_offsets(prob2, x2)
    assert po2.test.selected
    c = po2.covered & np.isfinite(po2.std)
    err = (po2.value[c] - (off[c] - np.average(off[c], weights=1 / po2.std[c] ** 2)))
    assert np.sqrt(np.mean((err / po2.std[c]) ** 2)) == pytest.approx(1.0, abs=0.5)


def test_score_test_of_a_block_does_not_depend_on_the_other_blocks_tested():
    """Each block's score test conditions on the fitted parameters wherever the
    extended layout puts them: with a 3rd harmonic fitted, testing the 2nd harmonic
    (which the layout orders before it) beside the 5th leaves the 5th's statistic as
    it is alone, and a drawn-from-the-model wall gives each block a χ² of its size."""
    from mems_stereo.calib.hardware_fit import extended_problem
    from mems_stereo.calib.solver import FitState, newton

    prob, x = _synthetic_problem(np.random.default_rng(2))
    prob3, x3 = extended_problem(prob, x, harmonic_orders((3,)))
    x3 = newton(prob3, x3, FitState()).x  # the fit with the 3rd harmonic free
    blocks = candidate_blocks((2, 5))
    alone = score_tests(prob3, x3, {"harmonic 5": blocks["harmonic 5"]})[0]
    both = {t.name: t for t in score_tests(prob3, x3, blocks)}
    assert both["harmonic 5"].lm == pytest.approx(alone.lm, rel=1e-9, abs=1e-12)
    assert all(t.lm < 30.0 for t in both.values()), both


def test_log_p_value_is_finite_where_the_p_value_underflows():
    """ln of the χ² survival function: scipy's where finite; for 2 dof it is −LM/2
    exactly (the χ²₂ survival function is exp(−x/2)), also past underflow; the
    ranking of strong blocks follows the statistic and the dof."""
    from mems_stereo.calib.hardware_fit import log_p_value
    from scipy import stats

    assert log_p_value(20.0, 1) == pytest.approx(float(stats.chi2.logsf(20.0, 1)), rel=1e-12)
    for lm in (30.0, 1438.0, 5000.0):
        assert log_p_value(lm, 2) == pytest.approx(-lm / 2, rel=1e-9)
    assert log_p_value(3000.0, 1) < log_p_value(3000.0, 2) < log_p_value(2900.0, 2) < 0


def test_hardware_page_renders(tmp_path):
    from types import SimpleNamespace

    from matplotlib.backends.backend_pdf import PdfPages
    from matplotlib.figure import Figure
    from mems_stereo.calib.code_density import code_widths
    from mems_stereo.calib.goodness import calibration_goodness
    from mems_stereo.calib.pulse_shape import PulseFit
    from mems_stereo.viz.calib_report_hardware import hardware_page, inl_panel

    rng = np.random.default_rng(3)
    prob, x = _synthetic_problem(rng)
    result = SimpleNamespace(system=prob.system, extra={
        "problem": prob, "x": x, "pixel_offsets": pixel_offsets(prob, x),
        "hardware_tests": score_tests(prob, x, candidate_blocks((3,))),
        "goodness": calibration_goodness(prob, x),
        "pulse": PulseFit(0.0, 1e-9, 0.2, 2e-9, 0.4e-9, 0.01, dict.fromkeys(
            ("shift", "sigma", "tail_fraction", "tail_decay", "background", "mean_delay"),
            0.1), np.eye(5), -10.0, -20.0, 1.2e-9, 1000, 0.0)})
    path = tmp_path / "hw.pdf"
    with PdfPages(str(path)) as pdf:
        assert hardware_page(pdf, result)
        assert not hardware_page(pdf, SimpleNamespace(extra={}))  # a failure: no page
    assert path.read_bytes()[:4] == b"%PDF"
    codes = rng.integers(0, 33, size=(500, 4))
    inl_panel(Figure().subplots(), code_widths(codes, 32))


def test_calibration_goodness_refuses_naming_the_effect():
    from types import SimpleNamespace

    from mems_stereo.calib.goodness import judge

    def result(offsets):
        prob, x = _synthetic_problem(np.random.default_rng(2), offsets)
        return SimpleNamespace(extra={"problem": prob, "x": x}, warnings=[], elapsed=0.0)

    clean = result(None)
    assert judge(clean) is clean and clean.extra["goodness"][0].passed
    off = np.zeros(192)
    off[::2] = 1.5e-9
    failed = judge(result(off - off.mean()))
    assert not failed and failed.kind == "estimate"
    assert "per-pixel TDC offsets" in failed.reason and "--inflate-sigma" in failed.reason


def test_pulse_tail_is_tested_and_fitted_with_honest_sigma():
    """No tail in the data: the tail's score test selects nothing; a 30 % tail of 2 ns
    (σ 1 ns): selected, and the joint fit finds share, decay and the core's offset
    within 4σ (the σ from the fit's information)."""
    from mems_stereo.calib import observability as obs
    from mems_stereo.calib.hardware_fit import tail_score_test
    from mems_stereo.calib.solver import FitState, newton

    for tail, want in ((None, False), ((0.3, 2e-9), True)):
        prob, x = _synthetic_problem(np.random.default_rng(4), tail=tail)
        x = newton(prob, x, FitState()).x  # the ideal model's fit first
        test, decay = tail_score_test(prob, x)
        assert test.selected is want, test
    lay = Layout(["theta0", "tdc_offset", "pulse_tail_fraction", "pulse_tail_decay"], 1, False)
    p2 = Problem(prob.walls, prob.system, lay, prob.sigma)
    p2.cells = prob.cells
    v, walls = prob.layout.unpack(x)
    x2 = lay.pack({**v, "pulse_tail_fraction": 0.1, "pulse_tail_decay": decay}, walls)
    st = FitState()
    nr = newton(p2, x2, st)
    assert st.converged
    cov, _, _ = obs.covariance(nr.info, lay.scales)
    sd = np.sqrt(np.diag(cov))
    truth = {"tdc_offset": 0.0, "pulse_tail_fraction": 0.3, "pulse_tail_decay": 2e-9}
    # informative σ (6000 shots at σ 1 ns): share to 0.1, decay to 0.5 ns, offset to 0.5 ns
    assert np.all(sd[1:4] < [0.5e-9, 0.1, 0.5e-9]), sd
    for name, t in truth.items():
        i = lay.names.index(name)
        assert abs(nr.x[i] - t) < 4 * sd[i], (name, nr.x[i], sd[i])


def test_fitted_pulse_tail_is_written_with_its_sigma():
    from mems_stereo.calib.hardware_fit import hardware_std

    from mems_stereo.model.hardware import pulse_mean_delay
    from mems_stereo.model.system import system_from_dict, system_to_dict

    names = ["pulse_tail_fraction", "pulse_tail_decay"]
    vals = {"pulse_tail_fraction": 0.2, "pulse_tail_decay": 3e-9}
    s = hardware_std(burkard2022().with_params(**vals), vals,
                     {"pulse_tail_fraction": 0.05, "pulse_tail_decay": 4e-10}, np.eye(2), names)
    d = system_to_dict(s)["laser"]["pulse_shape"]
    assert d == {"model": "ex-gaussian", "tail_fraction": 0.2, "tail_decay": 3e-9,
                 "tail_fraction_std": 0.05, "tail_decay_std": 4e-10}
    back = system_from_dict(system_to_dict(s))
    assert pulse_mean_delay(back.laser) == pytest.approx(0.2 * 3e-9)


def test_a_failure_by_another_check_names_the_effect(monkeypatch):
    """``name_failure``: a fit refused by a plausibility or observability check whose
    residuals show structure gets a reason naming the effect first and its own reason
    after it, with the same kind (exit code) and the reports in its details; clean
    residuals, or a failure without fitted values, leave it unchanged."""
    from mems_stereo.calib import goodness
    from mems_stereo.calib.result import CalibrationFailure
    from mems_stereo.calib.solver import FitState, newton

    off = np.zeros(192)
    off[::2] = 1.5e-9
    why = "not observable from these data: baseline_z σ = 30 mm > 20 mm"
    for offsets, named in ((None, False), (off - off.mean(), True)):
        prob, x = _synthetic_problem(np.random.default_rng(2), offsets)
        x = newton(prob, x, FitState()).x  # a fitted point, as failed_problem gives
        monkeypatch.setattr(goodness, "failed_problem", lambda *a, p=prob, x=x: (p, x))
        fail = CalibrationFailure(why, "input", {"values": {}, "walls": []}, ["w"], 1.0)
        out = goodness.name_failure(fail, prob.walls, prob.system)
        assert not out and out.kind == "input" and out.warnings == ["w"]
        if not named:
            assert out is fail
            continue
        assert out.reason.startswith("the model does not fit these walls: residuals differ "
                                     "from pixel to pixel")
        assert "per-pixel TDC offsets" in out.reason
        assert out.reason.endswith("; refused besides: " + why)
        assert out.details["goodness"][0]["passed"] is False
    monkeypatch.undo()
    bare = CalibrationFailure("no recording shows a usable wall return", "input")
    assert goodness.name_failure(bare, prob.walls, prob.system) is bare
