"""Exact continuous-time response of a causal rational detection chain.

The simulator needs a truth that does not share the forward model's discretisation: a chain
written as poles and residues, ``H(s) = sum_i r_i / (s - p_i)`` with s = 2 pi i f, has a closed
form response to the ring-down input ``x(t) = 1`` (t < 0), ``exp(-t/tau)`` (t >= 0):

    y(t) = sum_i r_i [ exp(p_i t) (1/(p_i + 1/tau) - 1/p_i) - exp(-t/tau)/(p_i + 1/tau) ], t >= 0
    y(t) = H(0),                                                                               t < 0

sampled exactly at any instant, and for an input that starts at t = 0 from nothing,
``x(t) = exp(lam t)`` (t >= 0, complex lam allowed):

    y(t) = sum_i r_i (exp(p_i t) - exp(lam t)) / (p_i - lam) + D x(t).

Both are evaluated through E(t) = (exp(p t) - exp(lam t)) / (p - lam) = t exp(p t) phi1((lam - p)
t), phi1(z) = (e^z - 1)/z, whose series is used for small |z|: where tau meets a real pole
(p -> -1/tau) the two exponentials coincide, their coefficients diverge and cancel, and the
direct form would lose about eps/|1 + p tau| (more in derivatives).

A direct term D (H(s) -> D at high frequency) describes an ideal chain (D = 1, no poles).
Units: poles and lam in rad/s (1/s), times in s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bayes_tfcrds.physics.transfer_function import TFParams

PHI_SERIES = 0.5  # |z| below which phi1 and its derivative come from their series


def _phi1(z):
    """phi1(z) = (e^z - 1)/z and phi1'(z) for complex |z| < PHI_SERIES (series; ~1e-33 tail)."""
    z = np.asarray(z, complex)
    f, df = np.zeros_like(z), np.zeros_like(z)
    term = np.ones_like(z)  # z^k / (k + 1)!
    for k in range(24):
        f = f + term
        df = df + term * (k + 1) / (k + 2)  # (k + 1) z^k / (k + 2)!
        term = term * z / (k + 2)
    return f, df


def pole_term(p, lam, t, derivative: bool = False):
    """E = (e^{p t} - e^{lam t}) / (p - lam) (s) and dE/dlam (s^2), exact also as lam -> p.

    ``p``, ``lam`` complex (1/s) and ``t`` (s, >= 0) broadcast together.
    """
    p, lam, t = np.broadcast_arrays(
        np.asarray(p, complex), np.asarray(lam, complex), np.asarray(t, float)
    )
    d = p - lam
    near = np.abs(d * t) < PHI_SERIES
    ept = np.exp(p * t)
    elt = np.exp(lam * t)
    with np.errstate(divide="ignore", invalid="ignore"):
        e = (ept - elt) / d
        de = (
            (e - t * elt) / d if derivative else None
        )  # [(e^{pt} - e^{lam t}) - d t e^{lam t}] / d^2
    if np.any(near):  # where the two exponentials (nearly) coincide
        tn, en = t[near], ept[near]
        f, df = _phi1(-d[near] * tn)
        e[near] = tn * en * f
        if derivative:
            de[near] = tn * tn * en * df
    return (e, de) if derivative else e


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
        return (
            np.sum(
                np.asarray(self.residues, complex) / (s - np.asarray(self.poles, complex)), axis=-1
            )
            + self.direct
        )

    def causal_exponential_response(self, t_s, lam) -> np.ndarray:
        """Complex response at times t (s) to exp(lam t) switched on at t = 0 (lam in 1/s).

        ``lam`` of shape (n,) and ``t_s`` of shape (k,) give (n, k); zero for t < 0.
        """
        t = np.asarray(t_s, float)[None, :]
        lam = np.asarray(lam, complex).reshape(-1, 1)
        tp = np.clip(t, 0.0, None)
        y = self.direct * np.exp(lam * tp)
        for p, r in zip(self.poles, self.residues):
            y = y + r * pole_term(p, lam, tp)
        return np.where(t < 0, 0.0, y)

    def ringdown_response(self, t_s, tau_s, derivative: bool = False):
        """Exact response (dimensionless, steady level 1) at times t (s) for decay times tau (s).

        ``tau_s`` of shape (n,) and ``t_s`` of shape (k,) or (n, k) give (n, k); with
        ``derivative`` also d/dtau (1/s). Exact where tau meets a real pole (see the module notes).
        """
        t = np.asarray(t_s, float)
        t = t[None, :] if t.ndim == 1 else t
        tau = np.asarray(tau_s, float).reshape(-1, 1)
        tp = np.clip(t, 0.0, None)
        lam = -1.0 / tau
        e = np.exp(lam * tp)
        y = self.direct * e
        dy = self.direct * e * tp / tau**2 if derivative else None
        for p, r in zip(self.poles, self.residues):
            # r [ (e^{pt} - e^{-t/tau}) / (p + 1/tau) - e^{pt}/p ];  dlam/dtau = 1/tau^2
            out = pole_term(p, lam, tp, derivative=derivative)
            term = out[0] if derivative else out
            y = y + np.real(r * (term - np.exp(p * tp) / p))
            if derivative:
                dy = dy + np.real(r * out[1]) / tau**2
        y = np.where(t < 0, self.dc_gain, np.real(y))
        return (y, np.where(t < 0, 0.0, np.real(dy))) if derivative else y

    def impulse_response(self, t_s) -> np.ndarray:
        """h(t) in 1/s at times t (s), zero for t < 0 (the direct term's delta is omitted)."""
        t = np.asarray(t_s, float)[..., None]
        h = np.real(
            np.sum(
                np.asarray(self.residues) * np.exp(np.asarray(self.poles) * np.clip(t, 0, None)), -1
            )
        )
        return np.where(t[..., 0] < 0, 0.0, h)

    def slowest_time_s(self) -> float:
        """Longest pole time constant (s): how long the chain remembers its input."""
        if not len(self.poles):
            return 0.0
        return float(np.max(-1.0 / np.asarray(self.poles).real))

    def with_optical_pole(self, tau_x_s: float) -> RationalChain:
        """The chain in series with 1/(1 + s tau_x) (residues recomputed; unit DC gain kept)."""
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
        raise ValueError(
            "critically damped resonance (gamma_r = 0.5) has a double pole; perturb gamma_r"
        )
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
