"""Output helpers shared by every layer that writes.

Atomic file writes, the plotting backend, the self-contained HTML/PDF report with its
provenance, and the tables and figures of the notebook views (``output.notebook``).

May import: bayes_tfcrds.core (and bayes_tfcrds._version).
"""
