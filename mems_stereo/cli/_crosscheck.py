"""Cross-checks of a recording's redundant data, before any work (docs/reliability.md).

The polarity of the zero crossings (``/scanner/rising``) is not checked by
the format: inverting every flag shifts the interpolated phase by π, so the
scan angle θ = θ0 + θ_mech becomes θ0 − θ_mech, with crossings that are
still alternating and spaced for ``f_mech``.  The detections tell which is
right: a laser return at pixel u in a shot of angle θ has a code inside the
interval that triangulation accepts for (θ, u) (the run's own
:class:`~mems_stereo.pipeline.intervals.IntervalTable`, angles on its grid,
rows shared with the run through the table's disk cache), while the
background's codes do not depend on θ.  :func:`polarity_evidence` counts the
detections of a sample of shots inside the accepted intervals for the
recorded angles (``I_rec``) and for the mirrored ones θ0 − (θ − θ0)
(``I_inv``), and the count expected by chance (codes independent of the
angle: each pixel's own code distribution, ``E``).  The detections inside
one interval only (``n_rec`` for the recorded polarity, ``n_inv`` for the
inverted one) decide, as in McNemar's test for paired counts: without
information on the polarity each is as likely, so

    z = (n_inv − n_rec) / sqrt(n_inv + n_rec)

is about N(0, 1) then, and a run is refused when ``z >= REFUSE_Z`` (the
inverted polarity explains the detections far better) and warned about when
``WARN_Z <= z < REFUSE_Z``.
Without a laser return among the detections (all background) both counts
are equal within their noise and nothing is said.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mems_stereo.errors import FormatError
from mems_stereo.io import hdf5 as h5
from mems_stereo.io.recording import read_header

#: z from which a recording's crossing polarity is refused as inverted
REFUSE_Z = 5.0
#: z from which it is reported as probably inverted (a warning)
WARN_Z = 3.0
#: shots sampled: blocks of consecutive shots (every phase of the mirror) at random places
SAMPLE_BLOCKS = 32
SAMPLE_BLOCK_SHOTS = 64


@dataclass(frozen=True)
class PolarityEvidence:
    """Counts of :func:`polarity_evidence` (see the module's text)."""

    shots: int          # shots sampled (with a known angle)
    i_recorded: int     # detections inside the accepted intervals, polarity as recorded
    i_inverted: int     # the same with the polarity inverted
    expected: float     # expected by chance (angle-independent codes), recorded polarity
    only_recorded: int  # inside the interval of the recorded polarity only
    only_inverted: int  # inside the interval of the inverted polarity only

    @property
    def z(self) -> float:
        n = self.only_recorded + self.only_inverted
        return (self.only_inverted - self.only_recorded) / np.sqrt(n) if n else 0.0

    def text(self) -> str:
        return (f"{self.only_inverted} detections fit only the inverted polarity, "
                f"{self.only_recorded} only the recorded one (z = {self.z:.1f})")


def _sample_shots(n_shots: int, valid: np.ndarray, seed: int = 0) -> list[slice]:
    """Blocks of consecutive shots with known angles, spread over the recording."""
    idx = np.flatnonzero(valid)
    if idx.size == 0:
        return []
    lo, hi = int(idx[0]), int(idx[-1]) + 1
    span = hi - lo
    if span <= SAMPLE_BLOCKS * SAMPLE_BLOCK_SHOTS:
        return [slice(lo, hi)]
    rng = np.random.default_rng(seed)
    starts = np.sort(rng.choice(span - SAMPLE_BLOCK_SHOTS, SAMPLE_BLOCKS, replace=False)) + lo
    out, end = [], -1
    for s in starts:
        s = max(int(s), end)
        out.append(slice(s, s + SAMPLE_BLOCK_SHOTS))
        end = s + SAMPLE_BLOCK_SHOTS
    return out


def _intervals(table, theta) -> tuple[np.ndarray, np.ndarray]:
    """Accepted code intervals ``(lo, hi)`` (K, P) int64 of the angles ``theta`` (K,)
    on the table's grid (nothing accepted off the grid)."""
    rows = table.rows(theta, np.ones(theta.shape, bool))
    table.ensure(rows)
    on = (rows >= 0)[:, None]
    lo = np.where(on, table.lo[rows].astype(np.int64), 1)
    hi = np.where(on, table.hi[rows].astype(np.int64), 0)
    return lo, hi


def polarity_evidence(path, system=None, settings=None) -> PolarityEvidence:
    """Evidence on the crossing polarity of a FORMAT v1 recording (one-axis).

    ``path`` : the recording; ``system`` : the system it is processed with
    (default: its ``/system``); ``settings`` : the run's
    :class:`~mems_stereo.pipeline.settings.Settings` (confidence, min_range;
    default ``Settings()``).  Reads the header and a sample of
    :data:`SAMPLE_BLOCKS` × :data:`SAMPLE_BLOCK_SHOTS` shots.
    """
    # the pipeline loads on use: every command's start-up imports this module
    from mems_stereo.pipeline.angles import shot_angles
    from mems_stereo.pipeline.intervals import IntervalTable
    from mems_stereo.pipeline.settings import Settings

    head = read_header(path)
    s = system if system is not None else head.system
    K, H, W = head.shape
    if tuple(s.receiver.image_size) != (W, H):  # the run refuses it, naming both sizes
        return PolarityEvidence(0, 0, 0, 0.0, 0, 0)
    theta, valid = shot_angles(head, s)
    P = H * W
    N = s.tdc.n_bins
    blocks = []
    with h5.open_h5(path) as f:
        b_ds = h5.dataset(f, "/shots/bins", str(path))
        for sl in _sample_shots(K, valid):
            b = h5.read(b_ds, str(path), sl).reshape(-1, P).astype(np.int64)
            v = valid[sl]
            blocks.append((b[v], theta[sl][v]))
    n = sum(len(t) for _, t in blocks)
    if n == 0:
        return PolarityEvidence(0, 0, 0, 0.0, 0, 0)
    # each pixel's code distribution over the sample: the chance level
    hist = np.zeros((P, N + 1))
    for b, _ in blocks:
        pix = np.broadcast_to(np.arange(P), b.shape)
        np.add.at(hist, (pix[b > 0], np.minimum(b[b > 0], N)), 1)
    cum = np.cumsum(hist, axis=1) / n
    pix = np.arange(P)[None, :]
    table = IntervalTable.for_settings(s, Settings() if settings is None else settings)
    table.load_cache()
    counts, only, expected = [0, 0], [0, 0], 0.0
    for b, th in blocks:
        inside = []
        for k, angle in enumerate((th, 2 * s.scanner.theta0 - th)):
            lo, hi = _intervals(table, angle)
            inside.append((b > 0) & (b >= lo) & (b <= hi))
            counts[k] += int(inside[k].sum())
            if k == 0:
                e = cum[pix, np.clip(hi, 0, N)] - cum[pix, np.clip(lo - 1, 0, N)]
                expected += float(np.where(hi >= lo, e, 0.0).sum())
        only[0] += int((inside[0] & ~inside[1]).sum())
        only[1] += int((inside[1] & ~inside[0]).sum())
    table.save_cache()
    return PolarityEvidence(n, counts[0], counts[1], expected, only[0], only[1])


def check_polarity(path, system=None, warn=None, settings=None) -> PolarityEvidence:
    """Refuse a recording whose crossing polarity is inverted (FormatError naming
    ``/scanner/rising``); call ``warn(text)`` where it is only probably inverted."""
    ev = polarity_evidence(path, system, settings)
    if ev.z >= REFUSE_Z:
        raise FormatError("the zero-crossing polarity looks inverted: " + ev.text(),
                          str(path), "/scanner/rising")
    if ev.z >= WARN_Z and warn is not None:
        warn(f"{path}: /scanner/rising: the zero-crossing polarity is probably inverted: "
             + ev.text())
    return ev
