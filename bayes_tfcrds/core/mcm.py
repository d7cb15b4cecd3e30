"""Propagation of distributions by the adaptive Monte Carlo method of JCGM 101:2008 (GUM-S1).

The measurement model Y = f(X_1, ..., X_N) is a vectorised function: it is called with one array of
M draws per input (a jointly distributed block of n inputs gives n arrays) and returns M values of
Y. The inputs are described by their probability distributions (JCGM 101 clause 6):

* :class:`Normal` (6.4.7), :class:`Rectangular` (6.4.2), :class:`StudentT` (the scaled and shifted
  t of a Type A evaluation with nu degrees of freedom, 6.4.9), :class:`MultivariateNormal`
  (jointly normal inputs with a covariance matrix, 6.4.8);
* :class:`Empirical`: draws the caller already holds (posterior draws of an MCMC or of a Laplace
  posterior, or the Monte Carlo output of an upstream model), resampled with replacement, so that
  their joint distribution, tails and correlations between columns are propagated as sampled.

:func:`monte_carlo` makes a fixed number of trials (clause 7.2-7.7); :func:`adaptive_monte_carlo`
repeats batches of M = max(J, 10^4) trials, J = ceil(100/(1 - p)) (7.2.2, 7.9.4 b), until twice the
standard deviation of the batch means of y, u(y) and both endpoints of the coverage interval is
below the numerical tolerance delta of u(y) (7.9.2, 7.9.4 i). Both return a frozen
:class:`MonteCarloResult`: y, u(y), the probabilistically symmetric coverage interval (and the
shortest one on request), k = half-width/u, the number of trials, delta and whether the results
stabilised. Randomness only through the numpy Generator passed in. Units are the caller's: y, u and
the interval are in the unit the model returns.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

__all__ = [
    "Normal",
    "Rectangular",
    "StudentT",
    "MultivariateNormal",
    "Empirical",
    "MonteCarloResult",
    "batch_size",
    "numerical_tolerance",
    "coverage_interval",
    "shortest_interval",
    "monte_carlo",
    "adaptive_monte_carlo",
]


# --- input distributions (JCGM 101 clause 6) --------------------------------------------------
@dataclass(frozen=True)
class Normal:
    """N(mean, u^2): an input known by its estimate and standard uncertainty (6.4.7)."""

    mean: float
    u: float

    def __post_init__(self):
        if not (math.isfinite(self.mean) and math.isfinite(self.u) and self.u >= 0):
            raise ValueError(f"Normal needs a finite mean and u >= 0, got {self.mean}, {self.u}")

    def sample(self, rng: np.random.Generator, m: int) -> np.ndarray:
        """M draws, shape (M,)."""
        return self.mean + self.u * rng.standard_normal(m)


@dataclass(frozen=True)
class Rectangular:
    """R(a, b): the input lies in [a, b] with no value preferred (6.4.2); u = (b - a)/sqrt(12)."""

    a: float
    b: float

    def __post_init__(self):
        if not (math.isfinite(self.a) and math.isfinite(self.b) and self.b >= self.a):
            raise ValueError(f"Rectangular needs finite limits a <= b, got {self.a}, {self.b}")

    @classmethod
    def from_u(cls, mean: float, u: float) -> Rectangular:
        """The rectangular distribution of expectation ``mean`` and standard deviation ``u``."""
        half = math.sqrt(3.0) * float(u)
        return cls(float(mean) - half, float(mean) + half)

    def sample(self, rng: np.random.Generator, m: int) -> np.ndarray:
        """M draws, shape (M,)."""
        return rng.uniform(self.a, self.b, m)


@dataclass(frozen=True)
class StudentT:
    """t_nu(mean, scale^2): scaled and shifted t of a Type A evaluation (6.4.9).

    From n indications with mean x and sd s: mean = x, scale = s/sqrt(n), dof = n - 1. Its
    standard deviation is scale sqrt(nu/(nu - 2)) (defined for nu > 2).
    """

    mean: float
    scale: float
    dof: float

    def __post_init__(self):
        if not (self.scale >= 0 and self.dof > 0):
            raise ValueError(f"StudentT needs scale >= 0 and dof > 0, got {self.scale}, {self.dof}")

    def sample(self, rng: np.random.Generator, m: int) -> np.ndarray:
        """M draws, shape (M,)."""
        return self.mean + self.scale * rng.standard_t(self.dof, m)


@dataclass(frozen=True)
class MultivariateNormal:
    """N(mean, cov): n jointly normal inputs (6.4.8); gives n arguments of the model, in order."""

    mean: tuple
    cov: tuple

    def __post_init__(self):
        mu = np.atleast_1d(np.asarray(self.mean, float))
        c = np.atleast_2d(np.asarray(self.cov, float))
        if mu.ndim != 1 or c.shape != (mu.size, mu.size) or not np.allclose(c, c.T):
            raise ValueError(f"MultivariateNormal needs a symmetric {mu.size}x{mu.size} cov")
        if np.linalg.eigvalsh(c).min() < -1e-12 * max(np.abs(c).max(), 1e-300):
            raise ValueError("MultivariateNormal: cov is not positive semi-definite")
        object.__setattr__(self, "mean", tuple(mu.tolist()))
        object.__setattr__(self, "cov", tuple(map(tuple, c.tolist())))

    def sample(self, rng: np.random.Generator, m: int) -> np.ndarray:
        """M draws, shape (M, n)."""
        return rng.multivariate_normal(np.array(self.mean), np.array(self.cov), m, method="eigh")


@dataclass(frozen=True, eq=False)
class Empirical:
    """Draws the caller holds (e.g. posterior draws), resampled with replacement.

    ``draws``: shape (N,) for one input or (N, n) for n inputs drawn jointly (rows kept together,
    so their correlations propagate). The Monte Carlo then cannot be more accurate than the N
    draws themselves: their own sd has a relative standard error of about 1/sqrt(2N).
    """

    draws: np.ndarray

    def __post_init__(self):
        d = np.asarray(self.draws, float)
        if d.ndim not in (1, 2) or d.shape[0] < 2 or not np.all(np.isfinite(d)):
            raise ValueError("Empirical needs >= 2 finite draws, shape (N,) or (N, n)")
        d = d.copy()
        d.flags.writeable = False
        object.__setattr__(self, "draws", d)

    def sample(self, rng: np.random.Generator, m: int) -> np.ndarray:
        """M draws (rows picked uniformly with replacement), shape (M,) or (M, n)."""
        return self.draws[rng.integers(0, self.draws.shape[0], m)]


# --- summaries (clauses 7.5-7.9) ----------------------------------------------------------------
@dataclass(frozen=True)
class MonteCarloResult:
    """Summary of the Monte Carlo distribution of Y (JCGM 101 7.6, 7.7), in the model's unit.

    value: y, the mean of the model values; u: u(y), their sd; interval: (low, high), the
    probabilistically symmetric coverage interval for probability ``p``; shortest: the shortest
    coverage interval, or None when not asked for; k = (high - low)/(2 u), the coverage factor the
    symmetric interval implies (1.96 for a normal Y at p = 0.95); trials: number of model
    evaluations; tolerance: the numerical tolerance delta of u(y) (7.9.2) for ``n_digits``
    significant digits; stabilised: whether 2 s of y, u and both endpoints fell below delta
    (always False for a fixed-M run, which does not check).
    """

    value: float
    u: float
    interval: tuple
    p: float
    k: float
    trials: int
    tolerance: float
    n_digits: int
    stabilised: bool
    shortest: tuple | None = None

    @property
    def expanded(self) -> float:
        """Half-width of the symmetric coverage interval (expanded uncertainty U_p), model unit."""
        return 0.5 * (self.interval[1] - self.interval[0])

    def to_dict(self) -> dict:
        """JSON-ready dict (floats and ints only)."""
        return {
            "value": self.value,
            "u": self.u,
            "interval": [float(self.interval[0]), float(self.interval[1])],
            "interval_shortest": None if self.shortest is None else list(map(float, self.shortest)),
            "coverage_probability": self.p,
            "k": self.k,
            "expanded": self.expanded,
            "trials": self.trials,
            "tolerance": self.tolerance,
            "n_digits": self.n_digits,
            "stabilised": self.stabilised,
        }


def batch_size(p: float = 0.95) -> int:
    """M = max(J, 10^4) trials per batch, J = ceil(100/(1 - p)) (JCGM 101 7.2.2, 7.9.4 b)."""
    j = math.ceil(100.0 / (1.0 - p) - 1e-9)
    return max(j, 10_000)


def numerical_tolerance(u: float, n_digits: int = 2) -> float:
    """delta = 10^l / 2 when u is written c x 10^l with c an n_digits-digit integer (7.9.2).

    E.g. u = 0.0754 with 2 digits: c = 75, l = -3, delta = 0.0005; u = 2.00 gives 0.05.
    """
    u = abs(float(u))
    if u == 0.0 or not math.isfinite(u):
        return 0.0
    ell = math.floor(math.log10(u)) - (int(n_digits) - 1)
    if round(u / 10.0**ell) >= 10 ** int(n_digits):  # e.g. 9.96 with 2 digits is 10 x 10^0
        ell += 1
    return 0.5 * 10.0**ell


def _order_indices(m: int, p: float) -> tuple[int, int]:
    """0-based indices (low, high) of the symmetric interval's endpoints among M sorted values.

    q = pM if integer, else floor(pM + 1/2); r = (M - q)/2 if integer, else (M - q + 1)/2; the
    interval is [y_(r), y_(r+q)] in 1-based order statistics (7.7.2).
    """
    q = int(round(p * m)) if abs(p * m - round(p * m)) < 1e-9 else math.floor(p * m + 0.5)
    r = (m - q) // 2 if (m - q) % 2 == 0 else (m - q + 1) // 2
    r = max(r, 1)
    return r - 1, min(r + q, m) - 1


def coverage_interval(values: np.ndarray, p: float = 0.95) -> tuple[float, float]:
    """Probabilistically symmetric coverage interval of the model values (7.7.2)."""
    v = np.asarray(values, float).ravel()
    lo, hi = _order_indices(v.size, p)
    part = np.partition(v, (lo, hi))
    return float(part[lo]), float(part[hi])


def shortest_interval(values: np.ndarray, p: float = 0.95) -> tuple[float, float]:
    """Shortest coverage interval: the narrowest [y_(r), y_(r+q)] over r (7.7.3)."""
    v = np.sort(np.asarray(values, float).ravel())
    q = int(round(p * v.size))
    width = v[q:] - v[: v.size - q]
    r = int(np.argmin(width))
    return float(v[r]), float(v[r + q])


def _evaluate(model: Callable, inputs: Sequence, rng: np.random.Generator, m: int) -> np.ndarray:
    """M model values: one set of draws per input (a joint block gives its columns in order)."""
    args = []
    for dist in inputs:
        x = dist.sample(rng, m)
        args.extend([x] if x.ndim == 1 else list(x.T))
    y = np.asarray(model(*args), float)
    if y.shape != (m,):
        raise ValueError(f"the model must return one value per trial, shape ({m},); got {y.shape}")
    if not np.all(np.isfinite(y)):
        raise ValueError("the model returned non-finite values for some input draws")
    return y


def _summarise(y, p, trials, n_digits, stabilised, shortest) -> MonteCarloResult:
    u = float(np.std(y, ddof=1))
    lo, hi = coverage_interval(y, p)
    return MonteCarloResult(
        value=float(np.mean(y)),
        u=u,
        interval=(lo, hi),
        p=float(p),
        k=(hi - lo) / (2.0 * u) if u > 0 else math.nan,
        trials=int(trials),
        tolerance=numerical_tolerance(u, n_digits),
        n_digits=int(n_digits),
        stabilised=bool(stabilised),
        shortest=shortest_interval(y, p) if shortest else None,
    )


def _check(inputs, p):
    if not 0.0 < p < 1.0:
        raise ValueError(f"coverage probability must be in (0, 1), got {p}")
    if not inputs:
        raise ValueError("the model needs at least one input distribution")


def monte_carlo(
    model: Callable,
    inputs: Sequence,
    rng: np.random.Generator,
    trials: int = 1_000_000,
    p: float = 0.95,
    n_digits: int = 2,
    shortest: bool = False,
) -> MonteCarloResult:
    """Fixed-M Monte Carlo (JCGM 101 7.2-7.7): ``trials`` model evaluations, summarised.

    Evaluated in batches of at most 10^6 trials to bound memory; ``stabilised`` is False (no
    stability test is made; use :func:`adaptive_monte_carlo` for that).
    """
    _check(inputs, p)
    if int(trials) < batch_size(p) // 100:
        raise ValueError(f"need at least {batch_size(p) // 100} trials for p = {p}")
    chunks, left = [], int(trials)
    while left > 0:
        m = min(left, 1_000_000)
        chunks.append(_evaluate(model, inputs, rng, m))
        left -= m
    return _summarise(np.concatenate(chunks), p, trials, n_digits, False, shortest)


def adaptive_monte_carlo(
    model: Callable,
    inputs: Sequence,
    rng: np.random.Generator,
    p: float = 0.95,
    n_digits: int = 2,
    batch: int | None = None,
    max_trials: int = 2_000_000,
    shortest: bool = False,
) -> MonteCarloResult:
    """Adaptive Monte Carlo of JCGM 101 7.9.4 for the model value Y = model(*draws).

    Batches of ``batch`` trials (default M = max(J, 10^4), 7.9.4 b) are added until, after at
    least two batches, twice the standard deviation of the h batch means of y, u(y) and both
    endpoints of the symmetric interval is below delta, the numerical tolerance of u(y) computed
    from all h M values with ``n_digits`` significant digits (7.9.2, 7.9.4 f-i). The summary is
    then computed from all h M values (7.9.4 j). Stops at ``max_trials`` with
    ``stabilised=False`` rather than run on (the result says so; callers report it).
    """
    _check(inputs, p)
    m = batch_size(p) if batch is None else int(batch)
    if m < 100 or m * (1.0 - p) < 2:
        raise ValueError(f"batch of {m} trials is too small for p = {p}")
    values, stats = [], []
    stable = False
    pooled = _PooledMoments()
    while True:
        y = _evaluate(model, inputs, rng, m)
        values.append(y)
        pooled.add(y)
        stats.append((y.mean(), y.std(ddof=1), *coverage_interval(y, p)))
        h = len(stats)
        if h >= 2:
            s = np.std(np.array(stats), axis=0, ddof=1) / math.sqrt(h)  # sd of the means
            u_all = pooled.sd
            stable = bool(np.all(2.0 * s < numerical_tolerance(u_all, n_digits)))
            if stable or (h + 1) * m > max_trials:
                break
    allv = np.concatenate(values)
    return _summarise(allv, p, allv.size, n_digits, stable, shortest)


class _PooledMoments:
    """Running sd (ddof = 1) of all values seen, about the first batch's mean (no cancellation)."""

    def __init__(self):
        self.n, self.shift, self.s1, self.s2 = 0, None, 0.0, 0.0

    def add(self, y: np.ndarray) -> None:
        if self.shift is None:
            self.shift = float(y.mean())
        d = y - self.shift
        self.n += y.size
        self.s1 += float(d.sum())
        self.s2 += float(d @ d)

    @property
    def sd(self) -> float:
        return math.sqrt(max(self.s2 - self.s1 * self.s1 / self.n, 0.0) / (self.n - 1))
