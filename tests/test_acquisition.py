"""Acquisition statistics (paper Sec. 2.1, Fig. 2) against independent derivations."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mems_stereo.model.acquisition import acquisition_statistics, shot_pixels


def test_shots_over_angle_follow_the_arcsine_law(system):
    """A resonant cosine sampled at an irrational rate: density 1/(π√(A²−θ²))."""
    st = acquisition_statistics(system, 200_000, 2.5, frequency_ratio=(math.sqrt(5) - 1) / 7,
                                n_angle_bins=20)
    A = system.scanner.theta_mech_max
    cdf = 0.5 + np.arcsin(np.clip(st.angle_edges / A, -1, 1)) / math.pi
    expect = np.diff(cdf) * 200_000
    np.testing.assert_allclose(st.angle_counts, expect, rtol=0.01, atol=30)


def test_shot_pixels_against_planar_trigonometry(system):
    """Paper geometry: the beam leaves at 2θ from the x axis and meets z = D."""
    theta = np.linspace(0.62, 0.9, 15)
    D = 3.0
    b = -system.scanner.position[0]
    x = -b + D / np.tan(2 * theta)
    K = system.receiver.camera_matrix
    col = K[0, 2] + K[0, 0] * x / D
    col[(col < -0.5) | (col >= 191.5)] = np.nan
    np.testing.assert_allclose(shot_pixels(system, theta, D), col, atol=1e-9)


def test_paper_fig2_setting(system):
    """f_mech/f_rep = 0.0785 and 400 shots (Fig. 2): totals and the weighted mean."""
    st = acquisition_statistics(system, 400, 2.5, frequency_ratio=0.0785)
    n = st.pixel_counts.astype(float)
    assert n.sum() == pytest.approx(400 * st.fraction_on_sensor)
    assert st.mean_accumulations == pytest.approx((n**2).sum() / n.sum())
    assert st.mean_per_illuminated_pixel == pytest.approx(n[n > 0].mean())
    # the turning points of the cosine gather more shots than the centre of the sweep
    assert st.angle_counts[0] > st.angle_counts[len(st.angle_counts) // 2]
    assert st.angle_counts[-1] > st.angle_counts[len(st.angle_counts) // 2]


def test_more_shots_more_accumulations(system):
    a = acquisition_statistics(system, 400, 2.5)
    b = acquisition_statistics(system, 4000, 2.5)
    assert b.mean_per_illuminated_pixel > 5 * a.mean_per_illuminated_pixel
