"""JCGM 101 Monte Carlo of the whole budget model, beside the GUM budgets of A, S(T_ref), A/A_ref.

The model is the one the GUM budgets linearise, evaluated at every draw:

* A = A_stat + sum_i c_i delta_i. A_stat: the H-shifted posterior draws of A the budget already
  forms (ring-down noise and every H row at once, with their correlations), resampled
  (:class:`~bayes_tfcrds.core.mcm.Empirical`); delta_i: each other row of the A budget as a
  zero-mean effect, rectangular where the row says rectangular, else normal with its u.
* S(T_ref) = :func:`~bayes_tfcrds.uncertainty.line_budget.intensity_model` (A, p, T, x), the
  function the GUM budget of S evaluates: p and T normal with the bundle's u (the bundle states
  no distribution), x exact (the bundle has no u(x)). The isotopic abundance is not an input of
  the shipped model (HITRAN intensities include the natural abundance and x is that of CO).
* A/A_ref with A_ref from the CMDS posterior draws (resampled) times its rectangular Type B.
* T, when the budget has the row of T through the fits' Doppler width
  (:mod:`~bayes_tfcrds.uncertainty.doppler`): one normal draw of T per trial moves A by
  dA/dT (T - T_hat), A_ref by dA_ref/dT (T - T_hat) and enters S's model, so the three
  quantities see the same T, as the GUM budgets' total sensitivities do.

Each by :func:`~bayes_tfcrds.core.mcm.adaptive_monte_carlo` (2 significant digits of u, 95 %),
in the budget's SI units (A in Hz/m, S in cm/molecule); unit conversion happens at the edges.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bayes_tfcrds.core.constants import edge_budget, line_area_to_cm2
from bayes_tfcrds.core.gum import Budget
from bayes_tfcrds.core.mcm import (
    Empirical,
    MonteCarloResult,
    Normal,
    Rectangular,
    adaptive_monte_carlo,
)
from bayes_tfcrds.uncertainty.doppler import ROW_NAME, DopplerSensitivity
from bayes_tfcrds.uncertainty.instrument import CMDS_SPREAD_REL

# rows of the A budget that the H-shifted posterior draws of A already carry
STATISTICAL_ROWS = ("ring-down noise", "H: ")
MAX_TRIALS = 1_500_000  # cap: the three runs stay under a second; reported if reached


@dataclass(frozen=True)
class BudgetMonteCarlo:
    """The JCGM 101 results of one budget: A (Hz/m), S(T_ref) (cm/molecule), A/A_ref (or None)."""

    line_area: MonteCarloResult
    intensity: MonteCarloResult
    ratio: MonteCarloResult | None
    inputs: str


def _effect_inputs(budget_a: Budget) -> list:
    """The A budget's rows not in the posterior draws: zero-mean effects times their c_i."""
    out = []
    for c in budget_a.components:
        # T's row: a shared input of every model below (a draw of T, not an effect of A alone)
        if c.name.startswith(STATISTICAL_ROWS) or c.name == ROW_NAME or c.u == 0.0:
            continue
        u = abs(c.sensitivity) * c.u  # in A's unit: the model adds c_i delta_i
        out.append(Rectangular.from_u(0.0, u) if "rectangular" in c.note.lower() else Normal(0, u))
    return out


def _area_sum(a_stat, *effects):
    return a_stat + sum(effects) if effects else a_stat


def budget_monte_carlo(
    budget_a: Budget,
    a_total: np.ndarray,
    sample,
    a_ref: np.ndarray | None,
    rng: np.random.Generator,
    s_model,
    max_trials: int = MAX_TRIALS,
    doppler: DopplerSensitivity | None = None,
) -> BudgetMonteCarlo:
    """Adaptive Monte Carlo of A, S(T_ref) and A/A_ref (module doc).

    ``sample``: the bundle's (p, T, x and their u); ``s_model``: S(T_ref) = s_model(A, p, T, x),
    the function the GUM budget of S evaluates (``line_budget.intensity_model``). ``doppler``:
    dA/dT and dA_ref/dT through the fits' Doppler width (None: the fits do not read T).
    """
    if doppler is None and any(c.name == ROW_NAME for c in budget_a.components):
        raise ValueError(f"A's budget has the row {ROW_NAME!r}: pass its DopplerSensitivity")
    effects = _effect_inputs(budget_a)
    a_inputs = [Empirical(np.asarray(a_total, float)), *effects]
    n_a = len(a_inputs)
    t_hat = sample.temperature_k
    temperature = Normal(t_hat, sample.temperature_u_k)
    da_dt = 0.0 if doppler is None else doppler.da_dt
    da_ref_dt = 0.0 if doppler is None or doppler.da_ref_dt is None else doppler.da_ref_dt

    def run(model, inputs):
        return adaptive_monte_carlo(model, inputs, rng, max_trials=max_trials)

    def area(x, t):  # A of one set of draws: its statistical draw, the effects and T's shift
        return _area_sum(*x[:n_a]) + da_dt * (t - t_hat)

    if doppler is None:
        res_a = run(_area_sum, a_inputs)
    else:
        res_a = run(lambda *x: area(x, x[n_a]), a_inputs + [temperature])
    state = [
        Normal(sample.pressure_pa, sample.pressure_u_pa),
        temperature,
        Normal(sample.mole_fraction, 0.0),
    ]
    res_s = run(lambda *x: s_model(area(x, x[n_a + 1]), *x[n_a:]), a_inputs + state)
    res_r = None
    if a_ref is not None:
        # A_ref: its posterior draws, shifted with T, times (1 + the CMDS Type B relative error,
        # rectangular)
        cmds_b = Rectangular.from_u(0.0, CMDS_SPREAD_REL / 2.0 / np.sqrt(3.0))
        res_r = run(
            lambda *x: (
                area(x, x[n_a + 2])
                / ((x[n_a] + da_ref_dt * (x[n_a + 2] - t_hat)) * (1.0 + x[n_a + 1]))
            ),
            a_inputs + [Empirical(np.asarray(a_ref)), cmds_b, temperature],
        )
    note = (
        f"A: {np.size(a_total)} H-shifted posterior draws of A (ring-down noise and H, "
        f"resampled) + {len(effects)} other rows (rectangular where the row says so, else "
        "normal)"
        + (
            "; T normal with the bundle's u, one draw per trial shifting A, A_ref (dA/dT through "
            "the fits' Doppler width) and S's model alike"
            if doppler is not None
            else ""
        )
        + "; S: p, T normal with the bundle's u, x exact; A_ref: CMDS posterior draws times "
        "its rectangular Type B"
    )
    return BudgetMonteCarlo(res_a, res_s, res_r, note)


def _entry(res: MonteCarloResult, scale: float = 1.0, unit: str = "") -> dict:
    """JSON entry of one result; y, u, interval multiplied by ``scale`` into ``unit``."""
    d = res.to_dict()
    for key in ("value", "u", "expanded"):
        d[key] = d[key] * scale
    d["interval"] = [v * scale for v in d["interval"]]
    if d["interval_shortest"] is not None:
        d["interval_shortest"] = [v * scale for v in d["interval_shortest"]]
    d["tolerance"] = d["tolerance"] * scale
    d["unit"] = unit
    return d


def _gum_entry(budget: Budget, scale: float = 1.0) -> dict:
    """nu_eff (Welch-Satterthwaite), k = 2 and U, and k = t_95(nu_eff) with U_95, ``scale``d."""
    nu = budget.effective_dof
    k95 = budget.coverage_factor(0.95) if nu > 0 else float("nan")
    return {
        "effective_dof": "inf" if np.isinf(nu) else float(nu),
        "k": 2.0,
        "expanded": budget.expanded(2.0) * scale,
        "k_95": k95,
        "expanded_95": budget.expanded(k95) * scale,
    }


def add_to_summary(summary: dict, budgets: dict, mc: BudgetMonteCarlo | None) -> None:
    """GUM dof, k, U and the Monte Carlo result into the budget.json entries, in their units.

    ``budgets``: {"line_area": Budget of A (Hz/m), "intensity": of S, "ratio": of A/A_ref or
    None}; A's entries in cm^-2 like the rest of ``line_area``. The full GUM tables go under
    ``gum_budgets`` (Budget.to_dict, line areas in cm^-2), one per quantity.
    """
    to_cm2 = float(line_area_to_cm2(1.0))
    scales = {
        "line_area": (to_cm2, "cm^-2"),
        "intensity": (1.0, "cm/molecule"),
        "ratio": (1.0, "1"),
    }
    for key, (scale, unit) in scales.items():
        entry, budget = summary.get(key), budgets.get(key)
        if entry is None or budget is None:
            continue
        entry.update(_gum_entry(budget, scale))
        res = None if mc is None else getattr(mc, key)
        entry["monte_carlo"] = None if res is None else _entry(res, scale, unit)
    summary["gum_budgets"] = {
        key: edge_budget(b).to_dict() for key, b in budgets.items() if b is not None
    }
    if mc is not None:
        summary["monte_carlo_inputs"] = mc.inputs
