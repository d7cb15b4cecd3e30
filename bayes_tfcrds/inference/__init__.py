"""Bayesian sampling.

The emcee ensemble runner, convergence diagnostics and gates, chain stores that resume after
interruption, and the posterior densities of H and of the line parameters.

May import: core, output, physics.
"""
