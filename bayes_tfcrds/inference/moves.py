"""Sampler moves beyond emcee's own: vectorised differential evolution, mode jumps.

Not used, on purpose: emcee 3.1.6's ``DESnookerMove``. It does not leave the target invariant:
it scales the projected step by |x - z| (``u = delta / sqrt(|delta|)`` where a unit vector is
meant) and weights the Jacobian by (d - 1)/2 where the snooker update of ter Braak & Vrugt
(2008) needs d - 1 (fixed upstream after 3.1.6 in dfm/emcee#531, not released). On an
8-dimensional unit normal it samples a variance of 0.65 alone and 0.90 in an 80/20 mixture with
``DEMove`` (tests/inference/test_moves.py), so a posterior sampled with it is too narrow.

An affine-invariant ensemble explores one basin well and crosses between separated basins
almost never: a walker started (or wandered) into a minor mode stays there, and R-hat between
ensembles fails on a posterior that is simply multimodal. When the modes are known in advance
(the local optima of a multi-start least-squares fit), an independence Metropolis-Hastings move
whose proposal is a mixture of heavy-tailed densities centred on them lets every walker jump
between modes, with the acceptance ratio keeping the posterior exactly invariant (Tierney 1994,
Ann. Statist. 22, 1701). Mixed with the local moves, it leaves a unimodal posterior unchanged
and makes a multimodal one mix.

When the optima are not enough (a curved ridge joining them, as an over-damped resonance's fast
pole makes when it runs out of the measured band), :func:`fitted_mixture` builds the proposal
from a pilot run's samples instead: many small components laid along wherever the pilot went.
The proposal is fixed before the run that uses it starts, so that run is a time-homogeneous
Metropolis-Hastings chain with the posterior invariant (adapting it during the run would not be).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import emcee
import numpy as np
from scipy import special
from scipy.cluster.vq import kmeans2

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


# a fitted mixture: at most this many components, each from at least MIN_POINTS_PER_DIM * d pilot
# samples (enough for a covariance in d dimensions), widened FITTED_INFLATE times (a proposal a
# little wider than the target keeps the independence sampler's ratio bounded), its weights
# FITTED_UNIFORM_SHARE uniform so that rarely visited parts are still proposed
FITTED_COMPONENTS = 32
MIN_POINTS_PER_DIM = 10
FITTED_INFLATE = 1.5
FITTED_UNIFORM_SHARE = 0.3


def fitted_mixture(samples, rng: np.random.Generator, n_components: int = FITTED_COMPONENTS):
    """A Student-t mixture laid over pilot ``samples`` (n, d), for :func:`mode_jump_move`.

    k-means (on coordinates scaled by their sd) cuts the samples into up to ``n_components``
    clusters; each cluster with enough points gives one component: its mean, its covariance
    widened FITTED_INFLATE times. Many small components follow a curved or multimodal posterior
    that one Gaussian per optimum cannot. Weights: the clusters' shares, mixed with a uniform
    share. Raises ValueError when the samples are too few or do not vary.
    """
    x = np.asarray(samples, float)
    n, d = x.shape
    sd = x.std(axis=0)
    if not np.all(sd > 0) or n < MIN_POINTS_PER_DIM * d:
        raise ValueError(f"need >= {MIN_POINTS_PER_DIM * d} varying samples, got {n}")
    k = int(min(n_components, n // (MIN_POINTS_PER_DIM * d)))
    _, label = kmeans2(x / sd, k, seed=rng, minit="++")
    means, covs, counts = [], [], []
    for j in range(k):
        xj = x[label == j]
        if len(xj) < MIN_POINTS_PER_DIM * d:
            continue
        cov = FITTED_INFLATE * np.cov(xj.T) + np.diag((1e-6 * sd) ** 2)
        if np.linalg.eigvalsh(cov)[0] <= 0:
            continue  # a cluster of repeated points (walkers that did not move): no shape
        means.append(xj.mean(axis=0))
        covs.append(cov)
        counts.append(len(xj))
    if not counts:
        raise ValueError("no cluster of the samples has a covariance")
    w = np.asarray(counts, float)
    w = (1.0 - FITTED_UNIFORM_SHARE) * w / w.sum() + FITTED_UNIFORM_SHARE / w.size
    return MixtureProposal(np.array(means), np.array(covs), w / w.sum())


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

    def propose(coords, random):
        new = proposal.draw(random, coords.shape[0])
        return new, proposal.log_density(coords) - proposal.log_density(new)

    return emcee.moves.MHMove(propose, ndim=proposal.ndim)


class DifferentialEvolutionMove(emcee.moves.Move):
    """Differential evolution (ter Braak 2006) within each of ``n_groups`` independent ensembles.

    The sampler's walkers are ``n_groups`` ensembles of equal size, stored one after the other.
    Each ensemble is split at random into two halves; every walker x of one half proposes
    x' = x + gamma (z1 - z2), (z1, z2) a random ordered pair of distinct walkers of the other half
    *of its own ensemble*, gamma = gamma0 (1 + sigma N(0, 1)), gamma0 = 2.38/sqrt(2 d) (Nelson et
    al. 2014, ApJS 210, 11). Given the other half the proposal is symmetric, so it is accepted
    with probability min(1, p(x')/p(x)). For one group this is emcee 3.1.6's ``DEMove`` (its
    proposal, split and acceptance rule; its random numbers drawn in another order). No walker
    ever uses another ensemble's, so the ensembles stay independent chains for R-hat, while the
    proposals of all of them are evaluated in one call of the posterior and accepted in one
    array step: the Python cost of a step is paid once for all ensembles instead of once each.
    """

    def __init__(self, gamma0: float | None = None, sigma: float = 1.0e-5, n_groups: int = 1):
        self.gamma0, self.sigma, self.n_groups = gamma0, float(sigma), int(n_groups)

    def for_groups(self, n_groups: int) -> DifferentialEvolutionMove:
        """The same move acting within each of ``n_groups`` ensembles."""
        return DifferentialEvolutionMove(self.gamma0, self.sigma, n_groups)

    def propose(self, model, state):
        n, d = state.coords.shape
        n_groups = self.n_groups
        width = n // n_groups
        if width * n_groups != n or width < 4:
            raise ValueError(f"{n} walkers do not make {n_groups} ensembles of at least 4 walkers")
        g0 = 2.38 / np.sqrt(2.0 * d) if self.gamma0 is None else self.gamma0
        random = model.random
        base = (np.arange(n_groups) * width)[:, None]
        order = np.argsort(random.rand(n_groups, width), axis=1)  # each group's random halves
        accepted = np.zeros(n, dtype=bool)
        for split in (0, 1):
            active = base + np.sort(order[:, split::2], axis=1)  # (groups, n_s), ascending
            other = base + order[:, 1 - split :: 2]  # (groups, n_c)
            n_s, n_c = active.shape[1], other.shape[1]
            i = random.randint(n_c, size=(n_groups, n_s))
            j = random.randint(n_c - 1, size=(n_groups, n_s))
            j += j >= i  # a partner distinct from i, uniform over the others
            z1 = state.coords[np.take_along_axis(other, i, axis=1)]
            z2 = state.coords[np.take_along_axis(other, j, axis=1)]
            gamma = g0 * (1.0 + self.sigma * random.randn(n_groups, n_s, 1))
            rows = active.ravel()
            q = (state.coords[active] + gamma * (z1 - z2)).reshape(-1, d)
            new_lp, new_blobs = model.compute_log_prob_fn(q)
            subset = np.zeros(n, dtype=bool)
            subset[rows] = True
            acc = np.zeros(n, dtype=bool)
            acc[rows] = new_lp - state.log_prob[rows] > np.log(random.rand(rows.size))
            accepted |= acc
            new = emcee.State(q, log_prob=new_lp, blobs=new_blobs)
            state = self.update(state, new, acc, subset)
        return state, accepted


def ensemble_local(moves, n_groups: int) -> list:
    """``moves`` made to act within each of ``n_groups`` ensembles, as (move, weight) pairs.

    ``moves`` as emcee takes them: one move, a list of moves, or (move, weight) pairs. A move
    with ``for_groups`` is told the groups; an ``MHMove`` (each walker proposes on its own, as
    :func:`mode_jump_move` does) needs nothing. Any other move (emcee's stretch, DEMove, ...)
    draws on walkers of other ensembles and would couple them: refused.
    """
    if isinstance(moves, emcee.moves.Move):  # emcee's forms: one move, moves, (move, weight)s
        moves = [moves]
    moves = [m if isinstance(m, tuple) else (m, 1.0 / len(moves)) for m in moves]
    out = []
    for move, weight in moves:
        if hasattr(move, "for_groups"):
            move = move.for_groups(n_groups)
        elif not isinstance(move, emcee.moves.MHMove):
            raise ValueError(
                f"{type(move).__name__} draws on other walkers and would couple the independent "
                "ensembles; use DifferentialEvolutionMove or an MHMove"
            )
        out.append((move, float(weight)))
    return out
