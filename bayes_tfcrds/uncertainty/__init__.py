"""Uncertainty of the line area.

Propagation of H into tau and A, the posteriors the budget samples, the line-shape model
average over candidate profiles, the GUM budget of A, S and A/A_ref (run_budget), its output
files and its notebook views (``uncertainty.views``); interlaboratory comparisons of budget
results (comparison: reference value, chi-squared test, degrees of equivalence with
correlations).

May import: core, output, physics, fit, inference.
"""
