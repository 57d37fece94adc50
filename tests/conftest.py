"""Shared fixtures: the paper's system and small helpers."""

from __future__ import annotations

import os

import numpy as np
import pytest

os.environ.setdefault("NUMBA_THREADING_LAYER", "omp")
os.environ.setdefault("MPLBACKEND", "Agg")

from mems_stereo.model.system import burkard2022


@pytest.fixture
def system():
    """The paper's Table 1 system (burkard2022 preset)."""
    return burkard2022()


@pytest.fixture
def rng():
    return np.random.default_rng(12345)
