"""The weight of the n_r-free form of Eq. 2 from all the data (Laplace evidence of nested forms)."""

from types import SimpleNamespace

import numpy as np
import pytest
from scipy import integrate, stats

from bayes_tfcrds.fit.h_calibration import free_order_weight
from bayes_tfcrds.physics.transfer_function import SUPPORT


def _forms_and_updates(n_hat, s, w=0.2, chi2_beat_2=60.0, d_beat=-1.0, prior_2=0.7):
    """Stand-ins for a Gaussian likelihood of n_r (mean n_hat, sd s) in the free form.

    The free form's -2 ln L at its optimum is lower than the n_r = 2 form's by
    ((2 - n_hat)/s)^2, split between the beat note, the ring-downs (times w) and the prior term.
    """
    delta = -(((2.0 - n_hat) / s) ** 2)
    d_rd = (delta - d_beat) / 2.0  # half from the ring-downs' weighted chi2, half from the prior
    forms = SimpleNamespace(free_fit=SimpleNamespace(chi2=chi2_beat_2 + d_beat))
    beat_2 = SimpleNamespace(chi2=chi2_beat_2)
    r_2 = SimpleNamespace(weight=w, chi2=1000.0, prior_chi2=prior_2)
    r_f = SimpleNamespace(
        weight=w * 1.07,  # the form's own adjustment differs a little: it must not be used
        chi2=1000.0 + d_rd / w,
        prior_chi2=prior_2 + d_rd,
        free=("f_c_hz", "n_r"),
        cov=np.diag([1.0, s**2]),
    )
    return forms, beat_2, r_2, r_f


@pytest.mark.parametrize("n_hat,s", [(2.0, 0.01), (1.97, 0.01), (1.7, 0.05), (1.9, 0.1)])
def test_weight_is_the_exact_posterior_probability_for_a_gaussian_likelihood(n_hat, s):
    """Against the Bayes factor integrated numerically: n_r uniform over SUPPORT, L Gaussian."""
    lo, hi = SUPPORT["n_r"]
    like = lambda n: stats.norm.pdf(n, n_hat, s) / stats.norm.pdf(2.0, n_hat, s)  # noqa: E731
    z_free = integrate.quad(like, lo, hi, points=[n_hat], epsabs=0, epsrel=1e-10)[0] / (hi - lo)
    exact = z_free / (1.0 + z_free)  # equal prior odds; Z_2 = L(2) = 1 in these units
    got = free_order_weight(*_forms_and_updates(n_hat, s))
    # Laplace is exact for a Gaussian likelihood inside the prior range (these all are, to 1e-6)
    assert got == pytest.approx(exact, rel=1e-6, abs=1e-12)


def test_weight_grows_as_the_data_move_n_r_away_from_2():
    """Flip the sign of the likelihood difference and the weight must fall, not rise."""
    w = [free_order_weight(*_forms_and_updates(n, 0.01)) for n in (2.0, 1.99, 1.98, 1.95)]
    assert np.all(np.diff(w) > 0) and w[0] < 0.05 and w[-1] > 0.999


def test_two_updates_compared_share_the_records_noise_when_the_bundle_has_none():
    """Without noise_v each update estimates the noise at its own start: the second must take
    the first's, or the two chi2 are in different units (the form weight compares them)."""
    from dataclasses import replace

    from bayes_tfcrds.fit.h_calibration import BEAT_FREE, beat_note_fit, refine_on_records
    from bayes_tfcrds.fit.refine import HPrior
    from bayes_tfcrds.simulate.campaign import Campaign, simulate_campaign

    bundle, _ = simulate_campaign(
        ["letter-D2"], np.random.default_rng(4), replace(Campaign(), n_points=9)
    )
    config = bundle.configs["D2"]
    noisy = np.asarray(config.ringdowns.noise_v)
    config = replace(config, ringdowns=replace(config.ringdowns, noise_v=None))
    beat = beat_note_fit(config, free=BEAT_FREE)
    args = (("f_c_hz",), "extinction", (2e-6, 4e-6, 6e-6), 3, HPrior.from_beat(beat))
    first, idx = refine_on_records(config, beat.params, *args)
    start = replace(beat.params, f_c_hz=1.01 * beat.params.f_c_hz)  # another start
    second, _ = refine_on_records(config, start, *args, noise_v=first.noise_v)
    np.testing.assert_array_equal(second.noise_v, first.noise_v)
    # the estimate is the records' noise: within 10 % (several thousand samples per record)
    np.testing.assert_allclose(first.noise_v, noisy[idx], rtol=0.1)
