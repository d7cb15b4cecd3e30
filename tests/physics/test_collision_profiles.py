"""Power-law speed dependence and soft collisions (physics.collision_profiles) against
independent evaluations: the closed-form profiles of physics.lineshape in their limits, a fine
uniform-grid quadrature of the Galatry correlation function, the Dicke limit in closed form,
and unit area.

Tolerances: the Gauss-Legendre quadratures are converged to ~1e-13 of the peak (measured); the
closed forms (wofz) are good to ~1e-14. 1e-11 leaves room for platform rounding and fails on any
error of physics (a wrong sign of a shift moves the profile by ~1e-2 of its peak).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import integrate

from bayes_tfcrds.physics.collision_profiles import (
    galatry,
    maxwell_moment,
    power_law_sdvoigt,
    speed_averaged,
)
from bayes_tfcrds.physics.lineshape import hard_collision, sdvoigt, voigt

GD = 227.5e6  # Hz, Doppler HWHM of CO at 1.57 um and 300 K
G0 = 10e6  # Hz, collisional HWHM at a few Torr
D0 = -1.5e6  # Hz, pressure shift
DET = np.linspace(-3e9, 3e9, 241)


def _rel(a, b):
    return np.max(np.abs(a - b)) / np.max(np.abs(b))


def test_maxwell_moments():
    # <x^0> = 1, <x^2> = 3/2, <x^4> = 15/4 for P(x) = 4 x^2 exp(-x^2) / sqrt(pi)
    np.testing.assert_allclose(maxwell_moment([0.0, 2.0, 4.0]), [1.0, 1.5, 3.75], rtol=1e-14)


def test_power_law_limits_are_the_closed_forms():
    # m = 0: no speed dependence, the Voigt profile
    assert _rel(power_law_sdvoigt(DET, 0.0, GD, G0, 0.0, D0), voigt(DET, 0.0, GD, G0, D0)) < 1e-11
    # m = 2: Gamma(x) = Gamma0 x^2/<x^2> = Gamma0 + (2/3) Gamma0 (x^2 - 3/2), and the shift's
    # speed-dependent part delta_sd (x^2/<x^2> - 1) = (2/3) delta_sd (x^2 - 3/2): the qSDV profile
    # with Gamma2 = 2 Gamma0 / 3 and Delta2 = 2 delta_sd / 3 (two-Faddeeva closed form). Gamma -> 0
    # at low speed makes the speed integrand's resonances narrow there: the quadrature is good to
    # ~1e-6 of the peak at this extreme (module notes), 5e-6 allowed; a wrong sign of the shift
    # law moves the profile by 1e-3
    got = power_law_sdvoigt(DET, 0.0, GD, G0, 2.0, D0, delta_sd_hz=0.6e6)
    ref = sdvoigt(DET, 0.0, GD, G0, 2 * G0 / 3, D0, 0.4e6)
    assert _rel(got, ref) < 5e-6
    assert _rel(power_law_sdvoigt(DET, 0.0, GD, G0, 2.0, D0, delta_sd_hz=-0.6e6), ref) > 1e-4


@pytest.mark.parametrize(
    ("g0", "g2", "d2"), [(10e6, 1e6, 0.2e6), (50e6, 12e6, -1e6), (3e6, 0.5e6, 0)]
)
def test_any_speed_law_quadratic_case_is_the_sdvoigt(g0, g2, d2):
    got = speed_averaged(
        DET, 0.0, GD, lambda x: g0 + g2 * (x * x - 1.5), lambda x: D0 + d2 * (x * x - 1.5), g0
    )
    assert _rel(got, sdvoigt(DET, 0.0, GD, g0, g2, D0, d2)) < 1e-11


@pytest.mark.parametrize("m", [-0.5, 0.2, 1.0])
def test_power_law_profile_has_unit_area(m):
    # adaptive quadrature over +-200 GHz plus the Lorentzian wings beyond (2 Gamma0/(pi 2e11))
    def re(nu):
        return power_law_sdvoigt(np.array([nu]), 0.0, GD, G0, m, D0)[0].real

    core = integrate.quad(re, -2e11, 2e11, points=[-GD, 0.0, GD], limit=500)[0]
    assert abs(core + 2 * G0 / (np.pi * 2e11) - 1.0) < 1e-6


def test_speed_dependence_narrows_the_line():
    # slower molecules broaden less (m > 0): the core sharpens, so the peak rises above the Voigt
    peak = power_law_sdvoigt(np.array([D0]), 0.0, GD, G0, 0.3, D0).real[0]
    assert peak > voigt(np.array([D0]), 0.0, GD, G0, D0).real[0]


def test_galatry_without_collisions_is_the_voigt():
    assert _rel(galatry(DET, 0.0, GD, G0, D0, 0.0), voigt(DET, 0.0, GD, G0, D0)) < 1e-11


def test_galatry_against_a_uniform_grid_quadrature():
    # the correlation function integrated on a 1e-14 s grid by Simpson's rule (2e6 points)
    nu_d = 2.3e6
    kvp = 2 * np.pi * GD / np.sqrt(np.log(2.0))
    beta = 2 * np.pi * nu_d
    t = np.linspace(0.0, 2e-8, 2_000_001)
    phi = np.exp(-2 * np.pi * G0 * t) * np.exp(
        -(kvp**2) / (2 * beta**2) * (beta * t - 1 + np.exp(-beta * t))
    )
    for d in (-9e9, -5e8, 0.0, 3e7, 1e9):
        ref = 2 * integrate.simpson(phi * np.exp(2j * np.pi * (d - D0) * t), x=t)
        got = galatry(np.array([d]), 0.0, GD, G0, D0, nu_d)[0]
        assert abs(got - ref) < 1e-10 * abs(ref), d


def test_galatry_dicke_limit_and_area():
    # beta >> k v_p: the Doppler factor becomes exp(-(k v_p)^2 t / (2 beta)), a Lorentzian of HWHM
    # (k v_p)^2 / (4 pi beta) Hz beside Gamma0; the remainder is O((k v_p/beta)^2) = 1e-4
    kvp = 2 * np.pi * GD / np.sqrt(np.log(2.0))
    beta = 100 * kvp
    hw = G0 + kvp**2 / (4 * np.pi * beta)
    d = np.linspace(-50e6, 50e6, 11)
    got = galatry(d, 0.0, GD, G0, 0.0, beta / (2 * np.pi))
    lorentz = (1 / np.pi) / (hw - 1j * d)
    assert _rel(got, lorentz) < 3e-4

    # unit area at a moderate rate (Lorentz wings beyond +-100 GHz: 2 Gamma0/(pi 1e11))
    def re(nu):
        return galatry(np.array([nu]), 0.0, GD, G0, D0, 4.6e6)[0].real

    core = integrate.quad(re, -1e11, 1e11, points=[-GD, 0.0, GD], limit=500)[0]
    assert abs(core + 2 * G0 / (np.pi * 1e11) - 1.0) < 1e-6


def test_galatry_narrows_less_than_hard_collisions_at_the_same_rate():
    # soft collisions need many to randomise a velocity, hard ones one: at the same rate the
    # Rautian profile's Doppler core is the narrower one, and both are narrower than the Voigt
    nu_d = 20e6
    peak_v = voigt(np.array([0.0]), 0.0, GD, G0).real[0]
    peak_g = galatry(np.array([0.0]), 0.0, GD, G0, 0.0, nu_d).real[0]
    peak_r = hard_collision(np.array([0.0]), 0.0, GD, G0, 0.0, nu_d).real[0]
    assert peak_v < peak_g < peak_r


def test_bad_inputs_are_refused():
    with pytest.raises(ValueError, match="doppler"):
        galatry(DET, 0.0, 0.0, G0)
    with pytest.raises(ValueError, match="gamma0"):
        power_law_sdvoigt(DET, 0.0, GD, 0.0, 0.2)
    with pytest.raises(ValueError, match="nu_d"):
        galatry(DET, 0.0, GD, G0, 0.0, -1.0)
