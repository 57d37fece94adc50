"""Physics shared by the simulator, the pipeline and calibration, one model each:

pulse (shape, FWHM ↔ σ) · first_photon (the first-photon model: arrival
probability and moments with and without background, the fusion's posterior,
the simulator's CDF) · spot (the imaged laser spot on the pixels) · background (rates and their
expectation per bin and angle step) · link_budget (signal photons per shot).
"""
