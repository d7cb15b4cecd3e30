"""The line-intensity temperature conversion against hitran-api (the test-only oracle).

Q(T) of 12C16O against hapi.partitionSum(5, 1, T) and S(T)/S(T_ref) against hapi's
EnvironmentDependency_Intensity (the HITRAN formula), with tolerances derived from what differs
between the two implementations (interpolation scheme, TIPS revision, hapi's value of c2).
"""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

import numpy as np
import pytest

from bayes_tfcrds.physics.intensity import (
    intensity_log_derivative,
    intensity_ratio,
    partition_function,
    partition_table,
)
from bayes_tfcrds.physics.linedata import load_line

with contextlib.redirect_stdout(io.StringIO()):  # hapi prints a banner on import
    import hapi

CO = (5, 1)  # HITRAN molecule 5 (CO), isotopologue 1 (12C16O)
E_CM = 1059.3718  # E'' of R(23), cm^-1 (the line file)
NU0_CM = 6410.879558  # cm^-1 (the line file)
C2_CODATA = 1.438776877  # hc/k_B, cm K (CODATA 2018, exact from the SI-defined h, c, k_B)
C2_HAPI = 1.4388028496642257  # the constant hapi 1.3.0.0 writes in EnvironmentDependency_Intensity


def _q_hapi(t, version=2021):
    return np.array([hapi.partitionSum(*CO, float(x), version=version) for x in np.atleast_1d(t)])


def _ratio_hapi(t, t_ref=296.0, version=2021):
    """hapi's own S(T)/S(T_ref) (its Q and its c2)."""
    q_ref = hapi.partitionSum(*CO, t_ref, version=version)
    return np.array(
        [
            hapi.EnvironmentDependency_Intensity(1.0, x, t_ref, q, q_ref, E_CM, NU0_CM)
            for x, q in zip(np.atleast_1d(t), _q_hapi(t, version))
        ]
    )


def _ratio_formula(t, t_ref=296.0, c2=C2_CODATA, e_cm=E_CM, nu0_cm=NU0_CM):
    """The formula of hapi's source with hapi's TIPS-2021 Q and a chosen c2."""
    t = np.atleast_1d(np.asarray(t, float))

    def pop(x):
        return np.exp(-c2 * e_cm / x) * -np.expm1(-c2 * nu0_cm / x)

    return _q_hapi(t_ref) / _q_hapi(t) * pop(t) / pop(t_ref)


def test_table_nodes_are_tips2021_digit_for_digit():
    table = partition_table("12C16O")
    assert table.t_min_k == 70.0 and table.t_max_k == 1000.0
    nodes = np.asarray(hapi.TIPS_2021_ISOT_HASH[CO])
    keep = (nodes >= 70.0) & (nodes <= 1000.0)
    np.testing.assert_array_equal(table.temperature_k, nodes[keep])
    np.testing.assert_array_equal(table.q, np.asarray(hapi.TIPS_2021_ISOQ_HASH[CO])[keep])
    assert "Gamache" in table.source and "10.1016/j.jqsrt.2021.107713" in table.source


def test_partition_function_matches_hapi_over_the_whole_table():
    # 0.37 K steps hit points between every pair of nodes. Both interpolate the same 10 K nodes
    # (hapi: 4-point Lagrange in Q; here: cubic spline in ln Q vs ln T); measured max 5e-8.
    t = np.arange(70.0, 1000.0, 0.37)
    q = partition_function(t)
    np.testing.assert_allclose(q, _q_hapi(t, 2021), rtol=2e-7, atol=0)
    # hapi's default table is the TIPS-2025 revision, which moved Q(12C16O) by < 1e-5 (7.4e-6
    # at 1000 K, 7e-6 in 200-400 K)
    np.testing.assert_allclose(q, _q_hapi(t, 2025), rtol=2e-5, atol=0)
    assert partition_function(296.0) == pytest.approx(107.4198, rel=1e-6)


def test_partition_function_log_derivative_matches_finite_differences_of_hapi():
    t = np.array([75.3, 203.0, 283.0, 296.0, 305.5, 397.0, 812.0])
    h = 0.05
    fd = (np.log(_q_hapi(t + h)) - np.log(_q_hapi(t - h))) / (2 * h)
    # hapi's piecewise Lagrange derivative differs from the spline's by ~1e-5 relative
    np.testing.assert_allclose(partition_table().log_derivative(t), fd, rtol=1e-4, atol=0)


def test_intensity_ratio_matches_hapi_within_its_c2():
    t = np.array([200.0, 230.0, 255.5, 280.0, 296.0, 301.0, 310.0, 333.3, 370.0, 400.0])
    nu0_hz, e_j = load_line().nu0_hz, load_line().lower_state_energy_j
    r = intensity_ratio(t, 296.0, nu0_hz, e_j, "12C16O")
    # 1. against the formula in hapi's source with the CODATA c2: only the Q interpolation
    #    differs (< 2e-7 on a ratio of two Q)
    np.testing.assert_allclose(r, _ratio_formula(t), rtol=4e-7, atol=0)
    # 2. against hapi's function itself: it uses c2 = 1.4388028 cm K, 1.8e-5 above CODATA, which
    #    shifts ln S(T)/S(T_ref) by dc2 E'' |1/T - 1/T_ref| (4.5e-5 at 200 K); that, plus the Q
    #    interpolation, is the tolerance at each T
    bound = abs(C2_HAPI - C2_CODATA) * E_CM * np.abs(1 / t - 1 / 296.0) + 1e-6
    assert np.all(np.abs(r / _ratio_hapi(t) - 1) <= bound)
    assert intensity_ratio(296.0, 296.0, nu0_hz, e_j) == 1.0


def test_stimulated_emission_term_on_a_line_where_it_matters():
    """At 6411 cm^-1 stimulated emission is exp(-31) of absorption and no test of R(23) sees it;
    the pure-rotation R(0) line of 12C16O (3.845 cm^-1, E'' = 0) has h nu0 << k_B T, so the
    emission ratio is about T_ref/T there."""
    from bayes_tfcrds.core.constants import C

    nu0_cm = 3.845033  # 12C16O J = 1 <- 0 (HITRAN), cm^-1
    t = np.array([200.0, 250.0, 280.0, 310.0, 400.0])
    r = intensity_ratio(t, 296.0, nu0_cm * 100 * C, 0.0)
    np.testing.assert_allclose(r, _ratio_formula(t, e_cm=0.0, nu0_cm=nu0_cm), rtol=4e-7, atol=0)
    # and its T derivative, where the emission term is -1/T instead of exp(-31)
    d = intensity_log_derivative(t, nu0_cm * 100 * C, 0.0)
    h = 0.05
    fd = (
        np.log(_ratio_formula(t + h, e_cm=0.0, nu0_cm=nu0_cm))
        - np.log(_ratio_formula(t - h, e_cm=0.0, nu0_cm=nu0_cm))
    ) / (2 * h)
    np.testing.assert_allclose(d, fd, rtol=2e-5, atol=0)


def test_conversion_is_invertible_and_the_line_helpers_agree():
    line = load_line()
    t = np.array([280.0, 310.0])
    s_t = line.intensity_cm_per_molecule_at(t)
    np.testing.assert_allclose(s_t, 8.0603e-25 * _ratio_formula(t), rtol=4e-7, atol=0)
    # back to T_ref through the ratio taken the other way
    back = s_t * intensity_ratio(296.0, t, line.nu0_hz, line.lower_state_energy_j)
    np.testing.assert_allclose(back, 8.0603e-25, rtol=1e-12, atol=0)


def test_log_derivative_matches_finite_differences_of_the_hapi_formula():
    line = load_line()
    t = np.array([203.0, 283.0, 296.0, 296.5, 305.0, 397.0])
    h = 0.05
    fd = (np.log(_ratio_formula(t + h)) - np.log(_ratio_formula(t - h))) / (2 * h)
    np.testing.assert_allclose(line.intensity_log_derivative(t), fd, rtol=2e-6, atol=0)
    # the number: d ln S(T_ref)/dT = 1/T - d ln S(T)/dT = -0.0107 /K at 296 K for R(23)
    assert 1 / 296.0 - line.intensity_log_derivative(296.0) == pytest.approx(-0.010647, rel=1e-3)
    assert intensity_log_derivative(296.0, line.nu0_hz, 0.0) < 0  # E'' = 0: only Q falls


@pytest.mark.parametrize("t", [69.9, 1000.1, 5.0, 3000.0, float("nan")])
def test_temperatures_outside_the_table_are_refused_not_extrapolated(t):
    with pytest.raises(ValueError, match="never extrapolated"):
        partition_function(t)
    with pytest.raises(ValueError, match="never extrapolated"):
        load_line().intensity_ratio(t)


def test_unknown_isotopologue_and_no_hapi_in_the_package():
    with pytest.raises(ValueError, match="no partition-function table"):
        partition_function(296.0, "13C16O")
    package = Path(__file__).resolve().parents[2] / "bayes_tfcrds"
    for path in package.rglob("*.py"):
        text = path.read_text(encoding="utf-8")
        assert "import hapi" not in text and "from hapi" not in text, path
