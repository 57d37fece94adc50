"""The scan's dwell skew (mems_stereo.pipeline.scan_dwell): the angle of a point, and the
shift of a footprint's mean angle toward the turning points, checked against the
arcsine density's first-order form and a direct integral over the mirror's phase."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import quad

import mems_stereo as ms
from mems_stereo.model.scanner import scan_direction
from mems_stereo.pipeline.cloud import PointCloud
from mems_stereo.pipeline.scan_dwell import DwellSkew


@pytest.fixture(scope="module")
def skew():
    return DwellSkew(ms.preset("burkard2022"))


def test_the_angle_of_a_point_on_a_beam_is_the_beam_angle(skew):
    sc = skew.system.scanner
    rng = np.random.default_rng(2)
    th = sc.theta0 + sc.theta_mech_max * rng.uniform(-1, 1, 50)
    pts = np.asarray(sc.position) + rng.uniform(0.5, 8.0, (50, 1)) * scan_direction(th, sc)
    np.testing.assert_allclose(skew.angle_of(pts), th, atol=2e-7)


@pytest.mark.parametrize("frac", [0.8, 0.9, 0.97, -0.95])
def test_far_from_a_turning_point_the_shift_is_s2_times_the_log_density_slope(skew, frac):
    """θ = θ0 + A·cos φ, φ uniform: ρ ∝ 1/sqrt(A² − x²), x = θ − θ0, so a narrow footprint
    N(θ_c, s²) has its mean shifted by s²·ρ'/ρ = s²·x/(A² − x²) (to first order)."""
    sc = skew.system.scanner
    A, s = sc.theta_mech_max, 5e-4
    x = frac * A
    got = skew.mean_shift(np.array([sc.theta0 + x]), np.array([s]))[0]
    want = s * s * x / (A * A - x * x)
    assert got == pytest.approx(want, rel=0.03)


@pytest.mark.parametrize("gap", [5e-4, 2e-3, 4e-3])
def test_near_a_turning_point_the_shift_is_the_integral_over_the_phase(skew, gap):
    """Within a few footprints of the turning point θ0 − A (first order fails there):
    the mean of θ(φ) − θ_c weighted by the footprint over φ uniform, by quadrature."""
    sc = skew.system.scanner
    A, th0, s = sc.theta_mech_max, sc.theta0, 8e-4
    tc = th0 - A + gap

    def g(phi):
        return np.exp(-0.5 * ((th0 + A * np.cos(phi) - tc) / s) ** 2)

    phi_c = np.arccos(np.clip((tc - th0) / A, -1, 1))
    opts = {"points": [phi_c], "limit": 400, "epsabs": 0, "epsrel": 1e-10}
    num = quad(lambda p: g(p) * (th0 + A * np.cos(p) - tc), np.pi / 2, np.pi, **opts)[0]
    den = quad(g, np.pi / 2, np.pi, **opts)[0]
    got = skew.mean_shift(np.array([tc]), np.array([s]))[0]
    assert got == pytest.approx(num / den, rel=0.02)


def test_the_systematic_sigma_is_small_in_the_middle_and_grows_at_the_edges(skew):
    """Points on the beam at 6 m from the middle of the scan to 3·10⁻³ rad from its end:
    σ_sys is |∂r/∂θ|·|Δθ| (a stereo weight of 1), micrometres in the middle, millimetres halfway and
    centimetres at the end; the displacement's norm is at least σ_sys."""
    sc = skew.system.scanner
    th = sc.theta0 - np.array([0.0, 0.5, 0.9, 0.985]) * sc.theta_mech_max
    d = scan_direction(th, sc)
    # the point at 6 m along the optical axis on each beam
    L = (6.0 - sc.position[2]) / d[:, 2]
    pts = np.asarray(sc.position) + L[:, None] * d
    uv = ms.project_points(pts, skew.system.receiver.camera_matrix,
                           skew.system.receiver.dist_coeffs)
    cloud = PointCloud(pts, {"pixel": np.rint(uv[:, 0]).astype(np.int32),
                             "row": np.zeros(4, np.int32)})
    common = skew.systematic(cloud)
    assert common.sigma_r[0] < 1e-4 and common.sigma_r[1] < 3e-3
    assert 0.01 < common.sigma_r[3] < 0.2
    assert np.all(np.diff(common.sigma_r) > 0)
    assert np.all(np.linalg.norm(common.dx, axis=1) >= 0.99 * common.sigma_r)
