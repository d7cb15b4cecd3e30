"""Complex isolated-line profiles built on the Faddeeva function ``scipy.special.wofz``.

Conventions (the project's data contract)
-----------------------------------------
* Frequencies are optical frequencies or detunings in Hz; every width, shift and rate is a
  half width at half maximum (HWHM) or a rate in Hz; profile values are in 1/Hz.
* A profile is complex, g(nu) = g_R + i g_I, normalised so that the integral of g_R over
  frequency is 1. g_I is the dispersive partner (its Hilbert transform), positive above
  the line centre: the Lorentzian is g = (1/pi) / (Gamma0 - i (nu - nu0 - Delta0)).

The general profile is the quadratic speed-dependent hard-collision profile (qSDHCP),
which is the Hartmann-Tran profile with correlation parameter eta = 0 [Ngo, Lisak, Tran,
Hartmann, JQSRT 129 (2013) 89, erratum JQSRT 134 (2014) 105]. It is evaluated with the
two-Faddeeva-function formula of Tran, Ngo, Hartmann [JQSRT 129 (2013) 199], rewritten in
Doppler units so that it stays accurate and finite in every limit a fitter or a sampler
visits (Gamma2 -> 0 and = 0, nu_VC -> 0, Doppler- and collision-dominated regimes, far
wings); see ``_speed_averaged`` for the branches. Gaussian, Lorentzian, Voigt, speed-
dependent Voigt and Rautian (hard-collision) profiles are thin limits of it; the full
Hartmann-Tran profile (``htp``, correlation parameter eta) reuses its speed averages.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.special import dawsn, wofz

from bayes_tfcrds.core.constants import AMU, K_B, C

__all__ = [
    "doppler_hwhm_hz",
    "qsdhcp",
    "gaussian",
    "lorentzian",
    "voigt",
    "sdvoigt",
    "hard_collision",
    "htp",
    "ProfileSpec",
    "PROFILES",
    "SHAPE_PARAMETERS",
    "HTP_PARAMETERS",
    "profile",
]

_SQRT_PI = np.sqrt(np.pi)
_SQRT_LN2 = np.sqrt(np.log(2.0))

# |4 kappa z0| = |X/Y| above which the two Faddeeva terms nearly cancel and the Y -> 0
# (Doppler-negligible) limit of Tran et al. is used instead. The direct difference loses
# about sqrt(|X/Y|)/2 times wofz's ~1e-14 relative accuracy, the limit is off by O(|Y/X|):
# both are ~1e-10 relative at this threshold (measured against 60-digit mpmath arithmetic).
_XY_RATIO_SWITCH = 1.0e10
# |R| above which 1 - sqrt(pi) R w(iR) is summed from its asymptotic series (10 terms,
# truncation < 1e-15 relative) instead of being formed by cancellation (error ~ 2|R|^2 eps).
_EPS_SERIES_R = 15.0
# |1/Z+| below which w(iZ+) is taken from its asymptotic series; this also gives the exact
# Gamma2 = Delta2 = 0 limit (Z+ = infinity, w = 0) without dividing by zero.
_WPLUS_SERIES_U = 1.0e-5


def doppler_hwhm_hz(nu0_hz, temperature_k, mass_u):
    """Doppler HWHM in Hz: nu0/c * sqrt(2 ln2 k_B T / m).

    nu0_hz: line frequency (Hz); temperature_k: kinetic temperature (K);
    mass_u: molecular mass in unified atomic mass units (u). Broadcasts.
    """
    m = np.asarray(mass_u, dtype=float) * AMU
    return (
        np.asarray(nu0_hz, dtype=float)
        / C
        * np.sqrt(2.0 * np.log(2.0) * K_B * np.asarray(temperature_k, dtype=float) / m)
    )


def _flat_broadcast(*xs):
    """(common shape, the inputs broadcast to it and flattened as float arrays)."""
    arrs = np.broadcast_arrays(*(np.asarray(x, dtype=float) for x in xs))
    return arrs[0].shape, [np.ravel(x) for x in arrs]


def _check_doppler(gd):
    """The Doppler-broadened profiles divide by GammaD.

    Refuse GammaD <= 0 (or NaN) loudly rather than return NaN; use `lorentzian` for the GammaD -> 0
    limit.
    """
    if not np.all(np.asarray(gd) > 0):
        raise ValueError("doppler_hwhm_hz must be > 0")


def _one_minus_sqrtpi_r_w(r):
    """epsilon(R) = 1 - sqrt(pi) R w(iR), dimensionless, for Re R >= 0.

    This is the small remainder once the Lorentzian-like 1/R part of w(iR) is removed;
    for large |R| it is summed from the asymptotic series sum_n (-1)^(n+1) (2n-1)!!/(2R^2)^n
    because forming it by subtraction would lose 2|R|^2 in relative accuracy.
    """
    out = np.empty_like(r)
    big = np.abs(r) >= _EPS_SERIES_R
    if np.any(big):
        t = 0.5 / r[big] ** 2
        acc = np.zeros_like(t)
        coef = 1.0
        coefs = []
        for n in range(1, 11):
            coef *= 2 * n - 1
            coefs.append((-1) ** (n + 1) * coef)
        for c in reversed(coefs):  # Horner in t: t (c1 + t (c2 + ...))
            acc = (acc + c) * t
        out[big] = acc
    small = ~big
    if np.any(small):
        rs = r[small]
        out[small] = 1.0 - _SQRT_PI * rs * wofz(1j * rs)
    return out


def _w_of_i_over_u(u):
    """The Maxwell-average term for the second qSD root Z+ = 1/u, finite as u -> 0.

    Dimensionless.

    It is w(i/u) when Re Z+ >= 0, which holds throughout the physical domain (Gamma2 >= 0,
    Re C0~ >= 0). For Gamma2 < 0 (Re Z+ < 0) it is -w(-i/u): the speed integral
    int exp(-t^2)/(iZ - t) dt gives that branch, whereas wofz's analytic continuation adds
    2 exp(Z+^2) ~ exp(1/kappa^2), which overflows. Both branches share the odd asymptotic
    series (u/sqrt(pi)) (1 - u^2/2 + 3u^4/4 - 15u^6/8), used for small |u| (exact to
    < 1e-28 relative, and w = 0 at the Gamma2 = Delta2 = 0 limit u = 0), so the profile is
    infinitely differentiable in Gamma2 through 0. (Not analytic: w(i/u) has an essential
    singularity at u = 0, so no continuation is unique; this one is the kinetic definition
    up to the Maxwell weight ~ exp(-(Gamma0 + nu_VC)/|Gamma2|) of speed classes whose
    width Gamma(v) + nu_VC would be negative, see ``qsdhcp``.)
    """
    series = np.abs(u) < _WPLUS_SERIES_U
    if not series.any():  # the common case: no masking, no copies
        return _w_right_branch(1j / u)
    out = np.empty_like(u)
    us = u[series]
    u2 = us * us
    out[series] = us / _SQRT_PI * (1.0 + u2 * (-0.5 + u2 * (0.75 - 1.875 * u2)))
    rest = ~series
    if np.any(rest):
        out[rest] = _w_right_branch(1j / u[rest])  # i Z+; Im z = Re Z+
    return out


def _w_right_branch(z):
    """w(z) where Im z >= 0 and -w(-z) where Im z < 0 (the speed integral's branch)."""
    left = z.imag < 0
    if not left.any():
        return wofz(z)
    return np.where(left, -wofz(np.where(left, -z, 0.0)), wofz(np.where(left, 0.0, z)))


def _speed_averaged(z0, kappa):
    """Dimensionless speed-averaged complex Lorentzian a = A(nu) * GammaD/sqrt(ln2).

    A(nu) (1/Hz) is the Maxwell average of 1/(nu_VC + Gamma(v) + i Delta(v) - i(nu - nu0
    - k.v)) for quadratic speed dependence. In Doppler units (cte = sqrt(ln2)/GammaD)

        z0 = cte (C0~ - i (nu - nu0)),  C0~ = Gamma0 - 3/2 Gamma2 + nu_VC + i (Delta0 - 3/2 Delta2)
        kappa = cte (Gamma2 + i Delta2)

    Tran et al.'s X = z0/kappa and Y = 1/(4 kappa^2), and their roots
    Z-+ = sqrt(X + Y) -+ sqrt(Y) become, with s = sqrt(1 + 4 kappa z0),

        Z- = 2 z0 / (1 + s)          (no cancellation; Z- -> z0 as kappa -> 0)
        Z+ = 1/u,  u = kappa / (1 + kappa Z-)   (u -> 0 as kappa -> 0)

    and a = sqrt(pi) [w(iZ-) - w(iZ+)]. This single expression is continuous into the
    Voigt/Rautian limit kappa = 0 (where w(iZ+) = 0), so Gamma2 -> 0 needs no switch and
    has no cancellation. (s/(2 kappa) equals the principal sqrt(X+Y) of the paper whenever
    Re C0~ >= 0, i.e. for every physical parameter set: along the line traced by 1 + 4 kappa
    z0 as nu varies, s never crosses the branch cut, and Re s/(2 kappa) > 0 far out.)

    When |X/Y| = |4 kappa z0| is huge the two w terms nearly cancel, so the Y -> 0 limit
    of Tran et al. is used: a = (2/kappa) * (1 - sqrt(pi) R w(iR)), R = s/(2 kappa), with the
    bracket from its asymptotic series for large |R| (the Lorentzian far-wing limit).
    """
    p = 4.0 * kappa * z0
    s = np.sqrt(1.0 + p)
    far = np.abs(p) > _XY_RATIO_SWITCH
    if not far.any():  # the common case: no masking, no copies
        zm = 2.0 * z0 / (1.0 + s)
        return _SQRT_PI * (wofz(1j * zm) - _w_of_i_over_u(kappa / (1.0 + kappa * zm)))
    a = np.empty_like(z0)
    kappa = np.broadcast_to(kappa, z0.shape)
    near = ~far
    if np.any(near):
        zn, kn, sn = z0[near], kappa[near], s[near]
        zm = 2.0 * zn / (1.0 + sn)
        u = kn / (1.0 + kn * zm)
        a[near] = _SQRT_PI * (wofz(1j * zm) - _w_of_i_over_u(u))
    if np.any(far):
        kf = kappa[far]
        r = s[far] / (2.0 * kf)
        # Gamma2 < 0 (Re R < 0): the same Maxwell-integral branch as in _w_of_i_over_u,
        # -w(-iR) for w(iR), i.e. the bracket of -R. (The exp(Z-^2) that wofz keeps in the
        # near branch is below exp(-1e4) here.)
        r = np.where(r.real < 0, -r, r)
        a[far] = (2.0 / kf) * _one_minus_sqrtpi_r_w(r)
    return a


def qsdhcp(
    nu_hz,
    nu0_hz,
    doppler_hwhm_hz,
    gamma0_hz,
    gamma2_hz=0.0,
    delta0_hz=0.0,
    delta2_hz=0.0,
    nu_vc_hz=0.0,
):
    """Quadratic speed-dependent hard-collision profile (HTP with eta = 0), complex, 1/Hz.

    nu_hz, nu0_hz: frequency and unperturbed line centre (Hz); doppler_hwhm_hz: Doppler
    HWHM (Hz, > 0); gamma0_hz, gamma2_hz: speed-averaged collisional HWHM and its quadratic
    speed dependence (Hz); delta0_hz, delta2_hz: speed-averaged shift and its speed
    dependence (Hz); nu_vc_hz: hard-collision velocity-changing rate (Hz). All broadcast.

    g = (1/pi) A / (1 - nu_VC A), A the Maxwell-averaged complex Lorentzian with
    Gamma(v) = Gamma0 + Gamma2 (v^2/v_p^2 - 3/2) (likewise Delta), v_p the most probable
    speed. Physical domain: GammaD > 0, nu_VC >= 0, 0 <= Gamma2 <= 2/3 Gamma0 (so that
    Gamma(v) >= 0 at every speed); there Re g >= 0 everywhere and the result is finite.

    Continuation (for least-squares estimators, which must be free to step past Gamma2 = 0
    and nu_VC = 0; priors keep the physical domain): g is analytic in nu_VC, so nu_VC < 0 is
    the same formula. Gamma2 < 0 takes the speed integral's branch for the second root
    (``_w_of_i_over_u``), smooth through Gamma2 = 0 and equal to the kinetic Maxwell average
    up to the weight of the speed classes with Gamma(v) + nu_VC < 0, ~exp(-(Gamma0 + nu_VC)
    /|Gamma2|) of the peak (2e-7 at Gamma2 = -0.1 Gamma0, nu_VC = 0.46 Gamma0). Gamma2 < 0
    is defined for Delta2 = 0 and 4 ln2 |Gamma2| Re C0~ < GammaD^2, where it is finite at
    every detuning; elsewhere it is NaN.
    """
    # the parameters keep their own shapes (one value per walker, say) and broadcast against the
    # frequencies only where a quantity depends on both: a sampler's call then does the
    # per-parameter arithmetic once per parameter set, not once per frequency
    nu, nu0, gd, g0, g2, d0, d2, nvc = (
        np.asarray(x, dtype=float)
        for x in (
            nu_hz, nu0_hz, doppler_hwhm_hz, gamma0_hz, gamma2_hz, delta0_hz, delta2_hz, nu_vc_hz
        )
    )  # fmt: skip
    shape = np.broadcast_shapes(nu.shape, nu0.shape, gd.shape, g0.shape, g2.shape, d0.shape,
                                d2.shape, nvc.shape)  # fmt: skip
    # the frequency-dependent arithmetic in numpy's array loops even for one point (its scalar
    # complex product rounds differently in the last bit)
    nu = np.atleast_1d(nu)
    _check_doppler(gd)
    cte = _SQRT_LN2 / gd  # 1/Hz
    c0t = (g0 - 1.5 * g2 + nvc) + 1j * (d0 - 1.5 * d2)  # Hz
    z0 = np.asarray(cte * (c0t - 1j * (nu - nu0)))  # every input's broadcast shape
    kappa = cte * (g2 + 1j * d2)
    # Gamma2 < 0 with Delta2 = 0: as nu varies, 1 + 4 kappa z0 runs parallel to the real axis
    # at Re = 1 + 4 kappa cte Re C0~; at or below 0 sqrt(1 + 4 kappa z0) jumps on its branch
    # cut and the continuation is undefined. With Delta2 != 0, w(iZ-) leaves the upper half
    # plane far out and overflows: not covered. NaN in both cases, never a wrong number.
    inside = ~((g2 < 0) & ((d2 != 0) | (1.0 + 4.0 * cte * cte * g2 * c0t.real <= 0)))
    if np.all(inside):
        a = cte * _speed_averaged(z0, kappa)  # A, 1/Hz
    else:
        inside = np.broadcast_to(inside, z0.shape)
        a = np.full_like(z0, np.nan)
        a[inside] = np.broadcast_to(cte, z0.shape)[inside] * _speed_averaged(
            z0[inside], np.broadcast_to(kappa, z0.shape)[inside]
        )
    with np.errstate(invalid="ignore"):
        g = a / (np.pi * (1.0 - nvc * a))
    return g.reshape(shape)


# |u| = |kappa/(1 + kappa Z-)| below which T(u) (see ``_htp_remainder``) is summed from its
# series (6 terms, truncation < 1e-17 relative at the switch) rather than formed as 1/u minus a
# nearly equal term (which loses ~1/|u|^2 x 1e-16, 3e-13 relative at the switch).
_T_SERIES_U = 0.02
# coefficients of T(u) = sum_n (a_n - a_(n+1)) u^(2n+1), a_n = (-1)^n (2n-1)!!/2^n
_T_COEFS = (1.5, -1.25, 2.625, -8.4375, 36.09375, -191.953125)


def _htp_remainder(u):
    """T(u) = 1/u + sqrt(pi) (1 - 1/u^2) w(i/u), dimensionless, finite as u -> 0 (T ~ 3u/2).

    The second root's part of Ngo et al.'s B term is -sqrt(pi) kappa (1 - Z+^2) w(iZ+) =
    kappa/u - kappa T(u) with Z+ = 1/u; kappa/u = 1 + kappa Z- cancels B's leading -1
    analytically, so B stays exact through Gamma2 = Delta2 = 0 (u = 0, Z+ = infinity).
    """
    out = np.empty_like(u)
    series = np.abs(u) < _T_SERIES_U
    if np.any(series):
        us = u[series]
        u2 = us * us
        acc = np.zeros_like(us)
        for c in reversed(_T_COEFS):
            acc = acc * u2 + c
        out[series] = us * acc
    rest = ~series
    if np.any(rest):
        ur = u[rest]
        out[rest] = 1.0 / ur + _SQRT_PI * (1.0 - 1.0 / (ur * ur)) * _w_of_i_over_u(ur)
    return out


def _htp_b_term(z0, kappa):
    """C2~ B of Ngo et al. (2013) Eq. 12 in Doppler units, dimensionless (``_speed_averaged``).

    B~ = (1/C2~) [-1 + sqrt(pi)/(2 sqrt Y) ((1 - Z-^2) w(iZ-) - (1 - Z+^2) w(iZ+))] with
    1/(2 sqrt Y) = kappa: returned is the bracket, written as kappa [sqrt(pi) (1 - Z-^2) w(iZ-)
    + Z- - T(u)] (``_htp_remainder``), which is 0 at kappa = 0. Where the two w terms nearly
    cancel (|4 kappa z0| > _XY_RATIO_SWITCH) Tran et al.'s Y -> 0 limit is used:
    1 - 2 (X + 2Y) (1 - sqrt(pi) R w(iR)), X = z0/kappa, Y = 1/(4 kappa^2), R = sqrt(X + Y);
    only its absolute accuracy matters (it is added to 1 in the profile's denominator).
    """
    b = np.empty_like(z0)
    p = 4.0 * kappa * z0
    s = np.sqrt(1.0 + p)
    far = np.abs(p) > _XY_RATIO_SWITCH
    near = ~far
    if np.any(near):
        zn, kn, sn = z0[near], kappa[near], s[near]
        zm = 2.0 * zn / (1.0 + sn)
        u = kn / (1.0 + kn * zm)
        b[near] = kn * (_SQRT_PI * (1.0 - zm * zm) * wofz(1j * zm) + zm - _htp_remainder(u))
    if np.any(far):
        kf, zf = kappa[far], z0[far]
        r = s[far] / (2.0 * kf)
        r = np.where(r.real < 0, -r, r)
        x_plus_2y = zf / kf + 0.5 / (kf * kf)
        b[far] = 1.0 - 2.0 * x_plus_2y * _one_minus_sqrtpi_r_w(r)
    return b


def htp(
    nu_hz,
    nu0_hz,
    doppler_hwhm_hz,
    gamma0_hz,
    gamma2_hz=0.0,
    delta0_hz=0.0,
    delta2_hz=0.0,
    nu_vc_hz=0.0,
    eta=0.0,
):
    """Hartmann-Tran profile (pCqSDHCP), complex, 1/Hz; ``eta`` the correlation parameter.

    Hz inputs as :func:`qsdhcp`; eta (dimensionless, 0 <= eta < 1) is the share of the
    velocity-changing collisions that also dephase [Ngo, Lisak, Tran, Hartmann, JQSRT 129
    (2013) 89, Eqs. 9-12; Tennyson et al., Pure Appl. Chem. 86 (2014) 1931, the IUPAC
    recommended profile]. With C0 = Gamma0 + i Delta0, C2 = Gamma2 + i Delta2:

        C0~ = (1 - eta)(C0 - 3/2 C2) + nu_VC,   C2~ = (1 - eta) C2,
        g = (1/pi) A / (1 - (nu_VC - eta (C0 - 3/2 C2)) A + eta C2 B),

    A and B the speed averages of :func:`qsdhcp`'s machinery with C0~, C2~. eta = 0 is the
    qSDHCP exactly (B drops out); Gamma2 = Delta2 = 0 is the hard-collision profile of rate
    nu_VC - eta C0 acting on C0~ (B = 0 there, see ``_htp_b_term``). Outside the domain
    (eta >= 1, or qsdhcp's undefined continuation) the value is NaN, never a wrong number.
    """
    shape, (nu, nu0, gd, g0, g2, d0, d2, nvc, et) = _flat_broadcast(
        nu_hz, nu0_hz, doppler_hwhm_hz, gamma0_hz, gamma2_hz, delta0_hz, delta2_hz, nu_vc_hz, eta
    )
    _check_doppler(gd)
    cte = _SQRT_LN2 / gd  # 1/Hz
    c0 = g0 + 1j * d0  # Hz
    c2 = g2 + 1j * d2
    c0t = (1.0 - et) * (c0 - 1.5 * c2) + nvc
    c2t = (1.0 - et) * c2
    z0 = cte * (c0t - 1j * (nu - nu0))
    kappa = cte * c2t
    # the same continuation domain as qsdhcp, on the effective Gamma2~ = (1 - eta) Gamma2
    # and eta < 1 (at eta = 1 every velocity change dephases and eta/(1 - eta) diverges)
    inside = ~((c2t.real < 0) & ((c2t.imag != 0) | (1.0 + 4.0 * cte * kappa.real * c0t.real <= 0)))
    inside &= et < 1.0
    a = np.full_like(z0, np.nan)
    bk = np.full_like(z0, np.nan)
    a[inside] = cte[inside] * _speed_averaged(z0[inside], kappa[inside])  # A, 1/Hz
    bk[inside] = _htp_b_term(z0[inside], kappa[inside])  # C2~ B, dimensionless
    with np.errstate(invalid="ignore", divide="ignore"):
        denom = 1.0 - (nvc - et * (c0 - 1.5 * c2)) * a + et / (1.0 - et) * bk
        g = a / (np.pi * denom)
    return g.reshape(shape)


def gaussian(nu_hz, nu0_hz, doppler_hwhm_hz, delta0_hz=0.0):
    """Complex Gaussian (Doppler) profile, 1/Hz, centred at nu0 + delta0 (all in Hz).

    g = (cte/sqrt(pi)) [exp(-x^2) + (2i/sqrt(pi)) F(x)], x = cte (nu - nu0 - delta0),
    cte = sqrt(ln2)/GammaD, F Dawson's integral: the real-axis value of w.
    """
    _check_doppler(doppler_hwhm_hz)
    cte = _SQRT_LN2 / np.asarray(doppler_hwhm_hz, dtype=float)
    x = cte * (np.asarray(nu_hz, dtype=float) - nu0_hz - delta0_hz)
    return cte / _SQRT_PI * (np.exp(-x * x) + 2j / _SQRT_PI * dawsn(x))


def lorentzian(nu_hz, nu0_hz, gamma0_hz, delta0_hz=0.0):
    """Complex Lorentzian, 1/Hz: (1/pi) / (Gamma0 - i (nu - nu0 - Delta0)), all in Hz."""
    det = np.asarray(nu_hz, dtype=float) - nu0_hz - delta0_hz
    return (1.0 / np.pi) / (np.asarray(gamma0_hz, dtype=float) - 1j * det)


def voigt(nu_hz, nu0_hz, doppler_hwhm_hz, gamma0_hz, delta0_hz=0.0):
    """Complex Voigt profile, 1/Hz: (cte/sqrt(pi)) w(cte (nu - nu0 - Delta0 + i Gamma0)).

    doppler_hwhm_hz, gamma0_hz: Gaussian and Lorentzian HWHM (Hz); cte = sqrt(ln2)/GammaD.
    """
    _check_doppler(doppler_hwhm_hz)
    cte = _SQRT_LN2 / np.asarray(doppler_hwhm_hz, dtype=float)
    z = cte * ((np.asarray(nu_hz, dtype=float) - nu0_hz - delta0_hz) + 1j * np.asarray(gamma0_hz))
    return cte / _SQRT_PI * wofz(z)


def sdvoigt(nu_hz, nu0_hz, doppler_hwhm_hz, gamma0_hz, gamma2_hz=0.0, delta0_hz=0.0, delta2_hz=0.0):
    """Quadratic speed-dependent Voigt profile, 1/Hz: the qSDHCP with nu_VC = 0 (Hz inputs)."""
    return qsdhcp(nu_hz, nu0_hz, doppler_hwhm_hz, gamma0_hz, gamma2_hz, delta0_hz, delta2_hz, 0.0)


def hard_collision(nu_hz, nu0_hz, doppler_hwhm_hz, gamma0_hz, delta0_hz=0.0, nu_vc_hz=0.0):
    """Rautian-Sobelman / Nelkin-Ghatak hard-collision profile, complex, 1/Hz (Hz inputs).

    Closed form: with cte = sqrt(ln2)/GammaD and W = w(cte (nu - nu0 - Delta0) +
    i cte (Gamma0 + nu_VC)), g = (cte/sqrt(pi)) W / (1 - sqrt(pi) cte nu_VC W): the Voigt
    of the total (dephasing + velocity-changing) rate, divided by the hard-collision
    "return" term that gives Dicke narrowing.
    """
    _check_doppler(doppler_hwhm_hz)
    cte = _SQRT_LN2 / np.asarray(doppler_hwhm_hz, dtype=float)
    nvc = np.asarray(nu_vc_hz, dtype=float)
    z = cte * (
        (np.asarray(nu_hz, dtype=float) - nu0_hz - delta0_hz)
        + 1j * (np.asarray(gamma0_hz, dtype=float) + nvc)
    )
    w = wofz(z)
    return cte / _SQRT_PI * w / (1.0 - _SQRT_PI * cte * nvc * w)


SHAPE_PARAMETERS = ("gamma0_hz", "gamma2_hz", "delta0_hz", "delta2_hz", "nu_vc_hz")
# the HTP adds the dimensionless correlation parameter eta to the qSDHCP's rates
HTP_PARAMETERS = (*SHAPE_PARAMETERS, "eta")


@dataclass(frozen=True)
class ProfileSpec:
    """Which shape parameters (HWHM/rates in Hz) a named profile uses, and how to call it."""

    name: str
    parameters: tuple[str, ...]
    uses_doppler: bool
    function: Callable


def _call_gaussian(nu, nu0, gd, p):
    return gaussian(nu, nu0, gd, p["delta0_hz"])


def _call_lorentzian(nu, nu0, gd, p):
    return lorentzian(nu, nu0, p["gamma0_hz"], p["delta0_hz"])


def _call_voigt(nu, nu0, gd, p):
    return voigt(nu, nu0, gd, p["gamma0_hz"], p["delta0_hz"])


def _call_sdvp(nu, nu0, gd, p):
    return sdvoigt(nu, nu0, gd, p["gamma0_hz"], p["gamma2_hz"], p["delta0_hz"], p["delta2_hz"])


def _call_rautian(nu, nu0, gd, p):
    return hard_collision(nu, nu0, gd, p["gamma0_hz"], p["delta0_hz"], p["nu_vc_hz"])


def _call_qsdhcp(nu, nu0, gd, p):
    return qsdhcp(
        nu, nu0, gd, p["gamma0_hz"], p["gamma2_hz"], p["delta0_hz"], p["delta2_hz"], p["nu_vc_hz"]
    )


def _call_htp(nu, nu0, gd, p):
    return htp(
        nu,
        nu0,
        gd,
        p["gamma0_hz"],
        p["gamma2_hz"],
        p["delta0_hz"],
        p["delta2_hz"],
        p["nu_vc_hz"],
        p["eta"],
    )


PROFILES: dict[str, ProfileSpec] = {
    "gaussian": ProfileSpec("gaussian", ("delta0_hz",), True, _call_gaussian),
    "lorentzian": ProfileSpec("lorentzian", ("gamma0_hz", "delta0_hz"), False, _call_lorentzian),
    "voigt": ProfileSpec("voigt", ("gamma0_hz", "delta0_hz"), True, _call_voigt),
    "sdvp": ProfileSpec(
        "sdvp", ("gamma0_hz", "gamma2_hz", "delta0_hz", "delta2_hz"), True, _call_sdvp
    ),
    "rautian": ProfileSpec("rautian", ("gamma0_hz", "delta0_hz", "nu_vc_hz"), True, _call_rautian),
    "qsdhcp": ProfileSpec("qsdhcp", SHAPE_PARAMETERS, True, _call_qsdhcp),
    "htp": ProfileSpec("htp", HTP_PARAMETERS, True, _call_htp),
}


def profile(name, nu_hz, nu0_hz, doppler_hwhm_hz, **shape):
    """Evaluate the named profile (complex, 1/Hz) at nu_hz; all inputs in Hz.

    shape: any of HTP_PARAMETERS (HWHM, shifts, rates in Hz; eta dimensionless). A parameter
    the profile does not use must be absent or zero (ValueError naming it otherwise), so a fit
    cannot silently drop physics. doppler_hwhm_hz is ignored by the Lorentzian.
    """
    try:
        spec = PROFILES[name]
    except KeyError:
        raise ValueError(f"unknown profile {name!r}; known: {sorted(PROFILES)}") from None
    params = dict.fromkeys(HTP_PARAMETERS, 0.0)
    for key, value in shape.items():
        if key not in params:
            raise ValueError(f"unknown shape parameter {key!r}; known: {HTP_PARAMETERS}")
        if key not in spec.parameters and np.any(np.asarray(value) != 0):
            raise ValueError(f"profile {name!r} does not use {key!r}, which must be 0 or absent")
        params[key] = value
    return spec.function(nu_hz, nu0_hz, doppler_hwhm_hz, params)
