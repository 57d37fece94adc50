"""The point cloud that processing produces and viz/ exports.

A :class:`PointCloud` is points plus named per-point attributes, all plain
NumPy arrays, so it travels between stages (and Dask workers) without files.

Required attributes (FORMAT v1 outputs):

=========== ================= ==============================================
name        dtype, shape      meaning
=========== ================= ==============================================
counts      int32 (N,)        signal counts in the point's peak (1 for events)
pixel       int32 (N,)        receiver column
range       float64 (N,)      distance from the projection centre, m
sigma_r     float64 (N,)      propagated standard deviation of range, m
sigma_phi   float64 (N,)      propagated std of the angle in the x–z plane, rad
=========== ================= ==============================================

Optional: ``row`` int32, ``label`` uint8 (when events are exported),
``sigma_x``, ``sigma_y``, ``sigma_z`` float64 (m), ``code`` float64 (peak
TDC code), anything else of shape (N,).  A frame's cloud
(:mod:`mems_stereo.pipeline.frames`) adds ``t`` float64 (s, the recording's clock: the
mean time of the shots the point's detections came from), ``age`` int32 (frames of
history fused into the point, :mod:`mems_stereo.pipeline.temporal`) and ``step_lo``,
``step_hi`` int32 (its scan-angle band); a cloud of the whole recording has none of them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mems_stereo.errors import ShapeError

REQUIRED_ATTRIBUTES = ("counts", "pixel", "range", "sigma_r", "sigma_phi")


@dataclass
class PointCloud:
    """Points (N, 3) float64 in metres, world (receiver camera) frame, and attributes.

    Examples
    --------
    >>> cloud = ms.PointCloud(np.array([[0.0, 0.0, 1.5], [0.2, 0.0, 3.0]]),
    ...                       {"range": np.array([1.5, 3.0])})
    >>> len(cloud), cloud.points.shape
    (2, (2, 3))
    >>> near = cloud.select(cloud.attributes["range"] < 2.0)
    >>> near.points.tolist()
    [[0.0, 0.0, 1.5]]
    """

    points: np.ndarray
    attributes: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self):
        self.points = np.asarray(self.points, dtype=np.float64).reshape(-1, 3)
        n = self.points.shape[0]
        for k, v in list(self.attributes.items()):
            v = np.asarray(v)
            if v.shape != (n,):
                raise ShapeError(f"attribute {k!r}: expected shape ({n},), found {v.shape}")
            self.attributes[k] = v

    def __len__(self) -> int:
        return int(self.points.shape[0])

    def __repr__(self) -> str:
        n = len(self)
        if n:
            r = self.attributes.get("range")
            rng = (f", range {np.nanmin(r):.3g}–{np.nanmax(r):.3g} m"
                   if r is not None and np.any(np.isfinite(r)) else "")
        else:
            rng = ""
        return (f"<PointCloud {n} points{rng}; attributes: "
                f"{', '.join(self.attributes) or 'none'}>")

    def to_structured(self) -> np.ndarray:
        """(N,) NumPy structured array: fields ``x``, ``y``, ``z`` (float64, m) and
        one field per attribute, each with the attribute's dtype (no dependency)."""
        dt = [("x", np.float64), ("y", np.float64), ("z", np.float64)]
        dt += [(k, v.dtype) for k, v in self.attributes.items() if k not in ("x", "y", "z")]
        out = np.empty(len(self), dtype=dt)
        out["x"], out["y"], out["z"] = self.points.T
        for k, v in self.attributes.items():
            if k not in ("x", "y", "z"):
                out[k] = v
        return out

    def to_pandas(self):
        """A ``pandas.DataFrame`` with columns x, y, z (m) and the attributes.

        pandas is not a dependency of mems-stereo: this raises ImportError
        (with the advice to install it or use :meth:`to_structured`) without it.
        """
        try:
            import pandas as pd
        except ImportError:
            raise ImportError("PointCloud.to_pandas needs pandas, which is not installed\n"
                              "  install it (pip install pandas) or use cloud.to_structured(), "
                              "a NumPy structured array with the same columns") from None
        return pd.DataFrame.from_records(self.to_structured())

    def __getitem__(self, name: str) -> np.ndarray:
        return self.attributes[name]

    def select(self, mask) -> PointCloud:
        """Subset by boolean mask or index array."""
        return PointCloud(self.points[mask], {k: v[mask] for k, v in self.attributes.items()})

    def missing_required(self) -> list[str]:
        return [k for k in REQUIRED_ATTRIBUTES if k not in self.attributes]

    @staticmethod
    def concatenate(clouds: list[PointCloud]) -> PointCloud:
        clouds = [c for c in clouds if c is not None]
        if not clouds:
            return PointCloud(np.zeros((0, 3)))
        keys = set(clouds[0].attributes)
        for c in clouds[1:]:
            keys &= set(c.attributes)
        return PointCloud(np.concatenate([c.points for c in clouds]),
                          {k: np.concatenate([c.attributes[k] for c in clouds])
                           for k in sorted(keys)})
