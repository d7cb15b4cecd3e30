"""Line-shape model uncertainty: candidate profiles weighted by their predictive evidence.

Each candidate profile is fitted to the same spectrum by least squares. Its expected log
predictive density is estimated by Akaike's criterion, elpd ~ ln L(theta_hat) - k (k free
parameters; AIC = -2 elpd): for a regular model with known noise this is the large-sample
equivalent of leave-one-out cross-validation (Stone, J. R. Stat. Soc. B 39 (1977) 44). Per
spectral point, elpd_i = -r_i^2/2 - k/n (r_i the normalised residual; the terms shared by all
candidates dropped). The weights are pseudo-BMA+ (Yao, Vehtari, Simpson, Gelman, Bayesian
Anal. 13 (2018) 917, Sec. 3.4; arviz ``compare(method="BB-pseudo-BMA")``): Akaike weights
exp(elpd_k) averaged over Bayesian-bootstrap resamples of the points, so that the weights carry
the uncertainty of the elpd differences. Two candidates that predict equally well get 1/2 each;
a profile many nats below the best (one the data reject: SDVP on a TF-CRDS spectrum,
chi2_red ~30-90) gets nothing. Plain Akaike weights swing to 0.99/0.01 with the noise where two
profiles fit about equally: on simulated HTP spectra that neither SDVP nor Rautian represents
the averaged A +/- 2 u covered the truth in 15/20 noise realisations with them, 19/20 with
pseudo-BMA+.

Why not PSIS-LOO on Laplace draws: the HTP's extra parameters (eta, Delta2) are barely
identified by one spectrum, so the Gaussian approximation of their posterior puts its mass where
the profile misfits; measured on a simulated D4 spectrum, p_loo = 11641 for 7 parameters and
Pareto k = inf (arviz ``loo``): the estimate is meaningless, whereas MCMC per candidate costs
minutes. AIC needs only the fits. Stacking is not used either: it may give any split between
candidates that predict identically (nested profiles whose extra parameter is not needed).

The model-averaged A is sum_k w_k A_k; the between-model variance sum_k w_k (A_k - A_bar)^2
is the line-shape row of the budget (the within-model variance is the noise row already).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from bayes_tfcrds.core.constants import line_area_to_cm2
from bayes_tfcrds.fit.line import DEFAULT_SHAPE_FREE, LineFit, fit_line
from bayes_tfcrds.uncertainty.propagate import line_gain


@dataclass(frozen=True)
class ShapeCandidate:
    """A candidate line-shape model: a profile and the shape parameters it fits (the rest 0)."""

    label: str
    profile: str
    shape_free: tuple


CANDIDATES = {
    c.label: c
    for c in (
        ShapeCandidate("qsdhcp", "qsdhcp", DEFAULT_SHAPE_FREE["qsdhcp"]),
        ShapeCandidate("htp", "htp", DEFAULT_SHAPE_FREE["htp"]),
        ShapeCandidate("htp+delta2", "htp", (*DEFAULT_SHAPE_FREE["htp"], "delta2_hz")),
        ShapeCandidate("sdvp", "sdvp", DEFAULT_SHAPE_FREE["sdvp"]),
        ShapeCandidate("rautian", "rautian", DEFAULT_SHAPE_FREE["rautian"]),
        ShapeCandidate("voigt", "voigt", DEFAULT_SHAPE_FREE["voigt"]),
    )
}
DEFAULT_CANDIDATES = tuple(CANDIDATES)
N_BOOTSTRAP = 1000  # Bayesian-bootstrap resamples (arviz's default b_samples)


@dataclass(frozen=True)
class CandidateFit:
    """One candidate on the spectrum: its fit (None if it failed, ``error`` says why), weight."""

    candidate: ShapeCandidate
    fit: LineFit | None = field(repr=False)
    weight: float = 0.0
    error: str = ""

    @property
    def failed(self) -> bool:
        """No fit, or one without a finite chi2, A or covariance.

        The profile is undefined where the search went, or next to where it ended (HTP +
        Delta2 with Gamma2 ~ 0: a step to Gamma2 < 0 leaves the profile's domain, so neither
        u(A) nor what H does to A is defined for that fit).
        """
        return self.fit is None or not (
            np.isfinite(self.fit.chi2)
            and np.isfinite(self.fit.line_area)
            and np.all(np.isfinite(self.fit.cov))
        )

    @property
    def n_free(self) -> int:
        """Parameters free at the solution (those held at a bound are not counted)."""
        return len(self.fit.names) - len(self.fit.at_bound)

    @property
    def aic(self) -> float:
        """AIC = chi2 + 2k (the data's constant ln-likelihood terms, shared by all, dropped)."""
        return float(self.fit.chi2 + 2 * self.n_free)

    @property
    def pointwise_elpd(self) -> np.ndarray | None:
        """elpd_i = -r_i^2/2 - k/n per spectral point (nats); None for a failed fit."""
        if self.failed:
            return None
        u = np.concatenate([sp.u for sp in self.fit.spectra])
        r = np.concatenate(self.fit.residuals) / u
        return -0.5 * r**2 - self.n_free / r.size

    @property
    def line_area(self) -> float:
        """A (Hz/m) of this candidate's least-squares fit (NaN if it failed)."""
        return float("nan") if self.fit is None else self.fit.line_area


@dataclass(frozen=True)
class ModelAverage:
    """The weighted candidates, A_bar and the between-model sd (Hz/m)."""

    candidates: tuple
    line_area: float
    u_between: float
    method: str = (
        "pseudo-BMA+ weights: Akaike weights exp(-AIC/2) of the least-squares fits, averaged "
        f"over {N_BOOTSTRAP} Bayesian-bootstrap resamples of the spectral points"
    )

    @property
    def weights(self) -> dict:
        return {c.candidate.label: c.weight for c in self.candidates}

    def to_dict(self) -> dict:
        """The ``line_shape_models`` record of budget.json (A in cm^-2, SI beside it)."""
        return {
            "method": self.method,
            "line_area": float(line_area_to_cm2(self.line_area)),
            "u_between": float(line_area_to_cm2(self.u_between)),
            "unit": "cm^-2",
            "line_area_si": self.line_area,
            "u_between_si": self.u_between,
            "unit_si": "Hz/m",
            "candidates": [
                {
                    "label": c.candidate.label,
                    "profile": c.candidate.profile,
                    "shape_free": list(c.candidate.shape_free),
                    "chi2_red": None if c.failed else float(c.fit.chi2_red),
                    "n_free": None if c.failed else c.n_free,
                    "aic": None if c.failed else c.aic,
                    "delta_aic": None
                    if c.failed
                    else c.aic - min(d.aic for d in self.candidates if not d.failed),
                    "weight": c.weight,
                    "failed": c.failed,
                    "error": c.error or None,
                    "line_area": float(line_area_to_cm2(c.line_area)) if not c.failed else None,
                    "line_area_si": c.line_area if not c.failed else None,
                }
                for c in self.candidates
            ],
        }


def model_average(values, weights) -> tuple[float, float]:
    """Weighted mean and between-model sd: (sum w_k x_k, sqrt(sum w_k (x_k - mean)^2)).

    ``weights`` must be >= 0 and sum to 1 (they are a probability over the candidates).
    """
    x = np.asarray(values, float)
    w = np.asarray(weights, float)
    if np.any(w < 0) or not np.isclose(w.sum(), 1.0, rtol=0, atol=1e-9):
        raise ValueError(f"model weights must be >= 0 and sum to 1, got {w}")
    mean = float(np.sum(w * x))
    return mean, float(np.sqrt(np.sum(w * (x - mean) ** 2)))


def bb_pseudo_bma_weights(pointwise_elpd, rng, n_boot: int = N_BOOTSTRAP) -> np.ndarray:
    """Pseudo-BMA+ weights of K models from their pointwise elpd (K, n points), nats.

    For each of ``n_boot`` Dirichlet(1, ..., 1) draws alpha over the points, z_k = n sum_i
    alpha_i elpd_ki and w_k = exp(z_k) / sum_j exp(z_j); the weights are the mean over draws
    (Yao et al. 2018, Sec. 3.4). A model with elpd -inf at any point gets 0. rng: numpy
    Generator.
    """
    e = np.asarray(pointwise_elpd, float)
    n = e.shape[1]
    alpha = rng.dirichlet(np.ones(n), size=n_boot)  # (n_boot, n)
    finite = np.all(np.isfinite(e), axis=1)
    z = np.full((n_boot, e.shape[0]), -np.inf)
    z[:, finite] = n * alpha @ e[finite].T
    w = np.exp(z - z.max(axis=1, keepdims=True))
    return np.mean(w / w.sum(axis=1, keepdims=True), axis=0)


def _shape_free(fit: LineFit) -> tuple:
    """The shape parameters a fit had free (its names minus area, position and baselines)."""
    return tuple(
        n
        for n in fit.names
        if n not in ("line_area", "position_offset_hz") and not n.startswith(("baseline", "slope"))
    )


def fit_candidates(spec, gd: float, nu_ref: float, labels=DEFAULT_CANDIDATES, primary=None):
    """Least-squares fit of every candidate in ``labels`` to ``spec`` (unweighted CandidateFits).

    gd, nu_ref: Doppler HWHM and nominal position (Hz). ``primary`` is a fit already made (the
    budget's profile), reused for its own label. Each candidate starts from the fit made so far
    that shares most of its shape parameters, so that a profile containing another (HTP: eta = 0
    is the qSDHCP; HTP + Delta2 contains the HTP) starts at that one's optimum. A candidate
    whose fit fails (its profile undefined where the search went: Gamma2 < 0 with Delta2 != 0
    on a distorted spectrum) is kept with ``failed`` set and the reason; it gets weight 0.
    """
    done = [] if primary is None else [primary]
    out = []
    for label in labels:
        try:
            cand = CANDIDATES[label]
        except KeyError:
            raise ValueError(
                f"unknown line-shape candidate {label!r}; known: {sorted(CANDIDATES)}"
            ) from None
        same = [f for f in done if (f.profile, _shape_free(f)) == (cand.profile, cand.shape_free)]
        try:
            one = CandidateFit(cand, same[0] if same else _fit_from(spec, gd, nu_ref, cand, done))
        except ValueError as exc:  # non-finite residuals or Jacobian where the search went
            one = CandidateFit(cand, None, error=f"fit failed: {exc}")
        if one.failed and not one.error:
            one = replace(one, error="fit failed: covariance undefined at the solution")
        if not one.failed:
            done.append(one.fit)
        out.append(one)
    return out


def _fit_from(spec, gd, nu_ref, cand: ShapeCandidate, done) -> LineFit:
    """Fit ``cand`` starting from the fit in ``done`` sharing most shape parameters (if any)."""
    start = {}
    if done:
        parent = max(done, key=lambda f: len(set(_shape_free(f)) & set(cand.shape_free)))
        keep = {*cand.shape_free, "line_area", "position_offset_hz"}
        start = {
            k: v
            for k, v in zip(parent.names, parent.values)
            if k in keep or k.startswith(("baseline", "slope"))
        }
    start.setdefault("eta", 0.0)
    start.setdefault("delta2_hz", 0.0)
    return fit_line([spec], cand.profile, gd, nu_ref, shape_free=cand.shape_free, start=start)


def averaged_area_gain(average: ModelAverage, primary: LineFit) -> np.ndarray:
    """dA_bar/dy (Hz/m per unit of y, one per spectral point): the gain of the reported A.

    The budget reports the averaged A_bar = sum_k w_k A_k, so what a shift of the spectrum
    (every decay time moved by H) does to it is sum_k w_k dA_k/dy, the weights held (their
    change is second order at the optima). Profiles differ in it: where the narrowing profiles
    carry the weight, a shift concentrated at the line centre moves their A more than the
    Voigt's, and propagating H through the primary profile alone would understate u(A) by that
    ratio. ``primary``'s gain when no candidate carries weight.
    """
    live = [c for c in average.candidates if c.weight > 0 and not c.failed]
    total = sum(c.weight for c in live)
    if not live or total <= 0:
        return _area_gain(primary)
    return sum((c.weight / total) * _area_gain(c.fit) for c in live)


def _area_gain(fit: LineFit) -> np.ndarray:
    return line_gain(fit)[fit.names.index("line_area")]


def average_candidates(fits, rng) -> ModelAverage:
    """Pseudo-BMA+ weights of the candidate fits, the averaged A, the between-model sd (Hz/m).

    rng: numpy Generator for the Bayesian bootstrap.
    """
    n = next(c.pointwise_elpd.size for c in fits if not c.failed)
    elpd = [np.full(n, -np.inf) if c.failed else c.pointwise_elpd for c in fits]
    w = bb_pseudo_bma_weights(elpd, rng)
    weighted = tuple(replace(c, weight=float(wk)) for c, wk in zip(fits, w))
    ok = w > 0  # a failed fit's A may be NaN; it has weight 0 and no say in the average
    a_bar, u_between = model_average([c.line_area for c, k in zip(weighted, ok) if k], w[ok])
    return ModelAverage(weighted, a_bar, u_between)
