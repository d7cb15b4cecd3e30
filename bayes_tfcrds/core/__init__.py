"""Foundations.

Physical constants and unit conversions, linear algebra, GUM arithmetic and budget tables, and the
Quantity (value, u, unit) that results report.

May import: nothing from bayes_tfcrds (numpy, scipy and the standard library only).
"""
