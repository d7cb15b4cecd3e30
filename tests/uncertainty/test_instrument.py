"""Instrument rows of the A budget: sized from the data, checked on simulated truth."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from bayes_tfcrds.fit.line_analysis import doppler_of
from bayes_tfcrds.fit.ringdown import fit_ringdowns
from bayes_tfcrds.fit.spectrum import crds_spectrum
from bayes_tfcrds.simulate.campaign import Campaign, simulate_campaign
from bayes_tfcrds.uncertainty.instrument import (
    CMDS_SPREAD_REL,
    bic_weight,
    cmds_type_b,
    nonlinearity_row,
    spectrum_extension_row,
)

T_CUT = 2e-6


def _campaign(effects, seed, n_points=15):
    """An ideal chain and a Voigt line (CRDS is exact) with only ``effects`` switched on."""
    rng = np.random.default_rng(seed)
    camp = replace(Campaign(), n_points=n_points)
    bundle, _ = simulate_campaign(["letter-D1"], rng, camp, effects, line_effects_default=False)
    return bundle, bundle.configs["D1"]


def _row(effects, seed):
    bundle, cfg = _campaign(effects, seed)
    rd = cfg.ringdowns
    return nonlinearity_row(
        rd, T_CUT, "crds", None, None, "voigt", doppler_of(bundle.sample), bundle.sample.nu0_hz
    )


@pytest.mark.parametrize("beta_true", [-2e-3, 1.5e-3])
def test_nonlinearity_row_recovers_the_simulated_beta(beta_true):
    """The fitted beta agrees with the simulator's within 4 u(beta) (Gaussian estimate: a false
    failure once in 1.6e4), its sign included, and the data flag it as a finding."""
    row = _row({"static_nonlinearity": {"beta": beta_true}}, seed=11)
    d = row.detail
    assert abs(d["beta"] - beta_true) < 4 * d["u_beta"]
    assert abs(beta_true) > 3 * d["u_beta"]  # the test campaign resolves this beta
    assert row.finding is not None
    assert row.component.u > 0


def test_nonlinearity_row_on_a_linear_detector_is_bounded_by_u_beta():
    """No nonlinearity simulated: beta is consistent with 0 (4 u), there is no finding, and the
    row is far smaller than with the letter-sized beta = -2e-3 on the same noise."""
    clean = _row({}, seed=12)
    bent = _row({"static_nonlinearity": {"beta": -2e-3}}, seed=12)
    assert abs(clean.detail["beta"]) < 4 * clean.detail["u_beta"]
    assert clean.finding is None
    assert clean.component.u < 0.5 * bent.component.u


def _spectrum(effects, seed):
    bundle, cfg = _campaign(effects, seed, n_points=31)
    fits = fit_ringdowns(cfg.ringdowns, [T_CUT], method="crds")
    spec = crds_spectrum(fits.nu_hz, fits.tau_s[:, 0], fits.tau_u_s[:, 0])
    return spec, doppler_of(bundle.sample), bundle.sample.nu0_hz


def test_etalon_row_sees_a_simulated_etalon():
    """A 5e-7 /m etalon (about 10 times the alpha noise of this campaign): the extended fit is
    preferred with weight ~1 and the row is the whole change of A."""
    effects = {"etalon": {"amplitude_per_m": 5e-7, "period_hz": 3.1e9, "phase_rad": 0.7}}
    spec, gd, nu_ref = _spectrum(effects, seed=3)
    row = spectrum_extension_row(spec, "voigt", gd, nu_ref, "etalon", "etalon")
    assert row.detail["weight_extended"] > 0.99
    assert row.component.u == pytest.approx(abs(row.detail["delta_a_hz_per_m"]), rel=0.01)


def test_baseline_slope_row_is_small_without_a_slope():
    """No slope simulated: the slope's BIC weight stays below 1/2 unless the noise mimics one, and
    the row is below A's fit u (a slope is odd about the line centre, nearly orthogonal to A)."""
    spec, gd, nu_ref = _spectrum({}, seed=4)
    row = spectrum_extension_row(spec, "voigt", gd, nu_ref, "baseline_slope", "baseline slope")
    assert row.component.u < row.detail["u_a_fit_hz_per_m"]
    assert row.finding is None


def test_bic_weight_limits():
    """Equal fit with 3 more parameters on 100 points: w = 1/(1 + 100^(3/2)) exactly; a chi2 drop
    far beyond the penalty gives w -> 1; swapping the two models gives 1 - w."""
    assert bic_weight(50.0, 5, 50.0, 8, 100) == pytest.approx(1 / (1 + 100**1.5), rel=1e-12)
    assert bic_weight(500.0, 5, 50.0, 8, 100) > 1 - 1e-12
    w = bic_weight(60.0, 5, 45.0, 8, 100)
    assert bic_weight(45.0, 8, 60.0, 5, 100) == pytest.approx(1 - w, rel=1e-12)


def test_cmds_type_b_is_the_letters_spread_as_a_rectangle():
    """u = A_ref x 0.06 % / (2 sqrt 3) (full width 0.06 %), sensitivity -r/A_ref of A/A_ref."""
    c = cmds_type_b(4.0e5, 0.999)
    assert CMDS_SPREAD_REL == 6e-4
    assert c.u == pytest.approx(4.0e5 * 3e-4 / np.sqrt(3), rel=1e-12)
    assert c.sensitivity == pytest.approx(-0.999 / 4.0e5, rel=1e-12)


@pytest.mark.parametrize(("beta_true", "seed"), [(0.0, 21), (-2e-3, 22), (8e-4, 23)])
def test_beta_newton_agrees_with_the_bounded_search(beta_true, seed):
    """The row's Newton steps reach the minimum discovery's bounded search finds: beta within
    0.01 u(beta) (the search's own tolerance, 1e-3 of a 5 % window about beta, is of that order;
    Newton's error after a step of 0.5 u is about 2e-3 u) and the same u(beta) within 2 % (two
    second differences of one chi2, steps u and 1e-3 beta)."""
    from bayes_tfcrds.fit.extensions import TransientSpec, fit_transient_rows, optimise_shared
    from bayes_tfcrds.uncertainty.instrument import _beta_by_newton

    effects = {"static_nonlinearity": {"beta": beta_true}} if beta_true else {}
    _, cfg = _campaign(effects, seed)
    rd = cfg.ringdowns
    rows = np.arange(rd.n_points)
    t_rows = np.full(rows.size, T_CUT)
    base = TransientSpec("crds")
    tau0 = fit_transient_rows(rd, t_rows, rows, base).tau_s
    beta, u_beta = _beta_by_newton(rd, t_rows, rows, base, tau0)
    params, _, cov = optimise_shared("static_nonlinearity", rd, t_rows, rows, base, tau0)
    assert abs(beta - params["beta"]) < 0.01 * u_beta
    assert u_beta == pytest.approx(np.sqrt(cov[0, 0]), rel=0.02)


def test_nonlinearity_row_falls_back_to_the_bounded_search(monkeypatch):
    """Where Newton gives up (chi2 not convex at a step), the row comes from discovery's bounded
    search and still recovers the simulated beta within 4 u(beta)."""
    import bayes_tfcrds.uncertainty.instrument as instrument

    monkeypatch.setattr(instrument, "_beta_by_newton", lambda *a: None)
    row = _row({"static_nonlinearity": {"beta": -2e-3}}, seed=11)
    assert abs(row.detail["beta"] + 2e-3) < 4 * row.detail["u_beta"]
    assert row.finding is not None
