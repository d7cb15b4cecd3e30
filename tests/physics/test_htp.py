"""The Hartmann-Tran profile (pCqSDHCP, correlation parameter eta) of physics.lineshape.

Compared against hitran-api's independent implementation, against the closed-form limits it
must reduce to, and for its normalisation. Units as in test_lineshape: Hz inside, hapi's
arguments are in any one consistent unit (its formula is homogeneous of degree -1).
"""

from __future__ import annotations

import contextlib
import io

import numpy as np
import pytest

import bayes_tfcrds.physics.lineshape as ls
from bayes_tfcrds.physics.lineshape import hard_collision, htp, profile, qsdhcp
from tests.physics.test_lineshape import GD, NU0, _integral_of_real_part

with contextlib.redirect_stdout(io.StringIO()):  # hapi prints a banner on import
    import hapi

DET = np.linspace(-30.0, 30.0, 601)  # detunings in Doppler HWHM


# (Gamma0, Gamma2, Delta0, Delta2, nu_VC) in GammaD, and eta: Doppler-, mixed- and
# collision-dominated, with and without speed-dependent shift
HTP_CASES = [
    (0.3, 0.08, 0.02, 0.01, 0.2, 0.5),
    (1.0, 0.2, 0.0, 0.0, 0.5, 0.3),
    (0.05, 0.01, 0.0, 0.0, 0.05, 0.8),
    (3.0, 1.0, 0.5, 0.1, 2.0, 0.2),
    (0.3, 0.0, 0.02, 0.0, 0.2, 0.4),
]


def _hapi(rates, eta):
    """hapi's pcqsdhc (Tran, Ngo, Hartmann 2013 code) at DET, GammaD = 1, complex."""
    g0, g2, d0, d2, nvc = rates
    re, im = hapi.pcqsdhc(0.0, 1.0, g0, g2, d0, d2, nvc, eta, DET)
    return re + 1j * im


def test_htp_reduces_to_the_qsdhcp_at_eta_zero():
    # eta = 0: C0~, C2~ are the qSDHCP's and the B term is multiplied by 0: the same numbers
    for g0, g2, d0, d2, nvc, _ in HTP_CASES:
        a = htp(DET * GD, 0.0, GD, g0 * GD, g2 * GD, d0 * GD, d2 * GD, nvc * GD, 0.0)
        b = qsdhcp(DET * GD, 0.0, GD, g0 * GD, g2 * GD, d0 * GD, d2 * GD, nvc * GD)
        np.testing.assert_allclose(a, b, rtol=1e-15, atol=0)


@pytest.mark.parametrize("case", HTP_CASES)
def test_htp_matches_hitran_api(case):
    *rates, eta = case
    ours = htp(DET * GD, 0.0, GD, *(r * GD for r in rates), eta) * GD  # per GammaD
    ref = _hapi(rates, eta)
    # hapi's Humlicek CPF is accurate to ~1e-6: its eta = 0 profile differs from our qSDHCP
    # (validated to 1e-10 against 60-digit arithmetic in test_lineshape) by that much, so the
    # tolerance is 3x hapi's own measured error on the same rates at eta = 0
    own = np.max(np.abs(_hapi(rates, 0.0) - qsdhcp(DET, 0.0, 1.0, *rates)))
    err = np.max(np.abs(ours - ref))
    assert err <= 3 * max(own, 1e-12), (err, own)
    # and the correlation changes the profile by far more than that tolerance
    assert np.max(np.abs(ref - _hapi(rates, 0.0))) > 100 * max(own, 1e-12)


def test_htp_without_speed_dependence_is_the_hard_collision_profile():
    # Gamma2 = Delta2 = 0, Delta0 = 0: C0~ = (1 - eta) Gamma0 + nu_VC and the denominator's
    # rate is nu_VC - eta Gamma0, i.e. the Rautian profile of width Gamma0 and velocity-changing
    # rate nu_VC - eta Gamma0 (closed form, no B term: it must vanish at C2 = 0). 1e-13: rounding
    # of two Faddeeva evaluations.
    for g0, nvc, eta in [(0.3, 0.2, 0.4), (1.5, 0.8, 0.7), (0.02, 0.05, 0.2)]:
        a = htp(DET * GD, 0.0, GD, g0 * GD, 0.0, 0.0, 0.0, nvc * GD, eta)
        b = hard_collision(DET * GD, 0.0, GD, g0 * GD, 0.0, (nvc - eta * g0) * GD)
        np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-13 * np.max(np.abs(b)))


def test_htp_is_normalised():
    # the integral of Re g is 1 (FORMAT.md) for eta != 0 too; 1e-6 as for the other profiles
    g0 = 0.4 * GD
    fun = lambda nu: htp(nu, NU0, GD, g0, 0.1 * GD, 0.03 * GD, 0.01 * GD, 0.3 * GD, 0.5)  # noqa: E731
    width = GD + g0
    total = _integral_of_real_part(fun, NU0, 0.05 * min(GD, g0), 1e4 * width, g0)
    assert abs(total - 1.0) < 1e-6


def test_htp_far_branch_matches_the_direct_formula(monkeypatch):
    # Collision-dominated far wing (|4 kappa z0| > 1e10): the B term's Y -> 0 limit against the
    # two-Faddeeva formula, which there loses ~sqrt(|4 kappa z0|)/2 x 1e-14 (<= 1e-8 relative
    # here); the profile differs by less than 1e-7 of itself
    det = np.array([5e6, -8e6, 2e7, -5e7]) * GD
    args = (0.0, GD, 1e4 * GD, 2e3 * GD, 50 * GD, 30 * GD, 1e3 * GD, 0.4)
    kappa = np.sqrt(np.log(2)) * (1 - 0.4) * 2e3  # cte C2~, dimensionless
    assert np.all(4 * kappa * np.sqrt(np.log(2)) / GD * np.abs(det) > ls._XY_RATIO_SWITCH)
    far = htp(det, *args)
    monkeypatch.setattr(ls, "_XY_RATIO_SWITCH", np.inf)
    near = htp(det, *args)
    np.testing.assert_allclose(far, near, rtol=1e-7, atol=0)


def test_htp_through_the_dispatcher_and_its_domain():
    nu = NU0 + np.linspace(-2, 2, 5) * GD
    shape = dict(gamma0_hz=0.3 * GD, gamma2_hz=0.05 * GD, nu_vc_hz=0.1 * GD)
    np.testing.assert_array_equal(
        profile("htp", nu, NU0, GD, eta=0.3, **shape),
        htp(nu, NU0, GD, shape["gamma0_hz"], shape["gamma2_hz"], 0.0, 0.0, shape["nu_vc_hz"], 0.3),
    )
    with pytest.raises(ValueError, match="eta"):
        profile("qsdhcp", nu, NU0, GD, eta=0.3, **shape)
    # eta = 1: every velocity change dephases, C2~ = 0 and eta/(1 - eta) diverges: NaN
    assert np.all(np.isnan(htp(nu, NU0, GD, 0.3 * GD, 0.05 * GD, 0, 0, 0.1 * GD, 1.0)))
