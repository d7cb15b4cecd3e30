"""Tests of bayes_tfcrds.core.gum against JCGM 100:2008 Example H.1 and hand-computed numbers.

GUM numbers below are those of JCGM 100:2008, Annex H.1 (end-gauge calibration) and its
Table H.1, cited section by section. Model (GUM Eq. H.3, first order):
    l = l_s + d - l_s (delta_alpha theta + alpha_s delta_theta)
with estimates delta_alpha = delta_theta = 0, so c(alpha_s) = c(theta) = 0,
c(delta_alpha) = -l_s theta, c(delta_theta) = -l_s alpha_s. Lengths in nm.
"""

from __future__ import annotations

import csv
import io
import json
import math

import numpy as np
import pytest
from scipy import stats

from bayes_tfcrds.core.gum import (
    COLUMNS,
    Budget,
    Component,
    format_uncertainty,
    format_value,
    monte_carlo_check,
    normalized_error,
    ratio,
)

# --- GUM H.1 inputs --------------------------------------------------------------------
L_S = 50_000_623.0  # nm; H.1.3.1: l_s = 50.000 623 mm from the calibration certificate
D_BAR = 215.0  # nm; H.1.5: d = 215 nm (mean of 5 comparator readings)
ALPHA_S = 11.5e-6  # 1/degC; H.1.3.3
THETA = -0.1  # degC; H.1.3.4: mean deviation of the bed from 20 degC


def _h1_d_budget() -> Budget:
    """H.1.3.2: the three parts of u(d) (Table H.1 rows d-bar, d1, d2)."""
    return Budget(
        "d",
        D_BAR,
        "nm",
        (
            # pooled s = 13 nm from 25 observations, mean of 5 readings: 13/sqrt(5) = 5.8 nm, nu=24
            Component("d_bar", D_BAR, 5.8, 1.0, "nm", 24, "Type A"),
            # comparator random effects: 0.01 um at 95 % from 6 readings: 10/2.57 = 3.9 nm, nu=5
            Component("d1", 0.0, 3.9, 1.0, "nm", 5, "Type B, t"),
            # comparator systematic effects: 0.02 um "at three sd": 6.7 nm, 25 % reliable, nu=8
            Component("d2", 0.0, 6.7, 1.0, "nm", 8, "Type B"),
        ),
    )


def _h1_budget() -> Budget:
    """Table H.1 with the unrounded Type B values the GUM derives them from (H.1.3)."""
    return Budget(
        "l",
        L_S + D_BAR,
        "nm",
        (
            # H.1.3.1: U = 0.075 um at k = 3 -> 25 nm; nu = 18 (certificate)
            Component("l_s", L_S, 25.0, 1.0, "nm", 18, "certificate, k=3"),
            # H.1.3.2: u(d) = 9.7 nm, nu_eff(d) = 25.6 (Table H.1)
            Component("d", D_BAR, 9.7, 1.0, "nm", 25.6, "comparator, combined"),
            # H.1.3.3: rectangular +-2e-6 /degC -> 2e-6/sqrt(3) = 1.2e-6 /degC; c = 0
            Component(
                "alpha_s", ALPHA_S, 2e-6 / math.sqrt(3), 0.0, "1/degC", math.inf, "rectangular"
            ),
            # H.1.3.4: sqrt(0.2^2 + (0.5/sqrt 2)^2) = 0.41 degC; c = 0 (its dof then do not matter)
            Component("theta", THETA, 0.41, 0.0, "degC", math.inf, "mean + arcsine cycle"),
            # H.1.3.5: rectangular +-1e-6 /degC -> 0.58e-6 /degC, 10 % reliable -> nu = 50
            Component(
                "delta_alpha", 0.0, 1e-6 / math.sqrt(3), -L_S * THETA, "1/degC", 50, "rectangular"
            ),
            # H.1.3.6: rectangular +-0.05 degC -> 0.029 degC, 50 % reliable -> nu = 2
            Component(
                "delta_theta", 0.0, 0.05 / math.sqrt(3), -L_S * ALPHA_S, "degC", 2, "rectangular"
            ),
        ),
    )


def test_gum_h1_sub_budgets_d_and_theta():
    d = _h1_d_budget()
    # H.1.3.2: u(d) = sqrt(5.8^2 + 3.9^2 + 6.7^2) = 9.7 nm
    assert d.combined_u == pytest.approx(math.sqrt(5.8**2 + 3.9**2 + 6.7**2), rel=1e-12)
    assert format_uncertainty(d.combined_u) == "9.7"
    # G.2b with the unrounded u(d) = 9.68 nm gives 25.4; the GUM's 25.6 uses u(d) = 9.7 nm
    den = 5.8**4 / 24 + 3.9**4 / 5 + 6.7**4 / 8
    assert d.effective_dof == pytest.approx(d.combined_u**4 / den, rel=1e-12)
    assert d.effective_dof == pytest.approx(25.4, abs=0.05)
    assert 9.7**4 / den == pytest.approx(25.6, abs=0.05)
    # H.1.3.4: u(theta) from u(theta_bar) = 0.2 degC and the arcsine cycle 0.5/sqrt(2) degC
    th = Budget(
        "theta",
        THETA,
        "degC",
        (
            Component("theta_bar", THETA, 0.2, 1.0, "degC"),
            Component("Delta", 0.0, 0.5 / math.sqrt(2), 1.0, "degC", note="arcsine"),
        ),
    )
    assert format_uncertainty(th.combined_u) == "0.41"
    assert th.effective_dof == math.inf


def test_gum_h1_end_gauge_budget():
    b = _h1_budget()
    # H.1.5: l = l_s + d = 50.000 623 mm + 215 nm = 50.000 838 mm
    assert b.value == 50_000_838.0
    assert format_value(b.value, b.combined_u) == "50000838"
    # Table H.1 sensitivity coefficients: c(delta_alpha) = -l_s theta = 5 mm degC,
    # c(delta_theta) = -l_s alpha_s = -0.575 um/degC (-575 nm/degC)
    comps = {c.name: c for c in b.components}
    assert comps["delta_alpha"].sensitivity == pytest.approx(5.0e6, rel=1e-3)
    assert comps["delta_theta"].sensitivity == pytest.approx(-575.0, rel=1e-4)
    # Table H.1 contributions |c_i| u(x_i): 25, 9.7, 0, 0, 2.9, 16.6 nm
    expected = {
        "l_s": 25.0,
        "d": 9.7,
        "alpha_s": 0.0,
        "theta": 0.0,
        "delta_alpha": 2.9,
        "delta_theta": 16.6,
    }
    for name, nm in expected.items():
        assert comps[name].contribution == pytest.approx(nm, abs=0.05), name
    # H.1.4 / Eq. H.5: u_c(l) = 32 nm
    assert round(b.combined_u) == 32
    assert b.combined_u == pytest.approx(
        math.sqrt(sum(c.contribution**2 for c in b.components)), rel=1e-12
    )
    # H.1.6: nu_eff(l) = 16.7 (G.2b), truncated to 16 for the t-table
    assert b.effective_dof == pytest.approx(16.7, abs=0.1)
    assert math.floor(b.effective_dof) == 16
    # H.1.6: k = t_99(16) = 2.92, U_99 = 2.92 x 32 nm = 93 nm (the GUM rounds u_c to 32
    # first; unrounded 2.9208 x 31.67 nm = 92.5 nm)
    k99 = b.coverage_factor(0.99)
    assert k99 == pytest.approx(2.92, abs=0.005)
    assert k99 == pytest.approx(stats.t.ppf(0.995, 16), rel=1e-12)
    assert round(k99 * round(b.combined_u)) == 93
    # 95 %: t_95(16) = 2.12, U_95 = 2.12 x 32 nm = 68 nm (67.1 nm unrounded)
    k95 = b.coverage_factor(0.95)
    assert k95 == pytest.approx(2.12, abs=0.005)
    assert round(k95 * round(b.combined_u)) == 68
    assert b.expanded(k95) == pytest.approx(67.1, abs=0.05)
    assert b.expanded() == pytest.approx(2.0 * b.combined_u)
    # shares of u_c^2 sum to 1; l_s dominates (625/1003), then delta_theta (275.5/1003)
    sh = b.shares()
    assert sum(sh.values()) == pytest.approx(1.0, abs=1e-12)
    assert sh["l_s"] == pytest.approx(25.0**2 / b.combined_u**2, rel=1e-12)
    assert sh["delta_theta"] == pytest.approx(0.2747, abs=5e-4)
    assert sh["alpha_s"] == 0.0 and sh["theta"] == 0.0


def test_coverage_factor_truncation_and_infinite_dof():
    b = _h1_budget()
    nu = b.effective_dof
    assert b.coverage_factor(0.95, truncate=False) == pytest.approx(stats.t.ppf(0.975, nu))
    assert b.coverage_factor(0.95) > b.coverage_factor(0.95, truncate=False)
    exact = Budget(
        "y", 1.0, "V", (Component("a", 1.0, 0.1, 1.0, "V"), Component("b", 2.0, 0.2, 1.0, "V"))
    )
    assert exact.effective_dof == math.inf
    assert exact.coverage_factor(0.95) == pytest.approx(1.959964, abs=1e-6)


# --- correlations ----------------------------------------------------------------------
def test_fully_correlated_inputs_with_opposite_sensitivities_cancel():
    comps = (Component("x1", 3.0, 0.5, +1.0, "m"), Component("x2", 1.0, 0.2, -1.0, "m"))
    corr = Budget("y", 2.0, "m", comps, {("x1", "x2"): 1.0})
    assert corr.combined_u == pytest.approx(abs(0.5 - 0.2), rel=1e-12)
    # same budget without the correlation adds in quadrature
    assert Budget("y", 2.0, "m", comps).combined_u == pytest.approx(math.hypot(0.5, 0.2))
    # key order does not matter
    assert Budget("y", 2.0, "m", comps, {("x2", "x1"): 1.0}).combined_u == pytest.approx(0.3)
    # shares c_i u_i (sum_j c_j u_j r_ij) / u_c^2: 0.5*0.3/0.09 and -0.2*0.3/0.09
    sh = corr.shares()
    assert sh["x1"] == pytest.approx(5.0 / 3.0)
    assert sh["x2"] == pytest.approx(-2.0 / 3.0)
    assert sum(sh.values()) == pytest.approx(1.0)
    # exact cancellation: u_c = 0, shares undefined
    zero = Budget(
        "y",
        2.0,
        "m",
        (Component("x1", 3.0, 0.2, 1.0), Component("x2", 1.0, 0.2, -1.0)),
        {("x1", "x2"): 1.0},
    )
    assert zero.combined_u == pytest.approx(0.0, abs=1e-12)
    assert all(math.isnan(v) for v in zero.shares().values())


def test_partial_correlation_matches_gum_eq16_by_hand():
    comps = (
        Component("a", 1.0, 0.3, 2.0),
        Component("b", 1.0, 0.4, -1.0),
        Component("c", 1.0, 1.0, 0.5),
    )
    b = Budget("y", 0.0, "", comps, {("a", "b"): 0.5, ("c", "a"): -0.25})
    s = (0.6, -0.4, 0.5)
    var = s[0] ** 2 + s[1] ** 2 + s[2] ** 2 + 2 * 0.5 * s[0] * s[1] + 2 * -0.25 * s[0] * s[2]
    assert b.combined_u == pytest.approx(math.sqrt(var), rel=1e-12)
    sh = b.shares()
    assert sh["a"] == pytest.approx(s[0] * (s[0] + 0.5 * s[1] - 0.25 * s[2]) / var)
    assert sum(sh.values()) == pytest.approx(1.0, abs=1e-12)


def test_ratio_budget_against_monte_carlo():
    # f = a/b, relative u 0.5 % and 0.8 %, r(a, b) = 0.6 (e.g. a shared calibration)
    a, ua, bb, ub, r = 10.0, 0.05, 5.0, 0.04, 0.6
    budget = Budget(
        "a/b",
        a / bb,
        "1",
        (
            Component("a", a, ua, 1.0 / bb, "V"),
            Component("b", bb, ub, -a / bb**2, "V"),
        ),
        {("a", "b"): r},
    )
    q, uq = ratio(a, ua, bb, ub, corr=r)
    assert q == pytest.approx(budget.value)
    assert uq == pytest.approx(budget.combined_u, rel=1e-12)
    cov = np.array([[ua**2, r * ua * ub], [r * ua * ub, ub**2]])
    mean, sd = monte_carlo_check(
        lambda x, y: x / y, [a, bb], cov, np.random.default_rng(20080101), n=200_000
    )
    assert budget.combined_u == pytest.approx(sd, rel=0.01)
    assert mean == pytest.approx(a / bb, rel=1e-3)
    # the check has teeth: dropping the correlation is off by ~47 %
    uncorrelated = Budget("a/b", a / bb, "1", budget.components)
    assert abs(uncorrelated.combined_u / sd - 1.0) > 0.2


def test_monte_carlo_check_linear_model_is_exact():
    cov = np.array([[0.04, -0.01], [-0.01, 0.09]])
    mean, sd = monte_carlo_check(lambda x, y: 2.0 * x - 3.0 * y, [1.0, 2.0], cov, 7, n=200_000)
    var = 4 * 0.04 + 9 * 0.09 - 2 * 2 * 3 * (-0.01)
    assert sd == pytest.approx(math.sqrt(var), rel=0.01)
    assert mean == pytest.approx(2.0 - 6.0, abs=0.01)
    with pytest.raises(ValueError):
        monte_carlo_check(lambda x, y: x.sum(), [1.0, 2.0], cov, 7, n=100)  # not vectorised


@pytest.mark.parametrize(
    "bad",
    [
        dict(correlations={("a", "zz"): 0.1}),  # unknown name
        dict(correlations={("a", "b"): 1.5}),  # |r| > 1
        dict(correlations={("a", "a"): 0.5}),  # self
        dict(correlations={("a", "b"): 0.3, ("b", "a"): 0.4}),  # conflicting
        dict(correlations={("a", "b"): 0.9, ("a", "c"): 0.9, ("b", "c"): -0.9}),  # not PSD
        dict(components=(Component("a", 1.0, 0.1, 1.0), Component("a", 2.0, 0.1, 1.0))),
    ],
)
def test_budget_rejects_inconsistent_input(bad):
    kw = dict(
        quantity="y",
        value=1.0,
        unit="",
        components=(
            Component("a", 1.0, 0.1, 1.0),
            Component("b", 1.0, 0.1, 1.0),
            Component("c", 1.0, 0.1, 1.0),
        ),
    )
    kw.update(bad)
    with pytest.raises(ValueError):
        Budget(**kw)


@pytest.mark.parametrize(
    "kw", [dict(u=-1.0), dict(dof=0.0), dict(u=math.nan), dict(sensitivity=math.inf), dict(name="")]
)
def test_component_rejects_bad_values(kw):
    args = dict(name="x", value=1.0, u=0.1, sensitivity=1.0) | kw
    with pytest.raises(ValueError):
        Component(**args)


# --- comparison helpers ----------------------------------------------------------------
def test_normalized_error_hand_numbers():
    # (10.3 - 10.0) / sqrt(0.2^2 + 0.15^2) = 0.3 / 0.25
    assert normalized_error(10.3, 0.2, 10.0, 0.15) == pytest.approx(1.2, rel=1e-12)
    assert normalized_error(10.0, 0.2, 10.3, 0.15) == pytest.approx(-1.2, rel=1e-12)
    with pytest.raises(ValueError):
        normalized_error(1.0, 0.0, 2.0, 0.0)


def test_ratio_hand_numbers():
    # 10/4 = 2.5; relative u 1 % and 2 %
    r, u = ratio(10.0, 0.1, 4.0, 0.08)
    assert r == 2.5
    assert u == pytest.approx(2.5 * math.sqrt(0.01**2 + 0.02**2), rel=1e-12)  # 0.0559
    _, u = ratio(10.0, 0.1, 4.0, 0.08, corr=0.5)
    assert u == pytest.approx(2.5 * math.sqrt(1e-4 + 4e-4 - 2e-4), rel=1e-12)  # 0.0433
    _, u = ratio(10.0, 0.1, 4.0, 0.04, corr=1.0)  # equal relative u, fully correlated
    assert u == pytest.approx(0.0, abs=1e-15)
    r, u = ratio(0.0, 0.3, 2.0, 0.1)  # a = 0: u_r = u_a / b
    assert (r, u) == (0.0, pytest.approx(0.15))


# --- reporting -------------------------------------------------------------------------
@pytest.mark.parametrize(
    "u, text",
    [
        (0.05 / math.sqrt(3), "0.029"),
        (2e-6 / math.sqrt(3), "1.2e-06"),
        (25.0, "25"),
        (9.96, "10"),
        (1234.5, "1200"),
        (0.406, "0.41"),
        (0.0, "0"),
    ],
)
def test_format_uncertainty_two_significant_digits(u, text):
    assert format_uncertainty(u) == text


@pytest.mark.parametrize(
    "x, u, text",
    [
        (50_000_838.2, 31.67, "50000838"),
        (1.23456, 0.0123, "1.235"),
        (98765.4, 1234.5, "98800"),
        (11.5e-6, 2e-6 / math.sqrt(3), "1.15e-05"),
        (-0.1, 0.41, "-0.10"),
        (215.0, 9.68, "215.0"),
        (3e-9, 1.2e-6, "0.0e-06"),
    ],
)
def test_format_value_to_the_decimal_place_of_u(x, u, text):
    assert format_value(x, u) == text


def test_markdown_csv_and_dict_outputs():
    b = _h1_budget()
    names = [c.name for c in b.components]
    md = b.to_markdown()
    for col in COLUMNS:
        assert col in md.splitlines()[0]
    for n in names:
        assert f"| {n} |" in md
    assert "| l_s | 50000623 | 25 | nm |" in md
    assert "| delta_theta | 0.000 | 0.029 | degC |" in md
    assert "u_c = 32 nm" in md

    rows = list(csv.DictReader(io.StringIO(b.to_csv())))
    assert b.to_csv().splitlines()[0] == ",".join(COLUMNS)
    assert [r["quantity"] for r in rows] == names
    for r, c in zip(rows, b.components):
        assert float(r["standard uncertainty"]) == c.u
        assert float(r["contribution to u(y)"]) == c.contribution
    assert rows[2]["dof"] == "inf"

    d = json.loads(json.dumps(b.to_dict(), allow_nan=False))
    assert [c["name"] for c in d["components"]] == names
    assert set(d["components"][0]) == {
        "name",
        "value",
        "u",
        "unit",
        "sensitivity",
        "contribution",
        "share",
        "dof",
        "note",
    }
    assert d["combined_u"] == pytest.approx(b.combined_u)
    assert d["effective_dof"] == pytest.approx(b.effective_dof)
    assert d["expanded_k2"] == pytest.approx(2.0 * b.combined_u)
    assert d["components"][2]["dof"] == "inf"
    assert sum(c["share"] for c in d["components"]) == pytest.approx(1.0)


def test_outputs_handle_none_values_correlations_and_pipes():
    b = Budget(
        "S",
        1.0,
        "cm/molecule",
        (
            Component("ring-down noise", None, 0.01, 1.0, note="Type A | emcee"),
            Component("p", 1333.0, 1.3, 1.0 / 1333.0, "Pa"),
        ),
        {("ring-down noise", "p"): 0.2},
    )
    md = b.to_markdown()
    assert "| ring-down noise | — |" in md and "Type A \\| emcee" in md
    assert "r(ring-down noise, p) = 0.2" in md
    assert list(csv.DictReader(io.StringIO(b.to_csv())))[0]["value"] == ""
    d = json.loads(json.dumps(b.to_dict(), allow_nan=False))
    assert d["components"][0]["value"] is None
    assert d["correlations"] == [{"a": "ring-down noise", "b": "p", "r": 0.2}]


def test_type_b_dof_from_the_reliability_of_u():
    """GUM G.4.2: u judged reliable to 25 % has nu = (1/2)(0.25)^-2 = 8 dof; exact u: inf."""
    from bayes_tfcrds.core.gum import dof_from_relative_u

    assert dof_from_relative_u(0.25) == pytest.approx(8.0)
    assert dof_from_relative_u(0.5) == pytest.approx(2.0)
    assert dof_from_relative_u(0.0) == math.inf
    with pytest.raises(ValueError):
        dof_from_relative_u(-0.1)


def test_a_budget_in_other_units_is_the_same_budget():
    """Converting a unit scales value, u and c_i so that every contribution is the same quantity
    in the new output unit; shares, dof and correlations do not change."""
    bud = Budget(
        "A",
        300.0,
        "Hz/m",
        (
            Component("noise", None, 2.0, 1.0, "Hz/m", dof=12),
            Component("f_c", 5e4, 900.0, -0.3, "Hz"),
        ),
        correlations={("noise", "f_c"): 0.4},
    )
    f = 1.0 / 2.99792458e10  # Hz/m -> cm^-2
    conv = bud.in_units({"Hz/m": ("cm^-2", f)})
    assert conv.unit == "cm^-2" and conv.components[0].unit == "cm^-2"
    assert conv.components[1].unit == "Hz" and conv.components[1].value == 5e4
    assert conv.combined_u == pytest.approx(f * bud.combined_u, rel=1e-12)
    assert conv.components[1].sensitivity == pytest.approx(-0.3 * f, rel=1e-12)
    assert conv.components[0].sensitivity == pytest.approx(1.0, rel=1e-12)
    assert conv.shares() == pytest.approx(bud.shares(), rel=1e-12)
    assert conv.effective_dof == pytest.approx(bud.effective_dof, rel=1e-12)
