"""Files: recordings (FORMAT v1), labels, histograms and real photon data.
"""
