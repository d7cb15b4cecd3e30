"""A multimodal beat note: every optimum found, walkers started in each, jumps between them."""

from dataclasses import replace

import numpy as np
import pytest

from bayes_tfcrds.fit.beat_note import MODE_DCHI2
from bayes_tfcrds.simulate.campaign import Campaign, ChainPreset, simulate_campaign
from bayes_tfcrds.simulate.zoo import draw_chain
from bayes_tfcrds.uncertainty.line_budget import BudgetOptions
from bayes_tfcrds.uncertainty.posterior_steps import _beat_posterior


def _zoo_config(index):
    # zoo chain 9 of benchmarks/chain_zoo.py (seed 7): f_c 17 MHz beside a heavily overdamped
    # resonance (Gamma_r 0.2) at 3.3 MHz: |H| fits with the poles in several roles
    rng = np.random.default_rng([7, index])
    tf = draw_chain(rng, ("tail", "pole")[index % 2])
    camp = replace(Campaign(), n_points=41)  # the benchmark's campaign
    bundle, _ = simulate_campaign([ChainPreset("Z", "zoo", tf)], rng, camp)
    return tf, bundle.configs["Z"]


def test_an_overdamped_chain_has_several_beat_note_optima_and_the_sampler_starts_in_each():
    tf, config = _zoo_config(9)
    beat, post, p0, modes = _beat_posterior(config, BudgetOptions())
    fits = (beat, *beat.alternatives)
    assert len(fits) >= 2
    assert all(f.chi2 - beat.chi2 <= MODE_DCHI2 for f in fits)  # best first, all close to it
    assert modes is not None and modes.weights.size >= 2
    # starts in every basin: each walker is nearest (Mahalanobis) to some component, and every
    # component is nearest to some walkers (1000 starts, weights >= 0.5 / k by construction)
    x = p0(np.random.default_rng(0), 1000)
    assert np.all(np.isfinite(post(x)))
    d = np.stack(
        [
            np.einsum("ni,ij,nj->n", x - m, np.linalg.inv(c), x - m)
            for m, c in zip(modes.means, modes.covs)
        ]
    )
    nearest = np.argmin(d, axis=0)
    assert set(nearest) == set(range(modes.weights.size))


def test_a_unimodal_beat_note_keeps_the_plain_sampler():
    # a letter-like chain (slow tail beside a fast resonance): one optimum, no jump move
    tf, config = _zoo_config(0)
    beat, _, _, modes = _beat_posterior(config, BudgetOptions())
    assert modes is None
    assert abs(beat.params.f_c_hz / tf.f_c_hz - 1) < 0.2


def test_a_pool_the_ring_downs_reject_entirely_has_zero_ess(monkeypatch):
    """Every draw at -inf (or nan) log-likelihood: ESS 0, so the pool fails its gate and a larger
    one is drawn, never NaN weights; a finite pool keeps the Kish ESS (two equal weights: 2)."""
    import warnings

    from bayes_tfcrds.uncertainty import posterior_steps as ps

    draws = np.zeros((4, 4))
    monkeypatch.setattr(
        ps, "ringdown_log_likelihood", lambda *a: np.array([-np.inf, np.nan, -np.inf, np.nan])
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no 'invalid value' on the way
        res = ps.ring_down_weights(None, draws, 4, np.random.default_rng(0))
    assert res.ess == 0.0 and not res.passed
    monkeypatch.setattr(
        ps, "ringdown_log_likelihood", lambda *a: np.array([0.0, 0.0, -np.inf, -np.inf])
    )
    res = ps.ring_down_weights(None, draws, 4, np.random.default_rng(0))
    assert res.ess == pytest.approx(2.0, rel=1e-12)
    assert set(res.picks) <= {0, 1}
