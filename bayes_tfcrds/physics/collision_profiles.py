"""Line profiles beyond the quadratic forms: power-law speed dependence and soft collisions.

The qSDHCP family of :mod:`bayes_tfcrds.physics.lineshape` assumes a quadratic speed dependence
of the width and hard (Rautian) velocity-changing collisions. Gases need not oblige: the
width's speed dependence of a power-law (hypergeometric) potential model goes as v^m
[Berman, JQSRT 12 (1972) 1331; Ward, Cooper, Smith, JQSRT 14 (1974) 555], and collisions
that deflect a molecule only slightly narrow the Doppler profile as Brownian velocity
diffusion does [Galatry, Phys. Rev. 122 (1961) 1218]. The discovery workflow offers these as
the other members of its speed-dependence and narrowing families, so that either effect is
named even where its form is not the quadratic one.

Both are computed from their definitions by quadrature, not from closed forms:

* :func:`power_law_sdvoigt`: for each reduced speed x = v/v_p the direction average of the
  Doppler-shifted Lorentzian is exact, ln((a + i k v)/(a - i k v)) / (2 pi i k v) with
  a = Gamma(v) - i (nu - nu0 - Delta(v)); the speeds are integrated with the Maxwell density
  by composite Gauss-Legendre quadrature.
* :func:`galatry`: g = 2 int_0^inf Phi(t) exp(2 pi i (nu - nu0) t) dt, with the soft-collision
  correlation function Phi (Doppler part exp(-(k v_p)^2/(2 beta^2) (beta t - 1 + e^(-beta t))),
  beta = 2 pi nu_D), integrated over t by composite Gauss-Legendre quadrature up to where
  Phi < 1e-15.

Conventions are those of :mod:`bayes_tfcrds.physics.lineshape`: Hz throughout (HWHM, shifts,
rates), complex profiles in 1/Hz whose real part has unit area and whose imaginary part is
the dispersion, positive above the centre. Both reduce to the Voigt profile (m = 0; nu_D = 0).
"""

from __future__ import annotations

import numpy as np
from scipy.special import gamma as gamma_fn

__all__ = ["power_law_sdvoigt", "speed_averaged", "galatry", "maxwell_moment"]

_SQRT_LN2 = np.sqrt(np.log(2.0))
_GL_NODES, _GL_WEIGHTS = np.polynomial.legendre.leggauss(8)
# reduced speeds beyond X_MAX carry a Maxwell weight below 1e-14
_X_MAX = 6.0
# speed panels: one per resonance width Gamma/(k v_p) of the log term, Gamma the smallest width
# of the speeds that matter (x in [0.2, 3]). Measured: the m = 0 profile equals the Voigt to
# 1e-13 of its peak for Gamma0 from 0.004 to 0.4 Doppler HWHM (half as many panels: 2e-10); power
# laws against 20000 panels: 3e-10 (m = 0.2), 3e-8 (0.5), 1e-6 (m = 1 to 2). At most
# _X_PANELS_MAX panels
_X_PANELS_MIN = 96
_X_PANELS_MAX = 6000
# evaluations of the integrand per block of detunings (bounds the memory to ~100 MB)
_BLOCK = 2_000_000
# the soft-collision correlation function is integrated until it falls below this
_PHI_FLOOR = 1e-15
# time panels per period of the largest detuning, and the cap on their number
_T_PANELS_PER_PERIOD = 2.0
_T_PANELS_MAX = 20000


def maxwell_moment(m):
    """<(v/v_p)^m> over the Maxwell speed distribution: 2 Gamma((3 + m)/2) / sqrt(pi)."""
    return 2.0 * gamma_fn(0.5 * (3.0 + np.asarray(m, float))) / np.sqrt(np.pi)


def _panels(lo, hi, n):
    """Nodes and weights of an n-panel, 8-point Gauss-Legendre rule on [lo, hi]."""
    edges = np.linspace(lo, hi, n + 1)
    half = 0.5 * np.diff(edges)
    mid = 0.5 * (edges[1:] + edges[:-1])
    nodes = (mid[:, None] + half[:, None] * _GL_NODES[None, :]).ravel()
    weights = (half[:, None] * _GL_WEIGHTS[None, :]).ravel()
    return nodes, weights


def _direction_average(gam, d, kv):
    """(1/pi) <1/(a + i k v mu)> over mu uniform on [-1, 1], a = gam - i d; (re, im) in 1/Hz.

    ``gam`` > 0 (Hz) is the speed's collisional width, ``d`` (Hz) the detuning from its shifted
    centre, ``kv`` > 0 (Hz) its Doppler shift; they broadcast. The average is
    (ln(a + i k v) - ln(a - i k v)) / (2 pi i k v), written in real arithmetic without
    cancellation: with gam > 0 both logarithms lie in the right half-plane, so their difference is
    ln|.|-ratio + i (sum of two arctangents), i.e.
    log1p(-4 k v d / (gam^2 + (k v + d)^2)) / 2 + i atan2(2 k v gam, gam^2 + d^2 - (k v)^2).
    Both stay exact to rounding as k v -> 0 (the log1p's argument and the atan2's first argument
    are then small, not differences of near-equal numbers), where the limit is 1/(pi a). Real
    log1p and atan2 cost about a third of two complex logarithms.
    """
    kd = kv * d
    den = gam * gam + (kv + d) ** 2
    log_ratio = np.log1p(-4.0 * kd / den)
    angle = np.arctan2(2.0 * kv * gam, gam * gam + d * d - kv * kv)
    scale = 1.0 / (2.0 * np.pi * kv)
    return angle * scale, -0.5 * log_ratio * scale


def power_law_sdvoigt(
    nu_hz, nu0_hz, doppler_hwhm_hz, gamma0_hz, sd_exponent, delta0_hz=0.0, delta_sd_hz=0.0
):
    """Speed-dependent Voigt profile with power-law speed dependence, complex, 1/Hz.

    Gamma(v) = gamma0 x^m / <x^m> (x = v/v_p, m = ``sd_exponent``), so that its Maxwell average
    is gamma0; the shift Delta(v) = delta0 + delta_sd (x^m / <x^m> - 1) has the same law and
    the Maxwell average delta0. m = 0 (or gamma0 = delta_sd = 0) gives the Voigt profile.
    Inputs in Hz (scalars for the shape); ``nu_hz`` any shape.
    """
    g0, m = float(gamma0_hz), float(sd_exponent)
    if not g0 > 0:
        raise ValueError(f"gamma0_hz must be > 0 for the speed average, got {gamma0_hz}")
    norm = maxwell_moment(m)

    def width(x):
        return g0 * x**m / norm

    def shift(x):
        return delta0_hz + delta_sd_hz * (x**m / norm - 1.0)

    narrowest = float(min(width(0.2), width(3.0)))
    return speed_averaged(nu_hz, nu0_hz, doppler_hwhm_hz, width, shift, narrowest)


def speed_averaged(nu_hz, nu0_hz, doppler_hwhm_hz, width, shift, gamma_scale_hz):
    """Speed-dependent Voigt profile for any width(x) and shift(x) (Hz) of x = v/v_p, 1/Hz.

    The Maxwell average of the exact direction average at each speed; ``gamma_scale_hz`` (Hz,
    > 0) sets the speed panels (one per Gamma/(k v_p)). The quadratic law gives the sdvoigt of
    :mod:`bayes_tfcrds.physics.lineshape` (a test).
    """
    gd = float(doppler_hwhm_hz)
    if not gd > 0:
        raise ValueError(f"doppler_hwhm_hz must be > 0, got {doppler_hwhm_hz}")
    nu = np.asarray(nu_hz, float)
    want = np.ceil(_X_MAX * gd / (_SQRT_LN2 * max(float(gamma_scale_hz), 1e-300)))
    n_panels = int(max(_X_PANELS_MIN, min(want, _X_PANELS_MAX)))
    x, w = _panels(0.0, _X_MAX, n_panels)
    maxwell = 4.0 / np.sqrt(np.pi) * x * x * np.exp(-x * x)
    kv = (gd / _SQRT_LN2 * x)[None, :]  # (nu0/c) v in Hz
    gam, dlt, wm = width(x)[None, :], shift(x)[None, :], w * maxwell
    det = (nu - nu0_hz).ravel()
    out = np.empty(det.size, complex)
    step = max(1, _BLOCK // x.size)
    for i in range(0, det.size, step):
        re, im = _direction_average(gam, det[i : i + step, None] - dlt, kv)
        out[i : i + step].real = re @ wm
        out[i : i + step].imag = im @ wm
    return out.reshape(nu.shape)


def _galatry_doppler(t, kvp, beta):
    """The Doppler factor of the soft-collision correlation function at times ``t`` (s).

    exp(-(k v_p t)^2 h(beta t) / 2), h(x) = (x - 1 + e^-x) / x^2 (h(0) = 1/2: the Gaussian),
    written with h so that beta -> 0 never divides by beta^2.
    """
    t = np.asarray(t, float)
    x = beta * t
    xs = np.maximum(x, 1e-2)
    h = np.where(
        x < 1e-2,
        0.5 - x * (1 / 6 - x * (1 / 24 - x * (1 / 120 - x / 720))),
        (xs + np.expm1(-np.minimum(xs, 700.0))) / (xs * xs),
    )
    return np.exp(-0.5 * (kvp * t) ** 2 * h)


def galatry(nu_hz, nu0_hz, doppler_hwhm_hz, gamma0_hz, delta0_hz=0.0, nu_d_hz=0.0):
    """Galatry (soft-collision) profile, complex, 1/Hz.

    ``nu_d_hz`` is the velocity-diffusion rate beta/(2 pi) in Hz (the Galatry narrowing
    parameter is z = beta/(k v_p)); nu_d = 0 gives the Voigt profile. Inputs in Hz (scalars
    for the shape); ``nu_hz`` any shape.
    """
    gd = float(doppler_hwhm_hz)
    if not gd > 0:
        raise ValueError(f"doppler_hwhm_hz must be > 0, got {doppler_hwhm_hz}")
    g0, beta = float(gamma0_hz), 2.0 * np.pi * float(nu_d_hz)
    if g0 < 0 or beta < 0:
        raise ValueError(f"gamma0_hz and nu_d_hz must be >= 0, got {gamma0_hz}, {nu_d_hz}")
    kvp = 2.0 * np.pi * gd / _SQRT_LN2  # rad/s
    nu = np.asarray(nu_hz, float)
    det = (nu - nu0_hz - delta0_hz).ravel()
    t_end = _galatry_extent(kvp, beta, 2.0 * np.pi * g0)
    f_max = max(float(np.max(np.abs(det))) if det.size else 0.0, gd)
    n_panels = int(np.ceil(_T_PANELS_PER_PERIOD * f_max * t_end)) + 8
    n_panels = min(n_panels, _T_PANELS_MAX)
    # equal panels of half-width h centred on mid_j, nodes t_jk = mid_j + h xi_k: the Fourier
    # factor splits as exp(i w mid_j) exp(i w h xi_k), so each detuning needs one exponential per
    # panel and eight per block, not one per node (8 times fewer; the sums are matrix products)
    h = 0.5 * t_end / n_panels
    mid = h * (2.0 * np.arange(n_panels) + 1.0)
    t = mid[:, None] + h * _GL_NODES[None, :]  # (panels, 8) s
    phi = np.exp(-2.0 * np.pi * g0 * t) * _galatry_doppler(t, kvp, beta) * (h * _GL_WEIGHTS)
    out = np.empty(det.size, complex)
    step = max(1, _BLOCK // n_panels)
    for i in range(0, det.size, step):
        w = 2j * np.pi * det[i : i + step, None]
        within = np.exp(w * (h * _GL_NODES)[None, :]) @ phi.T  # (detunings, panels)
        out[i : i + step] = 2.0 * np.einsum("dj,dj->d", np.exp(w * mid[None, :]), within)
    return out.reshape(nu.shape)


def _galatry_extent(kvp, beta, gam):
    """Time (s) after which the correlation function's envelope is below _PHI_FLOOR."""
    t = np.geomspace(1e-3 / kvp, 1e6 / kvp, 2000)
    env = np.exp(-gam * t) * _galatry_doppler(t, kvp, beta)
    below = np.nonzero(env < _PHI_FLOOR)[0]
    return float(t[below[0]]) if below.size else float(t[-1])
