"""Fit of the transfer-function model K |H(f)| to a beat-note measurement (letter Eq. 1).

Weighted least squares over several starts; the scale K is the letter's normalisation.
Frequencies in Hz, magnitudes dimensionless.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy import optimize

from bayes_tfcrds.core.linalg import central_jacobian, covariance_from_fisher
from bayes_tfcrds.physics.transfer_function import (
    PARAM_NAMES,
    SUPPORT,
    TFParams,
    transfer_function,
)

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
    # the other distinct local optima of the beat-note chi2 within MODE_DCHI2 of this one, best
    # first (the resonant term makes |H| multimodal: a sampler needs to know where the modes are)
    alternatives: tuple = field(default=(), repr=False)

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


MODE_DCHI2 = 50.0  # chi2 above the best beyond which a local optimum holds no posterior mass
MAX_MODES = 6  # distinct optima kept (best included)
MAX_POLISHED = 12  # coarse solutions polished (the starts mostly fall into a few basins)

#: smallest eigenvalue, relative to the largest, kept in an optimum's equilibrated Fisher matrix.
#: A direction below it (an sd 1e4 times that of the best-determined one) is one the beat note
#: does not determine (part of Eq. 2 beyond the band, or two paths that nearly cancel); lifting
#: it to the floor keeps the covariance positive definite. ~sqrt(eps): conditionals taken through
#: the covariance (the refinement's prior) lose ~eps/floor = 1e-8 to its condition number
#: (1e-4, up to 2e-2 at a floor of 1e-12), and the floor moves them by <= ~1e-8 itself.
FISHER_EIG_FLOOR = 1e-8


def default_starts(f_hz, h_mag, variant):
    """Starting points covering the two shapes Eq. 2 takes in practice.

    A fast first-order roll-off with a slow resonant correction, or (as in the letter's chains) a
    slow first-order tail carrying 1/(1 + A_r) of the gain beside a fast resonant main path.
    """
    reference = np.median(h_mag[: max(3, len(h_mag) // 10)])
    if not (np.isfinite(reference) and reference > 0):
        # the bundle reader refuses such files; a record built in code is refused here, since
        # the search below never ends on a NaN start
        raise ValueError(
            f"the beat note has no signal at its lowest frequencies (median |H| {reference:g}); "
            "|H| cannot be normalised"
        )
    hn = h_mag / reference
    below = np.nonzero(hn < 1 / np.sqrt(2))[0]
    f3 = f_hz[below[0]] if below.size else f_hz[-1]
    starts = []
    for fr_ratio in (0.01, 0.1):
        for a_r in (-0.1, 0.1, 0.3):
            starts.append(
                TFParams(
                    f_c_hz=f3, a_r=a_r, f_r_hz=fr_ratio * f3, gamma_r=0.7, n_r=2.0, variant=variant
                )
            )
    # a weaker resonance above, near or below a fast main pole, underdamped or overdamped
    for fr_ratio in (0.3, 3.0):
        for a_r in (0.1, 0.5):
            for gamma_r in (0.3, 1.0):
                starts.append(
                    TFParams(
                        f_c_hz=f3,
                        a_r=a_r,
                        f_r_hz=fr_ratio * f3,
                        gamma_r=gamma_r,
                        n_r=2.0,
                        variant=variant,
                    )
                )
    for fc_ratio in (1e-3, 1e-2, 1e-1):
        for a_r in (3.0, 10.0, 30.0):
            starts.append(
                TFParams(
                    f_c_hz=fc_ratio * f3, a_r=a_r, f_r_hz=f3, gamma_r=0.7, n_r=2.0, variant=variant
                )
            )
    return starts


def fit_beat_note(
    tf_data,
    variant: str = "causal",
    free=PARAM_NAMES,
    start: TFParams | None = None,
    fixed: TFParams | None = None,
) -> TFFit:
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
            raise ValueError(
                f"unknown transfer-function parameter {name!r}; choose from {PARAM_NAMES}"
            )
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

    starts = [start] if start is not None else default_starts(f, y, variant)
    if fixed is not None:
        starts = [
            replace(fixed, **{n: getattr(s, n) for n in free}, variant=variant) for s in starts
        ]
    # the physical domain (SUPPORT), in the search space
    lo = np.array([np.log(SUPPORT[n][0]) if lp else SUPPORT[n][0] for n, lp in zip(free, logp)])
    hi = np.array([np.log(SUPPORT[n][1]) if lp else SUPPORT[n][1] for n, lp in zip(free, logp)])
    lo, hi = np.append(lo, 0.0), np.append(hi, np.inf)

    def solve(x0, base, tol, nfev):
        try:
            return optimize.least_squares(
                resid,
                x0,
                args=(base,),
                bounds=(lo, hi),
                x_scale="jac",
                xtol=tol,
                ftol=tol,
                gtol=tol,
                max_nfev=nfev,
            )
        except ValueError:
            return None

    # coarse pass from every start, then polish the best and every other basin near it
    coarse = []
    for s in starts:
        x0 = np.append(
            np.where(logp, np.log(np.maximum(s.as_vector(free), 1e-300)), s.as_vector(free)),
            np.median(y[: max(3, len(y) // 10)]),
        )
        x0 = np.clip(x0, lo + 1e-9, hi - 1e-9)
        sol = solve(x0, s, 1e-6, 300) if len(starts) > 1 else solve(x0, s, 1e-14, 4000)
        if sol is not None:
            coarse.append((sol.cost, sol, s))
    coarse.sort(key=lambda c: c[0])
    if not coarse:
        raise RuntimeError("the beat-note fit failed from every starting point")
    polished = []
    for i, (cost, sol0, s) in enumerate(coarse):
        if i >= MAX_POLISHED or (i >= 3 and 2.0 * (cost - coarse[0][0]) > 2.0 * MODE_DCHI2):
            break
        sol = solve(sol0.x, s, 1e-14, 4000) if len(starts) > 1 else sol0
        if sol is not None:
            polished.append((sol, s))
    if not polished:
        raise RuntimeError("the beat-note fit failed from every starting point")
    polished.sort(key=lambda c: c[0].cost)
    fits = []
    for sol, base in polished:
        if 2.0 * (sol.cost - polished[0][0].cost) > MODE_DCHI2 or len(fits) >= MAX_MODES:
            break
        params, scale = unpack(sol.x, base)
        fit = _fit_at(params, scale, free, f, y, u, sig, weighted)
        if not any(same_mode(fit, g) for g in fits):
            fits.append(fit)
    return replace(fits[0], alternatives=tuple(fits[1:]))


def same_mode(a: TFFit, b: TFFit) -> bool:
    """Whether two optima are one basin: within 3 sd of each other in every parameter."""
    da = np.append(a.params.as_vector(a.free), a.scale)
    db = np.append(b.params.as_vector(b.free), b.scale)
    sd = np.sqrt(np.maximum(np.diag(a.cov), np.diag(b.cov)))
    return bool(np.all(np.abs(da - db) <= 3.0 * sd))


def _fit_at(params, scale, free, f, y, u, sig, weighted) -> TFFit:
    """The fit result at an optimum: chi2, residuals and the Gauss-Newton covariance."""
    # covariance in natural units: Jacobian by central differences in natural parameters
    theta = np.append(params.as_vector(free), scale)

    def model(th):
        return th[-1] * np.abs(transfer_function(f, params.with_vector(th[:-1], free)))

    steps = 1e-6 * np.maximum(np.abs(theta), 1e-3)
    jac = central_jacobian(model, theta, steps) / sig[:, None]
    r = (model(theta) - y) / sig
    chi2 = float(r @ r)
    dof = len(f) - len(theta)
    cov = covariance_from_fisher(jac.T @ jac, eig_floor=FISHER_EIG_FLOOR)
    if not weighted:
        cov = cov * chi2 / max(dof, 1)
    return TFFit(
        params=params,
        free=free,
        scale=float(scale),
        cov=cov,
        chi2=chi2,
        dof=dof,
        f_hz=f,
        h_mag=y,
        h_mag_u=np.asarray(u, float) if weighted else np.full_like(y, np.nan),
        residuals=r,
        weighted=weighted,
    )
