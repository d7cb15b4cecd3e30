"""Bayesian sampling.

The emcee ensemble runner, convergence diagnostics and gates, chain stores that resume after
interruption, the posterior densities of H and of the line parameters, and a mode-jumping move
for posteriors whose modes a least-squares search has found.

May import: core, output, physics.
"""
