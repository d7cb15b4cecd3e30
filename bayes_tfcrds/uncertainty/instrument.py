"""Instrument rows of the line-area budget, each sized from the data or a documented Type B.

The analysis model leaves out effects a real CRDS instrument may have. Each row below asks the
data how large the effect could be and carries the resulting change of A as a standard
uncertainty (Hz/m), without moving the estimate:

* **static detector nonlinearity** (V' = V + beta V^2/V_ref): beta is fitted on the ring-downs at
  the analysis H (the Appendix B refinement has absorbed what it can); the row is
  |dA/dbeta| sqrt(beta^2 + u(beta)^2), an uncorrected correction and its uncertainty taken
  together (JCGM 100 F.2.4.5). Consistent-with-zero data bound it by u(beta).
* **spectral baseline slope** and **etalon** (a sinusoidal alpha baseline): the line is refitted
  with the extra term; with BIC weight w of the extended model against the model used, the row is
  sqrt(w) |A_ext - A|, the root-mean-square shift of A over the two models about the estimate.
  An extension the data reject (w -> 0) adds nothing; one they prefer enters at full size, and
  is reported as a finding when it also moves A by more than A's fit uncertainty (the BIC
  does not charge for the etalon's period search, so a weight alone is no evidence).
* **CMDS reference, Type B** (for A/A_ref only): the relative spread of the letter's individual
  CMDS references, "below 0.06 %" under stable conditions (tf-crds-letter.tex, Results), taken as
  a rectangular distribution of full width 0.06 %: u = 0.03 %/sqrt(3) = 0.017 % of A_ref.

All fits reuse :mod:`bayes_tfcrds.fit.extensions`, the fitters discovery uses, so the budget and
discovery see one model of each effect.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from bayes_tfcrds.core.gum import Component
from bayes_tfcrds.fit.extensions import (
    PROFILE_SHAPE_FREE,
    SHARED,
    TransientSpec,
    bin_ringdowns,
    fit_spectrum_extended,
    fit_transient_rows,
    optimise_shared,
)
from bayes_tfcrds.fit.line import fit_line
from bayes_tfcrds.fit.spectrum import crds_spectrum

#: full width of the CMDS references' relative spread (letter, Results: "below 0.06 %")
CMDS_SPREAD_REL = 6e-4
#: a BIC weight above this marks an extension the data ask for (reported as a finding)
DEMANDED_WEIGHT = 0.5


@dataclass(frozen=True)
class InstrumentRow:
    """One instrument row: its component of u(A) (Hz/m) and what sized it.

    ``detail`` holds the numbers behind the row (SI units, keys say which); budget.json shows it
    with A in cm^-2 (:func:`~bayes_tfcrds.core.constants.edge_keys`).
    """

    component: Component
    detail: dict

    @property
    def finding(self) -> str | None:
        """A sentence when the data ask for the effect (the model used lacks it), else None."""
        return self.detail.get("finding")


def bic_weight(chi2_base: float, k_base: int, chi2_ext: float, k_ext: int, n: int) -> float:
    """BIC weight of the extended model against the base (equal prior odds), in [0, 1]."""
    d_bic = (chi2_ext + k_ext * np.log(n)) - (chi2_base + k_base * np.log(n))
    return float(1.0 / (1.0 + np.exp(np.clip(d_bic / 2.0, -700.0, 700.0))))


def spectrum_extension_row(spec, profile: str, gd: float, nu_ref: float, extra: str, label: str):
    """The row of one spectrum-level extension (``baseline_slope`` or ``etalon``).

    Both fits use the same fitter (the line with ``profile``), so A_ext - A is the effect of the
    extension alone, not of two fitters' conventions.
    """
    args = ("absorption", spec.nu_hz, spec.y, spec.u, profile, gd, nu_ref)
    base = fit_spectrum_extended(*args)
    ext = fit_spectrum_extended(*args, extras=(extra,))
    w = bic_weight(base.chi2, base.k, ext.chi2, ext.k, base.n)
    d_a = ext.value("line_area") - base.value("line_area")
    u = float(np.sqrt(w) * abs(d_a))
    detail = {
        "weight_extended": w,
        "chi2_base": base.chi2,
        "chi2_extended": ext.chi2,
        "delta_a_hz_per_m": float(d_a),
    }
    u_fit = base.stderr("line_area")
    detail["u_a_fit_hz_per_m"] = u_fit
    # a finding needs both: the data prefer the term, and it moves A beyond A's own fit u (the
    # BIC does not charge for the etalon's period search, so w alone is no evidence)
    if w > DEMANDED_WEIGHT and abs(d_a) > u_fit:
        detail["finding"] = (
            f"the spectrum asks for {label} (BIC weight {w:.2f}): A moves by "
            f"{d_a / base.value('line_area'):+.3%} with it"
        )
    comp = Component(
        label,
        None,
        u,
        1.0,
        "Hz/m",
        note=f"from the data: BIC weight of the line fit with {label} w = {w:.3g}; "
        "u = sqrt(w) |A(with it) - A|",
    )
    return InstrumentRow(comp, detail)


def _area_of(ringdowns, fit, profile, gd, nu_ref) -> float:
    """A (Hz/m) of the line fitted to the spectrum of one set of transient fits."""
    spectrum = crds_spectrum(ringdowns.nu_hz, fit.tau_s, fit.tau_u_s)
    return fit_line([spectrum], profile, gd, nu_ref).line_area


# Newton on chi2(beta): the first difference step (beta is dimensionless, V_ref = 1 V; the
# letter's chains give u(beta) of order 1e-5), then steps of u(beta) itself, where chi2 rises by
# about 1/2 and a quadratic model is accurate. The search runs on the records binned by
# BETA_SEARCH_BIN (as discovery's does), then Newton steps on the full records from there until
# a step is at most BETA_STEP_TOL u(beta). Newton's error after a step s is second order in s:
# on letter D4 a step of 0.17 u left 1.7e-4 u (the next step), so 0.5 u leaves about 2e-3 u
BETA_FIRST_STEP = 1e-5
BETA_SEARCH_BIN = 8
BETA_STEP_TOL = 0.5
BETA_MAX_ITER = 8


def _newton_1d(chi2, x, h, tol, lo, hi):
    """Newton steps on a scalar chi2 (central differences of step h, then u); (x, u) or None."""
    for _ in range(BETA_MAX_ITER):
        f0, fp, fm = chi2(x), chi2(x + h), chi2(x - h)
        curv = (fp - 2.0 * f0 + fm) / h**2
        if not (np.isfinite(curv) and curv > 0):
            return None
        step = -(fp - fm) / (2.0 * h) / curv
        u = float(np.sqrt(2.0 / curv))
        x += step
        if not lo < x < hi:
            return None
        if abs(step) <= tol * u:
            return float(x), u
        h = u
    return None


def _beta_by_newton(ringdowns, t_rows, rows, base, tau_start):
    """(beta, u(beta)) of V' = V + beta V^2/V_ref by Newton steps on the profiled ring-down chi2.

    Each chi2 refits every decay time (tau, B, b profiled) with the data mapped back through
    beta. The mapping acts on the data almost linearly, so chi2 is nearly quadratic in beta: a
    few steps on binned records and one or two on the full ones (three refits each) reach the
    minimum, where a bounded scalar search needed about 19 refits. u(beta) = sqrt(2 / chi2'')
    on the full records. Returns None when chi2 is not convex at a step, the minimum leaves the
    family's bounds, or BETA_MAX_ITER steps do not converge (the caller then searches).
    """
    ((_, _, lo, hi),) = SHARED["static_nonlinearity"]
    warm = np.asarray(tau_start, float)

    def chi2_of(data):
        def chi2(beta):
            spec = replace(base, shared={**base.shared, "static_nonlinearity": {"beta": beta}})
            return float(fit_transient_rows(data, t_rows, rows, spec, warm).chi2.sum())

        return chi2

    coarse = _newton_1d(
        chi2_of(bin_ringdowns(ringdowns, BETA_SEARCH_BIN)), 0.0, BETA_FIRST_STEP, 1e-3, lo, hi
    )
    if coarse is None:
        return None
    return _newton_1d(chi2_of(ringdowns), coarse[0], coarse[1], BETA_STEP_TOL, lo, hi)


def nonlinearity_row(ringdowns, t_cut_s, method, tf, window, profile, gd, nu_ref):
    """The static-nonlinearity row: beta fitted on the ring-downs, |dA/dbeta| sqrt(beta^2+u^2).

    dA/dbeta is a finite difference at beta_s = sqrt(beta^2 + u(beta)^2): the decay times are
    refitted with the data mapped back through beta_s and the line refitted, so the row carries
    the nonlinearity's whole path to A (distorted transients -> tau -> alpha -> profile fit). Both
    areas come from the same transient fitter, so their difference is the nonlinearity's alone.
    """
    m = ringdowns.n_points
    rows = np.arange(m)
    t_rows = np.full(m, float(t_cut_s))
    base = TransientSpec(method, window if method == "tf-crds" else None, tf)
    start = fit_transient_rows(ringdowns, t_rows, rows, base)
    fitted = _beta_by_newton(ringdowns, t_rows, rows, base, start.tau_s)
    if fitted is None:  # chi2 not convex about the steps: the bounded search of discovery
        params, _, cov = optimise_shared(
            "static_nonlinearity", ringdowns, t_rows, rows, base, start.tau_s
        )
        fitted = (params["beta"], float(np.sqrt(cov[0, 0])) if cov is not None else None)
    beta, u_beta = fitted
    cov = None if u_beta is None else u_beta**2
    u_beta = abs(beta) if u_beta is None else u_beta
    beta_s = float(np.hypot(beta, u_beta))
    shared = {"static_nonlinearity": {"beta": beta_s}}
    spec_s = TransientSpec(base.method, base.window, base.tf, shared)
    moved = fit_transient_rows(ringdowns, t_rows, rows, spec_s, start.tau_s)
    d_a = _area_of(ringdowns, moved, profile, gd, nu_ref) - _area_of(
        ringdowns, start, profile, gd, nu_ref
    )
    u = float(abs(d_a))
    detail = {"beta": beta, "u_beta": u_beta, "beta_used": beta_s, "delta_a_hz_per_m": d_a}
    if cov is not None and abs(beta) > 3.0 * u_beta:
        detail["finding"] = (
            f"the ring-downs show a static nonlinearity beta = {beta:.3g} +/- {u_beta:.2g} "
            "(V' = V + beta V^2 / 1 V): the analysis model lacks it"
        )
    comp = Component(
        "static detector nonlinearity",
        None,
        u,
        1.0,
        "Hz/m",
        note=f"from the data: beta = {beta:.3g} +/- {u_beta:.2g} fitted on the ring-downs at the "
        "analysis H; u = |A(beta_s) - A|, beta_s = sqrt(beta^2 + u(beta)^2)",
    )
    return InstrumentRow(comp, detail)


def instrument_rows(config, options, h_star, spec, gd: float, nu_ref: float) -> list:
    """The data-sized instrument rows of u(A) for one configuration (list of InstrumentRow).

    ``spec`` is the CRDS spectrum at the chosen t_cut (gd: Doppler HWHM, nu_ref: line
    centre, Hz). Spectrum rows are skipped (said in the row) for a profile the extended
    fitter does not know.
    """
    rows = [
        nonlinearity_row(
            config.ringdowns,
            options.t_cut_s,
            options.method,
            h_star,
            options.window,
            options.profile,
            gd,
            nu_ref,
        )
    ]
    profile = options.profile if options.profile in PROFILE_SHAPE_FREE else "qsdhcp"
    for extra, label in (("baseline_slope", "baseline slope"), ("etalon", "etalon")):
        rows.append(spectrum_extension_row(spec, profile, gd, nu_ref, extra, label))
    return rows


def cmds_type_b(a_ref_hat: float, ratio: float) -> Component:
    """The CMDS reference's Type B row of A/A_ref (sensitivity -A/A_ref^2, u in Hz/m)."""
    return Component(
        "reference area A_ref (CMDS), Type B",
        a_ref_hat,
        float(a_ref_hat * CMDS_SPREAD_REL / 2.0 / np.sqrt(3.0)),
        -ratio / a_ref_hat,
        "Hz/m",
        note="Type B: rectangular, full width 0.06 % of A_ref, the spread of the letter's "
        "individual CMDS references (tf-crds-letter.tex, Results)",
    )
