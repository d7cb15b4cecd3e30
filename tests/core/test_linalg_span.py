"""extend_span: the greedy orthonormal basis that writes many nearly dependent rows through few."""

import numpy as np

from bayes_tfcrds.core.linalg import extend_span


def _rows(rng, n, rank, d=400, noise=0.0):
    return rng.standard_normal((n, rank)) @ rng.standard_normal((rank, d)) + noise * (
        rng.standard_normal((n, d))
    )


def test_rows_of_rank_r_are_written_exactly_through_r_vectors():
    """Rank-7 rows in two chunks: 7 orthonormal vectors, and the rows rebuilt to round-off."""
    rng = np.random.default_rng(1)
    rows = _rows(rng, 90, 7)
    basis, c1, ok1 = extend_span(rows[:40], np.zeros((0, 400)), 1e-12, 0.0, 50)
    basis, c2, ok2 = extend_span(rows[40:], basis, 1e-12, 0.0, 50)
    assert basis.shape[0] == 7 and ok1.all() and ok2.all()
    np.testing.assert_allclose(basis @ basis.T, np.eye(7), atol=1e-13)
    coef = np.vstack([np.pad(c1, ((0, 0), (0, 7 - c1.shape[1]))), c2])
    np.testing.assert_allclose(coef @ basis, rows, atol=1e-11 * np.abs(rows).max())


def test_rows_beyond_the_rank_cap_are_flagged_not_spanned():
    """Full-rank rows with a cap of 5 vectors: the rows the basis misses come back flagged."""
    rng = np.random.default_rng(2)
    rows = _rows(rng, 30, 20)
    basis, coef, ok = extend_span(rows, np.zeros((0, 400)), 1e-10, 0.0, 5)
    assert basis.shape[0] == 5
    assert ok.sum() == 5 and not ok.all()  # only the 5 rows that joined the basis are spanned
    resid = np.linalg.norm(rows - coef @ basis, axis=1) / np.linalg.norm(rows, axis=1)
    assert np.all(resid[ok] < 1e-10) and np.all(resid[~ok] > 1e-3)


def test_the_absolute_floor_stops_the_basis_at_the_noise():
    """Rank-4 rows plus 1e-9 noise: with atol above the noise the basis stops at 4 vectors."""
    rng = np.random.default_rng(3)
    rows = _rows(rng, 60, 4, noise=1e-9)
    floor = 1e-9 * np.sqrt(400) * 3  # three times the noise norm of a row
    basis, _, ok = extend_span(rows, np.zeros((0, 400)), 0.0, floor, 50)
    assert basis.shape[0] == 4 and ok.all()


def test_non_finite_rows_are_not_spanned_and_leave_the_basis_clean():
    """A draw whose H overflows (a row of inf or nan) goes to the caller's exact path; the basis
    built from the finite rows, before or after it, holds no non-finite number."""
    rng = np.random.default_rng(4)
    rows = _rows(rng, 20, 3)
    rows[5] = np.inf
    rows[9, 7] = np.nan
    basis, _, ok = extend_span(rows[:12], np.zeros((0, 400)), 1e-12, 0.0, 50)
    basis, _, ok2 = extend_span(rows[12:], basis, 1e-12, 0.0, 50)
    assert np.all(np.isfinite(basis))
    assert not ok[5] and not ok[9] and ok2.all()
