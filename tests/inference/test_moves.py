"""Tests of the mode-jumping independence move against densities with known answers."""

from __future__ import annotations

import emcee
import numpy as np
import pytest
from scipy import special, stats

from bayes_tfcrds.inference.moves import MixtureProposal, fitted_mixture, mode_jump_move
from bayes_tfcrds.uncertainty.posterior_steps import sampler_moves

# a bimodal target: 80 % of the mass at (0, 0), 20 % at (30, 30); the modes are 30 sd apart, so
# an ensemble's local moves essentially never cross (checked below)
MODES = np.array([[0.0, 0.0], [30.0, 30.0]])
MASS = np.array([0.8, 0.2])
SD = np.array([1.0, 0.5])


def bimodal(x):
    x = np.atleast_2d(x)
    lp = [
        np.log(m) - 0.5 * np.sum(((x - c) / s) ** 2, axis=1) - 2 * np.log(s)
        for c, m, s in zip(MODES, MASS, SD)
    ]
    return special.logsumexp(lp, axis=0)


def test_one_component_density_is_scipys_multivariate_t():
    # an independent implementation of the same density
    cov = np.array([[2.0, 0.6], [0.6, 0.5]])
    q = MixtureProposal(np.array([[1.0, -1.0]]), cov[None], np.array([1.0]), df=4.0)
    x = np.random.default_rng(0).normal(size=(50, 2)) * 3
    ref = stats.multivariate_t(loc=[1.0, -1.0], shape=cov, df=4.0).logpdf(x)
    np.testing.assert_allclose(q.log_density(x), ref, rtol=1e-12, atol=1e-12)


def test_mixture_draws_follow_the_mixture_weights():
    q = MixtureProposal(MODES, np.stack([np.eye(2)] * 2), np.array([0.3, 0.7]))
    x = q.draw(np.random.default_rng(1), 20000)
    frac = np.mean(x[:, 0] > 15)
    # binomial sd sqrt(0.7 * 0.3 / 20000) = 0.0032; 4 sd
    assert abs(frac - 0.7) < 0.013


def run(moves, n_steps, seed):
    rng = np.random.default_rng(seed)
    sampler = emcee.EnsembleSampler(16, 2, bimodal, vectorize=True, moves=moves)
    sampler.random_state = np.random.RandomState(seed).get_state()
    p0 = MODES[0] + 0.5 * rng.standard_normal((16, 2))  # every walker in the major mode
    sampler.run_mcmc(p0, n_steps, progress=False)
    return sampler.get_chain(discard=n_steps // 5, flat=True)


def test_jump_move_recovers_the_mode_masses():
    # proposal weights 50/50 and 2x wider than the modes: only the Hastings ratio
    # ln q(x) - ln q(x') turns them into the true 80/20 (dropping or flipping it gives ~50/50)
    q = MixtureProposal(
        MODES, np.stack([np.eye(2) * (2 * s) ** 2 for s in SD]), np.array([0.5, 0.5])
    )
    moves = [(emcee.moves.DEMove(), 0.7), (mode_jump_move(q), 0.3)]
    x = run(moves, 3000, seed=2)
    frac = np.mean(x[:, 0] > 15)
    # 38 400 kept draws with integrated autocorrelation of a few steps: the fraction's sd is
    # below 0.01; 0.05 is a wide margin that still excludes the 0.5 of a broken ratio
    assert abs(frac - MASS[1]) < 0.05


def test_without_the_jump_move_walkers_never_reach_the_minor_mode():
    # the reason the move exists: local moves alone leave the 20 % mode unvisited
    x = run(sampler_moves(), 1500, seed=3)
    assert np.mean(x[:, 0] > 15) < 0.01


def normal_variance(moves, seed, d=8, n_walkers=32, n_steps=4000):
    """Mean per-coordinate variance sampled from a d-dimensional unit normal, and its sd.

    The sd comes from the spread of the four quarter-chains' variances (each holds many
    autocorrelation times), so it needs no model of the moves' mixing.
    """
    sampler = emcee.EnsembleSampler(
        n_walkers, d, lambda x: -0.5 * np.sum(x * x, axis=1), vectorize=True, moves=moves
    )
    sampler.random_state = np.random.RandomState(seed).get_state()
    p0 = np.random.default_rng(seed).standard_normal((n_walkers, d))
    sampler.run_mcmc(p0, n_steps, progress=False)
    quarters = np.array_split(sampler.get_chain(discard=n_steps // 5), 4, axis=0)
    v = np.array([q.reshape(-1, d).var(axis=0).mean() for q in quarters])
    return v.mean(), v.std(ddof=1) / 2.0


def test_the_budgets_moves_sample_the_target_variance():
    # the moves `budget` ships must leave the target invariant: variance 1 on a unit normal
    var, sd = normal_variance(sampler_moves(), seed=4)
    assert abs(var - 1.0) < max(4 * sd, 0.02), (var, sd)


def test_emcees_snooker_move_is_biased_and_not_shipped():
    # why sampler_moves has no snooker: emcee 3.1.6's DESnookerMove samples a unit normal's
    # variance as ~0.65 (its step and Jacobian are off, see bayes_tfcrds.inference.moves); the
    # check above must be able to see that
    var, sd = normal_variance([(emcee.moves.DESnookerMove(), 1.0)], seed=4)
    assert var < 1.0 - max(4 * sd, 0.02), (var, sd)
    assert not any(isinstance(m, emcee.moves.DESnookerMove) for m, _ in sampler_moves())


def test_mixture_checks_its_shapes():
    with pytest.raises(ValueError, match="weights"):
        MixtureProposal(MODES, np.stack([np.eye(2)] * 2), np.array([0.5, 0.6]))
    with pytest.raises(ValueError, match="agree"):
        MixtureProposal(MODES, np.stack([np.eye(3)] * 2), np.array([0.5, 0.5]))


# a curved ridge: a ~ N(0, 1), b = 3 a^2 + 0.1 z. Exact draws are cheap, so E[b] = 3 and
# Var[b] = 18.01 are known; the ridge is 0.1 thin and bends, as an over-damped resonance's
# (f_r, Gamma_r) ridge does in log coordinates
RIDGE_W = 0.1


def ridge(x):
    x = np.atleast_2d(x)
    return -0.5 * x[:, 0] ** 2 - 0.5 * ((x[:, 1] - 3 * x[:, 0] ** 2) / RIDGE_W) ** 2


def ridge_draws(rng, n):
    a = rng.standard_normal(n)
    return np.column_stack([a, 3 * a**2 + RIDGE_W * rng.standard_normal(n)])


def ridge_run(moves, seed, n_steps=3000):
    sampler = emcee.EnsembleSampler(16, 2, ridge, vectorize=True, moves=moves)
    sampler.random_state = np.random.RandomState(seed).get_state()
    p0 = ridge_draws(np.random.default_rng(seed), 16)
    sampler.run_mcmc(p0, n_steps, progress=False)
    return sampler.get_chain(discard=n_steps // 5)


def test_fitted_mixture_keeps_the_ridge_invariant():
    # started on the target, an invariant move leaves it there at every step, however slowly it
    # mixes: 4000 walkers from exact draws, 30 steps of fitted jumps alone (each walker its own
    # independence chain, about half the jumps accepted)
    rng = np.random.default_rng(7)
    mix = fitted_mixture(ridge_draws(rng, 4000), rng)
    assert mix.weights.size >= 8  # many small components laid along the bend
    sampler = emcee.EnsembleSampler(4000, 2, ridge, vectorize=True, moves=mode_jump_move(mix))
    sampler.random_state = np.random.RandomState(8).get_state()
    sampler.run_mcmc(ridge_draws(np.random.default_rng(9), 4000), 30, progress=False)
    assert np.mean(sampler.acceptance_fraction) > 0.3
    a = sampler.get_last_sample().coords[:, 0]
    # 4000 independent walkers: sd of var(a) is sqrt(2/4000) = 0.022, of P(|a| > 1.5) (0.134)
    # is 0.0054; 4 sd each. A ratio dropped or flipped pulls the walkers towards the proposal's
    # wider, off-ridge mass and fails both
    assert abs(a.var() - 1.0) < 0.09
    assert abs(np.mean(np.abs(a) > 1.5) - 0.1336) < 0.022


def test_fitted_jumps_cut_the_autocorrelation_along_a_curved_ridge():
    # why the budget falls back on them: DE alone crawls along a thin bent ridge
    rng = np.random.default_rng(7)
    mix = fitted_mixture(ridge_draws(rng, 4000), rng)
    fitted = ridge_run(sampler_moves(mix, jump_share=0.5), seed=8, n_steps=1500)
    local = ridge_run(sampler_moves(), seed=8, n_steps=1500)
    tau_fit = emcee.autocorr.integrated_time(fitted[..., 1:], quiet=True)[0]
    tau_de = emcee.autocorr.integrated_time(local[..., 1:], quiet=True)[0]
    # measured at seeds 8-10: 4-11 steps against 115-150
    assert tau_fit < tau_de / 5, (tau_fit, tau_de)


def test_fitted_mixture_needs_samples_that_vary():
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="varying"):
        fitted_mixture(np.ones((500, 2)), rng)
    with pytest.raises(ValueError, match="varying"):
        fitted_mixture(rng.standard_normal((5, 2)), rng)
