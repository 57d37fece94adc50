"""The model layer: what the hardware is.

hardware (the typed parameters: receiver, scanner, laser, TDC) · scanner
(trajectory, phase from zero crossings, reflection law) · scanner2d (second
mirror axis) · presets (named systems) · system (FORMAT v1 JSON; resolving a
name or a path) · camera (OpenCV intrinsics: pixel ↔ ray) · tdc (code ↔ time
↔ path length: the one convention) · acquisition (shots over angle and pixels,
paper Sec. 2.1).  Imports nothing above it; inside, each module imports only
those before it in this list.
"""
