"""bayes-tfcrds: transfer-function-corrected CRDS with honest uncertainty budgets."""
__version__ = "0.1.0"
