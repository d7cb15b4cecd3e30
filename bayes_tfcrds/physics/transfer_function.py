"""Detection-chain transfer function H(f) (letter Eqs. 1-2); the beat-note fit is in fit.beat_note.

Two variants share one parameter set:

* ``letter``: Eq. 2 as published, ``1/(1 + i f/f_c) + A_r/(1 - (f/f_r)^n_r + i f/(Gamma_r f_r))``
  for f >= 0 and ``H(-f) = conj(H(f))``. For n_r != 2 the resonant term is not the transform
  of a causal response: its impulse response leaks to t < 0.
* ``causal``: the resonant denominator ``1 + (i f/f_r)^n_r + i f/(Gamma_r f_r)`` (a
  fractional-order second-order system), identical to ``letter`` for n_r = 2 and causal for
  any n_r in (0, 2].

The forward model uses H normalised to H(0) = 1, so that the offset b and amplitude B of a
ring-down keep their meaning in volts; an overall gain of the chain is absorbed by B and b.
The beat-note fit carries the overall scale as a separate parameter ``scale`` (the letter's
normalisation: a static nonlinearity of the DC measurements only rescales |H|).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np
from scipy import fft as sfft

PARAM_NAMES = ("f_c_hz", "a_r", "f_r_hz", "gamma_r", "n_r")
VARIANTS = ("letter", "causal")
# the physical domain any fit or draw of H is kept in: frequencies from 1 Hz to 10 GHz (beyond the
# reach of any CRDS digitiser either way), a positive DC gain 1 + A_r, and orders up to 2.5
SUPPORT = {
    "f_c_hz": (1.0, 1.0e10),
    "a_r": (-0.99, 1.0e4),
    "f_r_hz": (1.0, 1.0e10),
    "gamma_r": (1.0e-3, 1.0e3),
    "n_r": (0.5, 2.5),
}


def outside_support(params: TFParams, names=PARAM_NAMES) -> list:
    """The names among ``names`` whose values lie outside :data:`SUPPORT` (or are not finite)."""
    out = []
    for n in names:
        v, (lo, hi) = getattr(params, n), SUPPORT[n]
        if not (np.isfinite(v) and lo < v < hi):
            out.append(n)
    return out


@dataclass(frozen=True)
class TFParams:
    """Parameters of Eq. 2.

    Cutoff f_c (Hz), resonance amplitude A_r, frequency f_r (Hz), quality factor Gamma_r and
    effective order n_r (dimensionless).
    """

    f_c_hz: float
    a_r: float = 0.0
    f_r_hz: float = 1.0e6
    gamma_r: float = 1.0
    n_r: float = 2.0
    variant: str = "causal"

    def __post_init__(self):
        if self.variant not in VARIANTS:
            raise ValueError(f"variant must be one of {VARIANTS}, got {self.variant!r}")
        if not (self.f_c_hz > 0 and self.f_r_hz > 0 and self.gamma_r > 0 and self.n_r > 0):
            raise ValueError(f"f_c_hz, f_r_hz, gamma_r and n_r must be > 0: {self}")
        if np.isclose(1.0 + self.a_r, 0.0):
            raise ValueError("1 + a_r must not vanish: H(0) = 1 + A_r is the DC gain")

    def as_vector(self, names=PARAM_NAMES) -> np.ndarray:
        return np.array([getattr(self, n) for n in names], dtype=float)

    def with_vector(self, values, names=PARAM_NAMES) -> TFParams:
        return replace(self, **{n: float(v) for n, v in zip(names, values)})


def transfer_function(f_hz, params: TFParams, normalise: bool = True) -> np.ndarray:
    """Complex H(f) at frequencies ``f_hz`` (Hz, any sign), dimensionless.

    With ``normalise`` the result is divided by H(0) = 1 + A_r (unit DC gain).
    Negative frequencies return conj(H(|f|)) so that the impulse response is real.
    """
    return transfer_function_array(
        f_hz,
        params.f_c_hz,
        params.a_r,
        params.f_r_hz,
        params.gamma_r,
        params.n_r,
        params.variant,
        normalise,
    )


def transfer_function_array(
    f_hz, f_c_hz, a_r, f_r_hz, gamma_r, n_r, variant="causal", normalise=True
):
    """Eq. 2 with array-valued parameters that broadcast against ``f_hz`` (Hz).

    The samplers evaluate many parameter sets at once (emcee's vectorised walkers): pass
    parameters of shape (n, 1) and frequencies of shape (m,) to get (n, m).
    """
    f = np.asarray(f_hz, dtype=float)
    af = np.abs(f)
    lowpass = 1.0 / (1.0 + 1j * af / f_c_hz)
    x = af / f_r_hz
    if variant == "letter":
        denom = 1.0 - x**n_r + 1j * x / gamma_r
    elif variant == "causal":
        # principal branch of (i x)^n for x >= 0: x^n exp(i n pi / 2)
        denom = 1.0 + x**n_r * np.exp(0.5j * np.pi * n_r) + 1j * x / gamma_r
    else:
        raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
    h = lowpass + a_r / denom
    if normalise:
        h = h / (1.0 + a_r)
    negative = f < 0
    if not negative.any():  # rfft grids and beat notes: no conjugate copy of a large array
        return np.asarray(h)
    return np.where(negative, np.conj(h), h)


def transfer_function_of_draws(f_hz, centre: TFParams, names, draws) -> np.ndarray:
    """Normalised H(f) of every posterior draw in one vectorised call; shape (n, len(f_hz)).

    ``draws`` (n, len(names)) in natural units; the parameters not in ``names`` stay at
    ``centre``. Frequencies in Hz.
    """
    d = np.atleast_2d(np.asarray(draws, float))
    cols = {n: getattr(centre, n) for n in PARAM_NAMES}
    cols.update({n: d[:, i : i + 1] for i, n in enumerate(names)})
    return transfer_function_array(
        np.asarray(f_hz, float)[None, :], *(cols[n] for n in PARAM_NAMES), centre.variant
    )


def transfer_function_derivatives(f_hz, params: TFParams, names, rel_step: float = 1e-6):
    """d H_normalised / d theta for each parameter in ``names``, shape (len(names), *f.shape).

    Central differences on the closed form: H is cheap, and the step (1e-6 relative) keeps
    truncation and round-off errors near 1e-10 of |H|, far below any statistical use.
    """
    out = []
    for name in names:
        v = getattr(params, name)
        h = rel_step * max(abs(v), 1e-3)
        hp = transfer_function(f_hz, replace(params, **{name: v + h}))
        hm = transfer_function(f_hz, replace(params, **{name: v - h}))
        out.append((hp - hm) / (2.0 * h))
    return np.stack(out)


def impulse_response(params: TFParams, dt_s: float, n: int, smoothing_s: float = 0.0):
    """Impulse response h(t) (1/s) on a periodic grid of ``n`` samples spaced ``dt_s`` (s).

    Returns ``(t_s, h)`` with t running from -n/2 dt to (n/2 - 1) dt. ``smoothing_s`` > 0
    multiplies H by a Gaussian of time width ``smoothing_s`` (s): the jump of the first-order
    term at t = 0 then no longer rings (Gibbs) into t < 0, so causality can be checked to the
    Gaussian's tail. The grid must be long enough for the response to decay (no time aliasing).
    """
    f = sfft.fftfreq(n, dt_s)
    hf = transfer_function(f, params)
    if smoothing_s > 0:
        hf = hf * np.exp(-0.5 * (2 * np.pi * f * smoothing_s) ** 2)
    h = np.real(sfft.ifft(hf)) / dt_s
    h = sfft.fftshift(h)
    t = (np.arange(n) - n // 2) * dt_s
    return t, h


@lru_cache(maxsize=64)
def settling_times(params: TFParams, dt_s: float, tol: float = 1e-7):
    """Times (s) after which the step response has settled and before which it has not begun.

    Returns ``(history_s, lead_s)``: |1 - a(t)| < tol for t > history_s and |a(t)| < tol for
    t < -lead_s, where a is the unit step response of normalised H. The forward model pads its
    FFT grid with this much history before the record (causal tails) and lead after it
    (pre-response of a non-causal H), so that the periodic wrap-around of the DFT stays below
    ``tol`` of the ring-down amplitude. The response is computed with a Gaussian smoothing of
    two samples, which removes the Gibbs ripple of sampling a non-band-limited H without
    touching its microsecond tails (the quantity that matters here).
    """
    n = 1 << 16
    while True:
        t, h = impulse_response(params, dt_s, n, smoothing_s=2.0 * dt_s)
        step = np.cumsum(h) * dt_s
        late = np.nonzero(np.abs(1.0 - step) >= tol)[0]
        early = np.nonzero(np.abs(step) >= tol)[0]
        history = t[late[-1]] + dt_s if late.size else dt_s
        lead = -t[early[0]] if early.size else dt_s
        if max(history, lead) < 0.25 * n * dt_s or n >= (1 << 23):
            return float(max(history, dt_s)), float(max(lead, dt_s))
        n <<= 2
