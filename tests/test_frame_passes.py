"""The frame path's fast forms give the same bits as the general ones: pass 1 and pass 2
of a frame by the compiled kernels (:func:`~mems_stereo.pipeline.classify_kernel.
compiled_blocks`) whatever its size, and the stereo's cross products
(:func:`~mems_stereo.geometry.triangulation.cross3`)."""

from pathlib import Path

import numpy as np
import pytest

from mems_stereo.geometry.triangulation import cross3
from mems_stereo.io.recording import read_recording
from mems_stereo.pipeline.classify_kernel import COMPILE_SLOTS, compiled_blocks, compiles
from mems_stereo.pipeline.run import process_recording

SAMPLES = Path(__file__).resolve().parents[1] / "samples"


def _bits(a):
    return np.asarray(a, np.float64).view(np.int64)


@pytest.mark.parametrize(("sa", "sb"), [((50, 3), (50, 3)), ((3,), (7, 3)), ((7, 3), (3,)),
                                        ((1, 3), (9, 3)), ((2, 4, 3), (4, 3))])
def test_cross3_same_bits_as_numpy(sa, sb):
    rng = np.random.default_rng(11)
    a = rng.normal(size=sa) * 10.0 ** rng.uniform(-6, 6, size=sa)
    b = rng.normal(size=sb)
    got, ref = cross3(a, b), np.cross(a, b)
    assert got.shape == ref.shape and got.dtype == ref.dtype
    assert np.array_equal(_bits(got), _bits(ref))
    # independent: orthogonal to both factors, and the right-handed basis
    assert np.allclose(np.sum(got * a, axis=-1), 0.0, atol=1e-9 * np.abs(a).max())
    ex, ey = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
    assert np.array_equal(cross3(ex, ey), [0.0, 0.0, 1.0])


def test_compiled_blocks_scope():
    small = COMPILE_SLOTS - 1
    assert not compiles(small) and compiles(COMPILE_SLOTS)
    pytest.importorskip("numba")
    with compiled_blocks():
        assert compiles(small) and compiles(0)
    assert not compiles(small)


def test_frame_passes_compiled_equal_numpy():
    """A small recording processed with its passes compiled (as a frame is) and by
    NumPy: the same histograms, peaks and cloud, bit for bit."""
    pytest.importorskip("numba")
    path = SAMPLES / "room.h5"
    ref = process_recording(path)
    with compiled_blocks():
        got = process_recording(path)
    for k in ("raw", "signal", "noise"):
        np.testing.assert_array_equal(got.histograms[k], ref.histograms[k])
    assert got.counts == ref.counts
    np.testing.assert_array_equal(got.peaks.row, ref.peaks.row)
    assert np.array_equal(_bits(got.cloud.points), _bits(ref.cloud.points))
    assert got.cloud.attributes.keys() == ref.cloud.attributes.keys()
    for k, v in ref.cloud.attributes.items():
        assert np.array_equal(np.asarray(got.cloud.attributes[k]).view(np.uint8),
                              np.asarray(v).view(np.uint8)), k
    # independent: every detection (code > 0) of a shot with a known angle is in raw
    rec = read_recording(path)
    known = np.isfinite(got.theta)
    assert got.histograms["raw"].sum() == np.count_nonzero(np.asarray(rec.bins)[known])
