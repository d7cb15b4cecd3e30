"""T through the line fits' Doppler width: a row of A; one T in S, A/A_ref and the Monte Carlo.

The line fits hold the Doppler HWHM at GammaD(T_gauge), so a gauge error in T moves the fitted
areas. The tests check the sensitivities against refits of the whole chain at other T (the S
budget's total c_T against S(A(T), p, T, x) differenced), and that the Monte Carlo draws one T
for A and S: with a large u(T) the correlated and the independent treatment differ by ~40 %.
S is ~1e-25 cm/molecule: every comparison is relative (pytest.approx's default abs=1e-12 would
accept any value).
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from bayes_tfcrds.core.gum import Budget, Component
from bayes_tfcrds.fit.line import LineModel, fit_line
from bayes_tfcrds.fit.spectrum import SpectrumData
from bayes_tfcrds.physics.linedata import load_line
from bayes_tfcrds.physics.lineshape import doppler_hwhm_hz
from bayes_tfcrds.uncertainty import line_budget as lb
from bayes_tfcrds.uncertainty.doppler import (
    ROW_NAME,
    DopplerSensitivity,
    area_temperature_derivative,
    doppler_sensitivity,
    temperature_row,
    without_temperature_row,
)
from bayes_tfcrds.uncertainty.monte_carlo import budget_monte_carlo

LINE = load_line()


def _sample(temperature_k=296.0, u_t=0.03):
    return SimpleNamespace(
        nu0_hz=LINE.nu0_hz,
        mass_u=LINE.mass_u,
        temperature_k=temperature_k,
        temperature_u_k=u_t,
        pressure_pa=666.6,
        pressure_u_pa=0.333,
        mole_fraction=1.0,
    )


def _spectrum(kind, true_t_k, rng, pressure_scale=1.0, noise=1e-4):
    """A qSDHCP spectrum (absorption 1/m or CMDS dispersion Hz) at the true T, noise ``noise``
    of its peak; widths of the letter's line at about 670 Pa times ``pressure_scale``."""
    gd = float(doppler_hwhm_hz(LINE.nu0_hz, true_t_k, LINE.mass_u))
    g0 = 0.25 * gd * pressure_scale
    model = LineModel("qsdhcp", ("gamma0_hz", "gamma2_hz", "nu_vc_hz"), (kind,),
                      (kind == "dispersion",), LINE.nu0_hz, gd, {})  # fmt: skip
    nu = LINE.nu0_hz + np.linspace(-5 * gd, 5 * gd, 121)
    theta = [3.0e2, 0.0, g0, 0.15 * g0, 0.4 * g0, 1e-6, *([0.0] if kind == "dispersion" else [])]
    probe = SpectrumData(kind, nu, np.zeros_like(nu), np.ones_like(nu))
    y = model.predict(np.asarray(theta, float), [probe])[0]
    u = np.full_like(nu, noise * np.max(np.abs(y)))
    return SpectrumData(kind, nu, y + u * rng.standard_normal(nu.size), u)


def _area_at(spec, temperature_k):
    gd = float(doppler_hwhm_hz(LINE.nu0_hz, temperature_k, LINE.mass_u))
    return fit_line([spec], "qsdhcp", gd, LINE.nu0_hz).line_area


@pytest.mark.parametrize("pressure_scale", [0.6, 1.0, 1.4])
def test_the_derivative_predicts_the_refit_at_a_wrong_gauge_reading(pressure_scale):
    """A fitted with the gauge 0.5 K high minus A at the true T = dA/dT x 0.5 K (sign, step,
    linearity): within 3 % of the shift, the curvature over 0.5 K being < 1 % of it."""
    rng = np.random.default_rng(3)
    spec = _spectrum("absorption", 296.0, rng, pressure_scale)
    base = fit_line(
        [spec], "qsdhcp", float(doppler_hwhm_hz(LINE.nu0_hz, 296.0, LINE.mass_u)), LINE.nu0_hz
    )
    d = area_temperature_derivative([spec], "qsdhcp", base, _sample())
    shift = _area_at(spec, 296.5) - _area_at(spec, 296.0)
    assert d < 0  # a too-wide Gaussian: the fit takes area out of the wings
    assert abs(shift) > 1e-5 * base.line_area  # a real effect at 0.5 K, not fitter noise
    assert d * 0.5 == pytest.approx(shift, rel=0.03, abs=0)


@pytest.mark.parametrize("temperature_k", [281.0, 296.0, 309.0])
def test_intensity_budget_has_the_total_temperature_sensitivity(temperature_k):
    """c_T of S(T_ref) = dS/dT of the whole chain S(A(T), p, T, x), A refitted at T +- 0.2 K.

    Tolerance 0.2 %: both are central differences (A's over +-1 K, S's over +-0.2 K), whose
    error is third order in the step (d ln A/d ln T varies by < 1e-3 of itself per K); the
    sensitivity without the fit's part misses by its share, 2.5 % on this line at 296 K.
    Also at the ends of the coverage study's 280-310 K: the spectrum made and read at T."""
    rng = np.random.default_rng(7)
    spec = _spectrum("absorption", temperature_k, rng, pressure_scale=1.4)
    sample = _sample(temperature_k)
    gd = float(doppler_hwhm_hz(LINE.nu0_hz, temperature_k, LINE.mass_u))
    lsq = fit_line([spec], "qsdhcp", gd, LINE.nu0_hz)
    sens = doppler_sensitivity(spec, lsq, None, None, "qsdhcp", sample)
    a = lsq.line_area
    bud = lb._budget_s(sample, a, 0.01 * a, da_dt=sens.da_dt)
    c_t = next(c.sensitivity for c in bud.components if c.name == "temperature T")
    model = lb.intensity_model(LINE)

    def s_of(t):
        return float(model(_area_at(spec, t), sample.pressure_pa, t, sample.mole_fraction))

    numeric = (s_of(temperature_k + 0.2) - s_of(temperature_k - 0.2)) / 0.4
    assert c_t == pytest.approx(numeric, rel=2e-3, abs=0)
    a_only = next(
        c.sensitivity for c in lb._budget_s(sample, a, 0.01 * a).components
        if c.name == "temperature T"
    )  # fmt: skip
    assert abs(a_only - numeric) > 0.01 * abs(numeric)


def test_ratio_budget_differences_the_two_fits_at_one_temperature():
    """A/A_ref's T row = d(A(T)/A_ref(T))/dT with both fits redone at T +- 0.2 K (CRDS
    absorption, CMDS dispersion: different sensitivities, so the row is not zero)."""
    rng = np.random.default_rng(11)
    spec = _spectrum("absorption", 296.0, rng)
    cm = _spectrum("dispersion", 296.0, rng)
    sample = _sample()
    gd = float(doppler_hwhm_hz(LINE.nu0_hz, 296.0, LINE.mass_u))
    lsq = fit_line([spec], "qsdhcp", gd, LINE.nu0_hz)
    ref = fit_line([cm], "qsdhcp", gd, LINE.nu0_hz)
    sens = doppler_sensitivity(spec, lsq, cm, ref, "qsdhcp", sample)
    a, a_ref = lsq.line_area, ref.line_area
    bud = lb._budget_ratio(a, 1e-4 * a, np.full(4, a_ref), doppler=sens)
    c_t = next(c.sensitivity for c in bud.components if c.name == ROW_NAME)
    numeric = (
        _area_at(spec, 296.2) / _area_at(cm, 296.2) - _area_at(spec, 295.8) / _area_at(cm, 295.8)
    ) / 0.4
    # c_T is a difference of two terms, each >= 10x it (asserted below): 2 % of c_T allows
    # 0.2 % per term, the size of the central differences' third-order error over +-1 K
    assert c_t == pytest.approx(numeric, rel=0.02, abs=0)
    assert abs(sens.da_dt / a - sens.da_ref_dt / a_ref) > 0.1 * abs(sens.da_dt / a)


def _budgets(da_dt_rel: float, u_t: float):
    """A budget with statistical draws and a T row, S's budget; T's fit sensitivity as given."""
    sample = _sample(u_t=u_t)
    a = 3.0e2
    sens = DopplerSensitivity(296.0, u_t, da_dt_rel * a, None)
    comps = (
        Component("ring-down noise (line fit given H)", None, 1e-4 * a, 1.0, "Hz/m"),
        temperature_row(sens, a, np.inf),
    )
    budget_a = Budget("line area A", a, "Hz/m", comps)
    but_t = without_temperature_row(budget_a)
    budget_s = lb._budget_s(sample, a, but_t.combined_u, da_dt=sens.da_dt)
    return sample, sens, budget_a, budget_s


def test_monte_carlo_draws_one_temperature_for_a_and_s():
    """u(T) = 2 K and d ln A/dT equal to d ln S/dT|_A (-0.0107 /K): T's two paths add, so u(S)
    is twice the T term alone and sqrt(2) times what independent draws would give. The JCGM 101
    u(S) agrees with the GUM budget's to 3 % (the adaptive Monte Carlo's two significant
    digits); u(A) too."""
    da_dt_rel = -0.0107
    sample, sens, budget_a, budget_s = _budgets(da_dt_rel, u_t=2.0)
    rng = np.random.default_rng(5)
    a_total = budget_a.value + 1e-4 * budget_a.value * rng.standard_normal(20000)
    mc = budget_monte_carlo(
        budget_a, a_total, sample, None, rng, lb.intensity_model(LINE), doppler=sens
    )
    assert mc.intensity.u == pytest.approx(budget_s.combined_u, rel=0.03, abs=0)
    assert mc.line_area.u == pytest.approx(budget_a.combined_u, rel=0.03, abs=0)
    # the GUM budget itself: one T, total sensitivity (the independent sum would be sqrt 2 less)
    s = budget_s.value
    dlns = 1.0 / 296.0 - float(LINE.intensity_log_derivative(296.0))
    assert budget_s.combined_u == pytest.approx(
        s * np.hypot(1e-4, (dlns + da_dt_rel) * 2.0), rel=0.01, abs=0
    )
    independent = s * np.sqrt(1e-4**2 + (dlns * 2.0) ** 2 + (da_dt_rel * 2.0) ** 2)
    assert abs(mc.intensity.u - independent) > 0.2 * independent


def test_spectrum_level_budget_carries_the_row():
    """A lab's spectrum is fitted with the same fixed Doppler width: the row is in its budget,
    and S's T row holds the total sensitivity."""
    from bayes_tfcrds.uncertainty.spectrum_budget import spectrum_budget

    rng = np.random.default_rng(13)
    spec = _spectrum("absorption", 296.0, rng, pressure_scale=1.4)
    gd = float(doppler_hwhm_hz(LINE.nu0_hz, 296.0, LINE.mass_u))
    lf = fit_line([spec], "qsdhcp", gd, LINE.nu0_hz)
    analysis = SimpleNamespace(line_fit=lf, spectrum=spec, profile="qsdhcp")
    sample = _sample()
    bud = spectrum_budget(analysis, sample)
    row = next(c for c in bud.budget_a.components if c.name == ROW_NAME)
    assert row.u == sample.temperature_u_k and row.sensitivity < 0
    c_t = next(c.sensitivity for c in bud.budget_s.components if c.name == "temperature T")
    plain = next(
        c.sensitivity
        for c in lb._budget_s(sample, lf.line_area, 1.0).components
        if c.name == "temperature T"
    )
    total = plain + bud.budget_s.value * row.sensitivity / lf.line_area
    assert c_t == pytest.approx(total, rel=1e-9, abs=0)


def test_s_and_ratio_budgets_take_a_without_its_temperature_row():
    """The budgets of S and A/A_ref carry A's u and dof without its T row (T has its own row of
    total sensitivity there): with u_c(A), T would count twice."""
    sample, sens, budget_a, _ = _budgets(-0.0107, u_t=2.0)
    sens = DopplerSensitivity(296.0, 2.0, sens.da_dt, 0.5 * sens.da_dt)
    a_ref = np.full(8, 1.01 * budget_a.value)
    bud_s, bud_r = lb._budgets_s_and_ratio(sample, budget_a, a_ref, 50.0, sens)
    but_t = without_temperature_row(budget_a)
    for bud, name in ((bud_s, "line area A"), (bud_r, "line area A (CRDS)")):
        row = next(c for c in bud.components if c.name == name)
        assert row.u == but_t.combined_u < 0.5 * budget_a.combined_u
        assert row.dof == but_t.effective_dof
    assert sum(c.name in ("temperature T", ROW_NAME) for c in bud_s.components) == 1
    assert sum(c.name == ROW_NAME for c in bud_r.components) == 1


def test_reference_u_and_en_count_temperature_once():
    """u(A_ref) from the ratio table holds its two CMDS rows only (Hz/m; T, in K, is the
    ratio's own row); E_n's u(A) moves T onto A - A_ref: equal derivatives cancel it."""
    sample, sens, budget_a, _ = _budgets(-0.0107, u_t=2.0)
    a = budget_a.value
    a_ref = a * (1.0 + 1e-4 * np.random.default_rng(1).standard_normal(4000))
    same = DopplerSensitivity(296.0, 2.0, sens.da_dt, sens.da_dt)
    _, bud_r = lb._budgets_s_and_ratio(sample, budget_a, a_ref, 50.0, same)
    value, u_ref = lb.reference_value_and_u(bud_r)
    cmds_rows = [c.u for c in bud_r.components if c.name.startswith("reference area A_ref")]
    assert len(cmds_rows) == 2 and u_ref == pytest.approx(np.hypot(*cmds_rows), rel=1e-12, abs=0)
    assert value == pytest.approx(np.mean(a_ref), rel=1e-12, abs=0)
    # equal d ln/dT: T cancels in A - A_ref (and nearly in A/A_ref)
    assert lb._u_a_for_en(budget_a, same) == pytest.approx(
        without_temperature_row(budget_a).combined_u, rel=1e-12, abs=0
    )
    assert lb._u_a_for_en(budget_a, sens) == pytest.approx(budget_a.combined_u, rel=1e-12, abs=0)


def test_monte_carlo_ratio_draws_one_temperature_for_a_and_a_ref():
    """u(T) = 2 K and equal d ln A/dT, d ln A_ref/dT (-0.0107 /K): T cancels in A/A_ref, whose
    JCGM 101 u then equals the GUM table's (3 %: two significant digits), ~40x below what
    separate T draws for A and A_ref would give."""
    sample, _, budget_a, _ = _budgets(-0.0107, u_t=2.0)
    a = budget_a.value
    rng = np.random.default_rng(9)
    a_ref = a * (1.0 + 1e-4 * rng.standard_normal(20000))
    a_total = a * (1.0 + 1e-4 * rng.standard_normal(20000))
    sens = DopplerSensitivity(296.0, 2.0, -0.0107 * a, -0.0107 * a)
    _, bud_r = lb._budgets_s_and_ratio(sample, budget_a, a_ref, 50.0, sens)
    mc = budget_monte_carlo(
        budget_a, a_total, sample, a_ref, rng, lb.intensity_model(LINE), doppler=sens
    )
    assert mc.ratio.u == pytest.approx(bud_r.combined_u, rel=0.03, abs=0)
    assert mc.ratio.u < 0.1 * np.sqrt(2.0) * 0.0107 * 2.0  # separate draws: ~0.03


def test_monte_carlo_refuses_a_temperature_row_without_its_sensitivities():
    sample, _, budget_a, _ = _budgets(-0.0107, u_t=2.0)
    with pytest.raises(ValueError, match="DopplerSensitivity"):
        budget_monte_carlo(
            budget_a, np.full(10, budget_a.value), sample, None, np.random.default_rng(0),
            lb.intensity_model(LINE),
        )  # fmt: skip
