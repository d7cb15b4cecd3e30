"""covariance_from_fisher: exact inverse, and the eigenvalue floor for undetermined directions.

The independent check is the information form: for a Gaussian with precision F, the conditional
variance of parameter i given all the others is 1/F_ii whatever the rank of F, so a covariance
that represents F faithfully must return it through c_ii - c_io c_oo^-1 c_oi.
"""

import numpy as np
import pytest

from bayes_tfcrds.core.linalg import covariance_from_fisher
from bayes_tfcrds.fit.beat_note import FISHER_EIG_FLOOR as FLOOR


def _fisher(rng, scales, singular: bool):
    """J'J of a random Jacobian in natural units; ``singular``: column 2 a multiple of column 0.

    The scales span decades (Hz beside dimensionless), as in the beat note.
    """
    jac = rng.standard_normal((40, len(scales))) / np.asarray(scales)
    if singular:
        jac[:, 2] = -2.5 * jac[:, 0] * scales[0] / scales[2]
    return jac.T @ jac


def _conditional_variance(cov, i):
    o = [k for k in range(cov.shape[0]) if k != i]
    return cov[i, i] - cov[i, o] @ np.linalg.solve(cov[np.ix_(o, o)], cov[o, i])


SCALES = (1e7, 0.3, 4e7, 2.0, 1.0)


@pytest.mark.parametrize("seed", range(5))
def test_a_determined_fisher_is_inverted_exactly_with_or_without_the_floor(seed):
    f = _fisher(np.random.default_rng(seed), SCALES, singular=False)
    exact = covariance_from_fisher(f)
    np.testing.assert_array_equal(covariance_from_fisher(f, eig_floor=FLOOR), exact)
    # against the plain inverse: agreement to the conditioning of the raw matrix
    np.testing.assert_allclose(exact @ f, np.eye(len(SCALES)), atol=1e-6)


@pytest.mark.parametrize("seed", range(5))
def test_an_undetermined_direction_gets_a_large_positive_variance(seed):
    f = _fisher(np.random.default_rng(seed), SCALES, singular=True)
    cov = covariance_from_fisher(f, eig_floor=FLOOR)
    np.linalg.cholesky(cov / np.sqrt(np.outer(np.diag(cov), np.diag(cov))))  # positive definite
    # the null direction (columns 0 and 2 together) has variance of order 1/floor in scaled units
    sd1 = 1 / np.sqrt(np.diag(f))
    assert cov[0, 0] / sd1[0] ** 2 > 1e-2 / FLOOR
    # information form: each parameter's variance given the others is 1/F_ii (rank-free). The
    # covariance's condition number (1/floor) costs ~eps/floor = 1e-8 through the cancellation
    # (worst 1e-6 over 3000 such matrices) and the floor itself ~1e-8: 1e-5 bounds both
    for i in range(len(SCALES)):
        assert _conditional_variance(cov, i) == pytest.approx(1 / f[i, i], rel=1e-5)


@pytest.mark.parametrize("seed", range(5))
def test_the_undetermined_direction_is_the_null_vector(seed):
    # columns 0 and 2 of J are dependent: J (a e0 + b e2) = 0 with a/b = 2.5 s0/s2 (natural units)
    f = _fisher(np.random.default_rng(seed), SCALES, singular=True)
    cov = covariance_from_fisher(f, eig_floor=FLOOR)
    null = np.zeros(len(SCALES))
    null[0], null[2] = 2.5 * SCALES[0] / SCALES[2], 1.0
    val, vec = np.linalg.eigh(cov)
    top = vec[:, -1]
    assert abs(top @ null) / np.linalg.norm(null) == pytest.approx(1.0, abs=1e-6)


def test_a_batch_floors_only_its_undetermined_members():
    rng = np.random.default_rng(7)
    good = _fisher(rng, SCALES, singular=False)
    bad = _fisher(rng, SCALES, singular=True)
    out = covariance_from_fisher(np.stack([good, bad, good]), eig_floor=FLOOR)
    np.testing.assert_array_equal(out[0], covariance_from_fisher(good))
    np.testing.assert_array_equal(out[2], covariance_from_fisher(good))
    assert np.all(np.diag(out[1]) > 0)


def test_nothing_determined_or_an_indefinite_matrix_raises():
    with pytest.raises(np.linalg.LinAlgError):
        covariance_from_fisher(np.zeros((3, 3)), eig_floor=FLOOR)
    # no J'J has an eigenvalue of -0.5 x its largest: an error upstream, not a direction to lift
    indefinite = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -0.5]])
    with pytest.raises(np.linalg.LinAlgError):
        covariance_from_fisher(indefinite, eig_floor=FLOOR)
