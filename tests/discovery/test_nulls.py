"""Bootstrap nulls of the discovery's gap metrics, and the model they resample from.

Oracles: an AR(1) process of known coefficient (the noise model must find it, and nothing on
white noise); the simulator's own transients (the forward model of a fit must reproduce the
recorded voltage to the noise); the chi2 of a correct linear-in-most-parameters fit, whose null
z is N(0, 1) analytically (the bootstrap must find location 0 and scale 1 there).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy import signal

from bayes_tfcrds.discovery.nulls import NoiseModel, gap_nulls, pre_extinction_noise
from bayes_tfcrds.discovery.workflow import ExperimentModel, ModelState, evaluate, step_alpha
from bayes_tfcrds.fit.extensions import TransientSpec, fit_transient_rows
from bayes_tfcrds.fit.transient_model import model_transients
from bayes_tfcrds.simulate.campaign import Campaign, simulate_campaign
from tests.discovery.campaigns import letter_d2_with_chain

CAMPAIGN = replace(Campaign(), n_points=21, n_samples=4096)


def _records(noise, n_rows=40, n_pre=200, n=600):
    """Ring-down-like records: a constant level before extinction, then an exponential."""
    from bayes_tfcrds.bundle.records import RingdownData

    t = -n_pre * 2e-8 + 2e-8 * np.arange(n)
    clean = 0.5 * np.where(t < 0, 1.0, np.exp(-np.clip(t, 0, None) / 5e-6))
    sig = clean[None, :] + 1e-3 * noise
    return RingdownData(
        nu_hz=np.linspace(1e14, 1.0001e14, n_rows),
        signal_v=sig,
        dt_s=2e-8,
        t0_s=float(t[0]),
        noise_v=np.full(n_rows, 1e-3),
    )


def test_noise_model_finds_an_ar1_colour_and_nothing_on_white_noise():
    rng = np.random.default_rng(3)
    white = rng.standard_normal((40, 600))
    assert pre_extinction_noise(_records(white)).phi.size == 0  # BIC keeps order 0
    ar = signal.lfilter([1.0], [1.0, -0.5], rng.standard_normal((40, 800)), axis=-1)[:, 200:]
    phi = pre_extinction_noise(_records(ar)).phi
    # 40 x 200 pre-extinction samples: the lag-1 coefficient is known to 1/sqrt(8000) ~ 0.011;
    # 0.05 is 4.5 of those
    assert phi.size >= 1 and abs(phi[0] - 0.5) < 0.05, phi
    # the draws have unit variance and the fitted lag-1 autocorrelation
    x = NoiseModel(np.array([0.5])).draw((200, 2000), np.random.default_rng(4))
    assert abs(x.var() - 1.0) < 0.02  # 4e5 samples of an AR(1): sd of the variance ~ 0.004
    r1 = np.mean(x[:, 1:] * x[:, :-1])
    assert abs(r1 - 0.5) < 0.01, r1  # the lag-1 autocorrelation of AR(1) is phi


@pytest.mark.parametrize(
    "effects,shared",
    [
        ({}, {}),
        (
            {"static_nonlinearity": {}, "baseline_drift": {}},
            {"static_nonlinearity": {"beta": -2e-3}, "baseline_drift": {"slope_v_per_s": 2.0}},
        ),
    ],
)
def test_forward_model_reproduces_the_recorded_transients(effects, shared):
    bundle, _ = simulate_campaign(
        ["letter-D2"], np.random.default_rng(5), CAMPAIGN, effects, line_effects_default=False
    )
    rd = bundle.configs["D2"].ringdowns
    rows = np.arange(rd.n_points)
    spec = TransientSpec(shared=shared)  # the simulator's own nonlinearity and drift
    res = fit_transient_rows(rd, np.full(rows.size, 2e-6), rows, spec)
    v, mask = model_transients(rd.time_s, 2e-6, spec, res.tau_s, res.coef)
    z = ((rd.signal_v - v) / rd.noise_v[:, None])[mask]
    # data minus the model run forward is the recorded noise: sd 1 to its sampling error
    # (~8e4 samples: 0.3 %), mean 0; the nonlinearity run the wrong way leaves 5 sigma per sample
    assert abs(z.std() - 1.0) < 0.02 and abs(z.mean()) < 0.02, (z.std(), z.mean())


def test_forward_model_of_the_higher_family_members():
    # a cubic detector and a quadratic drift written here, applied to a clean simulated record
    bundle, _ = simulate_campaign(
        ["letter-D2"], np.random.default_rng(6), CAMPAIGN, {}, line_effects_default=False
    )
    rd = bundle.configs["D2"].ringdowns
    t = rd.time_s
    beta, gamma, slope, curv = -2e-3, 4e-3, 2.0, 3e4
    v = rd.signal_v + slope * (t - t[0]) + curv * (t - t[0]) ** 2
    rd = replace(rd, signal_v=v + beta * v**2 + gamma * v**3)
    shared = {
        "static_nonlinearity": {"beta": beta, "gamma": gamma},
        "baseline_drift": {"slope_v_per_s": slope, "curvature_v_per_s2": curv},
    }
    spec = TransientSpec(shared=shared)
    rows = np.arange(rd.n_points)
    res = fit_transient_rows(rd, np.full(rows.size, 2e-6), rows, spec)
    model, mask = model_transients(t, 2e-6, spec, res.tau_s, res.coef)
    z = ((rd.signal_v - model) / rd.noise_v[:, None])[mask]
    # the recorded noise passes the cubic with slope ~1.000 (2 beta V + 3 gamma V^2 ~ 2e-3): sd
    # 1 to 2 %; the cubic term left out leaves 4e-3 x 0.6^3 V ~ 7 noise sd per sample
    assert abs(z.std() - 1.0) < 0.02 and abs(z.mean()) < 0.02, (z.std(), z.mean())


def test_bootstrap_finds_the_analytic_null_where_it_is_exact():
    bundle, _ = simulate_campaign(
        ["letter-D2"], np.random.default_rng(12), CAMPAIGN, {}, line_effects_default=False
    )
    config = bundle.configs["D2"]
    ev = evaluate(bundle, config, ModelState(ExperimentModel()))
    nulls = gap_nulls(bundle, config, ev, evaluate, np.random.default_rng(1), n_boot=40)
    chi2 = nulls["transient_chi2"]
    # white noise and a correct model: z = (chi2 - dof)/sqrt(2 dof) is N(0, 1). With 40
    # replicates the mean is known to 0.16 and the sd to 11 %: 3-sigma allowances
    assert abs(chi2.location) < 0.5, chi2.location
    assert 0.66 < np.std(chi2.replicates, ddof=1) < 1.34
    # the bootstrap's decay times come from the fitted line, so the spectrum's chi2 is that of a
    # correct model too: mean z 0 (E chi2 = dof), known to ~0.17 (with the line's residuals added
    # twice instead of removed, the location was 9)
    assert abs(nulls["spectrum_chi2"].location) < 0.6, nulls["spectrum_chi2"].location
    # the metrics that are not resampled keep their analytic null
    assert (
        not nulls["crds_cmds"].resampled and nulls["crds_cmds"].z_cal == ev.gaps["crds_cmds"]["z"]
    )
    # nothing is missing from the model, so every calibrated z is a draw of about N(0, 1)
    # (|z| < 4: one false failure in ~15000 per metric)
    assert all(abs(g.z_cal) < 4 for g in nulls.values()), {k: g.z_cal for k, g in nulls.items()}


def test_alpha_spending_sums_to_at_most_alpha():
    levels = [step_alpha(0.05, s) for s in range(1, 40)]
    assert sum(levels) <= 0.05 and levels[0] == 0.025 and all(np.diff(levels) < 0)


def test_bootstrap_analyses_each_replicate_with_an_h_drawn_from_its_uncertainty():
    from bayes_tfcrds.discovery.nulls import h_drawn_state
    from bayes_tfcrds.discovery.workflow import _start_state
    from bayes_tfcrds.physics.transfer_function import outside_support

    bundle = letter_d2_with_chain(8)
    cfg = bundle.configs["D2"]
    plain = ModelState(ExperimentModel())
    assert h_drawn_state(plain, np.random.default_rng(0)) is plain  # no H, nothing to draw
    state = _start_state(bundle, cfg, "transfer_function,window_history", (2e-6, 4e-6, 6e-6))
    cal = state.calibration
    rng = np.random.default_rng(1)
    draws = [h_drawn_state(state, rng).calibration for _ in range(400)]
    # the draws follow H's joint law (Calibration.covariance): the beat-note parameters the beat
    # fit's covariance, the refined ones that given the drawn others plus how they follow them.
    # 400 draws give each sd to 1/sqrt(800) = 3.5 %, so 15 % is 4 of those; a correlation to
    # (1 - rho^2)/sqrt(400) <= 0.05, so 0.2 is 4 of those
    names, cov = cal.covariance()
    assert cal.refined is not None and len(names) > len(cal.refined.free)  # something to follow
    x = np.array([[getattr(d.params, n) for n in names] for d in draws])
    sd = np.sqrt(np.diag(cov))
    for i, name in enumerate(names):
        assert abs(x[:, i].std() / sd[i] - 1) < 0.15, (name, x[:, i].std(), sd[i])
        assert abs(x[:, i].mean() - getattr(cal.params, name)) < 4 * sd[i] / np.sqrt(400), name
        assert not any(outside_support(d.params, [name]) for d in draws)
    rho, rho_x = cov / np.outer(sd, sd), np.corrcoef(x.T)
    for i, _ in enumerate(cal.refined.free):
        for j in range(len(cal.refined.free), len(names)):
            assert abs(rho_x[i, j] - rho[i, j]) < 0.2, (names[i], names[j], rho_x[i, j], rho[i, j])
    # something is correlated, or the check above could not fail
    assert np.abs(rho[: len(cal.refined.free), len(cal.refined.free) :]).max() > 0.3
    # the data's own analysis keeps its H: drawing never changes the state it was given
    assert state.calibration is cal
