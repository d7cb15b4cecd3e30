"""Estimation from the data.

The beat-note fit of H, ring-down decay times (CRDS, TF-CRDS), the Appendix B refinement of H on
many transients, the H calibration that combines them, which H parameters the data identify
(Eq. 2's two paths may share its poles out in more than one way), spectra, line-profile fits,
the line analysis of one configuration, the fits extended by instrument effects (static
nonlinearity, baseline drift, extra exponentials, beating, etalon, neighbour line) that the
budget sizes and discovery selects, and the notebook views of the results (``fit.views``).

May import: core, output, physics (bundle records are read by their fields, never imported).
"""
