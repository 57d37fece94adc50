"""The frame path's fast forms give the general ones' numbers: pass 1 and pass 2 of a
frame by the compiled kernels (:func:`~mems_stereo.pipeline.classify_kernel.
compiled_blocks`) whatever its size (the same bits; the fusion's compiled first-photon
loops to the last places), and the stereo's cross products
(:func:`~mems_stereo.geometry.triangulation.cross3`, the same bits)."""

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


#: largest relative difference of a frame cloud's float fields between the compiled
#: fusion of a frame and NumPy's: the compiled first-photon band loops
#: (:mod:`mems_stereo.physics.first_photon_band_kernel`) add their sums in another
#: order (sequential, not pairwise) and take ln μ0·f as ln μ0 + ln f, a few units in the
#: last place of the band's moments and figures; the σ, which go through the mean
#: angle's bias and binomial factor, moved by at most 4e-11 on room.h5 and the
#: benchmark's room recordings; the stereo–ToF z-score of a point whose two ranges agree
#: (z near 0) by more, relatively: its absolute difference is bounded instead
FRAME_REL = 1e-9


def test_frame_passes_compiled_equal_numpy():
    """A small recording processed with its passes compiled (as a frame is) and by
    NumPy: the same histograms, peaks and points, bit for bit; the cloud's float
    attributes within :data:`FRAME_REL` (the compiled fusion's order of sums)."""
    pytest.importorskip("numba")
    path = SAMPLES / "room.h5"
    ref = process_recording(path)
    with compiled_blocks():
        got = process_recording(path)
    for k in ("raw", "signal", "noise"):
        np.testing.assert_array_equal(got.histograms[k], ref.histograms[k])
    assert got.counts == ref.counts
    np.testing.assert_array_equal(got.peaks.row, ref.peaks.row)
    np.testing.assert_allclose(got.cloud.points, ref.cloud.points, rtol=FRAME_REL, atol=0)
    assert got.cloud.attributes.keys() == ref.cloud.attributes.keys()
    for k, v in ref.cloud.attributes.items():
        g = np.asarray(got.cloud.attributes[k])
        if g.dtype.kind != "f":
            np.testing.assert_array_equal(g, v, err_msg=k)
        elif k == "stereo_tof_z":
            np.testing.assert_allclose(g, v, rtol=0, atol=FRAME_REL, err_msg=k)
        else:
            np.testing.assert_allclose(g, v, rtol=FRAME_REL, atol=0, err_msg=k)
    # independent: every detection (code > 0) of a shot with a known angle is in raw
    rec = read_recording(path)
    known = np.isfinite(got.theta)
    assert got.histograms["raw"].sum() == np.count_nonzero(np.asarray(rec.bins)[known])
