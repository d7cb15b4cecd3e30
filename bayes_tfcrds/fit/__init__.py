"""Estimation from the data.

The beat-note fit of H, ring-down decay times (CRDS, TF-CRDS), the Appendix B refinement of H on
many transients, the H calibration that combines them, spectra, line-profile fits and the line
analysis of one configuration; their notebook views (``fit.views``).

May import: core, output, physics (bundle records are read by their fields, never imported).
"""
