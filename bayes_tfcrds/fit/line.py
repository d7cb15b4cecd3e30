"""Line-shape fits to spectra, with the line area as a parameter.

* CRDS: ``1/(c tau) = alpha(nu) + alpha_loss``; the empty-cavity loss is a fitted baseline
  (constant, optionally sloped), so decay times go in directly.
* CMDS: ``shift(nu) = c A g_I(nu) / (4 pi)`` plus a linear baseline (the lock-mode reference and
  the empty cavity's own dispersion); mode widths ``Gamma = c (alpha + alpha_loss)/(4 pi)``.

The integrated line area A (Hz/m; cm^-2 only at the edges) is a fitted parameter with
position and shape parameters, so its uncertainty and correlations come from the fit itself.
The Doppler width is fixed by T and the molecular mass (it is known better than the fit
could determine it); shape parameters a profile does not use are absent.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy import optimize

from bayes_tfcrds.core.constants import C, line_area_to_cm2
from bayes_tfcrds.core.linalg import central_jacobian, covariance_from_fisher
from bayes_tfcrds.physics.lineshape import PROFILES, profile

# shape parameters fitted by default per profile (delta0 is absorbed in the position)
DEFAULT_SHAPE_FREE = {
    "gaussian": (),
    "lorentzian": ("gamma0_hz",),
    "voigt": ("gamma0_hz",),
    "sdvp": ("gamma0_hz", "gamma2_hz"),
    "rautian": ("gamma0_hz", "nu_vc_hz"),
    "qsdhcp": ("gamma0_hz", "gamma2_hz", "nu_vc_hz"),
    "htp": ("gamma0_hz", "gamma2_hz", "nu_vc_hz", "eta"),
}
NONNEGATIVE = {"gamma0_hz", "line_area"}
# upper bounds of the estimator: the HTP is undefined at eta = 1 (eta/(1 - eta) in its
# denominator); 0.99 keeps the profile finite wherever the least-squares search steps
UPPER_BOUNDS = {"eta": 0.99}
# Gamma2 and nu_VC are physically >= 0 but the least-squares estimate is not bounded there:
# where the data barely resolve them (CMDS at 1e-3 noise: sd 0.26 Gamma0 and 0.54 Gamma0,
# correlation -0.99) a bounded fit ends on a bound in half the draws, and holding one at 0
# moves A along their correlation (+0.40 sd when Gamma2 is held, -0.29 sd for nu_VC): a
# +0.085 sd bias in A over 1000 draws (benchmarks/pulls_spectrum.py). The profile's smooth
# continuation past 0 (lineshape.qsdhcp) keeps the estimator unbiased; ``unphysical`` names
# the estimates that ended outside the physical domain, and the samplers keep its bounds.
PHYSICAL_NONNEGATIVE = ("gamma2_hz", "nu_vc_hz")


@dataclass(frozen=True)
class LineFit:
    """A line-shape fit: parameter ``names``/``values``/``cov`` (SI), chi2 and residuals.

    ``line_area`` is A in Hz/m; :meth:`line_area_cm2` gives it in cm^-2. When the data carried
    no trustworthy uncertainties (``scaled``), the covariance is scaled by chi2/dof. Parameters
    that ended on their lower bound (``at_bound``) have zero variance: they were not free at
    the solution. ``unphysical`` names shape estimates below zero (Gamma2, nu_VC): estimates on
    the profile's continuation, not measured negative rates; one many standard uncertainties
    below zero points to a wrong profile rather than to noise.
    """

    profile: str
    names: tuple
    values: np.ndarray
    cov: np.ndarray
    chi2: float
    dof: int
    nu_ref_hz: float
    doppler_hwhm_hz: float
    fixed: dict
    spectra: tuple = field(repr=False)
    residuals: tuple = field(repr=False)
    # d((model - y)/u)/d theta at the solution (n_y, n_par): the Jacobian the covariance was made
    # from, kept so that propagation (uncertainty.propagate.line_gain) uses the same one
    jacobian: np.ndarray = field(repr=False)
    scaled: bool = False
    at_bound: tuple = ()
    unphysical: tuple = ()
    physical_bounds: bool = False  # fitted with Gamma2, nu_VC >= 0 (``fit_line``'s option)

    def value(self, name):
        return float(self.values[self.names.index(name)])

    def stderr(self, name):
        i = self.names.index(name)
        return float(np.sqrt(self.cov[i, i]))

    @property
    def line_area(self) -> float:
        return self.value("line_area")

    @property
    def line_area_u(self) -> float:
        return self.stderr("line_area")

    def line_area_cm2(self):
        """(A, u(A)) in cm^-2."""
        return float(line_area_to_cm2(self.line_area)), float(line_area_to_cm2(self.line_area_u))

    @property
    def correlation(self) -> np.ndarray:
        """Correlation matrix; rows of parameters held at a bound (zero variance) are NaN."""
        d = np.sqrt(np.diag(self.cov))
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(np.outer(d, d) > 0, self.cov / np.outer(d, d), np.nan)

    @property
    def chi2_red(self) -> float:
        return self.chi2 / max(self.dof, 1)

    @property
    def position_hz(self) -> float:
        return self.nu_ref_hz + self.value("position_offset_hz")

    def model(self, nu_hz, k: int = 0) -> np.ndarray:
        """The fitted model of spectrum ``k`` at frequencies ``nu_hz`` (Hz), in its y unit.

        1/m for absorption, Hz for dispersion (mode shifts); baseline included.
        """
        names = self.names
        layout = LineModel(
            profile=self.profile,
            shape_free=names[2 : names.index("baseline0")],
            kinds=tuple(s.kind for s in self.spectra),
            slopes=tuple(f"slope{i}" in names for i in range(len(self.spectra))),
            nu_ref_hz=self.nu_ref_hz,
            doppler_hwhm_hz=self.doppler_hwhm_hz,
            fixed=self.fixed,
        )
        grid = [
            replace(s, nu_hz=np.asarray(nu_hz, float), y=np.zeros(np.size(nu_hz)), u=None)
            if i == k
            else s
            for i, s in enumerate(self.spectra)
        ]
        return layout.predict(self.values, grid)[k]

    def summary(self) -> str:
        """Plain-text table of the parameters with their units, chi2_red and A in cm^-2."""
        from bayes_tfcrds.fit.views import line_fit_text

        return line_fit_text(self)

    def to_dict(self) -> dict:
        """JSON-ready record: every parameter with its u and unit, A also in cm^-2."""
        from bayes_tfcrds.fit.views import line_fit_dict

        return line_fit_dict(self)

    def _repr_html_(self) -> str:
        from bayes_tfcrds.fit.views import line_fit_html

        return line_fit_html(self)

    def plot(self, ax=None):
        """Each spectrum with the fitted profile and its residuals; a matplotlib Figure."""
        from bayes_tfcrds.fit.views import plot_line_fit

        return plot_line_fit(self, ax)


@dataclass(frozen=True)
class LineModel:
    """Parameter layout of a (joint) fit: line parameters shared, one baseline per spectrum."""

    profile: str
    shape_free: tuple
    kinds: tuple
    slopes: tuple
    nu_ref_hz: float
    doppler_hwhm_hz: float
    fixed: dict

    @property
    def names(self) -> tuple:
        names = ["line_area", "position_offset_hz", *self.shape_free]
        for i, (_, slope) in enumerate(zip(self.kinds, self.slopes)):
            names.append(f"baseline{i}")
            if slope:
                names.append(f"slope{i}")
        return tuple(names)

    def shape(self, theta) -> dict:
        p = dict(self.fixed)
        for name, v in zip(self.shape_free, theta[2 : 2 + len(self.shape_free)]):
            p[name] = v
        return p

    def predict(self, theta, spectra):
        """Model values for each spectrum (1/m for absorption, Hz for dispersion)."""
        area, pos = theta[0], theta[1]
        # work in detuning from nu_ref: absolute optical frequencies (~2e14 Hz) resolve only
        # ~0.03 Hz in float64, which would swallow the position's finite-difference steps
        g_all = [
            profile(
                self.profile,
                s.nu_hz - self.nu_ref_hz,
                pos,
                self.doppler_hwhm_hz,
                **self.shape(theta),
            )
            for s in spectra
        ]
        out = []
        k = 2 + len(self.shape_free)
        for s, g, slope in zip(spectra, g_all, self.slopes):
            base = theta[k]
            k += 1
            lin = 0.0
            if slope:
                lin = theta[k] * (s.nu_hz - self.nu_ref_hz)
                k += 1
            if s.kind == "absorption":
                out.append(area * g.real + base + lin)
            else:
                out.append(C * area * g.imag / (4 * np.pi) + base + lin)
        return out


def _initial(spectra, model: LineModel, start: dict):
    theta = []
    ref = next((s for s in spectra if s.kind == "absorption"), None)
    if ref is not None:
        order = np.argsort(ref.nu_hz)
        nu, y = ref.nu_hz[order], ref.y[order]
        base = np.median(np.concatenate([y[:5], y[-5:]]))
        area0 = np.trapezoid(y - base, nu)
    else:
        s = spectra[0]
        order = np.argsort(s.nu_hz)
        nu, y = s.nu_hz[order], s.y[order]
        # dispersion: the extremes sit about one width either side of the centre
        area0 = (y.max() - y.min()) * 4 * np.pi / C * np.pi * model.doppler_hwhm_hz * 0.9
    theta.append(start.get("line_area", area0))
    theta.append(start.get("position_offset_hz", 0.0))
    for name in model.shape_free:
        default = {
            "gamma0_hz": 0.05 * model.doppler_hwhm_hz,
            "gamma2_hz": 0.01 * model.doppler_hwhm_hz,
            "nu_vc_hz": 0.01 * model.doppler_hwhm_hz,
            "delta2_hz": 0.0,
            "eta": 0.1,
        }[name]
        theta.append(start.get(name, default))
    for i, (s, slope) in enumerate(zip(spectra, model.slopes)):
        if s.kind == "absorption":
            o = np.argsort(s.nu_hz)
            theta.append(
                start.get(f"baseline{i}", np.median(np.concatenate([s.y[o][:5], s.y[o][-5:]])))
            )
        else:
            theta.append(start.get(f"baseline{i}", 0.0))
        if slope:
            theta.append(start.get(f"slope{i}", 0.0))
    return np.array(theta, float)


def fit_line(
    spectra,
    profile_name: str = "qsdhcp",
    doppler_hwhm_hz: float = None,
    nu_ref_hz: float = None,
    shape_free=None,
    fixed: dict | None = None,
    slopes=None,
    start: dict | None = None,
    scale_by_chi2: bool = False,
    physical_bounds: bool = False,
) -> LineFit:
    """Least-squares fit of one line to one or more spectra (CRDS absorption, CMDS dispersion).

    ``doppler_hwhm_hz`` (Hz) is held fixed; ``nu_ref_hz`` (Hz) is the nominal position (the fit
    returns ``position_offset_hz`` from it); ``shape_free`` names the shape parameters fitted
    (default per profile), ``fixed`` holds the others (Hz); ``slopes`` per spectrum whether the
    baseline is sloped (default: absorption constant, dispersion sloped). ``physical_bounds``
    holds Gamma2 and nu_VC >= 0 as well: the estimator of a model one knows to be wrong (CRDS
    without H, whose distorted line the free fit follows to nu_VC ~ -0.7 Gamma0) when its
    parameters are to be read as rates; it is biased where the data barely resolve them.
    """
    spectra = tuple(spectra)
    if profile_name not in PROFILES:
        raise ValueError(f"unknown profile {profile_name!r}; known: {sorted(PROFILES)}")
    if doppler_hwhm_hz is None or nu_ref_hz is None:
        raise ValueError("fit_line needs doppler_hwhm_hz and nu_ref_hz (Hz)")
    shape_free = DEFAULT_SHAPE_FREE[profile_name] if shape_free is None else tuple(shape_free)
    fixed = dict(fixed or {})
    for name in list(fixed):
        if name in shape_free:
            fixed.pop(name)
    slopes = tuple(s.kind == "dispersion" for s in spectra) if slopes is None else tuple(slopes)
    model = LineModel(
        profile=profile_name,
        shape_free=shape_free,
        kinds=tuple(s.kind for s in spectra),
        slopes=slopes,
        nu_ref_hz=float(nu_ref_hz),
        doppler_hwhm_hz=float(doppler_hwhm_hz),
        fixed=fixed,
    )
    names = model.names
    y = np.concatenate([s.y for s in spectra])
    u = np.concatenate([s.u for s in spectra])
    if np.any(~np.isfinite(y)) or np.any(~np.isfinite(u)) or np.any(u <= 0):
        raise ValueError("spectrum values must be finite and uncertainties > 0")
    theta0 = _initial(spectra, model, dict(start or {}))
    bounded = NONNEGATIVE | (set(PHYSICAL_NONNEGATIVE) if physical_bounds else set())
    lo = np.array([0.0 if n in bounded else -np.inf for n in names])
    theta0 = np.maximum(theta0, lo + 1e-300 * (lo == 0))
    scale = np.abs(theta0) + np.array(
        [1e-3 * doppler_hwhm_hz if n == "position_offset_hz" else 0.0 for n in names]
    )
    scale = np.where(scale > 0, scale, 1.0)

    def resid(x):
        return (np.concatenate(model.predict(x * scale, spectra)) - y) / u

    sol = optimize.least_squares(
        resid,
        theta0 / scale,
        bounds=(lo / scale, np.array([UPPER_BOUNDS.get(n, np.inf) for n in names]) / scale),
        x_scale="jac",
        xtol=1e-13,
        ftol=1e-13,
        gtol=1e-13,
        max_nfev=5000,
    )
    theta = sol.x * scale
    steps = 1e-6 * np.maximum(np.abs(theta), 1e-3 * scale)
    jac = (
        central_jacobian(lambda th: np.concatenate(model.predict(th, spectra)), theta, steps)
        / u[:, None]
    )
    r = resid(sol.x)
    chi2 = float(r @ r)
    # parameters pinned at their lower bound (e.g. Gamma2 = 0 when the data cannot resolve
    # speed dependence) are held fixed in the covariance: treating them as free would state
    # the uncertainty of an estimator the fit did not use (the active set of the solution)
    at_bound = tuple(
        n
        for n, v, low in zip(names, theta, lo)
        if low == 0.0 and v <= 1e-9 * max(scale[names.index(n)], 1e-300)
    )
    free_idx = [i for i, n in enumerate(names) if n not in at_bound]
    dof = y.size - len(free_idx)
    cov = np.zeros((theta.size, theta.size))
    sub = jac[:, free_idx]
    cov[np.ix_(free_idx, free_idx)] = covariance_from_fisher(sub.T @ sub)
    if scale_by_chi2:
        cov = cov * chi2 / max(dof, 1)
    split = np.cumsum([s.y.size for s in spectra])[:-1]
    return LineFit(
        profile=profile_name,
        names=names,
        values=theta,
        cov=cov,
        chi2=chi2,
        dof=dof,
        nu_ref_hz=float(nu_ref_hz),
        doppler_hwhm_hz=float(doppler_hwhm_hz),
        fixed=fixed,
        spectra=spectra,
        residuals=tuple(np.split(r * u, split)),
        scaled=scale_by_chi2,
        at_bound=at_bound,
        unphysical=tuple(n for n, v in zip(names, theta) if n in PHYSICAL_NONNEGATIVE and v < 0),
        physical_bounds=bool(physical_bounds),
        jacobian=jac,
    )
