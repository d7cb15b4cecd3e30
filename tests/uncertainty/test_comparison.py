"""Statistics of an interlaboratory comparison (bayes_tfcrds.uncertainty.comparison).

The published-digits oracle (CCQM-K145 nickel, from the IUPAC guide's Example 4F: Cochran's Q, p,
the REML consensus with Knapp-Hartung interval) is in test_random_effects.py and, through the
command line, in tests/cli/test_compare_cli.py. Here the statistics are checked against
independent results: the closed forms for independent
results (M. G. Cox, "The evaluation of key comparison data", Metrologia 39 (2002) 589-595,
Procedure A: eqs. for x_ref, u(x_ref), chi2_obs and u^2(d_i) = u_i^2 - u_ref^2), the two-laboratory
limit, the chi-squared distribution of chi2_obs, and a brute-force Monte Carlo of correlated
results.
"""

import math

import numpy as np
import pytest
from scipy import stats

from bayes_tfcrds.uncertainty.comparison import (
    Reference,
    compare,
    covariance_matrix,
    degrees_of_equivalence,
    weighted_mean,
)

LABS = ("A", "B", "C", "D")
X = np.array([10.12, 10.05, 9.98, 10.31])
U = np.array([0.05, 0.04, 0.08, 0.10])


def test_independent_results_follow_the_closed_forms_of_procedure_a():
    comp = compare(LABS, X, U)
    w = 1 / U**2
    x_ref = np.sum(w * X) / np.sum(w)
    u_ref = 1 / math.sqrt(np.sum(w))
    chi2 = np.sum((X - x_ref) ** 2 / U**2)
    # rtol 1e-12: the same arithmetic in another order (linear solve vs sums), rounding only
    assert comp.reference.value == pytest.approx(x_ref, rel=1e-12)
    assert comp.reference.u == pytest.approx(u_ref, rel=1e-12)
    assert comp.consistency.chi2 == pytest.approx(chi2, rel=1e-12)
    assert comp.consistency.dof == 3
    assert comp.consistency.p_value == pytest.approx(stats.chi2.sf(chi2, 3), rel=1e-12)
    assert comp.consistency.birge_ratio == pytest.approx(math.sqrt(chi2 / 3), rel=1e-12)
    for e, x, u in zip(comp.equivalence, X, U):
        assert e.d == pytest.approx(x - x_ref, abs=1e-13)  # abs: d is a difference of ~10
        assert e.u == pytest.approx(math.sqrt(u**2 - u_ref**2), rel=1e-10)
        assert e.U == pytest.approx(2 * e.u, rel=1e-15)
        assert e.zeta == pytest.approx(e.d / e.u, rel=1e-12)
        assert e.en == pytest.approx(e.d / (2 * e.u), rel=1e-12)


def test_these_results_fail_the_chi2_test_and_the_verdict_follows_p():
    comp = compare(LABS, X, U)
    # chi2 = 8.04 on 3 dof: p = 0.045 < 0.05, the set is inconsistent (D is 2.4 u(d) high)
    assert comp.consistency.chi2 > stats.chi2.ppf(0.95, 3)
    assert not comp.consistency.passed
    shrunk = compare(LABS, 10.1 + (X - 10.1) / 3, U)  # chi2 / 9: consistent
    assert shrunk.consistency.passed


def test_two_equal_laboratories():
    comp = compare(("A", "B"), [1.0, 1.3], [0.1, 0.1])
    # mean, u/sqrt(2), d = -/+ 0.15 with u(d) = u/sqrt(2); chi2 = 0.3^2/(2 0.1^2) = 4.5
    assert comp.reference.value == pytest.approx(1.15, rel=1e-14)
    assert comp.reference.u == pytest.approx(0.1 / math.sqrt(2), rel=1e-14)
    assert comp.consistency.chi2 == pytest.approx(4.5, rel=1e-12)
    # one dof: p is the two-sided normal tail of z = 0.3/sqrt(0.02)
    assert comp.consistency.p_value == pytest.approx(math.erfc(0.3 / 0.2), rel=1e-10)
    a, b = comp.equivalence
    assert (a.d, b.d) == pytest.approx((-0.15, 0.15), abs=1e-14)
    assert a.u == pytest.approx(0.1 / math.sqrt(2), rel=1e-12)
    (pair,) = comp.pairs
    assert pair.d == pytest.approx(-0.3, abs=1e-14)
    assert pair.U == pytest.approx(2 * math.sqrt(0.02), rel=1e-12)


@pytest.mark.parametrize("r", [0.6, -0.6])
def test_a_declared_correlation_enters_every_statistic_with_its_sign(r):
    u = np.array([0.1, 0.1])
    comp = compare(("A", "B"), [1.0, 1.3], u, [[1, r], [r, 1]])
    # equal u: x_ref is still the mean; u^2(x_ref) = u^2 (1 + r)/2, u^2(d_AB) = 2u^2(1 - r),
    # chi2 = d^2 / (2u^2 (1 - r)), u(d_i) = u sqrt((1 - r)/2). A sign flip of r in the code
    # swaps the two rows of the parametrisation and fails both.
    assert comp.reference.u == pytest.approx(0.1 * math.sqrt((1 + r) / 2), rel=1e-12)
    assert comp.pairs[0].u == pytest.approx(0.1 * math.sqrt(2 * (1 - r)), rel=1e-12)
    assert comp.consistency.chi2 == pytest.approx(0.09 / (0.02 * (1 - r)), rel=1e-12)
    assert comp.equivalence[0].u == pytest.approx(0.1 * math.sqrt((1 - r) / 2), rel=1e-12)


def test_correlated_gls_against_a_brute_force_monte_carlo():
    """Draw correlated results about a true value; x_ref, d_i and chi2 from each draw."""
    r = np.array([[1, 0.7, 0, 0], [0.7, 1, 0.3, 0], [0, 0.3, 1, -0.2], [0, 0, -0.2, 1]])
    cov = covariance_matrix(U, r)
    comp = compare(LABS, X, U, r)
    rng = np.random.default_rng(17)
    draws = rng.multivariate_normal(np.full(4, 10.0), cov, size=40_000)
    a = np.array(comp.reference.weights)
    x_ref = draws @ a
    d = draws - x_ref[:, None]
    chi2 = np.einsum("ij,jk,ik->i", d, np.linalg.inv(cov), d)
    # 40 000 draws: an sd is within 4 x its relative standard error 1/sqrt(2N) = 0.35 % -> 1.5 %
    assert np.std(x_ref) == pytest.approx(comp.reference.u, rel=0.015)
    assert np.std(d, axis=0) == pytest.approx([e.u for e in comp.equivalence], rel=0.015)
    # chi2_obs is chi-squared with n - 1 = 3 dof: mean 3 +/- 4 sqrt(6/N) = 0.05
    assert np.mean(chi2) == pytest.approx(3.0, abs=0.05)
    # GLS is the minimum-variance unbiased mean: no other normalised weights do better
    for trial in rng.normal(size=(200, 4)):
        other = a + 0.05 * (trial - trial.mean())
        assert other @ cov @ other >= a @ cov @ a
    # ignoring the correlations gives different u(d): the matrix is used, not the diagonal
    plain = compare(LABS, X, U)
    assert abs(plain.equivalence[0].u - comp.equivalence[0].u) > 0.1 * comp.equivalence[0].u


def test_a_laboratory_as_reference():
    r = np.array([[1, 0.4, 0, 0], [0.4, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    comp = compare(LABS, X, U, r, Reference("laboratory", lab="B"))
    assert comp.reference.value == X[1] and comp.reference.u == U[1]
    b = comp.equivalence[1]
    assert b.d == 0 and b.u == 0 and b.en is None and b.zeta is None
    # u^2(d_A) = u_A^2 + u_B^2 - 2 r u_A u_B (shared input), u^2(d_C) = u_C^2 + u_B^2
    assert comp.equivalence[0].u == pytest.approx(
        math.sqrt(U[0] ** 2 + U[1] ** 2 - 0.8 * U[0] * U[1]), rel=1e-12
    )
    assert comp.equivalence[2].u == pytest.approx(math.hypot(U[2], U[1]), rel=1e-12)
    # the consistency test is about the weighted mean whatever the reference
    assert comp.consistency == compare(LABS, X, U, r).consistency


def test_a_stated_reference_value_is_independent_of_the_results():
    comp = compare(LABS, X, U, reference=Reference("value", value=10.0, u=0.03))
    assert [e.d for e in comp.equivalence] == pytest.approx(X - 10.0, abs=1e-14)
    assert [e.u for e in comp.equivalence] == pytest.approx(np.hypot(U, 0.03), rel=1e-12)
    assert comp.equivalence[0].en == pytest.approx(0.12 / (2 * math.hypot(0.05, 0.03)), rel=1e-9)


def test_degrees_of_equivalence_sum_to_zero_with_gls_weights():
    # sum_i a_i d_i = a.x - x_ref = 0 for any V: a property of the reference, not of the data
    r = np.array([[1, 0.5, 0.2, 0], [0.5, 1, 0, 0], [0.2, 0, 1, 0], [0, 0, 0, 1]])
    cov = covariance_matrix(U, r)
    ref = weighted_mean(X, cov)
    d, _ = degrees_of_equivalence(X, cov, ref.weights)
    assert np.dot(ref.weights, d) == pytest.approx(0.0, abs=1e-13)
    assert sum(ref.weights) == pytest.approx(1.0, rel=1e-14)


@pytest.mark.parametrize(
    "labs, u, r, message",
    [
        (("A", "A"), [0.1, 0.1], None, "different names"),
        (("A", "B"), [0.1, 0.0], None, "> 0"),
        (("A", "B", "C"), [0.1] * 3, [[1, 1, 0], [1, 1, 0.9], [0, 0.9, 1]], "positive definite"),
    ],
)
def test_bad_inputs_are_refused(labs, u, r, message):
    with pytest.raises(ValueError, match=message):
        compare(labs, np.ones(len(labs)), u, r)


def test_result_objects_are_frozen_and_serialise():
    comp = compare(LABS, X, U)
    with pytest.raises(AttributeError):
        comp.reference.value = 0.0
    data = comp.to_dict()
    assert data["reference"]["value"] == comp.reference.value
    assert data["equivalence"][3]["lab"] == "D"
    assert len(data["pairs"]) == 6
