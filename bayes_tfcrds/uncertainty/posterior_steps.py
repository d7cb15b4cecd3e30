"""The posteriors the budget samples.

H (beat note, then the ring-down refinement update), the line parameters given a spectrum (CRDS or
CMDS), and their Laplace (least-squares) stand-ins.

Each returns draws in SI units and, for MCMC, the
:class:`~bayes_tfcrds.inference.result.SamplingResult`
whose gates decide whether the budget may be shown.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import partial

import numpy as np

from bayes_tfcrds.fit.h_calibration import (
    BEAT_FREE,
    AnalysisError,
    beat_note_fit,
    refine_on_records,
)
from bayes_tfcrds.fit.h_identification import identification_grid
from bayes_tfcrds.fit.refine import (
    HPrior,
    from_sample,
    ringdown_log_likelihood,
    sample_jacobian,
    to_sample,
)
from bayes_tfcrds.inference.diagnostics import Gates
from bayes_tfcrds.inference.moves import (
    DifferentialEvolutionMove,
    MixtureProposal,
    fitted_mixture,
    mode_jump_move,
)
from bayes_tfcrds.inference.posteriors import (
    H_PRIORS,
    BeatNotePosterior,
    LinePosterior,
    outside_priors,
)
from bayes_tfcrds.inference.runner import run_ensembles
from bayes_tfcrds.physics.transfer_function import PARAM_NAMES, transfer_function_array
from bayes_tfcrds.uncertainty.propagate import model_of

MODE_JUMP_SHARE = 0.15  # share of steps that propose a jump between the known modes
# commits of the chains to their HDF5 file per run length (n_steps): a killed budget resumes
# losing at most a tenth of a run (about a second of sampling at the default 2500 steps). Each
# commit opens the file once per ensemble (about 8 ms): commits every 100 steps cost 2.4 s of a
# letter budget's CPU. The chains do not depend on where commits fall.
COMMITS_PER_RUN = 10


def sampler_moves(modes: MixtureProposal | None = None, jump_share: float = MODE_JUMP_SHARE):
    """Differential-evolution proposals, and mode jumps when modes are known.

    On these correlated, bounded posteriors DE cuts the integrated autocorrelation time about
    threefold against emcee's default stretch move (measured: tau_int 100 -> 35 steps on the CMDS
    line posterior). emcee's snooker move is not used: in emcee 3.1.6 it does not leave the
    target invariant (see :mod:`bayes_tfcrds.inference.moves`), and the published update mixed
    in at 20 % gave a lower ESS than DE alone on all three budget posteriors (letter D2, seed 1:
    H 5724 vs 7104, line 5802 vs 6427, CMDS 5263 vs 6002 at 2500 steps) at more cost per step.
    With ``modes`` (a mixture over the least-squares optima, or one fitted to a pilot run), a
    share ``jump_share`` of steps is an independence Metropolis-Hastings jump between them, so
    walkers do not stay stuck in a minor mode of a multimodal posterior.
    """
    if modes is None:
        return [(DifferentialEvolutionMove(), 1.0)]
    return [
        (DifferentialEvolutionMove(), 1.0 - jump_share),
        (mode_jump_move(modes), jump_share),
    ]


def n_walkers(ndim: int) -> int:
    # the gates count chain length in autocorrelation times (steps), not draws, so a few walkers
    # per dimension suffice and each step is cheaper; ESS stays far above the 400 gate
    return max(3 * ndim, 16)


def _sample(
    post,
    p0,
    names,
    ndim,
    rng,
    options,
    backend,
    progress,
    label,
    derived=None,
    gates=Gates(),
    modes=None,
    units=None,
    jump_share=MODE_JUMP_SHARE,
):
    """emcee on ``post`` with the budget's ensembles, walkers, lengths and moves.

    The posterior's priors go with the run: they name the natural-unit parameters that are
    diagnosed and saved, and every output records them.
    """
    return run_ensembles(
        post,
        p0,
        names,
        rng,
        n_ensembles=options.n_ensembles,
        n_walkers=n_walkers(ndim),
        n_steps=options.n_steps,
        max_steps=options.max_steps,
        vectorize=True,
        backend_path=backend,
        chunk_steps=max(1, options.n_steps // COMMITS_PER_RUN),
        progress=progress,
        label=label,
        moves=sampler_moves(modes, jump_share),
        derived_fn=derived,
        gates=gates,
        priors=post.priors,
        units=units,
    )


SIGN_CLEARANCE = 5.0  # |A_r| / u(A_r) above which the A_r branch is fixed by the ring-downs
OVERDISPERSION = 3.0  # start spread in units of the least-squares sd


# closer and closer in until a start is inside the support; never onto the centre itself: walkers
# that coincide span less than the parameter space, and the ensemble moves could never leave it
START_SHRINKS = (0.7, 0.5, 0.3, 0.1, 0.03, 1e-2, 1e-3, 1e-4, 1e-6)
START_WIDTH_SHARE = 0.25  # the widest start spread: a quarter of the support in each coordinate


def capped_spread(post, spread, inflate=OVERDISPERSION) -> np.ndarray:
    """``spread`` with ``inflate * spread`` at most a quarter of each coordinate's support.

    A least-squares sd can exceed the whole support (a beat note that does not constrain the
    resonance gives relative sd of thousands); starts drawn with it are all outside.
    """
    width = np.array([p.sample_width for p in post.priors], float)
    cap = np.where(np.isfinite(width), START_WIDTH_SHARE * width / inflate, np.inf)
    return np.minimum(np.asarray(spread, float), cap)


def _redraw_outside(post, x, redraw, rng):
    """Draw the starts of ``x`` outside the support again, closer in (START_SHRINKS).

    ``redraw(shrink, rows, z)`` gives the new starts of ``rows`` from normal draws ``z``, their
    spread scaled by ``shrink``. Raises when no start near a centre is inside the support.
    """
    for shrink in START_SHRINKS:
        bad = ~np.isfinite(post(x))
        if not bad.any():
            return x
        x[bad] = redraw(shrink, bad, rng.standard_normal((int(bad.sum()), x.shape[1])))
    bad = ~np.isfinite(post(x))
    if bad.any():
        raise ValueError(
            f"no start inside the prior's support near the least-squares solution (sampled "
            f"coordinates {post.sample_names}, start {x[np.argmax(bad)]}): it lies on or outside "
            "a bound of the posterior's support"
        )
    return x


def dispersed_starts(post, x0, spread, rng, n, inflate=OVERDISPERSION):
    """``n`` starting points spread ``inflate`` times wider than the least-squares sd.

    Over-dispersed starts let R-hat see a second mode or a slow direction (Gelman & Rubin 1992);
    the spread is capped at a quarter of the support (:func:`capped_spread`), and points outside
    the support are drawn again, closer in, until every one is inside (never onto ``x0``).
    """
    spread = capped_spread(post, spread, inflate)
    x = x0 + inflate * spread * rng.standard_normal((n, x0.size))
    return _redraw_outside(post, x, lambda shrink, _, z: x0 + shrink * inflate * spread * z, rng)


IS_POOL = 2  # beat-note draws per kept H draw, weighted by the ring-down likelihood
IS_POOL_MAX = 8  # the most the pool grows to when the weights are uneven
IS_ESS_MIN = 200  # importance ESS below which the H posterior is not trusted (gate)


@dataclass(frozen=True)
class RingDownWeights:
    """Importance weights of beat-note draws under the ring-down likelihood, and the resample.

    ``ess`` (Kish) of ``pool`` draws; ``picks`` the systematic resample's indices; ``passed`` when
    ESS >= IS_ESS_MIN (else the ring-downs overrule the beat note on parameters they do not
    refine, and those should be refined too).
    """

    pool: int
    ess: float
    picks: np.ndarray = field(repr=False)

    @property
    def passed(self) -> bool:
        return bool(self.ess >= IS_ESS_MIN)


def ring_down_weights(
    refined, beat_draws, n: int, rng, names=BEAT_FREE, inside=None
) -> RingDownWeights:
    """Weight ``beat_draws`` (columns ``names``) by the ring-down likelihood; resample ``n``.

    ``inside`` (bool per draw) marks the draws inside the prior's support: the others have prior
    density 0, so weight 0.
    """
    logw = ringdown_log_likelihood(refined, beat_draws, names)
    inside = np.ones(logw.size, bool) if inside is None else np.asarray(inside, bool)
    logw = np.where(np.isfinite(logw) & inside, logw, -np.inf)
    top = np.max(logw)
    if np.isfinite(top):
        w = np.exp(logw - top)
        w /= w.sum()
        ess = float(1.0 / np.sum(w * w))
    else:  # the ring-downs reject every draw of this pool: ESS 0 (a larger pool is drawn)
        w = inside / inside.sum() if inside.any() else np.full(logw.size, 1.0 / logw.size)
        ess = 0.0
    positions = (rng.uniform() + np.arange(n)) / n
    picks = np.minimum(np.searchsorted(np.cumsum(w), positions), w.size - 1)
    return RingDownWeights(pool=int(w.size), ess=ess, picks=picks)


def _beat_posterior(config, options, beat=None):
    """The beat-note fit, its posterior (A_r branch fixed clear of 0), its modes, over-dispersed p0.

    ``beat`` is the beat-note fit when already made (with BEAT_FREE, the options' window; or with
    BEAT_FREE + n_r when the beat note asks for a free order): its ``free`` are sampled.
    Returns (fit, posterior, p0 function, the mode mixture or None when the fit found one mode).
    """
    if beat is None:
        beat = beat_note_fit(config, free=BEAT_FREE, window=options.window)
    tfd = config.transfer_function
    names = tuple(beat.free)
    sd0 = np.sqrt(np.diag(beat.cov))
    a_r, u_a_r = beat.params.a_r, sd0[names.index("a_r")]
    post = BeatNotePosterior(
        f_hz=np.asarray(tfd.f_hz),
        h_mag=np.asarray(tfd.h_mag),
        h_mag_u=np.asarray(tfd.h_mag_u),
        free=names,
        fixed=beat.params,
        # the branch of A_r chosen by the ring-downs, where the posterior sits clear of A_r = 0
        a_r_sign=int(np.sign(a_r)) if abs(a_r) > SIGN_CLEARANCE * u_a_r else 0,
    )
    modes = beat_modes(post, beat)
    if modes.weights.size > 1:
        return beat, post, lambda r, n: mixture_starts(post, modes, r, n), modes
    x0 = post.to_sample(beat.params, beat.scale)
    # initial spread: the least-squares covariance, in sample space (log params: relative sd)
    nat = np.append(beat.params.as_vector(names), beat.scale)
    spread = np.where([p.is_log for p in post.priors], sd0 / np.abs(nat), sd0)

    def p0(r, n):
        return dispersed_starts(post, x0, spread, r, n)

    return beat, post, p0, None


# a multimodal beat note mixes between its modes only through the jump move (measured on zoo
# chains with three optima: tau_int of H about 450 steps against about 100 in one mode), so its
# sampler may run this many times longer before the gates decide
MULTIMODAL_STEPS = 3
MODE_INFLATE = 1.0  # the mode-jump proposal's scale against each optimum's Laplace covariance


#: smallest eigenvalue kept in a mode's correlation matrix when it is not positive definite to
#: rounding: eigen-decompositions of a d x d correlation matrix are exact to ~d eps (1e-15), so
#: 1e-12 lifts rounding's negative eigenvalues and leaves every resolved direction as it was
CORR_EIG_FLOOR = 1e-12


def _positive_definite(corr, sd):
    """corr * sd sd^T (plus a 1e-9 sd jitter), positive definite even where ``corr`` is not.

    A beat-note fit whose resonance the data leave unconstrained has a covariance of condition
    ~1e25 (sd of f_c ~ 2e9 Hz); its correlation matrix, rescaled to the capped sd, can then be
    singular to rounding, with an eigenvalue of -3e-15 (coverage campaign 18 with numpy 2.4's
    arithmetic). Only then are its eigenvalues floored at CORR_EIG_FLOOR (unit diagonal
    restored); a matrix that passes Cholesky is returned as it always was.
    """
    cov = corr * np.outer(sd, sd) + np.diag((1e-9 * sd) ** 2)
    try:
        np.linalg.cholesky(0.5 * (cov + cov.T))
        return cov
    except np.linalg.LinAlgError:
        val, vec = np.linalg.eigh(0.5 * (corr + corr.T))
        fixed = (vec * np.maximum(val, CORR_EIG_FLOOR)) @ vec.T
        d = np.sqrt(np.diag(fixed))
        return fixed / np.outer(d, d) * np.outer(sd, sd) + np.diag((1e-9 * sd) ** 2)


def beat_modes(post, beat) -> MixtureProposal:
    """The beat-note optima inside the posterior's support as a Student-t mixture (sample space).

    Each component is centred on one least-squares optimum with its Gauss-Newton covariance
    (log parameters: relative), inflated MODE_INFLATE times and with every sd capped at a quarter
    of the support's width. Weights: half the Laplace evidence exp(-chi2/2) sqrt(det cov), half
    uniform, so a minor mode is still proposed; the Metropolis-Hastings ratio corrects either.

    An optimum whose covariance spans more than a quarter of the support in some parameter is
    not a mode but a plateau (e.g. f_r far above the band with Gamma_r free: that part of Eq. 2
    no longer changes H where it is measured); a Student-t cannot represent it and walkers
    started over it drift for the whole run, so it is left out, as the local moves alone would.
    """
    is_log = np.array([p.is_log for p in post.priors])
    # widths of both A_r branches: the scale of the physical domain, not of the branch kept
    width = np.array([H_PRIORS[p.parameter].sample_width for p in post.priors])
    means, covs, log_ev = [], [], []
    for fit in (beat, *beat.alternatives):
        m = post.to_sample(fit.params, fit.scale)
        if not np.isfinite(post(m)[0]):
            continue  # the other A_r branch, or outside the support
        nat = np.append(fit.params.as_vector(post.free), fit.scale)
        jac = np.where(is_log, np.abs(nat), 1.0)
        cov = fit.cov / np.outer(jac, jac)
        sd = np.sqrt(np.maximum(np.diag(cov), 1e-300))
        if fit is not beat and np.any(sd > 0.25 * width):
            continue  # a plateau, not a mode: part of Eq. 2 has left the band (see docstring)
        corr = cov / np.outer(sd, sd)
        sd = MODE_INFLATE * np.minimum(sd, 0.25 * np.where(np.isfinite(width), width, sd))
        cov = _positive_definite(corr, sd)
        means.append(m)
        covs.append(cov)
        log_ev.append(-0.5 * fit.chi2 + 0.5 * np.linalg.slogdet(cov)[1])
    log_ev = np.array(log_ev)
    w = np.exp(log_ev - log_ev.max())
    w = 0.5 * w / w.sum() + 0.5 / w.size
    return MixtureProposal(np.array(means), np.array(covs), w / w.sum())


def mixture_starts(post, modes: MixtureProposal, rng, n, inflate=OVERDISPERSION):
    """``n`` starts over every mode: a component by weight, then Gaussian ``inflate`` times wider.

    Starts in every basin let R-hat see whether the walkers mix between them; points outside the
    support are drawn again, closer in.
    """
    k = np.searchsorted(np.cumsum(modes.weights), rng.uniform(size=n))
    k = np.minimum(k, modes.weights.size - 1)
    chol = np.linalg.cholesky(modes.covs) / MODE_INFLATE
    z = rng.standard_normal((n, modes.ndim))
    x = modes.means[k] + inflate * np.einsum("nij,nj->ni", chol[k], z)

    def redraw(shrink, bad, z):
        return modes.means[k[bad]] + shrink * inflate * np.einsum("nij,nj->ni", chol[k[bad]], z)

    return _redraw_outside(post, x, redraw, rng)


H_GATE_FREQUENCIES = 8  # log-spaced frequencies at which H(f) is gated


# share of steps that jump within a mixture fitted to a pilot run (see _pilot_refit): the fitted
# proposal follows the posterior closely, so jumps do most of the mixing and DE the local rest
FITTED_JUMP_SHARE = 0.5


REFITS = 2  # at most this many runs with fitted jumps, each fitted to the run before


def _pilot_refit(post, pilot, sample, options, backend, rng):
    """Sample again, with jumps fitted to the failed run ``pilot``; returns the last run.

    Where the beat note's optima are joined by a long curved ridge (an over-damped resonance
    whose fast pole leaves the measured band: measured on zoo chains with a weak resonance below
    f_c, tau_int of H(f) about 7000 steps), neither the local moves nor jumps between the optima
    cross it within the budget's steps. The failed run has been along that ridge, slowly: a
    mixture fitted to its samples (:func:`~bayes_tfcrds.inference.moves.fitted_mixture`) lets
    every walker jump along it. A run that still fails (its pilot had not gone far enough) is
    the pilot of the next, up to REFITS runs. The pilot's samples serve only to build the
    proposal and the starts (drawn from it); each run's own gates judge it. ``sample`` is
    :func:`_sample` with the posterior's fixed arguments.
    """
    run = pilot
    for k in range(REFITS):
        try:
            mix = fitted_mixture(run.flat(), rng)
        except ValueError:
            return run  # a run that did not move gives no shape to fit: its failure stands
        run = sample(
            p0=partial(_mixture_starts, post, mix),
            options=options,
            backend=None if backend is None else backend.replace(".h5", f"_refit{k}.h5"),
            label=f"H | beat note (jumps fitted to a pilot run, {k + 1})",
            modes=mix,
            jump_share=FITTED_JUMP_SHARE,
        )
        if run.passed:
            break
    return run


def _mixture_starts(post, mix, rng, n):
    """``n`` draws of ``mix`` inside the support of ``post`` (outside ones drawn again)."""
    x = mix.draw(rng, n)
    for _ in range(100):
        bad = ~np.isfinite(post(x))
        if not bad.any():
            return x
        x[bad] = mix.draw(rng, int(bad.sum()))
    raise ValueError("the fitted mixture proposes no start inside the prior's support")


def h_predictions(post, ringdowns):
    """Derived quantities Re H, Im H (normalised) at log-spaced frequencies, and the gated names.

    From 1 kHz to the ring-downs' Nyquist frequency: the band the decay times see. The budget
    uses H only through H(f), so the sampler is gated on it (and on the scale K): the poles of
    Eq. 2 may trade roles (an overdamped resonance is two real poles beside f_c) without
    changing H, which would fail a parameter R-hat for no reason.
    """
    f = identification_grid(ringdowns.time_s, H_GATE_FREQUENCIES)

    def derived(x):
        p = post.to_params(x)
        cols = {n: np.full(x.shape[0], getattr(post.fixed, n)) for n in PARAM_NAMES}
        cols.update({n: p[n] for n in post.free})
        h = transfer_function_array(
            f[None, :], *(cols[n][:, None] for n in PARAM_NAMES), post.fixed.variant
        )
        out = {f"re_H_{fk:.3g}Hz": h[:, i].real for i, fk in enumerate(f)}
        out.update({f"im_H_{fk:.3g}Hz": h[:, i].imag for i, fk in enumerate(f)})
        return out

    names = tuple(f"{part}_H_{fk:.3g}Hz" for part in ("re", "im") for fk in f) + ("scale",)
    return derived, names


def h_prediction_units(gated) -> dict:
    """Units of the derived H(f) values (normalised H: dimensionless)."""
    return {n: "1" for n in gated if n != "scale"}


def _pool(beat, post, run, rng, size: int) -> np.ndarray:
    """``size`` beat-note posterior draws of the sampled H parameters ``post.free`` (natural units).

    From the MCMC run (without replacement, at most all of it) or, with ``run`` None, from the
    Laplace approximation in the sampled parametrisation (log of the positive parameters: every
    draw physical).
    """
    names = tuple(post.free)
    if run is None:
        centre = beat.params.as_vector(names)
        jac = sample_jacobian(names, centre)
        cov_s = beat.param_cov / np.outer(jac, jac)
        prior = {p.parameter: p for p in post.priors}
        lo = to_sample(names, np.array([prior[n].lower for n in names]))
        hi = to_sample(names, np.array([prior[n].upper for n in names]))
        cov_s = with_prior(cov_s, hi - lo)
        phi = draws_in_support(rng, to_sample(names, centre), cov_s, lo, hi, size, names)
        return from_sample(names, phi.T).T
    flat = run.flat()
    pick = rng.choice(flat.shape[0], size=min(size, flat.shape[0]), replace=False)
    nat_draws = post.to_params(flat[pick])
    return np.column_stack([nat_draws[n] for n in names])


def with_prior(cov, widths) -> np.ndarray:
    """A Gaussian likelihood's covariance combined with flat priors of the given widths.

    Each flat prior enters as the Gaussian of its variance width^2/12 (precisions add). Where the
    data constrain a direction this changes nothing measurable (a beat-note u of 0.1 % in f_c
    against a prior over 10 decades); where they do not (a resonance of amplitude 0.01, whose
    f_r and Gamma_r the beat note leaves free), the Laplace draws spread over the prior instead
    of to 10^100 Hz. ``cov`` in the sampled parametrisation, ``widths`` of the priors in it.
    """
    cov = 0.5 * (np.asarray(cov, float) + np.asarray(cov, float).T)
    lam, vec = np.linalg.eigh(cov)
    tiny = np.finfo(float).tiny
    precision = (vec / np.maximum(lam, tiny)) @ vec.T
    precision += np.diag(12.0 / np.asarray(widths, float) ** 2)
    lam_p, vec_p = np.linalg.eigh(0.5 * (precision + precision.T))
    return (vec_p / lam_p) @ vec_p.T


#: rounds of rejection sampling before a support the Gaussian barely reaches is refused
SUPPORT_ROUNDS = 50


def draws_in_support(rng, mean, cov, lo, hi, size: int, names) -> np.ndarray:
    """``size`` normal draws N(mean, cov) inside the box (lo, hi), by rejection (sampled coords).

    The Laplace posterior is the Gaussian restricted to the prior's support: no draw outside it
    reaches a physics function. Refuses, naming the parameters, when the Gaussian barely reaches
    the support.
    """
    out, n_tried = [], 0
    for _ in range(SUPPORT_ROUNDS):
        phi = rng.multivariate_normal(mean, cov, size=2 * size, method="eigh")
        n_tried += phi.shape[0]
        out.append(phi[np.all((phi > lo) & (phi < hi), axis=1)])
        if sum(len(o) for o in out) >= size:
            return np.concatenate(out)[:size]
    outside = [n for n, m, a, b in zip(names, mean, lo, hi) if not a < m < b]
    raise ValueError(
        f"the Laplace posterior of H lies outside the prior's support ({n_tried} draws, "
        f"{sum(len(o) for o in out)} inside; centre outside for {outside or 'none'}): the beat "
        "note does not constrain these parameters; use --posterior mcmc"
    )


def ring_down_update(config, options, beat, free, sens_names=(), noise_v=None, prior=None):
    """The multi-ring-down update of ``free`` with the beat-note fit ``beat`` as prior.

    The options' window, t_cuts and number of records; ``sens_names`` the parameters whose
    ring-down information is reported, ``noise_v`` the records' noise when it must be shared
    with another update. ``prior`` replaces the least-squares beat note as prior and start (see
    :func:`sampled_beat_prior`). Returns (refinement, records used).
    """
    start = beat.params
    if prior is None:
        prior = HPrior.from_beat(beat)
    else:
        start = replace(start, **dict(zip(prior.names, map(float, prior.mean))))
    return refine_on_records(
        config,
        start,
        free,
        options.window,
        options.t_cuts_s,
        options.n_refine_points,
        prior,
        sens_names,
        noise_v,
    )


def sampled_beat_prior(post, run) -> HPrior:
    """The beat-note posterior as the MCMC run sampled it, as a Gaussian :class:`HPrior`.

    Mean and covariance of the run's samples in the refinement's parametrisation (log of the
    positive parameters), so the refinement linearises where the posterior's mass is. Used when
    the least-squares optimum, the usual centre, lies in a mode or corner that holds little of
    that mass (a weak resonance beside a large region of out-of-band resonances that the beat
    note cannot tell from a gain): linear about the optimum, the refinement sends every draw
    from the other region outside the support.
    """
    names = tuple(post.free)
    nat = post.to_params(run.flat())
    phi = to_sample(names, np.array([nat[n] for n in names]))
    mean = phi.mean(axis=1)
    cov = np.atleast_2d(np.cov(phi))
    centre = from_sample(names, mean)
    jac = sample_jacobian(names, centre)
    return HPrior(names, centre, cov * np.outer(jac, jac), source="beat note (MCMC moments)")


#: the share of the sampled beat-note posterior, in each tail of a held parameter's marginal,
#: beyond which the refinement's linearisation point counts as outside the posterior's mass: 1e-3
#: per tail is ~3.1 sigma of a Gaussian, so an optimum inside its own posterior (where every
#: well-behaved chain has it: within about 1 sigma of the mean) is never taken for another region
AWAY_TAIL = 1.0e-3


def mass_away(refined, post, run) -> tuple:
    """The held parameters whose sampled beat-note posterior has no mass at the refined point.

    ``refined`` linearised about its point (its ``params``); its conditional of the refined
    parameters given the held ones is valid near that point only. Where the MCMC run's draws of a
    held parameter all lie beyond it (the point outside their central 1 - 2 AWAY_TAIL range), the
    beat note's posterior mass sits in another description of |H| (a non-minimum-phase one of
    the same |H| with a larger prior volume, say), and the conditional, extrapolated there, would
    put the refined parameters anywhere.
    """
    nat = post.to_params(run.flat())
    away = []
    for n in post.free:
        if n in refined.free:
            continue
        lo, hi = np.quantile(nat[n], [AWAY_TAIL, 1.0 - AWAY_TAIL])
        if not lo <= getattr(refined.params, n) <= hi:
            away.append(n)
    return tuple(away)


@dataclass(frozen=True)
class RefinementRegion:
    """Where the ring-down refinement of H is linearised, and which beat-note draws it weighs.

    ``prior`` None: the least-squares beat note (the usual case); else the sampled posterior's
    moments. ``run`` the MCMC run whose draws the ring-downs weigh, or None for the beat fit's
    Laplace approximation (the ring-downs reject where the run's mass lies). ``made`` the
    refinement (and its records) already made in that region. ``moments`` the sampled moments'
    prior and the refinement made about them, when they were compared (kept so that a fallback
    to them does not make it again); ``note`` says why, for budget.json; None in the usual case.
    """

    prior: HPrior | None
    run: object
    made: tuple
    note: str | None = None
    moments: tuple | None = None


def refinement_region(config, options, beat, post, run, free) -> RefinementRegion:
    """Choose the region of the beat-note posterior in which the ring-downs refine H.

    The beat note sees |H| only; a description of the same |H| with another phase can hold most
    of its posterior mass (a larger prior volume) while the ring-downs, which see the phase,
    reject it. So: refine about the least-squares beat note; where the sampled posterior has no
    mass there (:func:`mass_away`), refine about the sampled mass too, and keep the region the
    ring-downs accept. If they reject the sampled mass (tension) and accept the least-squares
    point, the joint posterior lies in the least-squares mode, which the run did not sample:
    its Laplace approximation supplies the draws. Otherwise the sampled mass is used.
    """
    first, idx = ring_down_update(config, options, beat, free, tuple(beat.free))
    if run is None:
        return RefinementRegion(None, None, (first, idx))
    away = mass_away(first, post, run)
    if not away:
        return RefinementRegion(None, run, (first, idx))
    prior = sampled_beat_prior(post, run)
    second, idx2 = ring_down_update(config, options, beat, free, tuple(beat.free), prior=prior)
    moments = (prior, (second, idx2))
    where = ", ".join(f"{n} = {getattr(second.params, n):.4g}" for n in away)
    if second.in_tension and not first.in_tension:
        c2 = second.tension_chi2
        return RefinementRegion(
            None,
            None,
            (first, idx),
            f"the beat-note MCMC's mass lies in another description of |H| ({where}) that the "
            f"ring-downs reject (tension chi2 {c2[0]:.3g} for {c2[1]} dof); they accept the "
            "least-squares beat note, so H is drawn from its Laplace approximation there",
            moments,
        )
    return RefinementRegion(
        prior,
        run,
        (second, idx2),
        f"the beat-note MCMC's mass lies away from the least-squares beat note ({where}): "
        "the refinement is linearised about the sampled posterior's moments",
        moments,
    )


def in_support(draws: np.ndarray, priors) -> np.ndarray:
    """Rows of ``draws`` (n, len(priors), natural units) where every prior's density is > 0."""
    d = np.atleast_2d(np.asarray(draws, float))
    return ~outside_priors(priors, {p.parameter: d[:, k] for k, p in enumerate(priors)})


SUPPORT_REDRAWS = 20  # conditional scatter redrawn for draws outside the prior's support


def _conditional_inside(draws, refined, others, io, ir, priors, rng):
    """``draws`` with the refined columns drawn from their conditional, truncated to the support.

    The refinement's conditional is Gaussian in the sampled parametrisation and knows nothing of
    the prior's bounds; a draw it puts outside has prior density 0 and is drawn again.
    """
    draws[:, ir] = refined.draw_given(draws[:, io], others, rng)
    for _ in range(SUPPORT_REDRAWS):
        out = ~in_support(draws, priors)
        if not out.any():
            break
        sub = draws[out]
        sub[:, ir] = refined.draw_given(sub[:, io], others, rng)
        draws[out] = sub
    return draws


def _support_error(joint, refined, names, priors, pool: int, outside: int) -> AnalysisError:
    """Why no joint draw of H is physical.

    The refined parameters that leave the prior's support, and the beat note's spread of the
    others against the point the refinement linearised about.
    """
    d = np.atleast_2d(np.asarray(joint, float))
    lines = []
    for k, (n, p) in enumerate(zip(names, priors)):
        col = d[:, k]
        bad = outside_priors([p], {p.parameter: col})
        if n in refined.free and bad.any():
            lines.append(
                f"{n}: {bad.mean():.0%} of draws outside ({p.lower:g}, {p.upper:g}) {p.unit}"
            )
        elif n not in refined.free:
            lo, hi = np.nanpercentile(col, [5, 95])
            lines.append(
                f"{n}: beat-note draws {lo:.3g} to {hi:.3g} (5-95 %) about the refinement's "
                f"{getattr(refined.params, n):.3g}"
            )
    at = ", ".join(f"{n} = {getattr(refined.params, n):.4g}" for n in refined.free)
    return AnalysisError(
        f"H posterior: the ring-down refinement ({at}) and the beat note's draws of the other H "
        f"parameters are incompatible: the refinement's conditional, linear about its own point, "
        f"puts {outside} of {pool} joint draws outside the prior's support"
        f"{'' if outside == pool else f' after {SUPPORT_REDRAWS} redraws'}. "
        f"{'; '.join(lines)}. The beat note leaves those others nearly free (a band that misses "
        "the chain's corner or resonance): measure it over a wider band, or refine them on the "
        "ring-downs too (--refine)"
    )


def _joint_draws(beat, post, run, refined, options, rng):
    """Draws of the joint posterior of H (beat note x ring-downs).

    Beat-note draws of the others, each followed by the refined parameters' conditional mean,
    weighted by the ring-down likelihood and resampled (the pool grows to IS_POOL_MAX times the
    draws when the weights are uneven); then the refined parameters' conditional scatter. Returns
    (draws, the same with the conditional mean, weights).
    """
    names = tuple(post.free)
    priors = [next(p for p in post.priors if p.parameter == n) for n in names]
    others = tuple(n for n in names if n not in refined.free)
    io = [names.index(n) for n in others]
    ir = [names.index(n) for n in refined.free]
    factor = IS_POOL
    while True:
        draws = _pool(beat, post, run, rng, factor * options.n_h_draws)
        beat_draws = draws.copy()
        beat_draws[:, ir] = refined.draw_given(draws[:, io], others, rng=None)
        inside = in_support(beat_draws, priors)
        weights = ring_down_weights(refined, beat_draws, options.n_h_draws, rng, names, inside)
        if weights.passed or factor >= IS_POOL_MAX or draws.shape[0] < factor * options.n_h_draws:
            break
        factor *= 4
    if not inside.any():
        raise _support_error(beat_draws, refined, names, priors, inside.size, inside.size)
    draws, beat_draws = draws[weights.picks], beat_draws[weights.picks]
    draws = _conditional_inside(draws, refined, others, io, ir, priors, rng)
    left = int(np.sum(~in_support(draws, priors)))
    if left:
        raise _support_error(draws, refined, names, priors, draws.shape[0], left)
    return draws, beat_draws, weights


def h_posterior(config, options, rng, backend, progress, beat=None):
    """The posterior of H: beat-note MCMC (or Laplace), updated by the ring-downs.

    ``beat`` the beat-note fit when already made; its ``free`` are the sampled H parameters
    (BEAT_FREE, or BEAT_FREE + n_r for the free-order form). Returns (beat-note fit, refinement or
    None, H*, H draws (n, len(beat.free)), sampler run or None, the draw's decomposition into
    beat-note and refined parts; ``parts["names"]`` the draws' columns).
    """
    beat, post, p0, modes = _beat_posterior(config, options, beat)
    run = None
    if options.posterior != "laplace":
        ndim = len(post.sample_names)
        derived, gated = h_predictions(post, config.ringdowns)
        steps = (
            options
            if modes is None
            else options.with_steps(max_steps=MULTIMODAL_STEPS * options.max_steps)
        )
        sample = partial(
            _sample,
            post,
            names=post.sample_names,
            ndim=ndim,
            rng=rng,
            progress=progress,
            derived=derived,
            gates=Gates(gated=gated),
            units=h_prediction_units(gated),
        )
        run = sample(p0=p0, options=steps, backend=backend, label="H | beat note", modes=modes)
        if not run.passed:
            run = _pilot_refit(post, run, sample, options, backend, rng)
    if options.method != "tf-crds" or not options.refine_free:
        draws = _pool(beat, post, run, rng, options.n_h_draws)
        parts = {"others": post.free, "refined": (), "records": None, "beat_draws": draws}
        parts["names"] = post.free
        return beat, None, beat.params, draws, run, parts
    free = tuple(options.refine_free)
    region = refinement_region(config, options, beat, post, run, free)
    prior, source, made, note = region.prior, region.run, region.made, region.note
    while True:
        if made is None:
            made = ring_down_update(config, options, beat, free, tuple(beat.free), prior=prior)
        (refined, idx), made = made, None
        try:
            draws, beat_draws, weights = _joint_draws(beat, post, source, refined, options, rng)
        except AnalysisError:
            if prior is not None or run is None:
                raise
            # linear about the least-squares optimum, the refinement reaches no draw of the
            # sampled posterior (or of its Laplace approximation, where refinement_region chose
            # that): linearise where the sampled posterior's mass is, and weigh again
            if source is None:  # the region the ring-downs accepted has no draw in the support
                note = (
                    f"{note}; but those Laplace draws leave the prior's support, so the "
                    "refinement is linearised about the sampled posterior's moments after all"
                )
            source = run
            if region.moments is not None and free == tuple(options.refine_free):
                prior, made = region.moments  # refinement_region made this refinement already
            else:
                prior = sampled_beat_prior(post, run)
            continue
        ratio = refined.information_ratio()
        if weights.passed or not ratio:
            break
        # the ring-downs overrule the beat note on a parameter they were not asked to refine:
        # refine the one they know best relative to the beat note too, and weigh again
        free = free + (max(ratio, key=ratio.get),)
    parts = {
        "names": tuple(post.free),
        "others": tuple(n for n in post.free if n not in free),
        "refined": free,
        "refined_asked": tuple(options.refine_free),
        "records": idx,
        "beat_draws": beat_draws,
        "weights": weights,
        "region": note,
    }
    return beat, refined, posterior_centre(refined.params, draws, post.free), draws, run, parts


def posterior_centre(params, draws, names=BEAT_FREE):
    """H at the mean of the draws in the sampled parametrisation (log of the positive ones).

    The decay times and the line fit are evaluated there: the ring-down weighting can move the
    parameters the refinement held at the beat note, and first-order propagation about a point
    away from the posterior's centre would bias every tau by the mean shift.
    """
    phi = to_sample(names, np.asarray(draws, float).T).mean(axis=1)
    return params.with_vector(from_sample(names, phi), names)


def fit_transients_noise(rd, records, t_cut_s, tf, window):
    """Per-record noise (V) estimated from TF-CRDS residuals, for bundles without noise_v."""
    from bayes_tfcrds.fit.ringdown import fit_transients

    f = fit_transients(
        rd.time_s, rd.signal_v[records], np.full(len(records), t_cut_s), "tf-crds", tf, window
    )
    return f.noise_v


def line_draws(lsq, rng, n=4000):
    """Laplace posterior: draws of the line parameters from the least-squares solution."""
    cov = 0.5 * (lsq.cov + lsq.cov.T)  # parameters at a bound have zero rows: singular, still PSD
    return rng.multivariate_normal(lsq.values, cov, size=n, method="eigh")


def line_mcmc(spectra, profile, gd, nu_ref, lsq, rng, options, backend, progress, label):
    """emcee on the line parameters given ``spectra``.

    Walkers start inside the physical prior around the least-squares solution ``lsq``.
    """
    model = model_of(lsq)
    post = LinePosterior(model=model, spectra=tuple(spectra), names=lsq.names)
    sd = np.sqrt(np.diag(lsq.cov))
    sd = np.where(
        sd > 0,
        sd,
        np.abs(lsq.values) * 1e-3
        + 1e-3 * lsq.doppler_hwhm_hz * (np.array(lsq.names) != "line_area"),
    )
    x0 = lsq.values.copy()
    for i, n in enumerate(lsq.names):  # start strictly inside the prior
        if n in ("gamma2_hz", "nu_vc_hz") and x0[i] <= sd[i]:
            x0[i] = sd[i]
    # the prior also caps Gamma2 at 2/3 Gamma0 (no negative width in any speed class); the
    # unbounded least-squares estimate and its sd can lie beyond it
    i2 = lsq.names.index("gamma2_hz") if "gamma2_hz" in lsq.names else None
    cap = (
        (2.0 / 3.0) * abs(x0[lsq.names.index("gamma0_hz")])
        if i2 is not None and "gamma0_hz" in lsq.names
        else np.inf
    )
    if i2 is not None and x0[i2] >= cap:
        x0[i2] = 0.5 * cap

    def p0(r, n):
        x = x0 + 0.5 * sd * r.standard_normal((n, x0.size))
        for i, name in enumerate(lsq.names):
            if name in ("gamma2_hz", "nu_vc_hz", "line_area", "gamma0_hz"):
                x[:, i] = np.abs(x[:, i])
        if np.isfinite(cap):  # each walker's own Gamma0 sets its cap
            cap_w = (2.0 / 3.0) * x[:, lsq.names.index("gamma0_hz")]
            over = x[:, i2] >= cap_w
            x[over, i2] = cap_w[over] * r.uniform(0.1, 0.9, int(over.sum()))
        return x

    return _sample(post, p0, lsq.names, x0.size, rng, options, backend, progress, label)


def priors_summary(runs: dict, units=None) -> dict:
    """The priors of every sampled posterior, read from the posteriors the samplers ran on.

    {run key: {"posterior": its label, "parameters": [Prior.to_dict(units), ...]}} (``units``
    shows the bounds in the outputs' unit, see :meth:`Prior.to_dict`); empty for the Laplace
    path, which samples nothing (Gaussians about the least-squares fits).
    """
    return {
        k: {"posterior": run.label, "parameters": [p.to_dict(units) for p in run.priors]}
        for k, run in runs.items()
    }
