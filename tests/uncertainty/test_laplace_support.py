"""The Laplace H draws stay in the prior's support, and the budget's correlations stay consistent.

Found by the stratified coverage study (zoo chains, issue 16): a beat note of a weak resonance
(A_r = 0.026) leaves f_r and Gamma_r free, its least-squares covariance has sd(f_c) = 3e9 Hz, and
the Laplace draws reached f_r = NaN in a physics function (#15 item 6); a campaign whose
refinement escalated to two parameters built a correlation matrix that was not positive
semi-definite.
"""

import numpy as np
import pytest

from bayes_tfcrds.core.gum import Budget, Component
from bayes_tfcrds.uncertainty.line_budget import consistent_correlations
from bayes_tfcrds.uncertainty.posterior_steps import draws_in_support, with_prior

WIDTHS = np.array([23.0, 60.0, 23.0, 9.0])  # sampled-coordinate widths of the H priors (log)


def test_a_constrained_likelihood_is_unchanged_by_the_flat_prior():
    sd = np.array([1e-3, 1e-4, 2e-3, 5e-3])
    r = np.array([[1, 0.3, 0, 0], [0.3, 1, -0.5, 0], [0, -0.5, 1, 0.2], [0, 0, 0.2, 1]])
    cov = r * np.outer(sd, sd)
    # the prior adds a precision 12/w^2 <= 0.15 to one of >= 4e4: relative change < 4e-6
    assert with_prior(cov, WIDTHS) == pytest.approx(cov, rel=1e-5, abs=1e-12)


def test_an_unconstrained_direction_spreads_over_the_prior_not_beyond():
    cov = np.diag([1e-6, 1e40, 1e-6, 1e30])
    out = np.sqrt(np.diag(with_prior(cov, WIDTHS)))
    assert out[0] == pytest.approx(1e-3, rel=1e-6)
    # no data: the prior's own sd, width/sqrt(12), to rounding
    assert out[1] == pytest.approx(WIDTHS[1] / np.sqrt(12), rel=1e-6)
    assert out[3] == pytest.approx(WIDTHS[3] / np.sqrt(12), rel=1e-6)


def test_draws_stay_inside_the_support_and_a_centre_outside_is_refused():
    rng = np.random.default_rng(1)
    lo, hi = np.zeros(2), np.ones(2)
    phi = draws_in_support(rng, np.array([0.05, 0.5]), np.diag([0.1, 0.1]) ** 2, lo, hi, 500, "ab")
    assert phi.shape == (500, 2) and np.all((phi > lo) & (phi < hi))
    # the truncated normal about 0.05 with sd 0.1: its mean is above the centre (drawn, not clipped)
    assert phi[:, 0].mean() > 0.09
    with pytest.raises(ValueError, match="outside the prior's support.*'a'"):
        draws_in_support(rng, np.array([-5.0, 0.5]), np.diag([0.1, 0.1]) ** 2, lo, hi, 10, "ab")


def test_contradicting_correlations_are_shrunk_to_a_valid_matrix():
    rc = np.array([[1.0, -0.9], [-0.9, 1.0]])
    bad = {"f_c_hz": 0.9, "a_r": 0.9}  # r = 0.9 with two parameters correlated at -0.9: impossible
    fixed = consistent_correlations(bad, ("f_c_hz", "a_r"), rc)
    c = np.array([fixed["f_c_hz"], fixed["a_r"]])
    assert c @ np.linalg.solve(rc, c) <= 1.0
    assert fixed["f_c_hz"] / fixed["a_r"] == pytest.approx(1.0)  # shrunk along c, sign kept
    comps = [Component(n, 0.0, 1.0, 1.0, "1") for n in ("noise", "f_c_hz", "a_r")]
    corr = {("noise", "f_c_hz"): fixed["f_c_hz"], ("noise", "a_r"): fixed["a_r"]}
    corr[("f_c_hz", "a_r")] = -0.9
    Budget("A", 0.0, "1", tuple(comps), correlations=corr)  # positive semi-definite: accepted
    with pytest.raises(ValueError, match="semi-definite"):
        bad_corr = {**corr, ("noise", "a_r"): 0.9, ("noise", "f_c_hz"): 0.9}
        Budget("A", 0.0, "1", tuple(comps), correlations=bad_corr)
    ok = {"f_c_hz": 0.3, "a_r": -0.2}
    assert consistent_correlations(ok, ("f_c_hz", "a_r"), rc) == ok
