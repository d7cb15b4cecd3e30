"""Sampler moves beyond emcee's own: a mode-jumping independence proposal.

An affine-invariant ensemble explores one basin well and crosses between separated basins
almost never: a walker started (or wandered) into a minor mode stays there, and R-hat between
ensembles fails on a posterior that is simply multimodal. When the modes are known in advance
(the local optima of a multi-start least-squares fit), an independence Metropolis-Hastings move
whose proposal is a mixture of heavy-tailed densities centred on them lets every walker jump
between modes, with the acceptance ratio keeping the posterior exactly invariant (Tierney 1994,
Ann. Statist. 22, 1701). Mixed with the local moves, it leaves a unimodal posterior unchanged
and makes a multimodal one mix.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import special

STUDENT_DF = 4.0  # heavy tails: the proposal must not be lighter-tailed than the posterior


@dataclass(frozen=True)
class MixtureProposal:
    """A mixture of multivariate Student-t densities, in the sampler's parametrisation.

    ``means`` (k, d), ``covs`` (k, d, d) (scale matrices), ``weights`` (k,) summing to 1.
    """

    means: np.ndarray
    covs: np.ndarray
    weights: np.ndarray
    df: float = STUDENT_DF
    _chol: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        means = np.atleast_2d(np.asarray(self.means, float))
        covs = np.asarray(self.covs, float)
        w = np.asarray(self.weights, float)
        if covs.shape != (means.shape[0], means.shape[1], means.shape[1]) or w.shape != (
            means.shape[0],
        ):
            raise ValueError("means (k, d), covs (k, d, d) and weights (k,) must agree")
        if np.any(w < 0) or not np.isclose(w.sum(), 1.0):
            raise ValueError("weights must be >= 0 and sum to 1")
        sym = 0.5 * (covs + np.swapaxes(covs, 1, 2))
        object.__setattr__(self, "means", means)
        object.__setattr__(self, "covs", sym)
        object.__setattr__(self, "weights", w)
        object.__setattr__(self, "_chol", np.linalg.cholesky(sym))

    @property
    def ndim(self) -> int:
        return self.means.shape[1]

    def draw(self, random, n: int) -> np.ndarray:
        """``n`` draws; ``random`` is a numpy Generator or RandomState."""
        k = _choice(random, self.weights, n)
        z = _normal(random, (n, self.ndim))
        g = _gamma(random, 0.5 * self.df, n) / (0.5 * self.df)
        return self.means[k] + np.einsum("nij,nj->ni", self._chol[k], z) / np.sqrt(g)[:, None]

    def log_density(self, x) -> np.ndarray:
        """log q(x) for points x (n, d)."""
        x = np.atleast_2d(np.asarray(x, float))
        d, nu = self.ndim, self.df
        out = np.empty((x.shape[0], self.weights.size))
        for j, (m, c) in enumerate(zip(self.means, self._chol)):
            sol = np.linalg.solve(c, (x - m).T)
            maha = np.sum(sol * sol, axis=0)
            log_det = 2.0 * np.sum(np.log(np.diag(c)))
            out[:, j] = (
                special.gammaln(0.5 * (nu + d))
                - special.gammaln(0.5 * nu)
                - 0.5 * d * np.log(nu * np.pi)
                - 0.5 * log_det
                - 0.5 * (nu + d) * np.log1p(maha / nu)
            )
        with np.errstate(divide="ignore"):
            return special.logsumexp(out + np.log(self.weights)[None, :], axis=1)


def _choice(random, p, n):
    u = random.random(n) if hasattr(random, "random") else random.rand(n)
    return np.minimum(np.searchsorted(np.cumsum(p), u), p.size - 1)


def _normal(random, shape):
    return random.standard_normal(shape)


def _gamma(random, shape, n):
    return random.gamma(shape, 1.0, n)


def mode_jump_move(proposal: MixtureProposal):
    """An emcee move: every walker proposes an independent draw of ``proposal``.

    The log proposal ratio ln q(x) - ln q(x') makes it an independence Metropolis-Hastings step.
    """
    import emcee

    def propose(coords, random):
        new = proposal.draw(random, coords.shape[0])
        return new, proposal.log_density(coords) - proposal.log_density(new)

    return emcee.moves.MHMove(propose, ndim=proposal.ndim)
