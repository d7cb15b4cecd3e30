"""The multi-ring-down refinement as an update of the beat note (letter Appendix B).

Data: ring-downs through exact rational chains (no FFT, so the truth does not share the forward
model's discretisation) and a beat note of the same chain with 0.15 % noise per point.
"""

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from scipy import stats

from bayes_tfcrds.fit import refine as refine_module
from bayes_tfcrds.fit.beat_note import fit_beat_note
from bayes_tfcrds.fit.h_calibration import h_model_forms
from bayes_tfcrds.fit.refine import HPrior, refine_transfer_function, ringdown_log_likelihood
from bayes_tfcrds.physics.detection_chain import chain_from_tf
from bayes_tfcrds.physics.transfer_function import TFParams, transfer_function

DT, K, T0 = 20e-9, 8192, -2.0e-6
T = T0 + DT * np.arange(K)
NAMES = ("f_c_hz", "a_r", "f_r_hz", "gamma_r")
TAUS = np.array([4e-6, 8e-6, 16e-6, 32e-6])
T_CUTS = np.array([2e-6, 3e-6, 4e-6, 5e-6, 6e-6, 8e-6])
ROWS = np.repeat(np.arange(TAUS.size), T_CUTS.size)
SIGMA = 1.3e-4  # V, the letter's averaged record noise
# a fast main pole with a weak slow resonance: the ring-downs hardly constrain f_c here
POLE = TFParams(f_c_hz=1.6e7, a_r=0.036, f_r_hz=6.5e5, gamma_r=1.47)
# the letter's shape: a slow tail beside a fast resonant main path (f_c well constrained)
TAIL = TFParams(f_c_hz=5.3e4, a_r=24.7, f_r_hz=5.0e6, gamma_r=0.7)


def _campaign(tf, seed):
    """Ring-down records (V), the beat-note fit of the same chain, and the records' noise (V)."""
    rng = np.random.default_rng(seed)
    clean = 0.002 + 0.6 * chain_from_tf(tf).ringdown_response(T, TAUS)
    sig = clean + SIGMA * rng.standard_normal((TAUS.size, K))
    f = np.logspace(3, np.log10(4e7), 60)
    h = np.abs(transfer_function(f, tf))
    u = 1.5e-3 * h
    beat_data = SimpleNamespace(f_hz=f, h_mag=h + u * rng.standard_normal(f.size), h_mag_u=u)
    return sig, fit_beat_note(beat_data, free=NAMES), np.full(TAUS.size, SIGMA)


def _refine(sig, start, noise, prior=None, **kw):
    return refine_transfer_function(
        T, sig, np.tile(T_CUTS, TAUS.size), start, noise_v=noise, rows_of=ROWS, prior=prior, **kw
    )


def test_update_keeps_what_the_ring_downs_cannot_constrain():
    """Today's overwrite sends f_c of a fast pole far off; the update keeps the beat note's."""
    sig, beat, noise = _campaign(POLE, 3)
    u_beat = float(np.sqrt(beat.param_cov[0, 0]))
    new = _refine(sig, beat.params, noise, prior=HPrior.from_beat(beat))
    assert abs(new.params.f_c_hz - POLE.f_c_hz) < 3 * new.stderr["f_c_hz"]
    assert new.stderr["f_c_hz"] <= u_beat * (1 + 1e-9)  # an update never loses information
    old = _refine(sig, beat.params, noise)  # ring-downs alone (the letter's refinement)
    assert abs(old.params.f_c_hz - POLE.f_c_hz) > 10 * u_beat
    # its draws in the sampled (log) parametrisation stay physical however wide the posterior
    draws = old.draw_given(np.zeros((500, 0)), (), np.random.default_rng(0))
    assert old.stderr["f_c_hz"] > old.params.f_c_hz / 10 and np.all(draws > 0)


def test_ring_downs_sharpen_what_they_constrain():
    sig, beat, noise = _campaign(TAIL, 5)
    new = _refine(sig, beat.params, noise, prior=HPrior.from_beat(beat))
    u_beat = float(np.sqrt(beat.param_cov[0, 0]))
    assert new.stderr["f_c_hz"] < 0.3 * u_beat
    assert abs(new.params.f_c_hz - TAIL.f_c_hz) < 3 * new.stderr["f_c_hz"]
    assert new.converged and abs(new.chi2_red - 1) < 0.05


def test_tension_z_is_standard_normal_when_beat_note_and_ring_downs_agree():
    """16 noise draws of beat note and ring-downs: sum z^2 follows chi2(16)."""
    z = []
    for seed in range(16):
        sig, beat, noise = _campaign(TAIL, 100 + seed)
        z.append(_refine(sig, beat.params, noise, prior=HPrior.from_beat(beat)).z[0])
    c2 = float(np.sum(np.square(z)))
    assert stats.chi2.ppf(0.001, 16) < c2 < stats.chi2.ppf(0.999, 16), z


def test_tension_is_found_and_signed():
    """A beat note 6 sd above the ring-downs' f_c: the update moves down, z < -3, a finding."""
    sig, beat, noise = _campaign(TAIL, 7)
    u = float(np.sqrt(beat.param_cov[0, 0]))
    prior = HPrior.from_beat(beat)
    shifted = replace(prior, mean=prior.mean + np.array([6 * u, 0, 0, 0]))
    start = beat.params.with_vector(shifted.mean, NAMES)
    ref = _refine(sig, start, noise, prior=shifted)
    t = ref.tension()["f_c_hz"]
    assert t["z"] < -3 and ref.in_tension and t["shift_in_beat_u"] < -3
    assert any("finding" in line for line in refine_module.tension_lines(ref))


def test_shared_record_parameters_equal_the_multiplicity_weighted_fit():
    """Extinction window: one row per record with summed weights is the composite fit itself."""
    sig, beat, noise = _campaign(TAIL, 9)
    rows = refine_module._layout(
        T, sig, np.tile(T_CUTS, TAUS.size), ROWS, noise[ROWS, None] * np.ones(K), "extinction"
    )
    one = refine_module._collapsed(rows, once=False)
    tau = np.array(TAUS)
    c_rows = refine_module._evaluate(rows, beat.params, ("f_c_hz",), tau)
    c_one = refine_module._evaluate(one, beat.params, ("f_c_hz",), tau)
    np.testing.assert_allclose(c_rows[1], c_one[1], rtol=1e-10)  # tau per record
    assert c_rows[0] == pytest.approx(c_one[0], rel=1e-10)  # chi2
    a_rows = np.einsum("npk,nqk,nk->pq", c_rows[4], c_rows[4], rows.wm)
    a_one = np.einsum("npk,nqk,nk->pq", c_one[4], c_one[4], one.wm)
    np.testing.assert_allclose(a_rows, a_one, rtol=1e-8)


def test_letter_window_shares_amplitude_across_truncations():
    """Letter window: each truncation's amplitude is B exp(-t_k/tau) of one record amplitude.

    With a chain of ~10 ns memory the flat history before t_cut is harmless, so the shared fit must
    reach the noise (a per-truncation B mis-scaled by exp(-t_k/tau) would not).
    """
    fast = TFParams(f_c_hz=2.0e7, a_r=0.01, f_r_hz=5.0e6, gamma_r=0.7)
    sig, beat, noise = _campaign(fast, 11)
    ref = _refine(sig, beat.params, noise, prior=HPrior.from_beat(beat), window="letter")
    assert ref.converged and abs(ref.chi2_red - 1) < 0.05
    np.testing.assert_allclose(ref.tau_s, TAUS, rtol=2e-3)


def test_ring_down_likelihood_matches_refits():
    """The first-order (function-space) likelihood against full refits at the moved H."""
    sig, beat, noise = _campaign(TAIL, 13)
    ref = _refine(sig, beat.params, noise, prior=HPrior.from_beat(beat))
    centre = ref.params.as_vector(NAMES)
    steps = np.array([[0, 1e-2, 0, 0], [0, 0, 1e-2, 0], [0, 0, 0, 3e-2]])
    draws = centre * (1 + steps)
    ll = ringdown_log_likelihood(ref, draws, NAMES)
    layout = ref.likelihood_layout
    chi0 = refine_module._evaluate(layout, ref.params, ("f_c_hz",), ref.tau_s)[0]
    full = [
        -0.5
        * (
            refine_module._evaluate(
                layout, ref.params.with_vector(d, NAMES), ("f_c_hz",), ref.tau_s
            )[0]
            - chi0
        )
        for d in draws
    ]
    np.testing.assert_allclose(ll, full, rtol=0.02, atol=0.05)
    assert min(full) < -2  # the steps are large enough to matter


@pytest.mark.parametrize(("n_r", "asks"), [(2.0, False), (1.7, True)])
def test_beat_note_decides_whether_the_order_n_r_is_free(n_r, asks):
    """BIC weight of the fractional-order form: small for a rational chain, ~1 for n_r = 1.7."""
    tf = replace(TAIL, n_r=n_r)
    rng = np.random.default_rng(17)
    f = np.logspace(3, np.log10(4e7), 60)
    h = np.abs(transfer_function(f, tf))
    u = 1.5e-3 * h
    config = SimpleNamespace(
        transfer_function=SimpleNamespace(f_hz=f, h_mag=h + u * rng.standard_normal(60), h_mag_u=u)
    )
    beat = fit_beat_note(config.transfer_function, free=NAMES)
    forms = h_model_forms(config, beat)
    assert forms.asks_for_free_order is asks
    if asks:
        assert forms.weight_free > 0.99 and abs(forms.free_fit.params.n_r - n_r) < 0.02
    else:
        assert forms.weight_free < 0.5  # one more parameter, no better fit: BIC penalises it


def test_no_tension_test_where_the_ring_downs_hold_almost_no_information():
    # f_c of 30 MHz, above the ring-downs' 25 MHz Nyquist frequency: the ring-downs carry well
    # under 1 % of its information, the shift is a sliver of the beat-note u, and its linear
    # scatter is not to be trusted (an independent simulator's bundle gave z = +5.1, -3.0, -2.1
    # over noise draws of one chain, a false finding). No z there; on the letter's shape (the
    # ring-downs dominate f_c) the test stays.
    fast = TFParams(f_c_hz=3.0e7, a_r=0.13, f_r_hz=2.0e5, gamma_r=0.43)
    for tf, testable in ((fast, False), (TAIL, True)):
        sig, beat, noise = _campaign(tf, 11)
        ref = _refine(sig, beat.params, noise, prior=HPrior.from_beat(beat))
        t = ref.tension()["f_c_hz"]
        assert (t["z"] is not None) is testable
        if not testable:
            assert not ref.in_tension
            assert "no tension test" in refine_module.tension_lines(ref)[0]
            assert abs(t["shift_in_beat_u"]) < 0.1  # the update kept the beat note's f_c


def test_prior_chi2_is_the_beat_notes_term_at_the_optimum():
    """A prior 2 sd off the ring-downs' own f_c, and ten times less informative, costs ~4.

    In the sampled coordinate phi = ln f_c, with ring-down information I_rd and prior
    information I_p, the optimum is the information-weighted mean, so the prior term is
    I_p (phi_p - phi_rd)^2 (I_rd/(I_p + I_rd))^2 (= (200/101)^2 = 3.92 for a prior ten times
    wider than the ring-downs and 2 of its sd off, up to the log's curvature). 1 % covers the
    change of the sandwich weight and of the model's curvature between the two optima.
    """
    sig, beat, noise = _campaign(TAIL, 5)
    alone = _refine(sig, beat.params, noise)  # the ring-downs' own f_c and its sd
    f_rd = alone.params.f_c_hz
    sd_rd = float(np.sqrt(alone.cov_naive[0, 0] / alone.weight))  # 1 / sqrt(w A), Hz
    sd_p = 10 * sd_rd
    mean = f_rd + 2 * sd_p
    prior = HPrior(("f_c_hz",), np.array([mean]), np.array([[sd_p**2]]))
    new = _refine(sig, replace(beat.params, f_c_hz=mean), noise, prior=prior)
    i_p, i_rd = (mean / sd_p) ** 2, (f_rd / sd_rd) ** 2  # information in ln f_c
    expected = i_p * np.log(mean / f_rd) ** 2 * (i_rd / (i_p + i_rd)) ** 2
    assert expected == pytest.approx((200 / 101) ** 2, rel=0.1)  # the set-up is what it says
    assert new.prior_chi2 == pytest.approx(expected, rel=0.01), (new.prior_chi2, expected)
    np.testing.assert_allclose(new.noise_v, noise)  # the noise the chi2 is in units of


@pytest.mark.parametrize(("tf", "window", "max_rank"), [
    (TAIL, "extinction", None), (TAIL, "letter", None), (POLE, "extinction", 3),
])  # fmt: skip
def test_ring_down_likelihood_through_the_basis_is_the_draw_by_draw_one(
    tf, window, max_rank, monkeypatch
):
    """The quadratic form on the basis of the draws' delta_H against the model run draw by draw.

    Draws scattered over 10x the refinement's u (and a few far ones, where the ring-downs exclude
    them). Both are the same first-order chi2 change, so they agree to round-off amplified by
    the nuisance projection: 1e-6 absolute on values down to -1e4 (measured: 1e-9 on the letter
    configurations). With a basis capped at 3 vectors most draws go through the fallback.
    """
    if max_rank is not None:
        monkeypatch.setattr(refine_module, "SPAN_MAX_RANK", max_rank)
    sig, beat, noise = _campaign(tf, 19)
    ref = _refine(sig, beat.params, noise, prior=HPrior.from_beat(beat), window=window)
    rng = np.random.default_rng(5)
    centre = ref.params.as_vector(NAMES)
    rel = np.array([ref.stderr.get(n, 0.0) for n in NAMES]) / np.abs(centre)
    rel = np.maximum(rel, 1e-3)
    draws = centre * np.exp(10 * rel * rng.standard_normal((150, len(NAMES))))
    draws[:5] = centre * np.exp(0.3 * rng.standard_normal((5, len(NAMES))))
    draws[:, 1] = centre[1] * (1 + 10 * rel[1] * rng.standard_normal(150))  # a_r: signed
    ll = ringdown_log_likelihood(ref, draws, NAMES)
    ev = refine_module._evidence(ref)
    exact = -0.5 * ev.weight * refine_module._dchi2_exact(ev, ref.params, NAMES, draws, 32)
    assert ll.min() < -10  # the draws reach where the ring-downs weigh them down
    np.testing.assert_allclose(ll, exact, rtol=1e-9, atol=1e-6)
    if max_rank is not None:
        spanned = refine_module._h_changes(ev.parts[0], ref.params, NAMES, draws)[2]
        assert not spanned.all()  # the fallback was exercised


def test_a_beat_note_with_an_undetermined_direction_gives_the_refinement_its_exact_prior():
    # Coverage campaign 18 (an f_c near 0.34 MHz on the A_r < 0 branch, resonance at 1.6 MHz):
    # one combination of f_c and f_r is undetermined by the beat note, its Fisher matrix singular
    # to rounding. The exact inverse then had variances of either sign (f_c: -1.6e21 Hz^2), the
    # refinement's prior information on f_c came out negative and the budget's Cholesky failed.
    # Independent check, the information form: f_c's precision given the other H parameters
    # (scale marginalised) is a Schur complement of the Fisher matrix, whatever its rank.
    from pathlib import Path

    from bayes_tfcrds.core.linalg import central_jacobian
    from bayes_tfcrds.fit.beat_note import FISHER_EIG_FLOOR
    from bayes_tfcrds.fit.h_calibration import BEAT_FREE, beat_note_fit
    from bayes_tfcrds.studies.coverage import settings_of, simulate_draw
    from bayes_tfcrds.studies.spec import load_study

    settings = settings_of(
        load_study(Path(__file__).resolve().parents[2] / "studies" / "coverage.toml")
    )
    draw, g_sim, _ = settings.draw(18)
    bundle, _ = simulate_draw(draw, g_sim, settings.campaign)
    beat = beat_note_fit(next(iter(bundle.configs.values())), free=BEAT_FREE)
    floored = 0
    for fit in (beat, *beat.alternatives):
        sd = np.sqrt(np.diag(fit.cov))
        np.linalg.cholesky(fit.cov / np.outer(sd, sd))  # a covariance: positive definite
        theta = np.append(fit.params.as_vector(fit.free), fit.scale)

        def model(th, fit=fit):
            return th[-1] * np.abs(
                transfer_function(fit.f_hz, fit.params.with_vector(th[:-1], fit.free))
            )

        jac = central_jacobian(model, theta, 1e-6 * np.maximum(np.abs(theta), 1e-3))
        jac = jac / (fit.h_mag_u if fit.weighted else np.sqrt(fit.chi2 / fit.dof))[:, None]
        f = jac.T @ jac
        val = np.linalg.eigvalsh(f / np.sqrt(np.outer(np.diag(f), np.diag(f))))
        floored += val[0] < FISHER_EIG_FLOOR * val[-1]
        marginal = f[:-1, :-1] - np.outer(f[:-1, -1], f[-1, :-1]) / f[-1, -1]
        i = fit.free.index("f_c_hz")
        # in the refinement's log f_c: information x f_c^2
        expected = marginal[i, i] * fit.params.f_c_hz**2
        _, info, _, _ = HPrior.from_beat(fit).conditional(("f_c_hz",), fit.params)
        # the floor and the covariance's condition number each cost ~1e-8 (test_linalg_fisher)
        assert info[0, 0] == pytest.approx(expected, rel=1e-5)
    assert floored  # the case the floor is for (else the campaign no longer tests it)
