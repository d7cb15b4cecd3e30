"""Log-posteriors for the samplers: H(f) from the beat note, and line parameters from spectra.

Both are vectorised over emcee's walkers (``log_prob(thetas)`` with thetas of shape
(n_walkers, ndim)). Each declares its priors as :class:`Prior` objects (``priors``), the one
source of truth for its support, its sampled coordinates and what every output says about it:
scale parameters of H (frequencies, the quality factor) are log-uniform (scale-invariant) on
wide physical ranges and sampled as logarithms; everything else is uniform, sampled as it is.
The priors also encode physics: 0 <= Gamma2 <= (2/3) Gamma0 keeps the qSDHCP absorption
non-negative, nu_VC >= 0, A > 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from fractions import Fraction
from functools import cached_property

import numpy as np

from bayes_tfcrds.physics.transfer_function import (
    PARAM_NAMES,
    SUPPORT,
    TFParams,
    transfer_function_array,
)

PRIOR_FAMILIES = ("uniform", "log-uniform")


@dataclass(frozen=True)
class Prior:
    """The prior of one sampled parameter, in the parameter's natural unit.

    ``family`` "uniform" is flat in the parameter between ``lower`` and ``upper`` (improper when
    a bound is infinite); "log-uniform" is flat in its logarithm (scale-invariant; needs
    0 < lower < upper < inf). The sampler moves in the coordinate in which the prior is flat (the
    logarithm for log-uniform), so inside the support the log-posterior there is the
    log-likelihood. ``cap`` = (other parameter, factor) adds the joint bound
    parameter < factor * other when the other parameter is sampled too.
    """

    parameter: str
    family: str
    lower: float
    upper: float
    unit: str
    cap: tuple = ()
    note: str = ""

    def __post_init__(self):
        if self.family not in PRIOR_FAMILIES:
            raise ValueError(
                f"prior of {self.parameter}: family {self.family!r} not in {PRIOR_FAMILIES}"
            )
        if not self.lower < self.upper:
            raise ValueError(f"prior of {self.parameter}: need lower < upper")
        if self.family == "log-uniform" and not (0 < self.lower and math.isfinite(self.upper)):
            raise ValueError(
                f"prior of {self.parameter}: log-uniform needs 0 < lower, finite upper"
            )

    @property
    def is_log(self) -> bool:
        return self.family == "log-uniform"

    @property
    def sample_name(self) -> str:
        """The sampler's coordinate: ``log_<parameter>`` for a log-uniform prior."""
        return "log_" + self.parameter if self.is_log else self.parameter

    @property
    def sample_width(self) -> float:
        """Width of the support in the sampled coordinate (inf when unbounded)."""
        if self.is_log:
            return math.log(self.upper) - math.log(self.lower)
        return self.upper - self.lower

    def to_sample(self, value):
        return np.log(value) if self.is_log else value

    def from_sample(self, x):
        if not self.is_log:
            return x
        with np.errstate(over="ignore"):  # far proposals overflow to inf, which the prior refuses
            return np.exp(x)

    @property
    def condition(self) -> str:
        """The joint bound in words ('' without a cap)."""
        if not self.cap:
            return ""
        factor = Fraction(self.cap[1]).limit_denominator(1000)
        return f"{self.parameter} < ({factor}) {self.cap[0]}"

    def to_dict(self, units=None) -> dict:
        """JSON form; an unbounded side is None.

        ``units`` ({SI unit: (shown unit, factor)}, e.g. core.constants.EDGE_UNITS) shows the
        bounds in the unit the outputs use for the parameter; ``unit_si`` then names the
        sampler's.
        """
        shown, f = (units or {}).get(self.unit, (self.unit, 1.0))
        out = {
            "parameter": self.parameter,
            "family": self.family,
            "lower": f * self.lower if math.isfinite(self.lower) else None,
            "upper": f * self.upper if math.isfinite(self.upper) else None,
            "unit": shown,
            "condition": self.condition,
            "sampled_as": self.sample_name,
            "note": self.note,
        }
        if shown != self.unit:
            out["unit_si"] = self.unit
        return out


def outside_priors(priors, values: dict) -> np.ndarray:
    """True where a sample (natural-unit ``values[parameter]`` arrays) lies outside ``priors``.

    Outside: not finite, at or beyond a bound, or at or beyond a cap whose other parameter is in
    ``values``.
    """
    bad = np.zeros(np.shape(values[priors[0].parameter]), bool)
    for p in priors:
        v = values[p.parameter]
        bad |= ~np.isfinite(v) | (v <= p.lower) | (v >= p.upper)
        if p.cap and p.cap[0] in values:
            bad |= v >= p.cap[1] * values[p.cap[0]]
    return bad


def sample_names(priors) -> tuple:
    return tuple(p.sample_name for p in priors)


def to_natural(priors, x) -> dict:
    """Natural-unit parameter arrays from samples x (..., ndim) in the priors' coordinates."""
    x = np.asarray(x, float)
    return {p.parameter: p.from_sample(x[..., i]) for i, p in enumerate(priors)}


# the priors of H: log-uniform frequencies and quality factor over the physical domain of Eq. 2
# (SUPPORT), a causal fractional order n_r <= 2, and the beat note's scale K
H_PRIORS = {
    "f_c_hz": Prior("f_c_hz", "log-uniform", *SUPPORT["f_c_hz"], "Hz"),
    "a_r": Prior("a_r", "uniform", *SUPPORT["a_r"], "1"),
    "f_r_hz": Prior("f_r_hz", "log-uniform", *SUPPORT["f_r_hz"], "Hz"),
    "gamma_r": Prior("gamma_r", "log-uniform", *SUPPORT["gamma_r"], "1"),
    "n_r": Prior("n_r", "uniform", 0.5, 2.0, "1"),
    "scale": Prior("scale", "uniform", 0.0, 10.0, "1", note="beat-note amplitude scale K"),
}
H_PRIOR = {n: (p.lower, p.upper) for n, p in H_PRIORS.items()}  # the bounds alone


def h_prior(name: str, a_r_sign: int = 0) -> Prior:
    """The prior of H parameter ``name``; A_r restricted to the branch of sign ``a_r_sign``."""
    p = H_PRIORS[name]
    if name != "a_r" or not a_r_sign:
        return p
    lo, hi = (max(p.lower, 0.0), p.upper) if a_r_sign > 0 else (p.lower, min(p.upper, 0.0))
    return Prior(
        p.parameter, p.family, lo, hi, p.unit, note="the branch of A_r the ring-downs chose"
    )


@dataclass(frozen=True)
class BeatNotePosterior:
    """log p(theta | beat note) for the H parameters ``free`` plus the scale K.

    Priors: :data:`H_PRIORS` (``priors``), sampled in their flat coordinates (``sample_names``:
    log of f_c, f_r, gamma_r). Likelihood: Gaussian in the measured |H(f_B)| with its stated
    uncertainty. |H| nearly repeats under A_r -> -A_r/(1 + 2 A_r), which maps A_r > 0 onto
    -1 < A_r < 0: ``a_r_sign`` restricts the prior to the branch the ring-downs chose, so a sampler
    cannot wander into the mirror mode that the ring-down data exclude.
    """

    f_hz: np.ndarray
    h_mag: np.ndarray
    h_mag_u: np.ndarray
    free: tuple
    fixed: TFParams
    a_r_sign: int = 0  # +1 or -1: the branch of A_r the ring-downs chose (0: both)

    @property
    def priors(self) -> tuple:
        return tuple(h_prior(n, self.a_r_sign) for n in (*self.free, "scale"))

    @property
    def sample_names(self) -> tuple:
        return sample_names(self.priors)

    def to_sample(self, params: TFParams, scale: float) -> np.ndarray:
        v = [getattr(params, n) for n in self.free] + [scale]
        return np.array([p.to_sample(x) for p, x in zip(self.priors, v)], float)

    def to_params(self, x) -> dict:
        """Natural-unit parameter arrays from samples x (..., ndim)."""
        return to_natural(self.priors, x)

    def __call__(self, x):
        x = np.atleast_2d(x)
        p = self.to_params(x)
        lp = np.where(outside_priors(self.priors, p), -np.inf, 0.0)
        ok = np.isfinite(lp)
        if not ok.any():
            return lp
        full = {n: np.full(ok.sum(), getattr(self.fixed, n)) for n in PARAM_NAMES}
        for n in self.free:
            full[n] = p[n][ok]
        col = {n: v[:, None] for n, v in full.items()}
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            h = np.abs(
                transfer_function_array(
                    self.f_hz[None, :],
                    col["f_c_hz"],
                    col["a_r"],
                    col["f_r_hz"],
                    col["gamma_r"],
                    col["n_r"],
                    self.fixed.variant,
                )
            )
            r = (p["scale"][ok, None] * h - self.h_mag[None, :]) / self.h_mag_u[None, :]
            chi2 = np.sum(r * r, axis=1)
        lp[ok] = np.where(np.isfinite(chi2), -0.5 * chi2, -np.inf)
        return lp


# the priors of the line parameters: flat (improper) within their physical bounds
LINE_PRIORS = {
    "line_area": Prior("line_area", "uniform", 0.0, math.inf, "Hz/m"),
    "position_offset_hz": Prior("position_offset_hz", "uniform", -math.inf, math.inf, "Hz"),
    "gamma0_hz": Prior("gamma0_hz", "uniform", 0.0, math.inf, "Hz"),
    # no negative width in any speed class (qSDHCP absorption >= 0)
    "gamma2_hz": Prior("gamma2_hz", "uniform", 0.0, math.inf, "Hz", cap=("gamma0_hz", 2.0 / 3.0)),
    "nu_vc_hz": Prior("nu_vc_hz", "uniform", 0.0, math.inf, "Hz"),
    "delta2_hz": Prior("delta2_hz", "uniform", -math.inf, math.inf, "Hz"),
}
# per spectrum: the baseline in the spectrum's unit and its slope per Hz of detuning
BASELINE_UNITS = {"absorption": ("1/m", "1/(m Hz)"), "dispersion": ("Hz", "1")}


def line_prior(name: str, kinds) -> Prior:
    """The prior of line-model parameter ``name``; baselines take the unit of their spectrum."""
    if name in LINE_PRIORS:
        return LINE_PRIORS[name]
    for stem, k in (("baseline", 0), ("slope", 1)):
        if name.startswith(stem) and name[len(stem) :].isdigit():
            unit = BASELINE_UNITS[kinds[int(name[len(stem) :])]][k]
            return Prior(name, "uniform", -math.inf, math.inf, unit)
    raise KeyError(f"no prior for line parameter {name!r}")


@dataclass(frozen=True)
class LinePosterior:
    """log p(line parameters | spectra) for a :class:`bayes_tfcrds.fit.line.LineModel` layout.

    Sample space: the model's parameters in natural SI units (A in Hz/m, position offset and
    widths in Hz, baselines in the spectrum's unit); priors :data:`LINE_PRIORS` (``priors``), flat
    within the physical bounds.
    """

    model: object
    spectra: tuple
    names: tuple

    @property
    def priors(self) -> tuple:
        return tuple(line_prior(n, self.model.kinds) for n in self.names)

    def __post_init__(self):
        if any(p.is_log for p in self.priors):
            raise ValueError("the line posterior samples its parameters as they are (uniform)")

    @cached_property
    def _support(self) -> tuple:
        """The priors as arrays: (lower (d,), upper (d,), caps ((i, j, factor), ...))."""
        pri = self.priors
        caps = tuple(
            (i, self.names.index(p.cap[0]), p.cap[1])
            for i, p in enumerate(pri)
            if p.cap and p.cap[0] in self.names
        )
        return np.array([p.lower for p in pri]), np.array([p.upper for p in pri]), caps

    def outside(self, x) -> np.ndarray:
        """:func:`outside_priors` of samples x (n, d), on the priors' arrays (one array step)."""
        lower, upper, caps = self._support
        bad = ~np.isfinite(x).all(axis=1) | (x <= lower).any(axis=1) | (x >= upper).any(axis=1)
        for i, j, factor in caps:
            bad |= x[:, i] >= factor * x[:, j]
        return bad

    def __call__(self, x):
        x = np.atleast_2d(np.asarray(x, float))
        bad = self.outside(x)
        lp = np.where(bad, -np.inf, 0.0)
        ok = ~bad
        if not ok.any():
            return lp
        cols = x[ok].T[:, :, None]  # (ndim, n_ok, 1): broadcasts in predict
        chi2 = np.zeros(ok.sum())
        for s, pred in zip(self.spectra, self.model.predict(cols, self.spectra)):
            r = (pred - s.y[None, :]) / s.u[None, :]
            chi2 += np.sum(r * r, axis=1)
        lp[ok] = np.where(np.isfinite(chi2), -0.5 * chi2, -np.inf)
        return lp
