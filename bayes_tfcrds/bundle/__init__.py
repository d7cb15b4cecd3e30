"""The measurement bundle (FORMAT.md, one HDF5 file per campaign).

Records, reader and validator, writer, and the human-readable summary.

May import: core, output.
"""
