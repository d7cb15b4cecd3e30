"""The line area of ``linefit``, the demo and the t_cut study: at H's posterior centre, u(A) whole.

A TF-CRDS line area depends on H through every decay time, and in common to all of them: an H
error is not averaged away by the spectrum's many points, and on short-tau chains it outweighs
their noise (letter D3/D4: about 3 times the line fit's u(A)). The line fit alone sees the
points' noise. Here A is fitted from decay times at the centre of H's posterior (the draws of
:func:`~bayes_tfcrds.uncertainty.decay_times.laplace_h_draws`, the budget's Laplace path) and
H's part of u(A) is the sd, over those draws, of A's first-order shift: the implicit-function
kernels of each decay time in H(f) combined with the line fit's gain dA/dy (the budget's
``_h_sensitivity``). It adds to the fit's u in quadrature: the refinement's few records share
their noise with the spectrum, which the budget (not this summary) accounts for.

The budget holds the rest (p, T, x, the line-shape model, the instrument); this is the line
fit with the whole of H, not a budget.

Units: Hz/m (A, u inside), s (tau), Hz (H's frequencies).
"""

from __future__ import annotations

import numpy as np

from bayes_tfcrds.core.constants import C
from bayes_tfcrds.fit.h_calibration import account_for_noise_colour
from bayes_tfcrds.fit.line_analysis import analyse_line
from bayes_tfcrds.uncertainty.decay_times import HDraws, laplace_h_draws
from bayes_tfcrds.uncertainty.line_budget import h_shifts
from bayes_tfcrds.uncertainty.propagate import line_gain, tau_h_kernels


def area_h_shifts(config, analysis, h: HDraws) -> np.ndarray:
    """First-order shifts of A (Hz/m), one per draw of ``h``, about ``analysis`` (tf-crds).

    ``analysis`` a :class:`~bayes_tfcrds.fit.line_analysis.LineAnalysis` of ``config`` fitted at
    ``h.centre``. Each decay time of the spectrum moves by its kernel in H(f); A moves by the
    line fit's gain dA/d(1/(c tau)) times d(1/(c tau))/dtau.
    """
    fits = analysis.ringdown_fits.converged_only()
    tau, u = fits.tau_s[:, 0], fits.tau_u_s[:, 0]
    good = np.nonzero(np.isfinite(tau) & np.isfinite(u) & (u > 0))[0]  # crds_spectrum's points
    lf = analysis.line_fit
    gain = line_gain(lf)[lf.names.index("line_area")] * (-1.0 / (C * tau[good] ** 2))
    rd = config.ringdowns
    kernel = tau_h_kernels(
        rd.time_s,
        np.full(good.size, analysis.t_cut_s),
        tau[good],
        np.asarray(fits.amplitude_v)[good, 0],
        fits.tf,
        analysis.window,
        noise_v=rd.fit_noise_v,
        rows_of=good,
    ).combine(gain)
    return h_shifts(kernel, h.draws, fits.tf, 1, names=h.names)[:, 0]


def analyse_line_with_h(
    bundle, config, calibration, rng: np.random.Generator, t_cut_s: float = 4e-6,
    h: HDraws | None = None, **options,
):  # fmt: skip
    """TF-CRDS line analysis at the centre of H's posterior, with H's part of u(A).

    ``config`` with its noise colour accounted for and its ``noise`` in ``options`` (as to
    :func:`~bayes_tfcrds.fit.line_analysis.analyse_line`, whose ``window``, ``profile_name`` and
    ``physical_bounds`` ``options`` also takes), or as read (its colour is then diagnosed here,
    and both H's posterior and the fits use the corrected config), ``calibration`` from
    :func:`~bayes_tfcrds.fit.h_calibration.calibrate`, ``h`` the draws of an earlier call (one
    posterior serves every t_cut; drawn with ``rng`` otherwise). Returns (LineAnalysis with
    ``line_area_u_h_si``, the :class:`~bayes_tfcrds.uncertainty.decay_times.HDraws`). Raises
    ``AnalysisError`` as :func:`~bayes_tfcrds.uncertainty.decay_times.laplace_h_draws` does.
    """
    window = options.get("window", "extinction")
    if options.get("noise") is None:  # the same colour-corrected config for H and the fits
        config, options["noise"], _ = account_for_noise_colour(config, window)
    if h is None:
        h = laplace_h_draws(config, calibration, rng, window)
    la = analyse_line(
        bundle, config, "tf-crds", t_cut_s=t_cut_s, calibration=calibration, tf=h.centre, **options
    )
    return la.with_h_uncertainty(float(np.std(area_h_shifts(config, la, h)))), h
