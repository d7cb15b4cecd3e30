"""Small numerical helpers shared by the fitters."""
from __future__ import annotations

import numpy as np


def covariance_from_fisher(fisher: np.ndarray) -> np.ndarray:
    """Inverse of a (batch of) Fisher matrices, with column equilibration.

    Parameters in natural units span many decades (f_r ~ 1e7 Hz beside gamma_r ~ 1), so the
    raw matrix is badly scaled; a pseudo-inverse would then silently drop the least-determined
    directions and report too small an uncertainty. Scaling by the diagonal first and
    inverting exactly keeps every direction; a genuinely singular matrix raises.
    """
    f = np.asarray(fisher, float)
    d = np.sqrt(np.abs(np.diagonal(f, axis1=-2, axis2=-1)))
    d = np.where(d > 0, d, 1.0)
    scaled = f / (d[..., :, None] * d[..., None, :])
    inv = np.linalg.inv(scaled)
    return inv / (d[..., :, None] * d[..., None, :])


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
