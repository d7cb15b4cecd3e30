"""Random-effects (dark-uncertainty) consensus of results that disagree beyond their u.

When a comparison fails its chi-squared test, the results scatter more than their stated
uncertainties allow. The laboratory-effects model accounts for this: each result is

    x_i = mu + lambda_i + e_i,   lambda ~ N(0, tau^2 I),   e ~ N(0, V),

so cov(x) = Sigma(tau) = V + tau^2 I, with V the stated covariance (declared correlations
included) and tau the dark uncertainty, in the unit of the results. The consensus is the GLS
mean under Sigma(tau). This module estimates tau three ways (CCQM guidance note CCQM13-22;
A. Possolo et al., "A brief guide to measurement uncertainty", IUPAC Technical Report, Pure
Appl. Chem. 2024, Examples 3E and 4F):

* ``DL``   DerSimonian-Laird, the method of moments on Cochran's Q about the weighted mean,
  generalised to correlated results: E[Q] = (n - 1) + tau^2 tr(P) with
  P = W - W 1 1^T W / (1^T W 1), W = V^-1 (for independent results tr(P) = S1 - S2/S1);
* ``REML`` restricted maximum likelihood (the error contrasts' likelihood);
* ``ML``   maximum likelihood, profiled over mu.

The Knapp-Hartung adjustment scales u(mu) by sqrt(q), q = r^T Sigma^-1 r / (n - 1) (not
truncated at 1), and takes the 95 % interval from Student's t with n - 1 dof.

Pure functions over numpy arrays; values and tau in the caller's unit.
"""

from __future__ import annotations

import numpy as np
from scipy import optimize, stats

ESTIMATORS = ("DL", "REML", "ML")


def cochran_q(x, cov) -> float:
    """Q = r^T V^-1 r about the GLS weighted mean: the chi2 of the consistency test (unitless)."""
    x = np.asarray(x, dtype=float)
    w_one = np.linalg.solve(cov, np.ones(x.size))
    r = x - (w_one @ x) / w_one.sum()
    return float(r @ np.linalg.solve(cov, r))


def tau_dersimonian_laird(x, cov) -> float:
    """DerSimonian-Laird tau (unit of x) for results with covariance ``cov`` (unit^2).

    tau^2 = max(0, (Q - (n - 1)) / tr(P)); P projects out the weighted mean (see module doc).
    """
    x = np.asarray(x, dtype=float)
    w = np.linalg.inv(cov)
    one = np.ones(x.size)
    w1 = w @ one
    trace_p = np.trace(w) - (w1 @ w1) / (one @ w1)
    return float(np.sqrt(max(0.0, (cochran_q(x, cov) - (x.size - 1)) / trace_p)))


def _neg_log_likelihood(tau: float, x, cov, restricted: bool) -> float:
    """-log L(tau) with mu profiled out (ML), or of the error contrasts (REML), up to a constant."""
    sigma = cov + tau**2 * np.eye(x.size)
    chol = np.linalg.cholesky(sigma)
    one = np.ones(x.size)
    a = np.linalg.solve(chol, one)
    b = np.linalg.solve(chol, x)
    s = a @ a  # 1^T Sigma^-1 1
    mu = (a @ b) / s
    r = b - mu * a  # whitened residuals
    value = np.sum(np.log(np.diag(chol))) + 0.5 * (r @ r)
    if restricted:
        value += 0.5 * np.log(s)
    return float(value)


def tau_likelihood(x, cov, restricted: bool = True) -> float:
    """REML (``restricted``) or ML estimate of tau (unit of x), on tau >= 0.

    The likelihood is one-dimensional: it is scanned on a grid from 0 to a bound well beyond the
    data's spread (so a secondary optimum cannot be mistaken for the global one) and the best
    grid cell refined by a bounded scalar search. An optimum at the boundary is returned as
    tau = 0 exactly (the results are consistent: no dark uncertainty).
    """
    x = np.asarray(x, dtype=float)
    spread = float(np.ptp(x)) + float(np.sqrt(np.max(np.diag(cov))))
    grid = np.concatenate([[0.0], np.geomspace(spread * 1e-6, 10 * spread, 400)])
    nll = np.array([_neg_log_likelihood(t, x, cov, restricted) for t in grid])
    i = int(np.argmin(nll))
    if i == 0:
        return 0.0
    lo, hi = grid[i - 1], grid[min(i + 1, grid.size - 1)]
    res = optimize.minimize_scalar(
        _neg_log_likelihood,
        bounds=(lo, hi),
        args=(x, cov, restricted),
        method="bounded",
        options={"xatol": spread * 1e-12},
    )
    best = float(res.x if res.fun <= nll[i] else grid[i])
    return 0.0 if nll[0] <= min(res.fun, nll[i]) else best


def dark_uncertainty(x, cov, estimator: str = "REML") -> float:
    """tau by ``estimator`` ('DL', 'REML' or 'ML'), in the unit of x."""
    if estimator == "DL":
        return tau_dersimonian_laird(x, cov)
    if estimator in ("REML", "ML"):
        return tau_likelihood(x, cov, restricted=estimator == "REML")
    raise ValueError(f"unknown dark-uncertainty estimator {estimator!r}; use one of {ESTIMATORS}")


def knapp_hartung_factor(x, sigma) -> float:
    """sqrt(q), q = r^T Sigma^-1 r / (n - 1) about the GLS mean under ``sigma`` (Knapp-Hartung)."""
    return float(np.sqrt(cochran_q(x, sigma) / (len(x) - 1)))


def coverage_interval(value: float, u: float, dof: float | None, level: float = 0.95) -> tuple:
    """value -/+ t_{(1+level)/2, dof} u (the normal quantile when dof is None: infinite)."""
    p = 0.5 + level / 2
    t = stats.norm.ppf(p) if dof is None else stats.t.ppf(p, dof)
    return (float(value - t * u), float(value + t * u))
