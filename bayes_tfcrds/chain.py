"""Exact continuous-time response of a causal rational detection chain.

The simulator needs a truth that does not share the forward model's discretisation: a chain
written as poles and residues, ``H(s) = sum_i r_i / (s - p_i)`` with s = 2 pi i f, has a closed
form response to the ring-down input ``x(t) = 1`` (t < 0), ``exp(-t/tau)`` (t >= 0):

    y(t) = sum_i r_i [ exp(p_i t) (1/(p_i + 1/tau) - 1/p_i) - exp(-t/tau)/(p_i + 1/tau) ],  t >= 0
    y(t) = H(0),                                                                                t < 0

sampled exactly at any instant, and for an input that starts at t = 0 from nothing,
``x(t) = exp(lam t)`` (t >= 0, complex lam allowed):

    y(t) = sum_i r_i (exp(p_i t) - exp(lam t)) / (p_i - lam) + D x(t).

A direct term D (H(s) -> D at high frequency) describes an ideal chain (D = 1, no poles).
Units: poles and lam in rad/s (1/s), times in s.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .transfer_function import TFParams


@dataclass(frozen=True)
class RationalChain:
    """H(s) = sum r_i/(s - p_i), normalised to H(0) = 1 (poles/residues complex, rad/s)."""

    poles: tuple
    residues: tuple
    direct: float = 0.0

    def __post_init__(self):
        p = np.asarray(self.poles, complex)
        if np.any(p.real >= 0):
            raise ValueError("a causal, stable chain needs every pole in the left half plane")

    @property
    def dc_gain(self) -> float:
        p, r = np.asarray(self.poles, complex), np.asarray(self.residues, complex)
        return float(np.real(np.sum(-r / p))) + self.direct if p.size else self.direct

    def frequency_response(self, f_hz) -> np.ndarray:
        """H(f) at frequencies f (Hz), dimensionless."""
        s = 2j * np.pi * np.asarray(f_hz, float)[..., None]
        return np.sum(np.asarray(self.residues, complex) / (s - np.asarray(self.poles, complex)), axis=-1) \
            + self.direct

    def causal_exponential_response(self, t_s, lam) -> np.ndarray:
        """Complex response at times t (s) to exp(lam t) switched on at t = 0 (lam in 1/s).

        ``lam`` of shape (n,) and ``t_s`` of shape (k,) give (n, k); zero for t < 0.
        """
        t = np.asarray(t_s, float)[None, :, None]
        lam = np.asarray(lam, complex).reshape(-1, 1, 1)
        tp = np.clip(t, 0.0, None)
        y = self.direct * np.exp(lam[..., 0] * tp[..., 0])
        if len(self.poles):
            p = np.asarray(self.poles, complex)[None, None, :]
            r = np.asarray(self.residues, complex)[None, None, :]
            y = y + np.sum(r * (np.exp(p * tp) - np.exp(lam * tp)) / (p - lam), axis=-1)
        return np.where(t[..., 0] < 0, 0.0, y)

    def ringdown_response(self, t_s, tau_s) -> np.ndarray:
        """Exact response (dimensionless, steady level 1) at times t (s) for decay times tau (s).

        ``tau_s`` of shape (n,) and ``t_s`` of shape (k,) give (n, k).
        """
        t = np.asarray(t_s, float)[None, :, None]
        tau = np.asarray(tau_s, float).reshape(-1, 1, 1)
        p = np.asarray(self.poles, complex)[None, None, :]
        r = np.asarray(self.residues, complex)[None, None, :]
        tp = np.clip(t, 0.0, None)
        y = self.direct * np.exp(-tp[..., 0] / tau[..., 0])
        if len(self.poles):
            inv = 1.0 / (p + 1.0 / tau)
            terms = r * (np.exp(p * tp) * (inv - 1.0 / p) - np.exp(-tp / tau) * inv)
            y = y + np.real(terms.sum(-1))
        return np.where(t[..., 0] < 0, self.dc_gain, y)

    def impulse_response(self, t_s) -> np.ndarray:
        """h(t) in 1/s at times t (s), zero for t < 0 (the direct term's delta is omitted)."""
        t = np.asarray(t_s, float)[..., None]
        h = np.real(np.sum(np.asarray(self.residues) * np.exp(np.asarray(self.poles) * np.clip(t, 0, None)), -1))
        return np.where(t[..., 0] < 0, 0.0, h)

    def slowest_time_s(self) -> float:
        """Longest pole time constant (s): how long the chain remembers its input."""
        if not len(self.poles):
            return 0.0
        return float(np.max(-1.0 / np.asarray(self.poles).real))

    def with_optical_pole(self, tau_x_s: float) -> "RationalChain":
        """This chain in series with 1/(1 + s tau_x) (residues recomputed; unit DC gain kept)."""
        wx = 1.0 / tau_x_s
        p = np.asarray(self.poles, complex)
        r = np.asarray(self.residues, complex)
        lx = wx / (p + wx)
        new_p = np.append(p, -wx)
        h_at = (np.sum(r / (-wx - p)) if p.size else 0.0) + self.direct
        new_r = np.append(r * lx, wx * h_at)
        return RationalChain(poles=tuple(new_p), residues=tuple(new_r), direct=0.0)


IDEAL_CHAIN = RationalChain(poles=(), residues=(), direct=1.0)


def _second_order(w_r: float, q: float, gain: float):
    """Poles and residues of gain w_r^2/(s^2 + s w_r/q + w_r^2)."""
    disc = np.sqrt(complex(1.0 / (4 * q * q) - 1.0))
    p1 = w_r * (-1.0 / (2 * q) + disc)
    p2 = w_r * (-1.0 / (2 * q) - disc)
    if abs(p1 - p2) < 1e-9 * w_r:
        raise ValueError("critically damped resonance (gamma_r = 0.5) has a double pole; "
                         "perturb gamma_r")
    return [p1, p2], [gain * w_r**2 / (p1 - p2), gain * w_r**2 / (p2 - p1)]


def chain_from_tf(params: TFParams, extra_poles_hz=(), extra_gains=()) -> RationalChain:
    """Rational chain equal to the causal Eq. 2 with n_r = 2, plus optional first-order terms.

    ``extra_poles_hz`` (Hz) and ``extra_gains`` add ``gain/(1 + i f/f_p)`` terms (e.g. a slow
    diffusion tail of the photodiode) before the whole is normalised to unit DC gain.
    """
    if params.n_r != 2.0:
        raise ValueError("only n_r = 2 is rational; the fractional order has no finite pole set")
    wc = 2 * np.pi * params.f_c_hz
    poles, res = [-wc], [wc]
    if params.a_r != 0.0:
        p, r = _second_order(2 * np.pi * params.f_r_hz, params.gamma_r, params.a_r)
        poles += p
        res += r
    for fp, gain in zip(extra_poles_hz, extra_gains):
        wp = 2 * np.pi * fp
        poles.append(-wp)
        res.append(gain * wp)
    poles = np.asarray(poles, complex)
    res = np.asarray(res, complex)
    dc = np.real(np.sum(-res / poles))
    return RationalChain(poles=tuple(poles), residues=tuple(res / dc))
