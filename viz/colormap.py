"""Colormaps in plain NumPy, so rendering and export need no matplotlib.

Each map is 33 anchor colours sampled from matplotlib's map of the same name
and interpolated linearly; the largest difference from matplotlib's own
256-entry table is below 0.025 (checked in ``tests/test_viz_render.py``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mems_stereo.errors import FormatError


@dataclass(frozen=True, slots=True)
class ColorScale:
    """How values become colours: the colormap and the values at its two ends.

    Attributes
    ----------
    cmap : ``turbo`` or ``viridis``.
    vmin, vmax : the values mapped to the colormap's start and end, in the
        coloured attribute's unit; None: the values' 2nd and 98th percentile.
    """

    cmap: str = "turbo"
    vmin: float | None = None
    vmax: float | None = None

_VIRIDIS = np.array([
    [0.267, 0.0049, 0.3294], [0.277, 0.0503, 0.3757], [0.2823, 0.095, 0.4173],
    [0.2829, 0.1359, 0.4534], [0.2788, 0.1755, 0.4834], [0.2706, 0.2141, 0.5071],
    [0.259, 0.2515, 0.5247], [0.245, 0.2877, 0.5373], [0.2297, 0.3224, 0.5457],
    [0.2143, 0.3556, 0.5512], [0.1994, 0.3876, 0.5546], [0.1856, 0.4186, 0.5568],
    [0.1727, 0.4488, 0.5579], [0.1607, 0.4785, 0.5581], [0.149, 0.5081, 0.5572],
    [0.1378, 0.5375, 0.5549], [0.1276, 0.5669, 0.5506], [0.1206, 0.5964, 0.5436],
    [0.1206, 0.6258, 0.5335], [0.1323, 0.655, 0.5197], [0.1579, 0.6838, 0.5017],
    [0.1966, 0.7118, 0.4792], [0.2461, 0.7389, 0.452], [0.3041, 0.7647, 0.4199],
    [0.3692, 0.7889, 0.3829], [0.4401, 0.8111, 0.341], [0.516, 0.8312, 0.2943],
    [0.5958, 0.8487, 0.2433], [0.6785, 0.8637, 0.1895], [0.7624, 0.8764, 0.1371],
    [0.8456, 0.8873, 0.0997], [0.9261, 0.8973, 0.1041], [0.9932, 0.9062, 0.1439],
])

_TURBO = np.array([
    [0.19, 0.0718, 0.2322], [0.225, 0.1635, 0.451], [0.2511, 0.2524, 0.6337],
    [0.2682, 0.3382, 0.7805], [0.2763, 0.4212, 0.8912], [0.2754, 0.5012, 0.9659],
    [0.2586, 0.5796, 0.9988], [0.2138, 0.6589, 0.9796], [0.1584, 0.7355, 0.923],
    [0.1117, 0.8057, 0.8452], [0.0927, 0.8655, 0.7623], [0.1201, 0.9119, 0.6866],
    [0.1966, 0.949, 0.5947], [0.3051, 0.977, 0.4899], [0.4278, 0.9942, 0.3858],
    [0.5466, 0.9991, 0.2958], [0.6436, 0.99, 0.2336], [0.726, 0.9647, 0.2064],
    [0.8047, 0.9245, 0.2046], [0.8753, 0.8727, 0.2156], [0.933, 0.8124, 0.2267],
    [0.9732, 0.7468, 0.2254], [0.9931, 0.6741, 0.2035], [0.9959, 0.587, 0.169],
    [0.9836, 0.4929, 0.1285], [0.958, 0.3996, 0.0883], [0.921, 0.3149, 0.0548],
    [0.8742, 0.2453, 0.033], [0.8161, 0.1846, 0.0181], [0.7462, 0.131, 0.0085],
    [0.6645, 0.0844, 0.0042], [0.571, 0.0447, 0.0053], [0.4796, 0.0158, 0.0106],
])

COLORMAPS = {"viridis": _VIRIDIS, "turbo": _TURBO}

#: colour of points whose value is NaN (mid grey)
NAN_COLOR = (0.5, 0.5, 0.5)


def apply_colormap(t, name: str = "turbo") -> np.ndarray:
    """Map values in [0, 1] to RGB.

    ``t`` : (N,) float, clipped to [0, 1]; NaN maps to :data:`NAN_COLOR`.
    Returns (N, 3) float64 RGB in [0, 1].
    """
    try:
        table = COLORMAPS[name]
    except KeyError:
        raise FormatError(f"unknown colormap {name!r}; expected one of {sorted(COLORMAPS)}",
                          field="cmap") from None
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    nan = ~np.isfinite(t)
    tc = np.clip(np.where(nan, 0.0, t), 0.0, 1.0)
    x = np.linspace(0.0, 1.0, table.shape[0])
    rgb = np.stack([np.interp(tc, x, table[:, i]) for i in range(3)], axis=1)
    rgb[nan] = NAN_COLOR
    return rgb


def normalize(values, vmin: float | None = None, vmax: float | None = None) -> np.ndarray:
    """Scale values linearly so vmin → 0 and vmax → 1 (defaults: 2nd/98th percentile).

    ``values`` : (N,) numeric.  Returns (N,) float64 (NaN stays NaN, not clipped).
    A constant input maps to 0.5.
    """
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    fin = v[np.isfinite(v)]
    if vmin is None:
        vmin = float(np.percentile(fin, 2)) if fin.size else 0.0
    if vmax is None:
        vmax = float(np.percentile(fin, 98)) if fin.size else 1.0
    span = vmax - vmin
    if not np.isfinite(span) or span <= 0:
        return np.where(np.isfinite(v), 0.5, np.nan)
    return (v - vmin) / span


def cloud_colors(cloud, color_by: str = "range", cmap: str = "turbo",
                 vmin: float | None = None, vmax: float | None = None) -> np.ndarray:
    """Per-point RGB for a :class:`~mems_stereo.pipeline.cloud.PointCloud`.

    ``color_by`` names an attribute (``range``, ``counts``, ``sigma_r``, ...)
    or one of ``x``, ``y``, ``z`` (point coordinates, m).  Returns (N, 3)
    float64 in [0, 1].  Raises FormatError when the attribute is missing.
    """
    axes = {"x": 0, "y": 1, "z": 2}
    if color_by in cloud.attributes:
        values = cloud.attributes[color_by]
    elif color_by in axes:
        values = cloud.points[:, axes[color_by]]
    else:
        choices = sorted(set(cloud.attributes) | set(axes))
        raise FormatError(f"cannot colour by {color_by!r}: expected one of {choices}",
                          field="color_by")
    return apply_colormap(normalize(values, vmin, vmax), cmap)
