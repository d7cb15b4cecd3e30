"""The letter's analysis chain for one configuration of a bundle.

beat-note |H| fit  ->  multi-ring-down refinement  ->  ring-down fits at each t_cut.
Each step is a pure function of the bundle's data and explicit options; the CLI, studies and
the Bayesian layer compose them.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np
from scipy import stats

from bayes_tfcrds.fit.beat_note import TFFit, fit_beat_note, same_mode
from bayes_tfcrds.fit.noise import NoiseDiagnosis, account_for_noise
from bayes_tfcrds.fit.refine import (
    HPrior,
    RefinedTF,
    refine_transfer_function,
)
from bayes_tfcrds.fit.ringdown import RingdownFits, fit_ringdowns, fit_transients
from bayes_tfcrds.physics.transfer_function import SUPPORT, TFParams, outside_support

DEFAULT_T_CUTS = (2e-6, 3e-6, 4e-6, 5e-6, 6e-6, 8e-6)  # the letter's truncation times, s
BEAT_FREE = ("f_c_hz", "a_r", "f_r_hz", "gamma_r")  # n_r = 2 keeps the chain rational (causal)
REFINE_FREE = ("f_c_hz",)  # the letter refines f_c only


class AnalysisError(ValueError):
    """A requested analysis cannot run on this configuration (the message says why)."""


@dataclass(frozen=True)
class Calibration:
    """The transfer function used for TF-CRDS: the beat-note fit and, if done, its refinement."""

    beat: TFFit
    refined: RefinedTF | None
    # d(refined)/d(others) by refits (natural units; rows refined.free, columns the beat note's
    # other free parameters in its order), from calibrate(..., sensitivities=True)
    gain: np.ndarray | None = None

    @property
    def params(self) -> TFParams:
        """The H used for TF-CRDS: the refined one when there is a refinement."""
        return self.refined.params if self.refined is not None else self.beat.params

    @property
    def others(self) -> tuple:
        """The beat note's free parameters the refinement held at the beat note's values."""
        return () if self.refined is None else held(self.beat.free, self.refined.free)

    def gain_on_others(self) -> np.ndarray:
        """d(refined)/d(others), natural units (n_refined, n_others).

        The refits' central differences when ``calibrate(..., sensitivities=True)`` made them,
        else the refinement's implicit derivative (:meth:`RefinedTF.conditional`). The latter is
        Gauss-Newton: exact where the model describes the ring-downs, 28-32 % low on a D2 campaign
        fitted with the letter's window while a window history was in the data.
        Raises ValueError when neither exists.
        """
        others = self.others
        if self.gain is not None:
            return np.asarray(self.gain, float)
        ref = self.refined
        if ref is None or ref.gain_sample is None or any(n not in ref.sens_names for n in others):
            raise ValueError(
                "no gain of the refinement on the beat-note parameters; "
                "calibrate(..., sensitivities=True) computes it"
            )
        return ref.conditional(others)[0]

    def refined_given(self, others_values, rng: np.random.Generator | None = None):
        """The refined parameters given values of the others (natural units, (n, n_refined)).

        Their conditional mean, plus with ``rng`` a draw of their scatter given the others
        (:meth:`RefinedTF.draw_given` with :meth:`gain_on_others`), both in the refinement's
        parametrisation (log of the positive parameters), so every value is where H is defined.
        """
        return self.refined.draw_given(others_values, self.others, rng, self.gain_on_others())

    def covariance(self) -> tuple[tuple, np.ndarray]:
        """Joint covariance of H's free parameters: (names, cov), natural units (Hz for f_c, f_r).

        The refinement's ``cov`` is that of the refined parameters R with the others O held at
        the beat note's values; R follows O through the gain G (:meth:`gain_on_others`). With S
        the beat note's covariance of O and C = Cov(R | O), Cov(R) = G S G' + C and
        Cov(R, O) = G S. Treating R and O as independent instead loses the correlation (|rho| up
        to 1 between f_c and the resonance on a letter chain) and mis-states whatever depends on
        several of them. The ring-downs' information on O is not used (the beat note alone
        states O), so the result is conservative on O.

        Raises ValueError when there is no gain (:meth:`gain_on_others`).
        """
        beat = self.beat
        names_b = tuple(beat.free)
        s = np.asarray(beat.param_cov, float)
        ref = self.refined
        if ref is None:
            return names_b, s
        others = self.others
        if not others:
            return tuple(ref.free), np.asarray(ref.cov, float)
        g = self.gain_on_others()
        io = [names_b.index(n) for n in others]
        s_oo = s[np.ix_(io, io)]
        c_ro = g @ s_oo
        c_rr = g @ s_oo @ g.T + np.asarray(ref.cov, float)
        cov = np.block([[c_rr, c_ro], [c_ro.T, s_oo]])
        return tuple(ref.free) + others, 0.5 * (cov + cov.T)

    def summary(self) -> str:
        """Plain text: H's parameters (beat note and refined) with their units, chi2_red, z."""
        from bayes_tfcrds.fit.views import calibration_text

        return calibration_text(self)

    def to_dict(self) -> dict:
        """JSON-ready record of the beat-note fit and the refinement, units labelled."""
        from bayes_tfcrds.fit.views import calibration_dict

        return calibration_dict(self)

    def _repr_html_(self) -> str:
        from bayes_tfcrds.fit.views import calibration_html

        return calibration_html(self)

    def plot(self, ax=None):
        """The beat note's |H| with the fitted and the refined K |H(f)|, and the residuals."""
        from bayes_tfcrds.fit.views import plot_calibration

        return plot_calibration(self, ax)


MIRROR_DCHI2 = 9.0  # beat-note chi2 difference below which |H| alone cannot choose (3 sigma)
# chi2 probability below which the best beat-note fit does not describe the beat note (the
# z of 5 sigma, one-sided): said, never passed on silently
BEAT_MISFIT_P = 2.9e-7

log = logging.getLogger(__name__)


def beat_note_fit(
    config, variant: str = "causal", free=BEAT_FREE, window: str = "extinction"
) -> TFFit:
    """Fit Eq. 2 to the configuration's beat-note measurement, its phase ambiguity resolved.

    The beat note measures |H| only, and |H| nearly repeats itself under A_r -> -A_r/(1 + 2 A_r)
    (the resonant path subtracting instead of adding), and other optima of Eq. 2 on the other
    side of A_r = 0 (a near-cancelling negative path beside a slow pole) can fit |H| as well.
    Their phase responses, and hence the ring-down distortion, may differ by percent-level
    decay-time biases, and the sampled posterior keeps to one sign of A_r (see
    :class:`~bayes_tfcrds.inference.posteriors.BeatNotePosterior`). So the ring-downs choose the
    branch: among every optimum within MIRROR_DCHI2 of the best beat-note fit (the best's
    mirror included), the other sign of A_r is taken, with its best beat-note fit, when its optima
    fit the refinement transients (total TF-CRDS chi2) better by more than MIRROR_DCHI2 than
    the best fit's branch does; otherwise the best fit stands (the ring-downs cannot tell the
    branches apart, and a choice by noise would flip from one seed to the next). Optima of one
    branch are not ranked by the ring-downs here: the posterior keeps all of them (mode jumps)
    and the ring-downs weigh them there; an unrefined optimum's ring-down chi2 says little
    about where that branch's refined H lies. The others stay known as ``alternatives``.
    """
    if config.transfer_function is None:
        raise AnalysisError(
            f"configuration {config.name!r} has no /configs/{config.name}/transfer_function "
            "group: TF-CRDS needs the beat-note measurement of the chain"
        )
    try:
        best = fit_beat_note(config.transfer_function, variant=variant, free=free)
    except RuntimeError as exc:  # no start converged: the measurement is not an Eq. 2 |H|
        raise AnalysisError(
            f"/configs/{config.name}/transfer_function: {exc}; check b12_v and b12_u_v "
            "(bayes-tfcrds validate shows the beat note)"
        ) from None
    _warn_misfit(config, best)
    if "a_r" not in free or config.ringdowns is None:
        return best
    candidates = _beat_candidates(config, best, variant, free)
    branches = {np.sign(f.params.a_r) for f in candidates}
    if len(branches) == 1:
        return best
    chi2 = np.array([_ringdown_chi2(config.ringdowns, f, window) for f in candidates])
    signs = np.array([np.sign(f.params.a_r) for f in candidates])
    own = np.sign(best.params.a_r)
    if not np.min(chi2[signs != own]) < np.min(chi2[signs == own]) - MIRROR_DCHI2:
        return best  # the ring-downs do not exclude the best fit's branch: |H| decides
    chosen = min((f for f, g in zip(candidates, signs) if g != own), key=lambda f: f.chi2)
    if chosen is best:
        return best
    # the other optima of |H| stay known to the sampler (the posterior keeps only this branch)
    others = tuple(f for f in (best, *best.alternatives) if not same_mode(f, chosen))
    return replace(chosen, alternatives=others)


def _warn_misfit(config, fit: TFFit) -> None:
    """Say so when the best beat-note fit leaves chi2 far beyond its degrees of freedom.

    Either Eq. 2 does not describe this chain, or the fit missed the optimum (a very precise beat
    note makes the optima sharp); either way the H it gives biases every TF-CRDS decay time.
    """
    if stats.chi2.sf(fit.chi2, max(fit.dof, 1)) >= BEAT_MISFIT_P:
        return
    log.warning(
        "/configs/%s/transfer_function: the best fit of Eq. 2 to the beat note leaves chi2 = %.4g "
        "for %d degrees of freedom (chi2_red %.3g): Eq. 2 does not describe this beat note, or the "
        "fit missed its optimum; every TF-CRDS decay time is biased by the misfit. Check the beat "
        "note and its uncertainties (bayes-tfcrds validate shows it)",
        config.name,
        fit.chi2,
        fit.dof,
        fit.chi2_red,
    )


def _beat_candidates(config, best: TFFit, variant: str, free) -> list:
    """The beat-note optima |H| cannot reject: ``best``, its alternatives and its mirror.

    Each within MIRROR_DCHI2 of ``best``; one per basin (:func:`same_mode`).
    """
    found = [best] + [f for f in best.alternatives if f.chi2 <= best.chi2 + MIRROR_DCHI2]
    a = best.params.a_r
    if abs(1 + 2 * a) >= 1e-3:
        mirror = replace(best.params, a_r=float(np.clip(-a / (1 + 2 * a), -0.98, 1e4)))
        try:
            alt = fit_beat_note(config.transfer_function, variant=variant, free=free, start=mirror)
        except RuntimeError:
            alt = None
        if (
            alt is not None
            and alt.chi2 <= best.chi2 + MIRROR_DCHI2
            and not any(same_mode(alt, f) for f in found)
            and abs(alt.params.a_r - a) >= 0.05 * max(1.0, abs(a))
        ):
            found.append(alt)
    return found


def _ringdown_chi2(rd, fit: TFFit, window: str) -> float:
    """Total chi2 of the TF-CRDS fits of the refinement transients with ``fit``'s H.

    A fit that does not converge from its plain-exponential start (behind a slow chain tail the
    start at a late t_cut can walk to tau -> 0) is fitted again from its record's decay time at
    another t_cut, as :func:`~bayes_tfcrds.fit.ringdown.fit_ringdowns` does, and its chi2 counts
    even when the refit's step test is not met: it is an upper bound of that fit's minimum, which
    is all the comparison of candidates needs. Counting a candidate with one unconverged fit as
    chi2 = inf made every candidate of such a chain lose and the branch fell to |H| alone: a zoo
    chain with f_c 18 kHz and A_r 2.07 (tail weight 0.33) took the mirror A_r = -0.40, and every
    decay time ended at chi2_red 7 (the right branch's unconverged fit, line centre at t_cut
    8 us, refitted to tau 3.678 us for 3.671 us at chi2_red 0.96). A mode whose fits are not
    finite (singular) loses outright.
    """
    idx = select_refinement_points(rd)
    t_cuts = np.asarray(DEFAULT_T_CUTS, float)
    noise = None if rd.fit_noise_v is None else np.asarray(rd.fit_noise_v)[idx]
    rows = np.repeat(np.arange(idx.size), t_cuts.size)
    tc = np.tile(t_cuts, idx.size)
    signal = rd.signal_v[idx]
    try:
        f = fit_transients(
            rd.time_s, signal, tc, "tf-crds", fit.params, window, noise_v=noise, rows_of=rows
        )
        chi2, ok = np.array(f.chi2, float), np.array(f.converged, bool)
        again = ~ok & np.isin(rows, rows[ok])
        if again.any():
            start = np.array([np.median(f.tau_s[ok & (rows == r)]) for r in rows[again]])
            g = fit_transients(
                rd.time_s, signal, tc[again], "tf-crds", fit.params, window, noise_v=noise,
                rows_of=rows[again], tau_start_s=start, warm_start=True,
            )  # fmt: skip
            chi2[again] = np.fmin(chi2[again], g.chi2)  # either may be NaN
    except (np.linalg.LinAlgError, ValueError, FloatingPointError):
        return np.inf
    return float(np.sum(chi2)) if np.all(np.isfinite(chi2)) else np.inf


@dataclass(frozen=True)
class HModelForms:
    """Eq. 2 with n_r = 2 (a rational, causal chain) against n_r free, judged by the beat note.

    ``weight_free`` is the BIC weight of the n_r-free form, 1/(1 + exp((BIC_free - BIC_2)/2))
    with BIC = chi2 + k ln n on the n beat-note points (Schwarz 1978): the posterior probability
    of that form when both are a priori equally likely. ``free_fit`` is its beat-note fit.
    """

    bic_fixed: float
    bic_free: float
    weight_free: float
    free_fit: TFFit | None

    @property
    def asks_for_free_order(self) -> bool:
        """True when the beat note prefers n_r free (weight above 1/2)."""
        return self.weight_free > 0.5


N_R_STARTS = (2.0, 1.5, 1.0)


def h_model_forms(config, beat: TFFit) -> HModelForms:
    """Fit the n_r-free form from the n_r = 2 optimum ``beat`` and weigh the two forms by BIC.

    The causal variant is fractional-order for n_r < 2 (n_r is searched in (0.5, 2.5)); a fit
    that fails leaves the n_r = 2 form alone (weight 0).
    """
    n = len(beat.f_hz)

    def bic(fit):
        return float(fit.chi2 + (len(fit.free) + 1) * np.log(n))

    fits = []
    for n_r in N_R_STARTS:  # the order surface has local optima: a few starts below 2
        try:
            fits.append(
                fit_beat_note(
                    config.transfer_function,
                    variant=beat.params.variant,
                    free=tuple(beat.free) + ("n_r",),
                    start=replace(beat.params, n_r=n_r),
                )
            )
        except (RuntimeError, ValueError):
            continue
    if not fits:
        return HModelForms(bic(beat), np.inf, 0.0, None)
    free_fit = min(fits, key=lambda f: f.chi2)
    d = bic(free_fit) - bic(beat)
    return HModelForms(
        bic(beat), bic(free_fit), float(1.0 / (1.0 + np.exp(np.clip(d, -700, 700) / 2))), free_fit
    )


def free_order_weight(forms: HModelForms, beat_2: TFFit, refined_2, refined_free) -> float:
    """Weight of the n_r-free form from the beat note and the ring-downs together.

    ``refined_2`` and ``refined_free`` (:class:`RefinedTF`) are the two forms updated on the same
    records, the second with n_r among its refined parameters. Laplace's approximation of the
    Bayes factor of the nested forms (Kass & Raftery 1995, Sec. 4.1):
    ln B = -Delta/2 + ln(sqrt(2 pi) u(n_r) / width), with Delta the difference of -2 ln L of all
    the data at the two optima (beat-note chi2 at its optimum, plus the beat note's Gaussian
    term and the ring-downs' composite chi2 at the update, both forms with one adjustment w),
    u(n_r) the posterior sd of n_r from all the data and n_r uniform over SUPPORT["n_r"] a priori.
    The beat note alone (``forms.weight_free``, BIC) cannot see what the ring-downs know: on a
    weak slow resonance it leaves n_r loose, and the ring-downs pin it. Returns 1/(1 + 1/B), or
    NaN when the update gives n_r no finite posterior width. Both updates must share their
    records' noise (``noise_v``), or their chi2 are in different units.
    """
    w = refined_2.weight  # one composite adjustment for both: the chi2 differ, not the weights
    delta = (
        (forms.free_fit.chi2 - beat_2.chi2)
        + w * (refined_free.chi2 - refined_2.chi2)
        + (refined_free.prior_chi2 - refined_2.prior_chi2)
    )
    lo, hi = SUPPORT["n_r"]
    i = refined_free.free.index("n_r")
    var = refined_free.cov[i, i]
    if not (np.isfinite(delta) and np.isfinite(var) and var > 0):
        return float("nan")  # no posterior width for n_r: the caller falls back to the beat note
    spread = min(np.sqrt(2 * np.pi * var), hi - lo)  # Occam factor <= 1
    ln_b = -0.5 * delta + np.log(spread / (hi - lo))
    return float(1.0 / (1.0 + np.exp(np.clip(-ln_b, -700, 700))))


def select_refinement_points(ringdowns, n: int = 6, t_cut_s: float = 4e-6) -> np.ndarray:
    """Indices of ``n`` unclipped transients spanning the decay-time range (CRDS tau quantiles).

    The letter refines H on six ring-downs from 4 to 32 us: short decays probe H at high
    frequency, long ones at low frequency.
    """
    good = np.nonzero(~np.asarray(ringdowns.clipped))[0]
    if good.size == 0:
        raise AnalysisError("every transient is clipped: nothing to refine H on")
    fits = fit_transients(
        ringdowns.time_s,
        ringdowns.signal_v[good],
        np.full(good.size, t_cut_s),
        "crds",
        noise_v=None if ringdowns.fit_noise_v is None else np.asarray(ringdowns.fit_noise_v)[good],
    )
    order = np.argsort(fits.tau_s)
    pick = order[
        np.unique(np.round(np.linspace(0, order.size - 1, min(n, order.size))).astype(int))
    ]
    return good[np.sort(pick)]


def refine_on_records(
    config,
    start,
    free,
    window,
    t_cuts_s,
    n_points,
    prior=None,
    sens_names=(),
    noise_v=None,
    idx=None,
) -> tuple:
    """The multi-ring-down refinement on ``n_points`` records spanning the decay times.

    Each record truncated at every t_cut of ``t_cuts_s`` (s), starting from the TFParams
    ``start``; returns (RefinedTF, indices of the records used). ``noise_v`` (V, one per record
    used) overrides the bundle's noise: two refinements whose chi2 are compared must share it.
    ``idx`` gives the records instead of choosing them (refits of one refinement share them).
    """
    rd = config.ringdowns
    idx = select_refinement_points(rd, n_points) if idx is None else np.asarray(idx)
    t_cuts = np.asarray(t_cuts_s, float)
    if noise_v is None and rd.fit_noise_v is not None:
        noise_v = np.asarray(rd.fit_noise_v)[idx]
    refined = refine_transfer_function(
        rd.time_s,
        rd.signal_v[idx],
        np.tile(t_cuts, idx.size),
        start,
        free=free,
        window=window,
        noise_v=noise_v,
        rows_of=np.repeat(np.arange(idx.size), t_cuts.size),
        prior=prior,
        sens_names=sens_names,
    )
    return refined, idx


def account_for_noise_colour(
    config, window: str = "extinction", beat: TFFit | None = None, confirm: bool = True
) -> tuple[object, NoiseDiagnosis, TFFit | None]:
    """(config whose ring-downs carry their noise colour, its NoiseDiagnosis, beat-note fit).

    The detector's noise is judged through the best model of the transients: TF-CRDS at the
    beat-note H (``beat``, fitted here when not given), or plain CRDS without a beat note. A
    misfit of that H (its f_c is what the ring-down refinement fixes) leaves slow structure that
    the tests would take for colour, so with ``confirm`` a colour found at the beat-note H is
    judged again at the refined H (stated white noise; a uniform noise factor leaves the
    refinement's estimate unchanged), and that verdict stands. White noise at the beat-note H
    costs no refinement. See :mod:`bayes_tfcrds.fit.noise`.
    """
    if beat is None and config.transfer_function is not None:
        beat = beat_note_fit(config, window=window)
    try:
        prepared, diagnosis = account_for_noise(
            config, tf=None if beat is None else beat.params, window=window
        )
        if confirm and beat is not None and diagnosis.kappa_applied:
            try:
                refined = calibrate(config, window=window, beat=beat).params
            except (ValueError, np.linalg.LinAlgError):  # AnalysisError: not converged
                refined = None
            if refined is not None:
                prepared, diagnosis = account_for_noise(config, tf=refined, window=window)
    except ValueError as exc:
        raise AnalysisError(f"configuration {config.name!r}: {exc}") from exc
    return prepared, diagnosis, beat


def calibrate(
    config,
    t_cuts_s=DEFAULT_T_CUTS,
    window: str = "extinction",
    refine: bool = True,
    free=REFINE_FREE,
    variant: str = "causal",
    n_points: int = 6,
    update: bool = True,
    beat: TFFit | None = None,
    sensitivities: bool = False,
) -> Calibration:
    """Beat-note fit (unless ``beat`` is given), then (with ``refine``) the refinement of ``free``.

    With ``update`` (the default) the refinement updates the beat note (a parameter the ring-downs
    do not constrain stays where the beat note puts it); without, the ring-downs alone decide, as
    in the letter.

    Parameters
    ----------
    config : Configuration
        One configuration of a bundle (``bundle.configs["D2"]``): its beat note and ring-downs.
    t_cuts_s : sequence of float
        Truncation times (s) of each refinement record.
    window : str
        ``extinction`` or ``letter`` (the forward model's window).
    refine : bool
        Refine H on the ring-downs (Appendix B) after the beat-note fit.
    free : tuple of str
        The H parameters refined (default f_c).
    variant : str
        ``causal`` or ``letter`` form of Eq. 2.
    n_points : int
        Records the refinement uses, spanning the decay times.
    update : bool
        The refinement updates the beat note (True) or replaces it (False).
    beat : TFFit, optional
        A beat-note fit already made.
    sensitivities : bool
        Also compute how the refined parameters follow the beat note's others (the gain that
        :meth:`Calibration.covariance` needs); the refined H is the same either way.

    Returns
    -------
    Calibration
        ``.params`` is the H to use; ``summary()``, ``plot()`` show the beat note and the fits.
    """
    if beat is None or beat.params.variant != variant:
        beat = beat_note_fit(config, variant=variant, window=window)
    if not refine:
        return Calibration(beat=beat, refined=None)
    prior = HPrior.from_beat(beat) if update else None
    sens = tuple(free) + held(beat.free, free) if sensitivities else ()
    refined, idx = refine_on_records(
        config, beat.params, free, window, t_cuts_s, n_points, prior, sens_names=sens
    )
    if not refined.converged:
        # a refinement that did not converge is not an H: stop rather than fit every decay time
        # with it (the beat-note H stays available)
        raise AnalysisError(
            f"configuration {config.name!r}: the ring-down refinement of H ({', '.join(free)}) did "
            "not converge; refine fewer parameters, or use the beat-note H alone (bayes-tfcrds "
            "fit --transfer-function beat)"
        )
    gain = None
    if sensitivities:
        gain = refit_gain(config, beat, refined, window, t_cuts_s, idx, prior)
    return Calibration(beat=beat, refined=refined, gain=gain)


GAIN_STEP = 0.3  # the refits' step of each held parameter, in its beat-note sd


def held(beat_free, refined_free) -> tuple:
    """The beat note's free parameters a refinement of ``refined_free`` holds, in beat order."""
    return tuple(n for n in beat_free if n not in refined_free)


def refit_gain(config, beat: TFFit, refined: RefinedTF, window, t_cuts_s, idx, prior):
    """d(refined)/d(others) of the refinement, by refits with each other parameter moved.

    The refinement's own derivative (:meth:`RefinedTF.conditional`) is Gauss-Newton: it drops
    the residuals' curvature, and where the forward model misses something (what discovery looks
    for) it was 28-32 % low on a letter D2 chain; the refits are the estimator itself. Each refit
    starts, as the refinement did, from the beat note's H, here with one held parameter moved
    +/- GAIN_STEP of its beat-note sd (on that chain the slope was the same within 0.02 % from
    0.1 to 1 sd), on the same records with the same noise.

    Parameters
    ----------
    config : Configuration
        The configuration refined.
    beat, refined : TFFit, RefinedTF
        The beat-note fit and the refinement made from it (``prior`` its :class:`HPrior`).
    window, t_cuts_s, idx
        The refinement's window, truncation times (s) and records.

    Returns
    -------
    numpy.ndarray or None
        (n_refined, n_others), natural units (Hz/Hz for f_c on f_r), the others in the beat
        note's order. A column with neither side refitted (outside H's domain, not converged)
        takes the implicit derivative; None when that is missing too.
    """
    free = tuple(refined.free)
    others = held(beat.free, free)
    sd = dict(zip(beat.free, np.sqrt(np.clip(np.diag(beat.param_cov), 0.0, None))))

    def refit(start):
        try:
            r, _ = refine_on_records(
                config,
                start,
                free,
                window,
                t_cuts_s,
                len(idx),
                prior,
                noise_v=refined.noise_v,
                idx=idx,
            )
        except (ValueError, np.linalg.LinAlgError, FloatingPointError):
            return None
        return r.params.as_vector(free) if r.converged else None

    r_star = refined.params.as_vector(free)
    cols = [_gain_column(refit, beat.params, name, GAIN_STEP * sd[name], r_star) for name in others]
    if any(c is None for c in cols):
        if refined.gain_sample is None or any(n not in refined.sens_names for n in others):
            return None
        implicit = refined.conditional(others)[0]
        cols = [implicit[:, j] if c is None else c for j, c in enumerate(cols)]
    return np.column_stack(cols) if cols else np.zeros((len(free), 0))


def _gain_column(refit, start: TFParams, name: str, h: float, r_star):
    """Central difference of ``refit`` in ``name`` (step ``h``, in its unit).

    One-sided against ``r_star`` (the refit at ``start`` itself) where one side fails; None
    where both do.
    """
    if not (np.isfinite(h) and h > 0):
        return None
    moved = {}
    for sign in (-1.0, 1.0):
        try:
            s = replace(start, **{name: getattr(start, name) + sign * h})
        except ValueError:  # outside what TFParams accepts
            continue
        if not outside_support(s, (name,)) and (v := refit(s)) is not None:
            moved[sign] = v
    if len(moved) == 2:
        return (moved[1.0] - moved[-1.0]) / (2 * h)
    if moved:
        sign, v = next(iter(moved.items()))
        return (v - r_star) / (sign * h)
    return None


def fit_config(
    config,
    t_cuts_s,
    method: str = "tf-crds",
    window: str = "extinction",
    calibration: Calibration | None = None,
    keep_residuals: bool = False,
    tf: TFParams | None = None,
) -> RingdownFits:
    """Fit every transient of ``config`` at every t_cut (s) with CRDS or TF-CRDS.

    Parameters
    ----------
    config : Configuration
        One configuration of a bundle.
    t_cuts_s : sequence of float
        Truncation times (s) from laser extinction.
    method : str
        ``crds`` (b + B exp(-t/tau)) or ``tf-crds`` (the forward model through H).
    window : str
        ``extinction`` or ``letter``.
    calibration : Calibration, optional
        The H for tf-crds (made by :func:`calibrate` when not given).
    keep_residuals : bool
        Keep every residual (V); ``RingdownFits.plot`` refits one transient otherwise.
    tf : TFParams, optional
        The H for tf-crds instead of ``calibration.params`` (e.g. the centre of its posterior).

    Returns
    -------
    RingdownFits
        tau (s), u(tau), chi2_red and status per point and t_cut.
    """
    if method != "tf-crds":
        tf = None
    elif tf is None:
        if calibration is None:
            calibration = calibrate(config, window=window)
        tf = calibration.params
    return fit_ringdowns(
        config.ringdowns,
        t_cuts_s,
        method=method,
        tf=tf,
        window=window,
        keep_residuals=keep_residuals,
    )
