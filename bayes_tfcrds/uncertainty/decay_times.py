"""The decay-time table of ``bayes-tfcrds fit``: tau at the centre of H's posterior, u(tau) whole.

A TF-CRDS fit returns tau at one H, and its u(tau) is the ring-down noise's alone. But H is
measured (beat note, Eq. 1) and refined (Appendix B), and what remains uncertain in it moves every
tau: at short decay times by as much as the noise does, and in common to all points. The table
therefore fits tau at the centre of H's posterior and adds the H part, first order about it,
over draws of that posterior's Laplace approximation (beat note x ring-downs: the budget's
``--posterior laplace``, whose coverage ``reports/coverage_laplace`` measures), so that its total
u(tau) is the standard uncertainty of each decay time.

The centre is not the letter's refined H (f_c refined, the rest held at the beat note): the
ring-downs also inform the parameters the refinement holds. On the letter's D3 chain the
letter's H sits at Mahalanobis^2 ~ 100 from the posterior's centre, which moved the line-centre
tau by 5-16 noise u on three of four seeds (about 1 at the centre).

The H part is fully correlated between points (one H error shifts every tau, most at short tau):
a line fit must not weight with it, which is why the spectra and the budget take the noise part
and propagate H on their own. Noise and H parts add in quadrature as independent, as in the
budget's decay-time table (the refinement's few records share their noise with H's estimate).
The centre is the mean of random draws: tau depends on ``--seed`` at the level of u_H / sqrt(ESS).

Units: s (tau, u), Hz (H's frequencies).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bayes_tfcrds.fit.h_calibration import BEAT_FREE, AnalysisError
from bayes_tfcrds.fit.ringdown import fit_ringdowns
from bayes_tfcrds.physics.transfer_function import TFParams
from bayes_tfcrds.uncertainty.line_budget import BudgetOptions, h_shifts_many
from bayes_tfcrds.uncertainty.posterior_steps import h_posterior
from bayes_tfcrds.uncertainty.propagate import tau_h_kernels

#: H draws behind u_H(tau). They are an importance resample of beat-note draws (ESS >= the
#: budget's IS_ESS_MIN, ~230 on the letter's D3): u_H's Monte Carlo relative sd is about
#: 1/sqrt(2 ESS), 5 % there
N_H_DRAWS = 1000


@dataclass(frozen=True)
class HDraws:
    """Draws of H's posterior (Laplace) and its centre.

    ``centre`` the H at the draws' mean in the sampled parametrisation (log of the positive
    parameters) when the ring-downs refined H, the beat-note optimum otherwise (the draws are
    then the beat note's Laplace posterior, centred there); ``draws`` (n, k) natural units of
    ``names``; ``refined`` the parameters the ring-downs updated (the requested ones, and any
    the budget's rule added because the ring-downs overruled the beat note on it; empty for the
    beat note alone).
    """

    centre: TFParams
    draws: np.ndarray
    names: tuple
    refined: tuple


def laplace_h_draws(
    config, calibration, rng: np.random.Generator, window: str = "extinction",
    n_draws: int = N_H_DRAWS,
) -> HDraws:  # fmt: skip
    """H's posterior as the budget's Laplace path draws it, for ``calibration``'s refinement.

    ``config`` the configuration (its ring-downs with their noise colour), ``calibration`` the
    :class:`~bayes_tfcrds.fit.h_calibration.Calibration` (its beat-note fit, and the parameters
    it refined: none for the beat note alone). Raises ``AnalysisError`` when the posterior
    cannot be drawn or fails the budget's gates (a refined parameter the budget does not refine,
    a posterior outside the priors' support, a refinement that did not converge, importance
    weights below the budget's ESS minimum, 200: ``n_draws`` well below it cannot pass).
    """
    refined = calibration.refined
    free = tuple(refined.free) if refined is not None else ()
    if any(n not in BEAT_FREE for n in free):
        raise AnalysisError(f"the posterior of H refines a subset of {BEAT_FREE}, not {free}")
    options = BudgetOptions(posterior="laplace", window=window, refine_free=free, n_h_draws=n_draws)
    _, upd, centre, draws, _, parts = h_posterior(
        config, options, rng, None, None, calibration.beat
    )
    if upd is not None and not upd.converged:
        raise AnalysisError(f"the ring-down refinement of {', '.join(upd.free)} did not converge")
    weights = parts.get("weights")
    if weights is not None and not weights.passed:
        raise AnalysisError(
            f"the ring-downs overrule the beat note (importance ESS {weights.ess:.0f}) with "
            f"{', '.join(upd.free)} refined; refine more H parameters (--refine)"
        )
    return HDraws(
        centre=centre,
        draws=draws,
        names=tuple(parts["names"]),
        refined=tuple(upd.free) if upd is not None else (),
    )


def h_part_of_tau_u(config, fits, h: HDraws) -> np.ndarray:
    """u_H(tau) (s), shaped like ``fits.tau_s``: the sd of tau over the draws ``h``.

    ``fits`` TF-CRDS :class:`~bayes_tfcrds.fit.ringdown.RingdownFits` of ``config`` made at
    ``fits.tf`` (``h.centre``); each draw moves tau by the implicit-function derivative of the fit
    in H(f) (the budget's first order). Zero for plain CRDS, whose model has no H; NaN where tau is
    not fitted or its fit did not converge.
    """
    tau = np.asarray(fits.tau_s, float)
    if fits.method != "tf-crds":
        return np.where(np.isfinite(tau), 0.0, np.nan)
    rd = config.ringdowns
    window = fits.window or "extinction"
    fitted = np.isfinite(tau) & np.isfinite(fits.tau_u_s) & np.asarray(fits.converged, bool)
    columns = [(j, np.nonzero(fitted[:, j])[0]) for j in range(tau.shape[1])]
    columns = [(j, rows) for j, rows in columns if rows.size]
    kernels = [
        (
            tau_h_kernels(
                rd.time_s,
                np.full(rows.size, fits.t_cut_s[j]),
                tau[rows, j],
                np.asarray(fits.amplitude_v)[rows, j],
                fits.tf,
                window,
                noise_v=rd.fit_noise_v,
                rows_of=rows,
            ),
            rows.size,
        )
        for j, rows in columns
    ]
    u_h = np.full(tau.shape, np.nan)
    for (j, rows), s in zip(columns, h_shifts_many(kernels, h.draws, fits.tf, names=h.names)):
        u_h[rows, j] = np.std(s, axis=0)
    return u_h


def fit_decay_times(
    config, t_cuts_s, calibration, rng: np.random.Generator, window: str = "extinction",
    n_draws: int = N_H_DRAWS, h: HDraws | None = None,
):  # fmt: skip
    """TF-CRDS decay times at the centre of H's posterior, with u(tau) whole (``fit``'s table).

    ``config`` with its noise colour accounted for
    (:func:`~bayes_tfcrds.fit.h_calibration.account_for_noise_colour`; as read, the stated
    noise is taken as white), ``t_cuts_s`` (s),
    ``calibration`` from :func:`~bayes_tfcrds.fit.h_calibration.calibrate` (whose refined
    parameters the posterior updates), ``h`` the draws when already made (``rng`` and ``n_draws``
    are then unused). Returns (RingdownFits with ``tau_u_h_s``, the :class:`HDraws`). Raises as
    :func:`laplace_h_draws`.
    """
    if h is None:
        h = laplace_h_draws(config, calibration, rng, window, n_draws)
    fits = fit_ringdowns(config.ringdowns, t_cuts_s, "tf-crds", tf=h.centre, window=window)
    return fits.with_h_uncertainty(h_part_of_tau_u(config, fits, h)), h
