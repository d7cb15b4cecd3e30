"""Random-effects consensus and dark uncertainty (bayes_tfcrds.uncertainty.random_effects).

Published oracle: A. Possolo, D. B. Hibbert, J. Stohner, O. Bodnar, J. Meija, "A brief guide to
measurement uncertainty (IUPAC Technical Report)", Pure and Applied Chemistry (2024), and its
supplementary R code (revision 2023-01-04):

* Example 4F, the mass fraction of nickel in bovine liver from the key comparison CCQM-K145
  (17 NMIs; INMC's u rounded to two digits as in the guide). Published with R/metafor:
  Cochran's Q(df = 16) = 40.1205, p = 0.0007; REML tau = 0.0463 mg/kg, consensus 2.0428 mg/kg,
  Knapp-Hartung se 0.0159 mg/kg and 95 % interval [2.0091, 2.0765] mg/kg; ML (bbmle)
  mu = 2.043 mg/kg, tau = 0.044 mg/kg.
* Example 3E, the molar mass of iridium from three isotope-ratio measurements: Q(df = 2) =
  9.61, p = 0.0082, DerSimonian-Laird tau 0.0006 g/mol, ML tau 0.0004 g/mol. The guide prints
  REML tau 0.0007 g/mol; we get 0.00056, and two formulations written independently of ours
  (the error contrasts' likelihood and metafor's Fisher scoring) give 0.00056 too, so that one
  printed digit is not used as an oracle here.

Every published digit is compared after rounding to the digits printed.
"""

import numpy as np
import pytest
from scipy import linalg, optimize

from bayes_tfcrds.uncertainty.comparison import Reference, compare, covariance_matrix
from bayes_tfcrds.uncertainty.random_effects import (
    cochran_q,
    tau_dersimonian_laird,
    tau_likelihood,
)

NI_LABS = "JSI INMC GLHK LNE NIST KRISS INACAL NMIA NIM NMIJ RISE NRC PTB LATU LGC UME HSA".split()
NI_W = [
    1.930,
    1.940,
    1.942,
    1.958,
    1.984,
    1.993,
    2.010,
    2.020,
    2.022,
    2.050,
    2.055,
    2.070,
    2.077,
    2.080,
    2.131,
    2.150,
    2.180,
]  # mg/kg
NI_U = [
    0.110,
    0.064,
    0.092,
    0.075,
    0.020,
    0.033,
    0.060,
    0.050,
    0.023,
    0.020,
    0.052,
    0.050,
    0.035,
    0.059,
    0.042,
    0.030,
    0.080,
]  # mg/kg


def iridium():
    """Example 3E's three molar masses (g/mol) and u from the isotope ratios and AME 2020 masses.

    The guide evaluates u by a Monte Carlo of 1e7 draws; the model is linear to 1e-6 relative
    over +/- 5 u, so first-order propagation gives the same u to the digits used.
    """
    m191, m193, u_m = 190.9605915, 192.9629238, 1.4e-6
    r = np.array([0.59399, 0.59418, 0.59290])
    u_r = np.array([0.00103, 0.00037, 0.00021])
    f = r / (1 + r)
    x = f * m191 + (1 - f) * m193
    u = np.sqrt((u_r * (m191 - m193) / (1 + r) ** 2) ** 2 + (f * u_m) ** 2 + ((1 - f) * u_m) ** 2)
    return x, u


def test_nickel_ccqm_k145_reml_knapp_hartung_to_the_published_digits():
    comp = compare(
        NI_LABS,
        NI_W,
        NI_U,
        reference=Reference("random-effects", estimator="REML", knapp_hartung="standard"),
    )
    ref = comp.reference
    assert round(comp.consistency.chi2, 4) == 40.1205
    assert comp.consistency.dof == 16
    assert round(comp.consistency.p_value, 4) == 0.0007
    assert round(ref.tau, 4) == 0.0463
    assert round(ref.value, 4) == 2.0428
    assert round(ref.u, 4) == 0.0159
    assert tuple(round(v, 4) for v in ref.interval) == (2.0091, 2.0765)
    assert ref.dof == 16
    # q = 0.9895 < 1 here: the standard form (metafor's) shrinks u a little, the modified does not
    assert ref.kh_q < 1
    modified = compare(
        NI_LABS,
        NI_W,
        NI_U,
        reference=Reference("random-effects", estimator="REML", knapp_hartung="modified"),
    ).reference
    plain = compare(NI_LABS, NI_W, NI_U, reference=Reference("random-effects")).reference
    assert modified.u == plain.u > ref.u
    assert modified.u == pytest.approx(ref.u / np.sqrt(ref.kh_q), rel=1e-12)


def test_nickel_ccqm_k145_maximum_likelihood_to_the_published_digits():
    ref = compare(NI_LABS, NI_W, NI_U, reference=Reference("random-effects", estimator="ML"))
    assert round(ref.reference.value, 3) == 2.043
    assert round(ref.reference.tau, 3) == 0.044


def test_iridium_q_dersimonian_laird_and_ml_to_the_published_digits():
    x, u = iridium()
    cov = np.diag(u**2)
    assert round(cochran_q(x, cov), 2) == 9.61
    comp = compare("CWZ", x, u)
    assert round(comp.consistency.p_value, 4) == 0.0082
    assert round(tau_dersimonian_laird(x, cov), 4) == 0.0006
    assert round(tau_likelihood(x, cov, restricted=False), 4) == 0.0004


def error_contrast_reml(x, cov):
    """REML tau written another way: the likelihood of K^T x, K an orthonormal basis of 1-perp."""
    k = linalg.null_space(np.ones((1, len(x))))
    y = k.T @ x

    def nll(tau):
        s = k.T @ (cov + tau**2 * np.eye(len(x))) @ k
        return 0.5 * (np.linalg.slogdet(s)[1] + y @ np.linalg.solve(s, y))

    scale = np.ptp(x) + np.sqrt(cov.diagonal().max())
    grid = np.linspace(0, 3 * scale, 3001)
    i = int(np.argmin([nll(t) for t in grid]))
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
    return optimize.minimize_scalar(
        nll, bounds=(lo, hi), method="bounded", options={"xatol": 1e-12 * scale}
    ).x


@pytest.mark.parametrize("seed", range(4))
def test_reml_with_correlated_results_equals_the_error_contrast_form(seed):
    rng = np.random.default_rng(seed)
    n = 6
    u = rng.uniform(0.5, 2.0, n)
    a = rng.normal(size=(n, n))
    c = a @ a.T + n * np.eye(n)
    r = c / np.sqrt(np.outer(c.diagonal(), c.diagonal()))  # a random valid correlation matrix
    cov = covariance_matrix(u, r)
    x = rng.multivariate_normal(np.zeros(n), cov + 1.5**2 * np.eye(n))
    # through compare(): the REML estimator is the one dispatched, correlations included
    ref = compare("ABCDEF", x, u, r, Reference("random-effects", estimator="REML")).reference
    # 1e-6 relative: two optimisers of the same smooth 1-D function, both to ~1e-12 in tau;
    # abs 1e-6 (u ~ 1): at a boundary optimum (tau = 0, seed 1) the bounded search stops a few
    # of its tolerances inside the interval
    assert ref.tau == pytest.approx(error_contrast_reml(x, cov), rel=1e-6, abs=1e-6)
    assert ref.tau == tau_likelihood(x, cov, restricted=True)


def test_the_dersimonian_laird_moment_holds_for_correlated_results():
    """E[Q] = (n - 1) + tau^2 tr(P) for correlated V: the equation DL solves, checked by draws."""
    rng = np.random.default_rng(5)
    n, tau = 5, 0.8
    u = np.array([0.3, 0.5, 1.0, 0.4, 0.7])
    r = np.eye(n)
    r[0, 1] = r[1, 0] = 0.7
    r[2, 3] = r[3, 2] = -0.4
    cov = covariance_matrix(u, r)
    draws = rng.multivariate_normal(np.full(n, 3.0), cov + tau**2 * np.eye(n), size=20_000)
    q = np.array([cochran_q(x, cov) for x in draws])
    # tr(P) as the shipped DL estimator uses it, read back from one draw with Q > n - 1
    x = next(x for x, qi in zip(draws, q) if qi > n)
    trace_p = (cochran_q(x, cov) - (n - 1)) / tau_dersimonian_laird(x, cov) ** 2
    expected = (n - 1) + tau**2 * trace_p
    # 20 000 draws: the mean of Q is within 4 standard errors (sd(Q)/sqrt(N), about 0.9 %)
    assert q.mean() == pytest.approx(expected, abs=4 * q.std() / np.sqrt(q.size))
    # the diagonal alone (correlations ignored) gives a different expectation: the test can fail
    wd = np.diag(1 / u**2)
    wrong = (n - 1) + tau**2 * (np.trace(wd) - wd.sum(axis=1) @ wd.sum(axis=1) / wd.sum())
    assert abs(wrong - expected) > 8 * q.std() / np.sqrt(q.size)


def test_consistent_results_have_no_dark_uncertainty_and_the_consensus_is_the_weighted_mean():
    x = np.array([10.0, 10.02, 9.99, 10.01])
    u = np.array([0.05, 0.04, 0.08, 0.10])  # Q = 0.4 on 3 dof: below its expectation
    for est in ("DL", "REML", "ML"):
        comp = compare("ABCD", x, u, reference=Reference("random-effects", estimator=est))
        fixed = compare("ABCD", x, u)
        # exactly 0: DL truncates at 0, and a likelihood optimum on the boundary is returned as 0
        assert comp.reference.tau == 0.0
        # the same GLS mean and u(d), up to rounding in another order of the same arithmetic
        assert comp.reference.value == pytest.approx(fixed.reference.value, rel=1e-12)
        assert [e.u for e in comp.equivalence] == pytest.approx(
            [e.u for e in fixed.equivalence], rel=1e-12
        )


def test_dark_uncertainty_widens_every_degree_of_equivalence():
    comp = compare(NI_LABS, NI_W, NI_U, reference=Reference("random-effects", estimator="DL"))
    tau, a = comp.reference.tau, np.array(comp.reference.weights)
    sigma = np.diag(np.array(NI_U) ** 2) + tau**2 * np.eye(len(NI_U))
    # independent results: u^2(d_i) = s_i^2 (1 - 2 a_i) + u^2(x_ref), s_i^2 = u_i^2 + tau^2
    s2 = np.diag(sigma)
    expected = np.sqrt(s2 * (1 - 2 * a) + a @ sigma @ a)
    assert [e.u for e in comp.equivalence] == pytest.approx(expected, rel=1e-10)
    fixed = compare(NI_LABS, NI_W, NI_U)
    assert all(r.u > f.u for r, f in zip(comp.equivalence, fixed.equivalence))


def test_an_unknown_estimator_or_adjustment_is_refused():
    with pytest.raises(ValueError, match="estimator"):
        compare("AB", [1.0, 2.0], [0.1, 0.1], reference=Reference("random-effects", estimator="X"))
    with pytest.raises(ValueError, match="knapp_hartung"):
        compare(
            "AB", [1.0, 2.0], [0.1, 0.1], reference=Reference("random-effects", knapp_hartung="x")
        )
