"""The bundle's temperature acting on the line areas through the Doppler width the fits hold.

Every line fit holds the Doppler HWHM at GammaD(T) = nu0/c sqrt(2 ln2 k_B T/m), T the gauge's
reading (``fit.line_analysis.doppler_of``). A gauge error in T therefore moves the fitted A and
A_ref as well as the conversion of A into S: the fit trades the wrong Gaussian width against the
collisional width, its speed dependence and the narrowing, and the area follows. On the coverage
study's draws (400-930 Pa, qSDHCP) d ln A / d ln T ranged from -0.07 to -0.57; the A errors of
its 199 campaigns correlated with the drawn T errors (r = -0.13) before this row existed.

GUM treatment: T is one input quantity with one u(T). Its row in the A budget has
c = dA/dT; in S(T_ref) = f(A(T), p, T, x) and in A/A_ref(T) the derivative through the fits and
the explicit one add before squaring (the same T), so those budgets carry A without this row and
T with the total sensitivity. The Monte Carlo draws one T per trial for all three.
"""

from __future__ import annotations

from dataclasses import dataclass

from bayes_tfcrds.core.constants import edge_keys
from bayes_tfcrds.core.gum import Budget, Component
from bayes_tfcrds.fit.line import fit_line
from bayes_tfcrds.physics.lineshape import doppler_hwhm_hz

#: half the span of the central difference (K): d ln A/d ln T is linear to < 1e-3 of itself over
#: +-1 K (second differences of the fitted A were < 4e-5 A per K^2 on the coverage draws, against
#: first differences of 2e-4 to 2e-3 A per K), and 1 K keeps A's change (>= 2e-4 A) far above
#: the fitter's tolerance (xtol 1e-13)
STEP_K = 1.0

#: name of the row in the A budget; the Monte Carlo and the S and A/A_ref budgets find it by it
ROW_NAME = "temperature T (Doppler width of the line fit)"


@dataclass(frozen=True)
class DopplerSensitivity:
    """dA/dT and dA_ref/dT (Hz/m per K) at the bundle's T (K), whose u is ``temperature_u_k``.

    ``da_ref_dt`` is None without CMDS.
    """

    temperature_k: float
    temperature_u_k: float
    da_dt: float
    da_ref_dt: float | None
    step_k: float = STEP_K

    def to_dict(self, a_hat: float, a_ref_hat: float | None = None) -> dict:
        """For budget.json: dA/dT in cm^-2 per K (A's unit in every output) and d ln A / d ln T.

        ``a_hat``, ``a_ref_hat`` in Hz/m, as the derivatives inside.
        """
        out = {
            "temperature_k": self.temperature_k,
            "temperature_u_k": self.temperature_u_k,
            "step_k": self.step_k,
            "da_dt_hz_per_m_per_k": self.da_dt,
            "dln_a_dln_t": self.da_dt * self.temperature_k / a_hat,
        }
        if self.da_ref_dt is not None and a_ref_hat:
            out["da_ref_dt_hz_per_m_per_k"] = self.da_ref_dt
            out["dln_a_ref_dln_t"] = self.da_ref_dt * self.temperature_k / a_ref_hat
        return edge_keys(out)


def area_temperature_derivative(spectra, profile: str, base, sample, step_k: float = STEP_K):
    """dA/dT (Hz/m per K) of the least-squares line fit to ``spectra`` at fixed data.

    Central difference of two fits with the Doppler HWHM of T +- ``step_k`` (K), made as
    ``base`` (the analysis' fit at T) was: same profile, line centre, bounds and default start,
    so the derivative is that of the estimator the budget reports. (Not started from
    ``base``: a width that ended on its bound, ~1e-17 Hz, would set the fitter's parameter
    scale and leave its Fisher matrix singular.) It is the derivative of the primary profile's
    A: the model-averaged A the budget reports is taken to move with T as that A does (the
    profiles' spread is a row of its own).
    """
    t = sample.temperature_k

    def area(temperature_k):
        gd = float(doppler_hwhm_hz(sample.nu0_hz, temperature_k, sample.mass_u))
        fit = fit_line(spectra, profile, gd, base.nu_ref_hz, physical_bounds=base.physical_bounds)
        return fit.line_area

    return (area(t + step_k) - area(t - step_k)) / (2.0 * step_k)


def doppler_sensitivity(spec, lsq, cmds_spec, cmds_lsq, profile: str, sample):
    """The :class:`DopplerSensitivity` of a budget: A's fit (``spec``, ``lsq``) and CMDS's.

    ``cmds_spec``/``cmds_lsq`` None without CMDS.
    """
    da_ref = None
    if cmds_spec is not None:
        da_ref = area_temperature_derivative([cmds_spec], profile, cmds_lsq, sample)
    return DopplerSensitivity(
        temperature_k=float(sample.temperature_k),
        temperature_u_k=float(sample.temperature_u_k),
        da_dt=float(area_temperature_derivative([spec], profile, lsq, sample)),
        da_ref_dt=None if da_ref is None else float(da_ref),
    )


def temperature_row(sens: DopplerSensitivity, a_hat: float, dof: float):
    """The A budget's row of T through the Doppler width: c = dA/dT (Hz/m per K), u = u(T).

    ``dof`` that of the bundle's u(T) (the S budget's T row uses the same).
    """
    return Component(
        ROW_NAME,
        sens.temperature_k,
        sens.temperature_u_k,
        sens.da_dt,
        "K",
        dof=dof,
        note="Type B, normal: bundle /sample@temperature_u_k; the line fit holds the Doppler "
        f"HWHM at GammaD(T); c = dA/dT from fits at T +- {sens.step_k:g} K "
        f"(d ln A/d ln T = {sens.da_dt * sens.temperature_k / a_hat:+.3g}); the S and A/A_ref "
        "budgets add it to their own T sensitivity",
    )


def without_temperature_row(budget: Budget) -> Budget:
    """``budget`` without :data:`ROW_NAME` (for models in which T enters a second way)."""
    comps = tuple(c for c in budget.components if c.name != ROW_NAME)
    corr = {k: r for k, r in budget.correlations.items() if ROW_NAME not in k}
    return Budget(budget.quantity, budget.value, budget.unit, comps, corr)
