"""3-D triangulation, 3x3 covariance and the readout gate of the two-axis system,
against independent derivations (numeric root finding, OpenCV, Monte Carlo, brute force)."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import brentq

from mems_stereo.geometry.gating import (
    GateSpec,
    epipolar_polylines,
    full_gate,
    gate_half_width,
    gate_pixels,
)
from mems_stereo.geometry.twoaxis import (
    Spreads2D,
    beam_point_2d,
    pixel_point_2d,
    propagate_2d,
)
from mems_stereo.model.presets import lissajous64
from mems_stereo.model.scanner2d import scan_direction_2d
from mems_stereo.pipeline.twoaxis import path_length_interval

DIST = np.array([-0.12, 0.05, 1e-3, -5e-4, 0.0])


def _system(distorted: bool = False, baseline=(-0.125, 0.0, 0.0)):
    s = lissajous64()
    rc = s.receiver
    if distorted:
        rc = replace(rc, dist_coeffs=DIST)
    return s.replace(receiver=rc, scanner=replace(s.scanner, position=np.array(baseline)))


def _path(x, p):
    return np.linalg.norm(x - p, axis=-1) + np.linalg.norm(x, axis=-1)


def test_beam_point_is_the_numeric_root_on_the_beam():
    s = _system(baseline=(-0.12, 0.015, 0.01))
    p = s.scanner.position
    rng = np.random.default_rng(1)
    t1 = s.scanner.theta0 + rng.uniform(-0.15, 0.15, 30)
    t2 = rng.uniform(-0.18, 0.18, 30)
    L = rng.uniform(1.0, 16.0, 30)
    x = beam_point_2d(s, L=L, theta1=t1, theta2=t2)
    d = scan_direction_2d(t1, t2, s.scanner)
    for i in range(30):
        s_ref = brentq(lambda u, i=i: u + np.linalg.norm(p + u * d[i]) - L[i], 0.0, L[i])
        np.testing.assert_allclose(x[i], p + s_ref * d[i], atol=1e-9)


@pytest.mark.parametrize("distorted", [False, True])
def test_pixel_point_reprojects_with_opencv_and_matches_the_numeric_root(distorted):
    s = _system(distorted, baseline=(-0.12, 0.02, -0.005))
    rc, p = s.receiver, s.scanner.position
    rng = np.random.default_rng(2)
    X = np.stack([rng.uniform(-1, 1, 40), rng.uniform(-1, 1, 40), rng.uniform(1.0, 7.0, 40)], 1)
    uv, _ = cv2.projectPoints(X.reshape(-1, 1, 3), np.zeros(3), np.zeros(3),
                              rc.camera_matrix, rc.dist_coeffs)
    uv = uv.reshape(-1, 2)
    L = _path(X, p)
    x = pixel_point_2d(s, uv[:, 0], uv[:, 1], L)
    np.testing.assert_allclose(x, X, atol=1e-7)
    # ρ as a numeric root along the ray through cv2.undistortPoints
    xy = cv2.undistortPoints(uv.reshape(-1, 1, 2), rc.camera_matrix, rc.dist_coeffs,
                             criteria=(3, 100, 1e-14)).reshape(-1, 2)
    rays = np.concatenate([xy, np.ones((40, 1))], 1)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    for i in range(5):
        rho = brentq(lambda r, i=i: _path(r * rays[i], p) - L[i], 1e-6, L[i])
        np.testing.assert_allclose(np.linalg.norm(x[i]), rho, rtol=1e-8)


@settings(max_examples=60, deadline=None)
@given(t1=st.floats(-0.15, 0.15), t2=st.floats(-0.19, 0.19), s_m=st.floats(0.4, 12.0))
def test_property_beam_point_pixel_point_round_trip(t1, t2, s_m):
    s = _system(baseline=(-0.125, 0.01, 0.0))
    p = s.scanner.position
    th1 = s.scanner.theta0 + t1
    d = scan_direction_2d(th1, t2, s.scanner)
    X = p + s_m * d
    if X[2] < 0.2:
        return
    L = _path(X, p)
    np.testing.assert_allclose(beam_point_2d(s, L=L, theta1=th1, theta2=t2)[0], X, atol=1e-8)
    K = s.receiver.camera_matrix
    u, v = K[0, 0] * X[0] / X[2] + K[0, 2], K[1, 1] * X[1] / X[2] + K[1, 2]
    np.testing.assert_allclose(pixel_point_2d(s, u, v, L)[0], X, atol=1e-8)
    # the beam point's image is inside the gate of that shot
    spec = GateSpec(0.3, 15.0, 1.0)
    g = gate_pixels(s, d[None], spec)
    if 0 <= round(u) < 64 and 0 <= round(v) < 64 and 0.3 <= np.linalg.norm(X) <= 15.0:
        assert g.contains([0], [round(v) * 64 + round(u)])[0]


@pytest.mark.parametrize("fn", [pixel_point_2d, beam_point_2d])
def test_covariance_against_monte_carlo(fn):
    s = _system(baseline=(-0.125, 0.01, 0.0))
    rng = np.random.default_rng(3)
    th1, th2 = s.scanner.theta0 + 0.05, -0.08
    X = beam_point_2d(s, L=7.0, theta1=th1, theta2=th2)[0]
    K = s.receiver.camera_matrix
    u, v = K[0, 0] * X[0] / X[2] + K[0, 2], K[1, 1] * X[1] / X[2] + K[1, 2]
    sp = Spreads2D(0.29, 0.29, 0.05, 2e-4, 3e-4)
    x0, cov = propagate_2d(fn, s, u, v, 7.0, th1, th2, sp)
    n = 20000
    z = rng.normal(size=(n, 5)) * np.sqrt(sp.variances())
    xs = fn(s, u + z[:, 0], v + z[:, 1], 7.0 + z[:, 2], th1 + z[:, 3], th2 + z[:, 4])
    mc = np.cov(xs.T)
    np.testing.assert_allclose(np.diag(mc), np.diag(cov[0]), rtol=0.06)
    w = np.linalg.eigh(cov[0])[1][:, -1]  # main axis: variance along it
    assert abs(w @ mc @ w / (w @ cov[0] @ w) - 1) < 0.05
    assert np.all(np.abs(xs.mean(0) - x0[0]) <= 4 * np.sqrt(np.diag(cov[0]) / n) + 1e-6)


def _brute_gate(s, d, spec, n=24):
    poly = epipolar_polylines(s, d[None], spec.r_min, spec.r_max, n)[0]
    w, h = s.receiver.image_size
    rr, cc = np.mgrid[0:h, 0:w]
    P = np.stack([cc.ravel(), rr.ravel()], 1).astype(float)
    best = np.full(P.shape[0], np.inf)
    for a, b in zip(poly[:-1], poly[1:]):
        e = b - a
        t = np.clip(((P - a) @ e) / (e @ e), 0, 1)
        best = np.minimum(best, np.linalg.norm(a + t[:, None] * e - P, axis=1))
    return np.flatnonzero(best <= spec.half_width)


@pytest.mark.parametrize("distorted", [False, True])
def test_gate_equals_brute_force_band(distorted):
    s = _system(distorted, baseline=(-0.12, 0.03, 0.01))
    rng = np.random.default_rng(4)
    t1 = s.scanner.theta0 + rng.uniform(-0.15, 0.15, 12)
    t2 = rng.uniform(-0.18, 0.18, 12)
    d = scan_direction_2d(t1, t2, s.scanner)
    spec = GateSpec(0.5, 8.0, gate_half_width(s))
    g = gate_pixels(s, d, spec)
    for k in range(12):
        ref = _brute_gate(s, d[k], spec)
        np.testing.assert_array_equal(g.pixels[g.offsets[k]:g.offsets[k + 1]], ref)
    assert 0 < g.read_fraction() < 0.05
    assert g.exposure().sum() == g.pixels.size
    fg = full_gate(3, 4096)
    assert fg.read_fraction() == 1.0 and fg.contains([2], [4095])[0]


def test_path_length_interval_against_dense_sampling():
    s = _system(baseline=(-0.12, 0.02, 0.0))
    p = s.scanner.position
    K = s.receiver.camera_matrix
    rng = np.random.default_rng(6)
    for _ in range(25):
        th1 = s.scanner.theta0 + rng.uniform(-0.15, 0.15)
        th2 = rng.uniform(-0.18, 0.18)
        d = scan_direction_2d(th1, th2, s.scanner)
        X = p + rng.uniform(1.0, 6.0) * d
        u0, v0 = K[0, 0] * X[0] / X[2] + K[0, 2], K[1, 1] * X[1] / X[2] + K[1, 2]
        uv = np.array([[np.rint(u0), np.rint(v0)]])
        L_lo, L_hi = path_length_interval(s, d[None], uv, 0.5, 8.0, 1.25)
        ss = np.linspace(0.0, 10.0, 400001)
        Y = p + ss[:, None] * d
        r = np.linalg.norm(Y, axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            uu, vv = K[0, 0] * Y[:, 0] / Y[:, 2] + K[0, 2], K[1, 1] * Y[:, 1] / Y[:, 2] + K[1, 2]
        inside = ((np.abs(uu - uv[0, 0]) <= 1.25) & (np.abs(vv - uv[0, 1]) <= 1.25)
                  & (r >= 0.5) & (r <= 8.0) & (Y[:, 2] > 0))
        Ls = ss[inside] + np.linalg.norm(Y[inside], axis=1)
        assert inside.any()
        np.testing.assert_allclose([L_lo[0], L_hi[0]], [Ls.min(), Ls.max()], atol=2e-4)
