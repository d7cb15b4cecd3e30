"""The budget's named steps, each on its own: what a step promises holds without the rest of
run_budget around it (independent arithmetic or the step's contract, never its own code)."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from bayes_tfcrds.simulate.campaign import Campaign, simulate_campaign
from bayes_tfcrds.uncertainty import line_budget as lb


def test_ratio_step_is_first_order_propagation_of_a_over_a_ref():
    """u(A/A_ref)^2 = (u_A/A_ref)^2 + (A u_ref/A_ref^2)^2 + (A u_B/A_ref^2)^2 for independent A
    and A_ref (GUM Eq. 10); A_ref and u_ref are the mean and sd of the CMDS posterior draws, u_B the
    CMDS Type B: A_ref x 0.06 % full width, rectangular (0.03 %/sqrt 3)."""
    rng = np.random.default_rng(1)
    a_ref = rng.normal(2.0e3, 3.0, size=20000)
    bud = lb._budget_ratio(2.004e3, 4.0, a_ref)
    m, s = a_ref.mean(), a_ref.std()
    assert bud.value == pytest.approx(2.004e3 / m, rel=1e-15, abs=0)
    u_b = m * 3e-4 / np.sqrt(3.0)
    expected = np.sqrt((4.0 / m) ** 2 + (2.004e3 * s / m**2) ** 2 + (2.004e3 * u_b / m**2) ** 2)
    assert bud.combined_u == pytest.approx(expected, rel=1e-12, abs=0)
    # sensitivities d(A/A_ref)/dA = 1/A_ref and d(A/A_ref)/dA_ref = -A/A_ref^2 (signs matter as
    # soon as the two are correlated)
    c = [comp.sensitivity for comp in bud.components]
    assert c[0] == pytest.approx(1 / m, rel=1e-12, abs=0)
    assert c[1] == pytest.approx(-2.004e3 / m**2, rel=1e-12, abs=0)
    assert c[2] == pytest.approx(-2.004e3 / m**2, rel=1e-12, abs=0)
    assert lb._budget_ratio(1.0, 0.1, None) is None


def _s_ref_oracle(a_hz_per_m, p_pa, t_k, x):
    """S(296 K) in cm/molecule from A, p, T, x: the HITRAN conversion with hapi's TIPS-2021 Q and
    the formula of hapi's EnvironmentDependency_Intensity (CODATA c2), written out here so that
    the budget step is checked against a model it does not share code with."""
    import contextlib
    import io

    with contextlib.redirect_stdout(io.StringIO()):  # hapi prints a banner on import
        import hapi

    c2, e_cm, nu_cm, k_b, c = 1.438776877, 1059.3718, 6410.879558, 1.380649e-23, 299792458.0

    def population(t):  # Boltzmann factor x stimulated emission / Q
        q = hapi.partitionSum(5, 1, t, version=2021)
        return np.exp(-c2 * e_cm / t) * -np.expm1(-c2 * nu_cm / t) / q

    s_t = a_hz_per_m / (1e4 * c) / (p_pa * x / (k_b * t_k) * 1e-6)  # A/N, cm/molecule
    return s_t * population(296.0) / population(t_k)


@pytest.mark.parametrize("temperature_k", [280.0, 296.0, 310.0])
def test_intensity_step_is_s_at_296_k_with_the_sensitivities_of_the_full_model(temperature_k):
    """S(296 K) = A k_B T/(p x) Q(T)/Q(296) exp(c2 E'' (1/T - 1/296)) x stimulated emission:
    value and every c_i against central differences of an independent model (hapi's Q), and
    c_T = S d ln S(296 K)/dT, about -0.0107 S /K, never the +S/T of S = A/N at T."""
    sample = SimpleNamespace(
        pressure_pa=666.6,
        pressure_u_pa=0.5,
        temperature_k=temperature_k,
        temperature_u_k=0.1,
        mole_fraction=0.98,
    )
    a, u_a = 3.0e2, 1.5
    bud = lb._budget_s(sample, a, u_a)
    x0 = {"A": a, "p": 666.6, "T": temperature_k, "x": 0.98}
    s = _s_ref_oracle(*x0.values())
    # S is ~1e-25 cm/molecule: relative tolerances only (pytest.approx's default abs=1e-12
    # would accept any sign); 4e-7 covers the two Q interpolations (TIPS-2021 nodes, 5e-8 each)
    assert bud.value == pytest.approx(s, rel=4e-7, abs=0)
    assert "296" in bud.quantity and bud.unit == "cm/molecule"
    names = {"A": "line area A", "p": "pressure p", "T": "temperature T", "x": "mole fraction x"}
    c = {comp.name: comp.sensitivity for comp in bud.components}
    steps = {"A": 1e-4 * a, "p": 1e-4 * 666.6, "T": 0.05, "x": 1e-5}
    for key, h in steps.items():
        up, down = dict(x0), dict(x0)
        up[key] += h
        down[key] -= h
        fd = (_s_ref_oracle(*up.values()) - _s_ref_oracle(*down.values())) / (2 * h)
        # central differences: O(h^2) ~ 1e-8 relative; hapi's piecewise-Lagrange Q has a
        # derivative 1e-5 off the spline's (the T row), so 1e-4 relative
        assert c[names[key]] == pytest.approx(fd, rel=1e-4, abs=0), key
    dlns_dt = c["temperature T"] / bud.value
    # -c2 E''/T^2 dominates: -0.0123 /K at 280 K, -0.0106 at 296 K, -0.0094 at 310 K
    assert -0.0125 < dlns_dt < -0.0092
    if temperature_k == 296.0:
        assert dlns_dt == pytest.approx(-0.010647, rel=1e-3)
    rel = np.sqrt((u_a / a) ** 2 + (0.5 / 666.6) ** 2 + (dlns_dt * 0.1) ** 2)
    assert bud.combined_u == pytest.approx(bud.value * rel, rel=1e-12, abs=0)


def _run(passed):
    return SimpleNamespace(
        rhat_max=1.002 if passed else 1.3,
        ess_min=900.0 if passed else 40.0,
        passed=passed,
        status="ok" if passed else "rhat",
        n_steps=2500,
    )


@pytest.mark.parametrize("passed", [True, False])
def test_gates_step_never_shows_a_failed_result(passed):
    summary = {
        "line_area": {"value": 1.0},
        "reference_area": {"value": 1.0},
        "ratio": {"value": 1.0},
        "en": 0.1,
        "intensity": {"value": 1.0},
    }
    options = lb.BudgetOptions(posterior="mcmc")
    lb._apply_gates(summary, options, {"h": _run(True), "line": _run(passed)})
    assert summary["diagnostics"]["passed"] is passed
    if passed:
        assert summary["status"] == "ok" and summary["line_area"] == {"value": 1.0}
    else:
        assert summary["status"].startswith("failed")
        assert all(
            summary[k] is None for k in ("line_area", "reference_area", "ratio", "en", "intensity")
        )
        assert summary["unconverged_estimates"]["line_area"] == {"value": 1.0}


def test_with_steps_refuses_inconsistent_lengths():
    o = lb.BudgetOptions()
    assert o.with_steps(100).max_steps == max(800, o.max_steps)
    assert o.with_steps(100, 300).max_steps == 300
    with pytest.raises(ValueError, match="--steps"):
        o.with_steps(500, 100)
    with pytest.raises(ValueError):
        o.with_steps(0)


def test_inputs_step_refuses_a_t_cut_beyond_the_record():
    from bayes_tfcrds.fit.line_analysis import LineFitError

    small = replace(Campaign(), n_points=15, n_samples=2048, n_avg=5)
    bundle, _ = simulate_campaign(["letter-D2"], np.random.default_rng(0), small)
    cfg = bundle.configs["D2"]
    late = float(cfg.ringdowns.time_s[-1])
    with pytest.raises(LineFitError, match="beyond the record"):
        lb._inputs(
            bundle, cfg, lb.BudgetOptions(t_cut_s=late), np.random.default_rng(0), None, False
        )
    inp = lb._inputs(bundle, cfg, lb.BudgetOptions(), np.random.default_rng(0), None, False)
    assert set(inp.streams) == {"h", "line", "cmds", "pair", "mc", "shapes"}
    assert inp.chain_file("line") is None
    assert inp.gd > 0  # the Doppler HWHM (Hz) from the sample


def test_monte_carlo_of_the_s_model_agrees_with_the_gum_budget():
    """JCGM 101 on the budget's own S(296 K) model: with near-linear inputs (u/x ~ 1e-3) the MC u
    and y match the GUM budget's; tolerance 1.5 % on u (MC se of u at >= 2e4 trials < 0.5 %, the
    resampled 2e5 A draws carry 0.16 %, the adaptive delta of 2 digits <= 0.6 %) and 0.2 u on y."""
    from bayes_tfcrds.core.gum import Budget, Component
    from bayes_tfcrds.physics.linedata import load_line
    from bayes_tfcrds.uncertainty.monte_carlo import budget_monte_carlo

    rng = np.random.default_rng(3)
    sample = SimpleNamespace(
        pressure_pa=666.6,
        pressure_u_pa=0.5,
        temperature_k=301.0,
        temperature_u_k=0.1,
        mole_fraction=0.98,
    )
    a, u_stat, u_rect = 3.0e2, 0.3, 0.2
    budget_a = Budget(
        "line area A",
        a,
        "Hz/m",
        (
            Component("ring-down noise (line fit given H)", None, u_stat, 1.0, "Hz/m"),
            Component("t_cut choice", None, u_rect, 1.0, "Hz/m", note="Type B: rectangular"),
        ),
    )
    a_total = rng.normal(a, u_stat, 200_000)
    bud = lb._budget_s(sample, a, budget_a.combined_u)
    mc = budget_monte_carlo(budget_a, a_total, sample, None, rng, lb.intensity_model(load_line()))
    assert mc.intensity.stabilised and mc.ratio is None
    assert mc.intensity.u == pytest.approx(bud.combined_u, rel=0.015)
    assert abs(mc.intensity.value - bud.value) < 0.2 * bud.combined_u
    assert mc.line_area.u == pytest.approx(budget_a.combined_u, rel=0.015)
    # near-normal output: k from the MC interval close to 1.96 (GUM k = 2 is 2 % wider)
    assert mc.intensity.k == pytest.approx(1.96, abs=0.03)


def test_budget_md_names_the_parameters_the_data_do_not_identify():
    from bayes_tfcrds.uncertainty.outputs import identification_markdown

    ident = {
        "not_identified": ["f_c_hz", "a_r"],
        "threshold_max_z": 4.5,
        "descriptions": [
            {
                "f_c_hz": 2.87e6,
                "a_r": 0.026,
                "f_r_hz": 5e5,
                "gamma_r": 0.17,
                "max_z": 0.07,
                "differs_in": ["f_c_hz", "a_r"],
            }
        ],
    }
    md = identification_markdown(ident)
    assert "**Not identified: f_c_hz, a_r.**" in md and "| 2.87e+06 | 0.026 |" in md
    ident.update(not_identified=[], descriptions=[])
    assert "Every sampled H parameter" in identification_markdown(ident)


def test_h_shifts_of_many_kernels_are_each_kernels_own_with_h_evaluated_once_per_grid(
    monkeypatch,
):
    # the decay-time table propagates the same H draws through one kernel per t_cut: H(f) of a
    # chunk of draws is evaluated once per frequency grid and the shifts stay the same to the bit
    from bayes_tfcrds.physics.transfer_function import TFParams
    from bayes_tfcrds.uncertainty import propagate

    rng = np.random.default_rng(3)
    h_star = TFParams(f_c_hz=2e6, a_r=0.2, f_r_hz=5e6, gamma_r=1.5)
    draws = np.column_stack(
        [
            h_star.f_c_hz * (1 + 0.01 * rng.standard_normal(250)),
            h_star.a_r + 0.01 * rng.standard_normal(250),
            h_star.f_r_hz * (1 + 0.01 * rng.standard_normal(250)),
            h_star.gamma_r * (1 + 0.01 * rng.standard_normal(250)),
        ]
    )
    names = ("f_c_hz", "a_r", "f_r_hz", "gamma_r")
    shared, other = np.arange(513) * 1e5, np.arange(257) * 2e5  # two rfft grids (Hz)

    def kernel(f_hz, n_rows):
        k = rng.standard_normal((n_rows, f_hz.size)) + 1j * rng.standard_normal((n_rows, f_hz.size))
        return propagate.TauKernels(((np.arange(n_rows), f_hz, k),))

    sets = [(kernel(shared, 5), 5), (kernel(shared, 3), 3), (kernel(other, 4), 4)]
    alone = [lb.h_shifts(k, draws, h_star, n, names=names) for k, n in sets]
    calls = []
    real = propagate.transfer_function_of_draws
    monkeypatch.setattr(
        propagate, "transfer_function_of_draws", lambda *a: calls.append(a[0].size) or real(*a)
    )
    together = lb.h_shifts_many(sets, draws, h_star, names=names)
    for a, b in zip(alone, together):
        np.testing.assert_array_equal(a, b)
    # 3 chunks of 100 draws, each through the shared grid once and the other grid once
    assert sorted(calls) == [257] * 3 + [513] * 3
    assert lb.h_shifts_many([], None, h_star) == []
