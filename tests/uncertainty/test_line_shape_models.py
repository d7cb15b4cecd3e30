"""Line-shape model uncertainty: candidate profiles weighted by pseudo-BMA+ (Akaike) weights.

Spectra are synthesised here from the profiles themselves (alpha = A Re g + loss, the CRDS
absorption spectrum), so the true A is known; the arithmetic of the average is checked against
closed forms it does not share code with.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from bayes_tfcrds.fit.line import fit_line
from bayes_tfcrds.fit.spectrum import SpectrumData
from bayes_tfcrds.physics.lineshape import profile
from bayes_tfcrds.uncertainty.line_shape_models import (
    average_candidates,
    bb_pseudo_bma_weights,
    fit_candidates,
    model_average,
)

GD = 2.238e8  # Doppler HWHM of CO (3-0) R(23) at 296 K, Hz
NU0 = 1.9219333406e14  # Hz
A_TRUE = 3.9415e5  # line area, Hz/m (the letter's D4)
LOSS = 2e-4  # empty-cavity loss, 1/m
# qSDHCP rates in GammaD: a mixed Doppler/collision regime where speed dependence and Dicke
# narrowing are both resolved at a 1e-3 signal-to-noise ratio
SHAPE = dict(gamma0_hz=0.3 * GD, gamma2_hz=0.06 * GD, delta0_hz=-0.01 * GD, nu_vc_hz=0.15 * GD)


def _spectrum(name, shape, rel_noise, rng=None, n=61):
    """CRDS absorption spectrum (1/m) over +-5 GammaD; noise-free (expected data) without rng."""
    nu = NU0 + np.linspace(-5.0, 5.0, n) * GD
    g = profile(name, nu - NU0, 0.0, GD, **shape).real
    u = np.full(n, rel_noise * A_TRUE * g.max())
    y = A_TRUE * g + LOSS
    if rng is not None:
        y = y + rng.normal(0.0, u)
    return SpectrumData("absorption", nu, y, u)


def test_two_models_of_equal_evidence_average_to_the_midpoint():
    # identical pointwise elpd -> every bootstrap draw gives 1/2 each; A_bar = (A1 + A2)/2 and the
    # between-model sd is |A1 - A2|/2
    elpd = np.random.default_rng(0).normal(-1.0, 0.5, size=40)
    w = bb_pseudo_bma_weights([elpd, elpd], np.random.default_rng(1))
    np.testing.assert_allclose(w, [0.5, 0.5], rtol=1e-15)
    a_bar, sd = model_average([3.0, 7.0], w)
    assert a_bar == pytest.approx(5.0, rel=1e-15)
    assert sd == pytest.approx(2.0, rel=1e-15)


def test_a_uniform_elpd_offset_gives_the_akaike_weight_ratio():
    # elpd lower by c at every one of n points: n sum_i alpha_i c = n c in every bootstrap draw
    # (the Dirichlet weights sum to 1), so the weight ratio is exp(n c) exactly: ln 3 in total
    n = 25
    base = np.random.default_rng(2).normal(-1.0, 0.5, size=n)
    w = bb_pseudo_bma_weights([base, base - np.log(3.0) / n], np.random.default_rng(3))
    assert w.sum() == pytest.approx(1.0, abs=1e-15)
    assert w[0] / w[1] == pytest.approx(3.0, rel=1e-12)
    # a model with an undefined point (failed fit) gets exactly 0
    w = bb_pseudo_bma_weights([base, np.full(n, -np.inf)], np.random.default_rng(3))
    assert list(w) == [1.0, 0.0]


def test_between_model_variance_is_the_law_of_total_variance():
    # sum w (A - A_bar)^2 = sum w A^2 - A_bar^2 (the second form shares no code with the first);
    # a sign flip (A + A_bar) or a missing square root breaks it
    a = np.array([10.0, 11.0, 13.5, 9.0])
    w = np.array([0.4, 0.3, 0.2, 0.1])
    a_bar, sd = model_average(a, w)
    assert a_bar == pytest.approx(np.dot(w, a), rel=1e-15)
    assert sd**2 == pytest.approx(np.dot(w, a**2) - a_bar**2, rel=1e-12)
    with pytest.raises(ValueError, match="sum to 1"):
        model_average(a, [0.5, 0.5, 0.5, 0.5])


def test_on_a_qsdhcp_spectrum_sdvp_gets_no_weight_and_the_model_row_is_small():
    """The simulator's profile: the candidates that contain it (qSDHCP, HTP, HTP + Delta2) share
    the weight, the ones that cannot represent Dicke narrowing and speed dependence together
    (SDVP, Rautian, Voigt: chi2_red 2.7, 1.5, 170 against 0.74) get ~none, and the between-model
    sd is a fraction of the fit's own u(A) (the HTPs differ from the qSDHCP only through the
    poorly determined eta)."""
    spec = _spectrum("qsdhcp", SHAPE, 1e-3, np.random.default_rng(1))
    avg = average_candidates(fit_candidates(spec, GD, NU0), np.random.default_rng(5))
    w = avg.weights
    assert sum(w.values()) == pytest.approx(1.0, abs=1e-12)
    assert w["sdvp"] < 1e-6 and w["voigt"] < 1e-6, w  # delta chi2 ~110 and ~1e4
    # Rautian misses by delta chi2 = 46 (23 nats): the bootstrap spread of that difference
    # leaves it ~1e-3
    assert w["rautian"] < 1e-2, w
    assert w["qsdhcp"] > 0.5  # the simplest of the nested profiles that fit (AIC penalty)
    u_fit = avg.candidates[0].fit.line_area_u
    assert avg.u_between < 0.5 * u_fit
    # the average stays on the truth within the fit u (3 sigma)
    assert abs(avg.line_area - A_TRUE) < 3 * np.hypot(u_fit, avg.u_between)
    # what the old row would have been: |A(qSDHCP) - A(SDVP)|/sqrt(12) is 3x the fit's u here
    sdvp = next(c for c in avg.candidates if c.candidate.label == "sdvp")
    assert abs(sdvp.line_area - avg.candidates[0].line_area) / np.sqrt(12) > 2 * u_fit


def test_two_profiles_that_fit_equally_share_the_weight_and_their_spread_covers_the_truth():
    """Expected (noise-free) spectrum of an HTP line with eta = 0.2: neither SDVP (speed
    dependence only) nor Rautian (Dicke narrowing only) can represent it, but at this SNR both
    fit it about equally (chi2 9.1 and 9.3 over 61 points). SDVP puts A 2.7 u above the truth,
    Rautian 3.9 u below: neither alone covers it, their average with the between-model sd does."""
    shape = {**SHAPE, "nu_vc_hz": 0.1 * GD, "eta": 0.2}
    spec = _spectrum("htp", shape, 2e-3)
    fits = fit_candidates(spec, GD, NU0, labels=("sdvp", "rautian", "voigt"))
    avg = average_candidates(fits, np.random.default_rng(6))
    sdvp, rautian, voigt = avg.candidates
    assert sdvp.weight + rautian.weight + voigt.weight == pytest.approx(1.0, abs=1e-12)
    assert voigt.weight < 1e-6  # no narrowing at all: rejected
    # delta AIC = delta chi2 = 0.2 -> Akaike weights 0.53/0.47; the bootstrap spreads them about
    # that; 0.3 leaves room for it
    assert sdvp.weight > 0.3 and rautian.weight > 0.3
    u_fit = max(sdvp.fit.line_area_u, rautian.fit.line_area_u)
    for c in (sdvp, rautian):
        assert abs(c.line_area - A_TRUE) > 2 * c.fit.line_area_u  # each alone misses the truth
    # two models (Voigt's weight ~0): the between-model sd is sqrt(w1 w2) |A1 - A2| (closed form)
    expected = np.sqrt(sdvp.weight * rautian.weight) * abs(sdvp.line_area - rautian.line_area)
    assert avg.u_between == pytest.approx(expected, rel=1e-6)
    assert avg.u_between > u_fit
    assert abs(avg.line_area - A_TRUE) < 2 * np.hypot(u_fit, avg.u_between)


def test_the_average_covers_a_truth_no_candidate_represents_over_noise_realisations():
    """20 noisy spectra of the HTP line above (SNR 3e-3): A_bar +/- 2 sqrt(u_fit^2 + u_between^2)
    covers the true A in at least 16 (19 measured; 16 is the 1.6 % binomial quantile of 20
    draws at 95 %). Plain Akaike weights (no bootstrap) cover it in 15: they swing to 0.99/0.01
    with the noise and drop the between-model spread."""
    shape = {**SHAPE, "nu_vc_hz": 0.1 * GD, "eta": 0.2}
    covered = 0
    for seed in range(1, 21):
        spec = _spectrum("htp", shape, 3e-3, np.random.default_rng(seed))
        fits = fit_candidates(spec, GD, NU0, labels=("sdvp", "rautian", "voigt"))
        avg = average_candidates(fits, np.random.default_rng(seed))
        u = np.hypot(fits[0].fit.line_area_u, avg.u_between)
        covered += abs(avg.line_area - A_TRUE) < 2 * u
    assert covered >= 16, covered


def test_a_failed_candidate_gets_no_weight():
    # a fit without finite chi2, or none at all (the search went where the profile is undefined):
    # the record says which failed and why; the average ignores its A instead of returning NaN
    from bayes_tfcrds.uncertainty.line_shape_models import CANDIDATES, CandidateFit
    from bayes_tfcrds.uncertainty.outputs import line_shape_markdown

    spec = _spectrum("qsdhcp", SHAPE, 1e-3, np.random.default_rng(2))
    fits = fit_candidates(spec, GD, NU0, labels=("qsdhcp", "sdvp"))
    broken = fits[1].fit.__class__(**{**fits[1].fit.__dict__, "chi2": float("nan")})
    fits[1] = CandidateFit(fits[1].candidate, broken)
    fits.append(CandidateFit(CANDIDATES["htp+delta2"], None, error="fit failed: NaN Jacobian"))
    # a fit that ended next to where its profile is undefined: chi2 and A finite, its covariance
    # (and what H does to its A) not
    htp = fit_candidates(spec, GD, NU0, labels=("htp",))[0].fit
    nan_cov = htp.__class__(**{**htp.__dict__, "cov": np.full_like(htp.cov, np.nan)})
    fits.append(CandidateFit(CANDIDATES["htp"], nan_cov))
    assert fits[-1].failed
    avg = average_candidates(fits, np.random.default_rng(7))
    assert avg.weights == {"qsdhcp": 1.0, "sdvp": 0.0, "htp+delta2": 0.0, "htp": 0.0}
    assert avg.line_area == fits[0].line_area and avg.u_between == 0.0
    rec = avg.to_dict()
    assert [c["failed"] for c in rec["candidates"]] == [False, True, True, True]
    assert rec["candidates"][2]["error"] == "fit failed: NaN Jacobian"
    assert rec["candidates"][1]["aic"] is None and rec["candidates"][2]["chi2_red"] is None
    md = line_shape_markdown({**rec, "line_area_of_profile": rec["line_area"]})
    assert "| htp+delta2 |" in md and "fit failed" in md
    with pytest.raises(ValueError, match="galatry"):
        fit_candidates(spec, GD, NU0, labels=("galatry",))


def test_budget_line_shape_row_is_the_between_model_sd_of_the_candidates():
    """The budget's steps 2 and 7 on a simulated D4 campaign (qSDHCP line, TF-CRDS at the beat
    note's H): the candidates are fitted to the spectrum at t_cut, the row is their between-model
    sd, A moves to the model average, and budget.json/budget.md list every candidate."""
    from dataclasses import replace

    from bayes_tfcrds.simulate.campaign import Campaign, simulate_campaign
    from bayes_tfcrds.uncertainty import line_budget as lb
    from bayes_tfcrds.uncertainty.outputs import line_shape_markdown

    tiny = replace(Campaign(), n_points=21, n_samples=4096, n_avg=25)
    bundle, _ = simulate_campaign(["letter-D4"], np.random.default_rng(21), tiny)
    options = lb.BudgetOptions(posterior="laplace", t_cuts_s=(4e-6, 8e-6))
    inp = lb._inputs(bundle, bundle.configs["D4"], options, np.random.default_rng(3), None, False)
    dt = lb._decay_times(inp, inp.beat.params)
    shapes = dt.shapes
    assert [c.candidate.label for c in shapes.candidates] == list(options.shape_candidates)
    assert shapes.candidates[0].fit is dt.lsq  # the budget's own fit is reused, not refitted
    w = shapes.weights
    assert sum(w.values()) == pytest.approx(1.0, abs=1e-12)
    assert w["sdvp"] < 1e-6 and w["voigt"] < 1e-6  # chi2_red ~90 and ~1000: rejected
    u_fit = dt.lsq.line_area_u
    a_total = np.random.default_rng(4).normal(dt.lsq.line_area, u_fit, 4000)
    bud = lb._budget_a(options, dt, a_total, u_fit, ([], {}))
    row = next(c for c in bud.components if c.name.startswith("line-shape model"))
    assert row.u == shapes.u_between and row.sensitivity == 1.0
    assert row.contribution < 0.5 * u_fit  # was |A(qSDHCP) - A(SDVP)|/sqrt(12) ~ 5 u_fit
    assert bud.value == pytest.approx(np.mean(a_total) + shapes.line_area - dt.lsq.line_area)
    budget_s = lb._budget_s(inp.sample, bud.value, bud.combined_u)
    summary = lb._summary(inp, dt, bud, budget_s, None, a_total, {}, None)
    rec = summary["line_shape_models"]
    assert rec["unit"] == "cm^-2" and rec["u_between_si"] == shapes.u_between
    assert {c["label"] for c in rec["candidates"]} == set(options.shape_candidates)
    for c in rec["candidates"]:
        assert {"chi2_red", "aic", "delta_aic", "weight", "line_area"} <= set(c)
    md = line_shape_markdown(rec)
    for label in options.shape_candidates:
        assert f"| {label} |" in md
    # H reaches the reported (averaged) A through the weighted gains of the candidates
    from bayes_tfcrds.uncertainty.propagate import line_gain

    sens = lb._h_sensitivity(inp, dt, inp.beat.params)
    live = [c for c in shapes.candidates if c.weight > 0]
    gains = [line_gain(c.fit)[c.fit.names.index("line_area")] for c in live]
    expected = sum(c.weight * g for c, g in zip(live, gains)) / sum(c.weight for c in live)
    assert sens.k_gain == pytest.approx(expected, rel=1e-9)


def test_the_gain_of_the_averaged_area_predicts_the_refitted_average():
    """What H does to the decay times reaches the reported A through the gain of A_bar =
    sum_k w_k A_k, not that of one profile. Noisy Voigt spectrum, a shift of the spectrum that is
    largest at the line centre (the form an error of H takes: it moves short decay times most):
    Voigt and qSDHCP move their A differently (qSDHCP's narrowing takes up part of the shape),
    and the averaged gain predicts the refitted average of both at fixed weights."""
    from bayes_tfcrds.uncertainty.line_shape_models import ModelAverage, averaged_area_gain
    from bayes_tfcrds.uncertainty.propagate import line_gain

    spec = _spectrum("voigt", {"gamma0_hz": 0.3 * GD}, 1e-3, np.random.default_rng(5))
    fits = fit_candidates(spec, GD, NU0, labels=("voigt", "qsdhcp"))
    weighted = tuple(replace(c, weight=w) for c, w in zip(fits, (0.3, 0.7)))
    avg = ModelAverage(weighted, 0.0, 0.0)
    g = averaged_area_gain(avg, fits[0].fit)
    # an error of H biases tau by a fraction growing with 1/tau, so alpha = 1/(c tau) moves by
    # about alpha^2: more peaked than the line itself (a shift proportional to it would change
    # only A, alike in every profile); 0.05 u at the centre
    dy = 0.05 * spec.u * (spec.y / spec.y.max()) ** 2

    def moved(c):
        f = c.fit
        start = dict(zip(f.names, f.values))
        moved_spec = SpectrumData("absorption", spec.nu_hz, spec.y + dy, spec.u)
        refit = fit_line(
            [moved_spec], c.candidate.profile, GD, NU0, shape_free=c.candidate.shape_free,
            start=start,
        )  # fmt: skip
        return refit.line_area - f.line_area

    d_voigt, d_qsdhcp = moved(weighted[0]), moved(weighted[1])
    # the two profiles answer differently, so the choice of gain matters (measured: qSDHCP 1.18x)
    assert abs(d_qsdhcp - d_voigt) > 0.1 * abs(d_voigt)
    refitted = 0.3 * d_voigt + 0.7 * d_qsdhcp
    # first order in a 0.05 u shift (measured within 0.2 %); 2 % is a fifth of what the primary
    # profile's gain misses by (11 %)
    assert g @ dy == pytest.approx(refitted, rel=0.02)
    one = line_gain(fits[0].fit)[fits[0].fit.names.index("line_area")]
    assert abs(one @ dy - refitted) > 0.05 * abs(refitted)  # the primary profile's gain alone
    # no candidate with weight: the primary's gain
    none = ModelAverage(tuple(replace(c, weight=0.0) for c in fits), 0.0, 0.0)
    np.testing.assert_array_equal(averaged_area_gain(none, fits[0].fit), one)


@pytest.mark.parametrize("rel_noise, seed", [(1e-4, 3), (3e-4, 10)])
def test_the_gain_holds_for_a_candidate_with_a_parameter_left_at_zero(rel_noise, seed):
    """HTP fitted from the qSDHCP optimum on a Voigt spectrum: eta stays at its start, 0, to the
    optimizer's round-off; with Gamma2 ~ 0 it has almost no effect. The gain of A must still be the
    weighted least-squares one, K = cov J^T W, whose noise propagation K W^-1 K^T is the fit's
    own covariance; a Jacobian step relative to eta's value (1e-36) gave round-off and, on a
    bundle of an independent simulator, 600 times u(A)."""
    from bayes_tfcrds.uncertainty.propagate import line_gain

    spec = _spectrum("voigt", {"gamma0_hz": 0.3 * GD}, rel_noise, np.random.default_rng(seed))
    qsdhcp, htp = fit_candidates(spec, GD, NU0, labels=("qsdhcp", "htp"))
    # the case: a free parameter at 0 (to the optimizer's round-off: 1e-13 to 2e-8 across machines;
    # a step relative to it, < 1e-12 in a quantity of order 0.1, is round-off)
    assert abs(htp.fit.value("eta")) < 1e-6
    for c in (qsdhcp, htp):
        ia = c.fit.names.index("line_area")
        k = line_gain(c.fit)[ia]
        # the gain is made from the fit's own Jacobian: K W^-1 K^T = cov is an identity, to
        # round-off (1e-6 is far above it; the relative-step Jacobian was off by 600x)
        assert np.sqrt(np.sum((k * spec.u) ** 2)) == pytest.approx(c.fit.line_area_u, rel=1e-6)
