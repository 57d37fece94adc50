"""The model layer: what the hardware is.

system (FORMAT v1 JSON, presets) · scanner (trajectory, phase from zero
crossings, reflection law) · camera (OpenCV intrinsics: pixel ↔ ray) · tdc
(code ↔ time ↔ path length: the one convention) · acquisition (shots over
angle and pixels, paper Sec. 2.1).  Imports nothing above it.
"""
