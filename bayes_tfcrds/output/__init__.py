"""Output helpers shared by every layer that writes.

Atomic file writes, the plotting backend, and the self-contained HTML/PDF report with its
provenance.

May import: bayes_tfcrds.core (and bayes_tfcrds._version).
"""
