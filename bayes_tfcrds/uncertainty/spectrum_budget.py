"""The GUM budget of a spectrum a lab kept (tau(nu) or alpha(nu)): no transfer-function rows.

Without ring-down records there is no detection chain to model, no t_cut to choose and no
posterior of decay times: the budget of A holds the line fit's own uncertainty and the
line-shape model (the chosen profile against an alternative), and T through the fit's Doppler
width (:mod:`~bayes_tfcrds.uncertainty.doppler`); the intensity budget adds p, T and x as the
full budget does (``line_budget._budget_s``). Labelled as spectrum-level
input wherever it is shown, so it is never read as a TF-CRDS budget.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bayes_tfcrds.core.constants import edge_budget
from bayes_tfcrds.core.gum import Budget, Component, dof_from_relative_u
from bayes_tfcrds.fit.line import LineFit, fit_line
from bayes_tfcrds.fit.line_analysis import SPECTRUM_LEVEL, LineAnalysis, doppler_of
from bayes_tfcrds.uncertainty.doppler import doppler_sensitivity, temperature_row
from bayes_tfcrds.uncertainty.line_budget import REL_U_CERTIFICATE, _budget_s

#: dof of the bundle's u(T): judged reliable to 10 %, as in the full budget (GUM G.4.2)
T_DOF = dof_from_relative_u(REL_U_CERTIFICATE)


def alternative_profile(profile: str) -> str:
    """The profile the line-shape row compares with: sdvp, or qsdhcp when sdvp was fitted."""
    return "qsdhcp" if profile == "sdvp" else "sdvp"


@dataclass(frozen=True)
class SpectrumBudget:
    """Budgets of A (Hz/m) and S(T_ref) (cm/molecule) from spectrum-level input.

    ``alternative`` is the fit with the other profile behind the line-shape row.
    """

    analysis: LineAnalysis
    alternative: LineFit
    budget_a: Budget
    budget_s: Budget
    note: str = SPECTRUM_LEVEL

    def to_dict(self) -> dict:
        """The JSON record: both budgets (A in cm^-2, as every output shows it) and the label."""
        return {
            "input": self.note,
            "line_area": edge_budget(self.budget_a).to_dict(),
            "intensity": edge_budget(self.budget_s).to_dict(),
        }


def spectrum_budget(analysis: LineAnalysis, sample) -> SpectrumBudget:
    """GUM budget of a spectrum-level line fit (``fit.line_analysis.analyse_spectrum``).

    Rows of A: the fit (Type A, from its covariance) and the line-shape model (Type B,
    rectangular over the difference of A between ``analysis.profile`` and the alternative
    profile, as in the full budget). ``sample`` (p, T, x with u, SI) feeds the S budget.
    """
    lf = analysis.line_fit
    alt_name = alternative_profile(analysis.profile)
    alt = fit_line([analysis.spectrum], alt_name, doppler_of(sample), sample.nu0_hz)
    sens = doppler_sensitivity(analysis.spectrum, lf, None, None, analysis.profile, sample)
    budget_a = Budget(
        quantity=f"line area A ({SPECTRUM_LEVEL})",
        value=float(lf.line_area),
        unit="Hz/m",
        components=(
            Component(
                "line fit (spectrum-level input)",
                None,
                float(lf.line_area_u),
                1.0,
                "Hz/m",
                note="Type A: the profile fit's covariance, from the stated u of the spectrum",
            ),
            Component(
                f"line-shape model ({analysis.profile} vs {alt_name})",
                None,
                float(abs(lf.line_area - alt.line_area) / np.sqrt(12)),
                1.0,
                "Hz/m",
                note="Type B: rectangular over the difference of the two profiles' A",
            ),
        ),
    )
    u_a_but_t = budget_a.combined_u  # S's model reads T itself: A enters without T's row
    budget_a = Budget(  # T through the fit's Doppler width, as in the full budget
        budget_a.quantity,
        budget_a.value,
        budget_a.unit,
        (*budget_a.components, temperature_row(sens, lf.line_area, T_DOF)),
    )
    budget_s = _budget_s(sample, float(lf.line_area), u_a_but_t, da_dt=sens.da_dt)
    return SpectrumBudget(analysis, alt, budget_a, budget_s)
