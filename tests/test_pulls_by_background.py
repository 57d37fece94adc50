"""benchmarks/pulls_by_background.py: the signed error/σ table of a sweep's dump."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _module():
    spec = importlib.util.spec_from_file_location(
        "pulls_by_background", ROOT / "benchmarks" / "pulls_by_background.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_table_shows_a_lean_of_one_estimate(tmp_path):
    mod = _module()
    rng = np.random.default_rng(3)
    n = 400
    r_true = rng.uniform(3.5, 5.5, n)  # one range band
    bg = np.where(np.arange(n) < 200, 5e4, 2e7)  # two background bands
    s_tof = np.full(n, 0.2)
    s_st = np.full(n, 0.1)
    # the ToF leans short by 0.5 σ under strong background only; the stereo does not
    tof = r_true + s_tof * (rng.standard_normal(n) - np.where(bg > 1e7, 0.5, 0.0))
    st = r_true + s_st * rng.standard_normal(n)
    err = 0.5 * ((tof - r_true) + (st - r_true))
    np.savez(tmp_path / "d.npz", err=err, sigma=np.full(n, 0.1), r_true=r_true,
             background_hz=bg, attr_range_tof=tof, attr_sigma_r_tof=s_tof,
             attr_range_stereo=st, attr_sigma_r_stereo=s_st)
    rows = mod.table(mod.load([tmp_path / "d.npz"]))
    body = [r for r in rows[2:]]
    assert len(body) == 2  # 3–6 m × (0–0.1 MHz, 10–inf MHz)
    z_tof = [float(r.split("|")[5].split()[0]) for r in body]
    z_st = [float(r.split("|")[6].split()[0]) for r in body]
    assert abs(z_tof[0]) < 0.25 and -0.8 < z_tof[1] < -0.25
    assert all(abs(z) < 0.25 for z in z_st)
    assert mod.main([str(tmp_path / "d.npz")]) == 0
