"""Detection-chain transfer function H(f) (letter Eqs. 1-2) and its fit to beat-note data.

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

from dataclasses import dataclass, field, replace
from functools import lru_cache

import numpy as np
from scipy import fft as sfft
from scipy import optimize

from .linalg import central_jacobian, covariance_from_fisher

PARAM_NAMES = ("f_c_hz", "a_r", "f_r_hz", "gamma_r", "n_r")
VARIANTS = ("letter", "causal")


@dataclass(frozen=True)
class TFParams:
    """Parameters of Eq. 2: cutoff f_c (Hz), resonance amplitude A_r, frequency f_r (Hz),
    quality factor Gamma_r and effective order n_r (dimensionless)."""

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

    def with_vector(self, values, names=PARAM_NAMES) -> "TFParams":
        return replace(self, **{n: float(v) for n, v in zip(names, values)})


def transfer_function(f_hz, params: TFParams, normalise: bool = True) -> np.ndarray:
    """Complex H(f) at frequencies ``f_hz`` (Hz, any sign), dimensionless.

    With ``normalise`` the result is divided by H(0) = 1 + A_r (unit DC gain).
    Negative frequencies return conj(H(|f|)) so that the impulse response is real.
    """
    return transfer_function_array(f_hz, params.f_c_hz, params.a_r, params.f_r_hz, params.gamma_r, params.n_r,
                                   params.variant, normalise)


def transfer_function_array(f_hz, f_c_hz, a_r, f_r_hz, gamma_r, n_r, variant="causal", normalise=True):
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
    return np.where(f < 0, np.conj(h), h)


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


# --------------------------------------------------------------------------- beat-note fit


@dataclass(frozen=True)
class TFFit:
    """Result of a weighted least-squares fit of K |H(f)| to a beat-note measurement.

    ``cov`` is the covariance of ``free`` (in that order, natural units) followed by
    ``scale`` (K, dimensionless). When the beat note carries no uncertainties the covariance
    is scaled by chi2/dof (the residual scatter stands in for the unknown noise).
    """

    params: TFParams
    free: tuple
    scale: float
    cov: np.ndarray
    chi2: float
    dof: int
    f_hz: np.ndarray
    h_mag: np.ndarray
    h_mag_u: np.ndarray
    residuals: np.ndarray = field(repr=False)
    weighted: bool = True

    @property
    def names(self):
        return tuple(self.free) + ("scale",)

    @property
    def stderr(self) -> dict:
        return dict(zip(self.names, np.sqrt(np.diag(self.cov))))

    @property
    def param_cov(self) -> np.ndarray:
        """Covariance of the free H parameters alone (the scale marginalised)."""
        k = len(self.free)
        return self.cov[:k, :k]

    @property
    def chi2_red(self) -> float:
        return self.chi2 / max(self.dof, 1)


def _default_starts(f_hz, h_mag, variant):
    """Starting points covering the two shapes Eq. 2 takes in practice: a fast first-order
    roll-off with a slow resonant correction, or (as in the letter's chains) a slow
    first-order tail carrying 1/(1 + A_r) of the gain beside a fast resonant main path."""
    hn = h_mag / np.median(h_mag[: max(3, len(h_mag) // 10)])
    below = np.nonzero(hn < 1 / np.sqrt(2))[0]
    f3 = f_hz[below[0]] if below.size else f_hz[-1]
    starts = []
    for fr_ratio in (0.01, 0.1):
        for a_r in (-0.1, 0.1, 0.3):
            starts.append(TFParams(f_c_hz=f3, a_r=a_r, f_r_hz=fr_ratio * f3, gamma_r=0.7, n_r=2.0,
                                   variant=variant))
    for fc_ratio in (1e-3, 1e-2, 1e-1):
        for a_r in (3.0, 10.0, 30.0):
            starts.append(TFParams(f_c_hz=fc_ratio * f3, a_r=a_r, f_r_hz=f3, gamma_r=0.7, n_r=2.0,
                                   variant=variant))
    return starts


def fit_beat_note(tf_data, variant: str = "causal", free=PARAM_NAMES, start: TFParams | None = None,
                  fixed: TFParams | None = None) -> TFFit:
    """Fit K |H(f_B; theta)| to a measured |H(f_B)| by weighted least squares.

    ``tf_data`` needs ``f_hz`` (Hz), ``h_mag`` and ``h_mag_u`` (dimensionless, u may be None).
    ``free`` names the H parameters to fit (others held at ``fixed``/``start`` values). Without
    ``start`` a small grid of starting points is tried and the best fit kept, since the
    resonant term makes the least-squares surface multimodal.
    """
    f = np.asarray(tf_data.f_hz, float)
    y = np.asarray(tf_data.h_mag, float)
    u = tf_data.h_mag_u
    weighted = u is not None
    sig = np.asarray(u, float) if weighted else np.ones_like(y)
    free = tuple(free)
    for name in free:
        if name not in PARAM_NAMES:
            raise ValueError(f"unknown transfer-function parameter {name!r}; choose from {PARAM_NAMES}")
    if len(f) < len(free) + 2:
        raise ValueError(f"{len(f)} beat frequencies cannot constrain {len(free) + 1} parameters")
    # positive parameters are searched in log space; a_r linearly
    logp = np.array([n != "a_r" for n in free])

    def unpack(x, base):
        with np.errstate(over="ignore"):
            v = np.where(logp, np.exp(x[:-1]), x[:-1])
        return base.with_vector(v, free), x[-1]

    def resid(x, base):
        try:
            p, k = unpack(x, base)
        except ValueError:
            return np.full_like(y, 1e6)
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            r = (k * np.abs(transfer_function(f, p)) - y) / sig
        return np.where(np.isfinite(r), r, 1e6)

    starts = [start] if start is not None else _default_starts(f, y, variant)
    if fixed is not None:
        starts = [replace(fixed, **{n: getattr(s, n) for n in free}, variant=variant) for s in starts]
    lo = np.where(logp, -np.inf, -0.99)
    lo = np.append(lo, 0.0)
    hi = np.append(np.full(len(free), np.inf), np.inf)

    def solve(x0, base, tol, nfev):
        try:
            return optimize.least_squares(resid, x0, args=(base,), bounds=(lo, hi), x_scale="jac",
                                          xtol=tol, ftol=tol, gtol=tol, max_nfev=nfev)
        except ValueError:
            return None

    # coarse pass from every start, then polish the three best
    coarse = []
    for s in starts:
        x0 = np.append(np.where(logp, np.log(np.maximum(s.as_vector(free), 1e-300)), s.as_vector(free)),
                       np.median(y[: max(3, len(y) // 10)]))
        x0 = np.clip(x0, lo + 1e-9, hi)
        sol = solve(x0, s, 1e-6, 300) if len(starts) > 1 else solve(x0, s, 1e-14, 4000)
        if sol is not None:
            coarse.append((sol.cost, sol, s))
    coarse.sort(key=lambda c: c[0])
    best = None
    for _, sol0, s in coarse[:3]:
        sol = solve(sol0.x, s, 1e-14, 4000) if len(starts) > 1 else sol0
        if sol is not None and (best is None or sol.cost < best[0].cost):
            best = (sol, s)
    if best is None:
        raise RuntimeError("the beat-note fit failed from every starting point")
    sol, base = best
    params, scale = unpack(sol.x, base)
    # covariance in natural units: Jacobian by central differences in natural parameters
    theta = np.append(params.as_vector(free), scale)

    def model(th):
        return th[-1] * np.abs(transfer_function(f, params.with_vector(th[:-1], free)))

    steps = 1e-6 * np.maximum(np.abs(theta), 1e-3)
    jac = central_jacobian(model, theta, steps) / sig[:, None]
    r = (model(theta) - y) / sig
    chi2 = float(r @ r)
    dof = len(f) - len(theta)
    cov = covariance_from_fisher(jac.T @ jac)
    if not weighted:
        cov = cov * chi2 / max(dof, 1)
    return TFFit(params=params, free=free, scale=float(scale), cov=cov, chi2=chi2, dof=dof, f_hz=f,
                 h_mag=y, h_mag_u=np.asarray(u, float) if weighted else np.full_like(y, np.nan),
                 residuals=r, weighted=weighted)
