"""Physics shared by the simulator, the pipeline and calibration, one model each:

pulse (shape, FWHM ↔ σ) · first_photon (first-photon arrival moments and
posterior) · first_photon_timing (the same with background, for calibration)
· spot (the imaged laser spot on the pixels) · background (rates and their
expectation per bin and angle step) · link_budget (signal photons per shot).
"""
