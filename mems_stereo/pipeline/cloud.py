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
TDC code), anything else of shape (N,).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

REQUIRED_ATTRIBUTES = ("counts", "pixel", "range", "sigma_r", "sigma_phi")


@dataclass
class PointCloud:
    """Points (N, 3) float64 in metres, world (receiver camera) frame, and attributes."""

    points: np.ndarray
    attributes: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self):
        self.points = np.asarray(self.points, dtype=np.float64).reshape(-1, 3)
        n = self.points.shape[0]
        for k, v in list(self.attributes.items()):
            v = np.asarray(v)
            if v.shape != (n,):
                raise ValueError(f"attribute {k!r}: expected shape ({n},), found {v.shape}")
            self.attributes[k] = v

    def __len__(self) -> int:
        return int(self.points.shape[0])

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
