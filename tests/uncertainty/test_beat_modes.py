"""A multimodal beat note: every optimum found, walkers started in each, jumps between them."""

from dataclasses import replace

import numpy as np
import pytest

from bayes_tfcrds.fit.beat_note import MODE_DCHI2
from bayes_tfcrds.inference.runner import run_ensembles
from bayes_tfcrds.simulate.campaign import Campaign, ChainPreset, simulate_campaign
from bayes_tfcrds.simulate.zoo import draw_chain
from bayes_tfcrds.uncertainty.line_budget import BudgetOptions
from bayes_tfcrds.uncertainty.posterior_steps import _beat_posterior, _pilot_refit, sampler_moves


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


def _walkers_independent(x):
    """emcee's check on an initial ensemble (EnsembleSampler refuses it otherwise)."""
    c = x - x.mean(axis=0)
    c = c / np.abs(c).max(axis=0)
    c = c / np.sqrt(np.sum(c**2, axis=0))
    return np.all(np.isfinite(c)) and np.linalg.cond(c) <= 1e8


def test_starts_stay_distinct_when_the_least_squares_sd_exceeds_the_support():
    # coverage campaign 18 (studies/coverage.toml): a zoo chain whose beat note leaves the
    # resonance unconstrained; its least-squares sd of log f_c was ~4000 (the support spans 23),
    # every start fell outside, and the old fallback put all walkers on the optimum: emcee
    # refused the ensemble ("large condition number") and the campaign could not be analysed
    from bayes_tfcrds.studies.coverage import settings_of, simulate_draw
    from bayes_tfcrds.studies.spec import load_study
    from bayes_tfcrds.uncertainty.posterior_steps import capped_spread

    root = __import__("pathlib").Path(__file__).resolve().parents[2]
    settings = settings_of(load_study(root / "studies" / "coverage.toml"))
    draw, g_sim, _ = settings.draw(18)
    bundle, _ = simulate_draw(draw, g_sim, settings.campaign)
    beat, post, p0, modes = _beat_posterior(next(iter(bundle.configs.values())), BudgetOptions())
    x = p0(np.random.default_rng(1), 16)
    assert np.all(np.isfinite(post(x)))
    assert len(np.unique(x, axis=0)) == 16 and _walkers_independent(x)
    # the cap binds here (that is the case), and a quarter of the support is its size
    width = np.array([p.sample_width for p in post.priors])
    sd0 = np.sqrt(np.diag(beat.cov))
    capped = capped_spread(post, np.full(width.size, 1e4))
    assert np.all(capped[np.isfinite(width)] <= 0.25 * width[np.isfinite(width)] / 3.0 + 1e-12)
    assert modes is not None or np.any(sd0 > width)


def test_a_start_outside_the_support_is_refused_with_the_reason():
    from bayes_tfcrds.inference.posteriors import Prior
    from bayes_tfcrds.uncertainty.posterior_steps import dispersed_starts

    class Box:  # a posterior flat on 0 < x < 1 in both coordinates
        priors = (Prior("a", "uniform", 0.0, 1.0, "1"), Prior("b", "uniform", 0.0, 1.0, "1"))
        sample_names = ("a", "b")

        def __call__(self, x):
            x = np.atleast_2d(x)
            return np.where(np.all((x > 0) & (x < 1), axis=1), 0.0, -np.inf)

    rng = np.random.default_rng(0)
    inside = dispersed_starts(Box(), np.array([0.5, 0.999999]), np.array([0.1, 0.1]), rng, 12)
    assert np.all(np.isfinite(Box()(inside))) and _walkers_independent(inside)
    on_bound = dispersed_starts(Box(), np.array([0.5, 1.0]), np.array([0.1, 0.1]), rng, 12)
    assert np.all(np.isfinite(Box()(on_bound)))  # half of every neighbourhood is inside
    with pytest.raises(ValueError, match="bound of the posterior's support"):
        dispersed_starts(Box(), np.array([0.5, 1.5]), np.array([0.1, 0.1]), rng, 12)


def test_draws_outside_the_prior_support_get_no_weight_and_are_drawn_again(monkeypatch):
    """The refinement's Gaussian conditional knows nothing of the prior's bounds: a joint draw it
    puts outside has prior density 0, so weight 0, and its conditional scatter is drawn again."""
    from bayes_tfcrds.inference.posteriors import H_PRIORS
    from bayes_tfcrds.uncertainty import posterior_steps as ps

    monkeypatch.setattr(ps, "ringdown_log_likelihood", lambda *a: np.zeros(4))
    priors = [H_PRIORS["f_c_hz"], H_PRIORS["a_r"]]
    draws = np.array([[1e5, 1.0], [np.inf, 1.0], [2e10, 1.0], [1e5, -2.0]])
    inside = ps.in_support(draws, priors)
    assert inside.tolist() == [True, False, False, False]
    res = ps.ring_down_weights(None, draws, 8, np.random.default_rng(0), inside=inside)
    assert set(res.picks) == {0}
    # every likelihood rejected: ESS 0, and the stand-in resample keeps to the support
    monkeypatch.setattr(ps, "ringdown_log_likelihood", lambda *a: np.full(4, -np.inf))
    res = ps.ring_down_weights(None, draws, 8, np.random.default_rng(0), inside=inside)
    assert res.ess == 0.0 and set(res.picks) == {0}

    class Refined:  # f_c's conditional: N(log 1e5 + 5 (a_r - 1), sd^2) in log f_c
        free = ("f_c_hz",)
        sd = 6.0

        def draw_given(self, others_values, others, rng):
            mean = np.log(1e5) + 5.0 * (np.asarray(others_values)[:, 0] - 1.0)
            e = 0.0 if rng is None else self.sd * rng.standard_normal(mean.size)
            return np.exp(mean + e)[:, None]

    d = np.column_stack([np.full(2000, 1e5), np.full(2000, 1.0)])
    # sd 6 in log f_c: P(f_c > 1e10 Hz) = P(z > 1.92) = 2.7 %, and P(f_c < 1 Hz) = 2.7 %
    first = Refined().draw_given(d[:, [1]], ("a_r",), np.random.default_rng(1))
    assert np.mean((first[:, 0] >= 1e10) | (first[:, 0] <= 1.0)) > 0.03
    out = ps._conditional_inside(
        d.copy(), Refined(), ("a_r",), [1], [0], priors, np.random.default_rng(1)
    )
    assert ps.in_support(out, priors).all()
    np.testing.assert_array_equal(out[:, 1], 1.0)  # the others untouched
    # nothing outside: the same random numbers as one plain conditional draw (no extra draws)
    Refined.sd = 0.5
    rng_a, rng_b = np.random.default_rng(2), np.random.default_rng(2)
    out = ps._conditional_inside(d.copy(), Refined(), ("a_r",), [1], [0], priors, rng_a)
    plain = Refined().draw_given(d[:, [1]], ("a_r",), rng_b)
    np.testing.assert_array_equal(out[:, 0], plain[:, 0])
    assert rng_a.bit_generator.state == rng_b.bit_generator.state
    far = np.column_stack([np.full(4, 1e5), np.full(4, 80.0)])  # conditional mean exp(407) Hz
    out = ps._conditional_inside(far, Refined(), ("a_r",), [1], [0], priors, rng_a)
    assert not ps.in_support(out, priors).any()  # a redraw cannot rescue a mean that far out


def test_incompatible_refinement_and_beat_note_fail_with_the_reason():
    # what campaign 18 of studies/coverage.toml met: the beat note leaves A_r nearly free, the
    # refinement linearised at another branch sends f_c to 1e17 Hz and beyond
    from types import SimpleNamespace

    from bayes_tfcrds.fit.h_calibration import AnalysisError
    from bayes_tfcrds.inference.posteriors import H_PRIORS
    from bayes_tfcrds.physics.transfer_function import TFParams
    from bayes_tfcrds.uncertainty import posterior_steps as ps

    refined = SimpleNamespace(
        free=("f_c_hz",), params=TFParams(f_c_hz=3.4e5, a_r=-0.918, f_r_hz=1.6e6, gamma_r=0.2)
    )
    joint = np.column_stack([np.full(10, 3e17), np.linspace(1.0, 380.0, 10)])
    err = ps._support_error(
        joint, refined, ("f_c_hz", "a_r"), [H_PRIORS["f_c_hz"], H_PRIORS["a_r"]], 10, 10
    )
    assert isinstance(err, AnalysisError)
    msg = str(err)
    assert "f_c_hz: 100% of draws outside" in msg and "about the refinement's -0.918" in msg
    assert "--refine" in msg and "10 of 10 joint draws" in msg


def _ridge(x):
    # a thin bent ridge (a ~ N(0, 1), b = 3 a^2 + 0.1 z): what an over-damped resonance's
    # (f_r, Gamma_r) makes in log coordinates when its fast pole leaves the band
    x = np.atleast_2d(x)
    return -0.5 * x[:, 0] ** 2 - 0.5 * ((x[:, 1] - 3 * x[:, 0] ** 2) / 0.1) ** 2


def test_a_failed_h_run_is_sampled_again_with_jumps_fitted_to_it():
    def sample(p0, options, backend, label, modes=None, jump_share=0.15):
        return run_ensembles(
            _ridge,
            p0,
            ("a", "b"),
            np.random.default_rng(5),
            n_walkers=16,
            n_steps=options.n_steps,
            max_steps=options.max_steps,
            vectorize=True,
            moves=sampler_moves(modes, jump_share),
            label=label,
        )

    def starts(r, n):
        return np.column_stack([r.normal(size=n), 0.1 * r.normal(size=n)])

    pilot = sample(starts, BudgetOptions().with_steps(4000, 4000), None, "pilot")
    assert not pilot.passed  # DE alone along the bend: tau_int about 150 steps, n_tau < 50
    options = BudgetOptions().with_steps(1500, 6000)
    run = _pilot_refit(_ridge, pilot, sample, options, None, np.random.default_rng(15))
    assert run.passed and "jumps fitted to a pilot run" in run.label
    # P(|a| > 1) = 0.3173; the gates passed with ESS >= 400, so its sd is <= 0.023; 4 sd
    assert abs(np.mean(np.abs(run.flat()[:, 0]) > 1) - 0.3173) < 0.093


def test_a_pilot_that_never_moved_keeps_its_failure():
    class Stuck:
        passed = False

        def flat(self):
            return np.ones((1000, 2))

    stuck = Stuck()
    assert _pilot_refit(_ridge, stuck, None, None, None, np.random.default_rng(0)) is stuck


def test_the_sampled_beat_prior_has_the_runs_moments_in_log_space():
    """The refinement's prior from an MCMC run: mean and covariance of the samples in the
    refinement's parametrisation (log f_c, log f_r, A_r linear), whatever the natural scale."""
    from types import SimpleNamespace

    from bayes_tfcrds.fit.refine import to_sample
    from bayes_tfcrds.physics.transfer_function import TFParams
    from bayes_tfcrds.uncertainty import posterior_steps as ps

    names = ("f_c_hz", "a_r", "f_r_hz")
    mean = np.array([np.log(3e6), 37.0, np.log(3e8)])  # the out-of-band region of campaign 99
    cov = np.array([[0.01, 0.02, 0.0], [0.02, 0.8, 0.5], [0.0, 0.5, 1.5]])
    phi = np.random.default_rng(3).multivariate_normal(mean, cov, size=40000)
    nat = {"f_c_hz": np.exp(phi[:, 0]), "a_r": phi[:, 1], "f_r_hz": np.exp(phi[:, 2])}
    post = SimpleNamespace(free=names, to_params=lambda x: nat)
    prior = ps.sampled_beat_prior(post, SimpleNamespace(flat=lambda: None))
    assert prior.names == names and "MCMC" in prior.source
    start = TFParams(**dict(zip(names, prior.mean)), gamma_r=0.5)
    mu, info, beta, others = prior.conditional(names, start)
    assert others == () and beta.shape == (3, 0)
    # 40000 draws: each mean within 4 s.e. (sd / 200) of the generating one, and the covariance
    # within 5 % (the s.e. of a variance is sqrt(2 / n) = 0.7 %)
    assert np.all(np.abs(mu - mean) < 4 * np.sqrt(np.diag(cov)) / 200)
    np.testing.assert_allclose(to_sample(names, prior.mean), mu)
    np.testing.assert_allclose(np.linalg.inv(info), cov, rtol=0.05, atol=0.005)


def test_a_refinement_that_reaches_no_draw_is_linearised_again_where_the_posterior_is(
    monkeypatch,
):
    """Campaign 99 of studies/coverage.toml: the beat-note MCMC holds its mass where the
    least-squares optimum is not, and linear about the optimum every joint draw leaves the
    support. The update is made again about the run's moments, and the result says so; without
    a run (Laplace) there is nothing else to linearise about, and the reason stands."""
    from types import SimpleNamespace

    from bayes_tfcrds.fit.h_calibration import AnalysisError
    from bayes_tfcrds.physics.transfer_function import TFParams
    from bayes_tfcrds.uncertainty import posterior_steps as ps

    names = ("f_c_hz", "a_r")
    lsq = TFParams(f_c_hz=2.9e6, a_r=0.026, f_r_hz=4e5, gamma_r=0.2)
    samples = np.column_stack([np.full(500, 3e6), np.random.default_rng(0).normal(37, 1, 500)])
    run = SimpleNamespace(passed=True, flat=lambda: samples)
    post = SimpleNamespace(
        free=names, sample_names=names, to_params=lambda x: dict(zip(names, x.T))
    )
    beat = SimpleNamespace(params=lsq, free=names)
    monkeypatch.setattr(ps, "_beat_posterior", lambda *a: (beat, post, None, None))
    monkeypatch.setattr(ps, "h_predictions", lambda *a: (None, ()))
    monkeypatch.setattr(ps, "_sample", lambda *a, **k: run)
    priors_seen = []

    def update(config, options, beat, free, sens_names=(), noise_v=None, prior=None):
        priors_seen.append(prior)
        start = lsq if prior is None else TFParams(**dict(zip(names, prior.mean)), f_r_hz=3e8)
        refined = SimpleNamespace(params=start, free=free, information_ratio=dict, prior=prior)
        return replace_ns(refined, in_tension=False, tension_chi2=(0.1, 1, 0.75)), None

    def joint(beat, post, run, refined, options, rng):
        if refined.params.a_r < 1:  # linear about the optimum: nothing inside the support
            raise AnalysisError("8000 of 8000 joint draws outside the prior's support")
        return samples, samples, SimpleNamespace(passed=True)

    monkeypatch.setattr(ps, "ring_down_update", update)
    monkeypatch.setattr(ps, "_joint_draws", joint)
    monkeypatch.setattr(ps, "posterior_centre", lambda params, draws, names: params)
    options = BudgetOptions()
    config = SimpleNamespace(ringdowns=None)
    out = ps.h_posterior(config, options, np.random.default_rng(1), None, False)
    assert priors_seen[0] is None and "MCMC" in priors_seen[1].source
    assert abs(priors_seen[1].mean[1] - 37) < 4 * 1 / np.sqrt(500)  # the run's mean A_r
    assert out[1].prior is priors_seen[1]  # the refinement returned (budget.json reads its source)
    # the Laplace path has no sampled posterior: the support error is what it reports
    with pytest.raises(AnalysisError, match="outside the prior's support"):
        ps.h_posterior(config, replace(options, posterior="laplace"), None, None, False)


def replace_ns(ns, **kw):
    """A SimpleNamespace with more attributes (a refinement's tension, for the fakes above)."""
    from types import SimpleNamespace

    return SimpleNamespace(**{**vars(ns), **kw})


def test_mode_covariance_is_positive_definite_when_its_correlation_is_singular_to_rounding():
    """A correlation matrix of a plateau (two directions for five parameters) with eigenvalues
    of -1e-13 where rounding put them (campaign 18: -3e-15), rescaled to very different sd, is
    lifted to positive definite, unit diagonal kept to 1e-9 (the jitter); a positive-definite
    one comes back bit for bit as before the repair existed."""
    from bayes_tfcrds.uncertainty.posterior_steps import _positive_definite

    rng = np.random.default_rng(2)
    sd = np.array([5.8, 491.0, 5.8, 3.5, 2.9e-4])
    for _ in range(50):
        vec, _ = np.linalg.qr(rng.standard_normal((5, 5)))
        val = np.array([-1e-13, -1e-13, -1e-13, 2.0, 3.0])
        c = (vec * val) @ vec.T
        corr = c / np.sqrt(np.outer(np.diag(c), np.diag(c)))
        with pytest.raises(np.linalg.LinAlgError):  # the plain matrix fails Cholesky
            np.linalg.cholesky(corr * np.outer(sd, sd) + np.diag((1e-9 * sd) ** 2))
        cov = _positive_definite(corr, sd)
        np.linalg.cholesky(0.5 * (cov + cov.T))  # raises if not positive definite
        np.testing.assert_allclose(np.sqrt(np.diag(cov)), sd, rtol=1e-9)
    good = np.array([[1.0, 0.3], [0.3, 1.0]])
    s2 = np.array([2.0, 5.0])
    assert np.array_equal(
        _positive_definite(good, s2), good * np.outer(s2, s2) + np.diag((1e-9 * s2) ** 2)
    )
