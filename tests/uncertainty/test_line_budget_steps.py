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
    """u(A/A_ref)^2 = (u_A/A_ref)^2 + (A u_ref/A_ref^2)^2 for independent A and A_ref (GUM Eq. 10);
    A_ref and u_ref are the mean and sd of the CMDS posterior draws."""
    rng = np.random.default_rng(1)
    a_ref = rng.normal(2.0e3, 3.0, size=20000)
    bud = lb._budget_ratio(2.004e3, 4.0, a_ref)
    m, s = a_ref.mean(), a_ref.std()
    assert bud.value == pytest.approx(2.004e3 / m, rel=1e-15, abs=0)
    expected = np.hypot(4.0 / m, 2.004e3 * s / m**2)
    assert bud.combined_u == pytest.approx(expected, rel=1e-12, abs=0)
    # sensitivities d(A/A_ref)/dA = 1/A_ref and d(A/A_ref)/dA_ref = -A/A_ref^2 (signs matter as
    # soon as the two are correlated)
    c = [comp.sensitivity for comp in bud.components]
    assert c[0] == pytest.approx(1 / m, rel=1e-12, abs=0)
    assert c[1] == pytest.approx(-2.004e3 / m**2, rel=1e-12, abs=0)
    assert lb._budget_ratio(1.0, 0.1, None) is None


def test_intensity_step_sensitivities_are_those_of_a_over_n():
    """S = A/N at the measured T, N = p x/(k_B T): c_A = S/A, c_p = -S/p, c_T = +S/T."""
    sample = SimpleNamespace(
        pressure_pa=666.6,
        pressure_u_pa=0.5,
        temperature_k=296.0,
        temperature_u_k=0.1,
        mole_fraction=1.0,
    )
    bud = lb._budget_s(sample, 3.0e2, 1.5)
    s = bud.value
    c = {comp.name: comp.sensitivity for comp in bud.components}
    # S is ~1e-25 cm/molecule: relative tolerances only (pytest.approx's default abs=1e-12
    # would accept any sign)
    assert c["line area A"] == pytest.approx(s / 3.0e2, rel=1e-12, abs=0)
    assert c["pressure p"] == pytest.approx(-s / 666.6, rel=1e-12, abs=0)
    assert c["temperature T"] == pytest.approx(s / 296.0, rel=1e-12, abs=0)
    rel = np.sqrt((1.5 / 3.0e2) ** 2 + (0.5 / 666.6) ** 2 + (0.1 / 296.0) ** 2)
    assert bud.combined_u == pytest.approx(s * rel, rel=1e-12, abs=0)


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
    assert set(inp.streams) == {"h", "line", "cmds", "pair"} and inp.chain_file("line") is None
    assert inp.gd > 0  # the Doppler HWHM (Hz) from the sample
