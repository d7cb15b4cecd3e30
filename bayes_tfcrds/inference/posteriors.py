"""Log-posteriors for the samplers: H(f) from the beat note, and line parameters from spectra.

Both are vectorised over emcee's walkers (``log_prob(thetas)`` with thetas of shape
(n_walkers, ndim)). Scale parameters (frequencies, widths, quality factor) are sampled as
logarithms with uniform priors on wide physical ranges (scale-invariant priors); the priors
also encode physics: 0 <= Gamma2 <= (2/3) Gamma0 keeps the qSDHCP absorption non-negative,
nu_VC >= 0, A > 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bayes_tfcrds.physics.transfer_function import (
    PARAM_NAMES,
    SUPPORT,
    TFParams,
    transfer_function_array,
)

LOG_PARAMS = {"f_c_hz", "f_r_hz", "gamma_r"}
# the physical domain of every H parameter; a causal fractional order n_r <= 2; the scale K
H_PRIOR = {**SUPPORT, "n_r": (0.5, 2.0), "scale": (0.0, 10.0)}


@dataclass(frozen=True)
class BeatNotePosterior:
    """log p(theta | beat note) for the H parameters ``free`` plus the scale K.

    Sample space: log of f_c, f_r, gamma_r; a_r, n_r and K as they are (see ``sample_names``).
    Likelihood: Gaussian in the measured |H(f_B)| with its stated uncertainty. |H| nearly repeats
    under A_r -> -A_r/(1 + 2 A_r), which maps A_r > 0 onto -1 < A_r < 0: ``a_r_sign`` restricts
    the support to the branch the ring-downs chose, so a sampler cannot wander into the mirror
    mode that the ring-down data exclude.
    """

    f_hz: np.ndarray
    h_mag: np.ndarray
    h_mag_u: np.ndarray
    free: tuple
    fixed: TFParams
    a_r_sign: int = 0  # +1 or -1: the branch of A_r the ring-downs chose (0: both)

    @property
    def sample_names(self) -> tuple:
        return tuple(("log_" + n if n in LOG_PARAMS else n) for n in self.free) + ("scale",)

    def to_sample(self, params: TFParams, scale: float) -> np.ndarray:
        v = [
            np.log(getattr(params, n)) if n in LOG_PARAMS else getattr(params, n) for n in self.free
        ]
        return np.array(v + [scale], float)

    def to_params(self, x) -> dict:
        """Natural-unit parameter arrays from samples x (..., ndim)."""
        x = np.asarray(x, float)
        with np.errstate(over="ignore"):  # far proposals overflow to inf, which the prior refuses
            out = {
                n: (np.exp(x[..., i]) if n in LOG_PARAMS else x[..., i])
                for i, n in enumerate(self.free)
            }
        out["scale"] = x[..., -1]
        return out

    def __call__(self, x):
        x = np.atleast_2d(x)
        p = self.to_params(x)
        lp = np.zeros(x.shape[0])
        for name, v in p.items():
            lo, hi = H_PRIOR[name]
            lp[(v <= lo) | (v >= hi) | ~np.isfinite(v)] = -np.inf
        if self.a_r_sign and "a_r" in p:
            lp[p["a_r"] * self.a_r_sign <= 0] = -np.inf
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


@dataclass(frozen=True)
class LinePosterior:
    """log p(line parameters | spectra) for a :class:`bayes_tfcrds.fit.line.LineModel` layout.

    Sample space: the model's parameters in natural SI units (A in Hz/m, position offset and
    widths in Hz, baselines in the spectrum's unit); flat priors with the physical bounds.
    """

    model: object
    spectra: tuple
    names: tuple

    def __call__(self, x):
        x = np.atleast_2d(np.asarray(x, float))
        lp = np.zeros(x.shape[0])
        idx = {n: i for i, n in enumerate(self.names)}
        bad = x[:, idx["line_area"]] <= 0
        g0 = x[:, idx["gamma0_hz"]] if "gamma0_hz" in idx else None
        if g0 is not None:
            bad |= g0 <= 0
        if "gamma2_hz" in idx:
            g2 = x[:, idx["gamma2_hz"]]
            bad |= (g2 < 0) | (g2 > (2.0 / 3.0) * (g0 if g0 is not None else np.inf))
        if "nu_vc_hz" in idx:
            bad |= x[:, idx["nu_vc_hz"]] < 0
        lp[bad] = -np.inf
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
