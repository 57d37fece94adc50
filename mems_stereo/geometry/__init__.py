"""The geometry layer: epipolar constraint, triangulation (ray ∩ path-length
ellipsoid, midpoint, the paper's 2-D equations) and uncertainty propagation.
"""
