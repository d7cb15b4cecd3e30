"""Small numerical helpers shared by the fitters."""

from __future__ import annotations

import numpy as np


def covariance_from_fisher(fisher: np.ndarray, eig_floor: float | None = None) -> np.ndarray:
    """Inverse of a (batch of) Fisher matrices, with column equilibration.

    Parameters in natural units span many decades (f_r ~ 1e7 Hz beside gamma_r ~ 1), so the
    raw matrix is badly scaled; a pseudo-inverse would then silently drop the least-determined
    directions and report too small an uncertainty. Scaling by the diagonal first and
    inverting exactly keeps every direction; a genuinely singular matrix raises.

    ``eig_floor`` is for fits where a direction the data do not determine is a result, not a
    failure (a beat note in which part of Eq. 2 has left the measured band). There, a scaled
    Fisher matrix whose smallest eigenvalue is below ``eig_floor`` times its largest is inverted
    through its eigen-decomposition with the eigenvalues lifted to that floor: the undetermined
    direction gets a large, finite variance and the covariance stays positive definite, where
    the exact inverse of a matrix singular to rounding has variances of either sign (-1.6e21
    Hz^2 for f_c in coverage campaign 18). Every other matrix is inverted exactly, as without it.
    A floor well above eps matters: conditionals taken through the result lose ~eps/eig_floor.
    """
    f = np.asarray(fisher, float)
    d = np.sqrt(np.abs(np.diagonal(f, axis1=-2, axis2=-1)))
    d = np.where(d > 0, d, 1.0)
    scaled = f / (d[..., :, None] * d[..., None, :])
    if eig_floor is None:
        inv = np.linalg.inv(scaled)
    else:
        inv = _floored_inverse(scaled, eig_floor)
    return inv / (d[..., :, None] * d[..., None, :])


def _floored_inverse(scaled: np.ndarray, eig_floor: float) -> np.ndarray:
    """Inverse of symmetric ``scaled`` (unit diagonal), eigenvalues below the floor lifted.

    Per matrix of a batch: those whose eigenvalues all clear ``eig_floor`` times their largest
    are inverted exactly. One with no positive eigenvalue (nothing determined), or with an
    eigenvalue below -``eig_floor`` times its largest (not a Fisher matrix: rounding leaves
    J'J's eigenvalues within ~n eps of zero), raises.
    """
    n = scaled.shape[-1]
    flat = scaled.reshape(-1, n, n)
    val, vec = np.linalg.eigh(0.5 * (flat + np.swapaxes(flat, -1, -2)))
    if not np.all(val[:, -1] > 0):
        raise np.linalg.LinAlgError("a Fisher matrix without a positive eigenvalue")
    floor = eig_floor * val[:, -1:]
    if np.any(val < -floor):
        raise np.linalg.LinAlgError("an indefinite Fisher matrix (an eigenvalue well below 0)")
    ok = np.all(val >= floor, axis=-1)
    out = np.empty_like(flat)
    out[ok] = np.linalg.inv(flat[ok])
    lifted = np.maximum(val[~ok], floor[~ok])
    out[~ok] = np.einsum("mik,mk,mjk->mij", vec[~ok], 1.0 / lifted, vec[~ok])
    return out.reshape(scaled.shape)


def central_jacobian(fn, theta, steps) -> np.ndarray:
    """d fn / d theta by central differences, shape (len(fn(theta)), len(theta)).

    ``steps`` are absolute step sizes per parameter (in its unit): the callers choose them
    relative to each parameter's scale, which matters when parameters span many decades.
    """
    theta = np.asarray(theta, float)
    cols = []
    for j, h in enumerate(np.broadcast_to(np.asarray(steps, float), theta.shape)):
        tp, tm = theta.copy(), theta.copy()
        tp[j] += h
        tm[j] -= h
        cols.append((np.asarray(fn(tp)) - np.asarray(fn(tm))) / (2.0 * h))
    return np.stack(cols, axis=-1)


def central_hessian(fn, theta, steps) -> np.ndarray:
    """Second derivatives of a scalar ``fn`` at ``theta`` by central differences, steps ``steps``.

    Diagonal: (f(+h) - 2 f0 + f(-h))/h^2. Off-diagonal from the two diagonal moves:
    (f(+i+j) - f(+i) - f(+j) + 2 f0 - f(-i) - f(-j) + f(-i-j)) / (2 h_i h_j), exact for a quadratic,
    with 2 p^2 + 1 evaluations in all. Units: those of fn per unit theta_i theta_j.
    """
    theta = np.asarray(theta, float)
    h = np.asarray(steps, float)
    p = theta.size
    eye = np.eye(p) * h
    f0 = fn(theta)
    fp = np.array([fn(theta + eye[i]) for i in range(p)])
    fm = np.array([fn(theta - eye[i]) for i in range(p)])
    hess = np.diag((fp - 2 * f0 + fm) / h**2)
    for i in range(p):
        for j in range(i + 1, p):
            fpp = fn(theta + eye[i] + eye[j])
            fmm = fn(theta - eye[i] - eye[j])
            hess[i, j] = hess[j, i] = (fpp - fp[i] - fp[j] + 2 * f0 - fm[i] - fm[j] + fmm) / (
                2 * h[i] * h[j]
            )
    return hess


def extend_span(rows, basis, rtol: float, atol: float, max_rank: int):
    """Express ``rows`` (c, d) in the orthonormal ``basis`` (r, d), growing it where needed.

    Greedy, deterministic (no random sketch, so no random stream is touched): while a row's
    residual off the span exceeds ``rtol * |row| + atol`` and the basis has fewer than
    ``max_rank`` vectors, the row with the largest excess joins the basis (its residual,
    orthogonalised twice). Used to write many nearly dependent vectors (the changes of H(f)
    over posterior draws: numerical rank about 15 for 2000 draws) through a few.

    Returns (basis (r', d) with r' >= r, coefficients (c, r'), spanned (c,) bool: the residual
    within tolerance). Rows not spanned when ``max_rank`` is reached are for the caller to
    treat exactly.
    """
    rows = np.asarray(rows, float)
    basis = np.asarray(basis, float).reshape(-1, rows.shape[1])
    coef = rows @ basis.T
    resid = rows - coef @ basis
    limit = rtol * np.linalg.norm(rows, axis=1) + atol
    excess = np.linalg.norm(resid, axis=1) - limit
    new = []
    while excess.size and excess.max() > 0 and basis.shape[0] + len(new) < max_rank:
        v = resid[int(np.argmax(excess))]
        for _ in range(2):  # twice is enough (Giraud et al. 2005): orthogonal to round-off
            v = v - (v @ basis.T) @ basis
            for u in new:
                v = v - (v @ u) * u
        norm = np.linalg.norm(v)
        if not norm > 0:
            break
        v = v / norm
        new.append(v)
        resid = resid - np.outer(resid @ v, v)
        excess = np.linalg.norm(resid, axis=1) - limit
    if new:
        added = np.array(new)
        basis = np.vstack([basis, added])
        coef = np.hstack([coef, rows @ added.T])
    return basis, coef, excess <= 0
