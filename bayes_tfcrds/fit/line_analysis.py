"""Line area of one configuration: ring-down fits -> CRDS spectrum -> profile fit, and CMDS.

The result is a :class:`LineAnalysis`; its ``to_dict()`` is the JSON record, with spectroscopic
units at that edge, each labelled.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from bayes_tfcrds.core.constants import (
    edge_entry,
    intensity_to_cm_per_molecule,
    line_area_to_cm2,
    number_density,
)
from bayes_tfcrds.core.gum import ratio
from bayes_tfcrds.core.quantity import Quantity
from bayes_tfcrds.fit.h_calibration import (
    AnalysisError,
    account_for_noise_colour,
    calibrate,
    fit_config,
)
from bayes_tfcrds.fit.line import PHYSICAL_NONNEGATIVE, LineFit, fit_line
from bayes_tfcrds.fit.ringdown import RingdownFits
from bayes_tfcrds.fit.spectrum import SpectrumData, check_repeats, cmds_spectrum, crds_spectrum
from bayes_tfcrds.fit.views import parameter_unit
from bayes_tfcrds.physics.linedata import load_line
from bayes_tfcrds.physics.lineshape import doppler_hwhm_hz


class LineFitError(ValueError):
    """The line analysis cannot run on this bundle (the message says what is missing)."""


def doppler_of(sample) -> float:
    """Doppler HWHM (Hz) from the bundle's sample: T and the absorber mass."""
    if sample.mass_u is None:
        raise LineFitError(
            "/sample@mass_u is absent: the Doppler width needs the absorber's mass (u)"
        )
    return float(doppler_hwhm_hz(sample.nu0_hz, sample.temperature_k, sample.mass_u))


def check_overlap(config):
    """Refuse a CMDS reference that does not cover the ring-down spectrum's frequency range.

    Comparing areas of two spectra of different stretches of the line would mean nothing.
    """
    if config.cmds is None:
        return
    rd_lo, rd_hi = np.min(config.ringdowns.nu_hz), np.max(config.ringdowns.nu_hz)
    cm_lo, cm_hi = np.min(config.cmds.nu_hz), np.max(config.cmds.nu_hz)
    inside = np.sum((config.cmds.nu_hz >= rd_lo) & (config.cmds.nu_hz <= rd_hi))
    if cm_hi < rd_lo or cm_lo > rd_hi or inside < 8:
        raise LineFitError(
            f"/configs/{config.name}/cmds/nu_hz spans {cm_lo / 1e12:.6f}-{cm_hi / 1e12:.6f} THz "
            f"and does not overlap the ring-down range /configs/{config.name}/ringdowns/nu_hz "
            f"{rd_lo / 1e12:.6f}-{rd_hi / 1e12:.6f} THz ({inside} CMDS points inside it; at least "
            "8 needed)"
        )


def check_t_cuts(config, t_cuts_s):
    """Refuse truncation times outside the ring-down record before any work is done.

    t_cut is in s from laser extinction; a fit needs t_cut >= 0, no earlier than the record's first
    sample, and some samples after it (8, as ringdown.fit_transients).
    """
    t = config.ringdowns.time_s
    last, dt = float(t[-1]), float(t[1] - t[0]) if t.size > 1 else 0.0
    for tc in np.atleast_1d(np.asarray(t_cuts_s, float)):
        if not np.isfinite(tc) or tc < 0:
            raise LineFitError(
                f"t_cut = {tc:g} s: t_cut is counted from laser extinction and must be >= 0 s"
            )
        if tc < float(t[0]) - dt:
            # every t_cut before the first sample fits the same samples: identical rows that
            # look like a t_cut study
            raise LineFitError(
                f"t_cut = {tc:g} s is before the first sample of /configs/{config.name}/ringdowns "
                f"(t0_s = {float(t[0]):g} s): choose t_cut >= t0_s"
            )
        if tc >= last - 8 * dt:
            raise LineFitError(
                f"t_cut = {tc:g} s is beyond the record of /configs/{config.name}/ringdowns (last "
                f"sample at {last:g} s; a fit needs samples after t_cut)"
            )


def intensity_entry(
    area_hz_per_m, u_hz_per_m, number_density_m3, temperature_k, u_holds: str = "fit"
) -> dict:
    """The JSON intensity of a line fit: S at the line data's T_ref (296 K), cm/molecule.

    S(T) = A/N at the sample's temperature_k (K), referred to T_ref through Q(T), E'' and
    stimulated emission (LineData.intensity_ratio), as the budget reports it. Its u is A's
    (``u_holds``: ``fit``, or ``fit + H``); p, T and x are the budget's.
    Outside the partition-function table (70-1000 K) S(T_ref) is None and the entry says why.
    """
    line = load_line()
    s_t = float(intensity_to_cm_per_molecule(area_hz_per_m, number_density_m3))
    u_t = float(intensity_to_cm_per_molecule(u_hz_per_m, number_density_m3))
    entry = {"unit": "cm/molecule", "t_ref_k": line.temperature_k, "u_holds": u_holds}
    try:
        to_ref = 1.0 / float(line.intensity_ratio(temperature_k))
    except ValueError as exc:
        entry.update(value=None, u=None, note=str(exc))
    else:
        entry.update(value=s_t * to_ref, u=u_t * to_ref)
    entry.update(sample_temperature_k=float(temperature_k), value_at_sample_temperature=s_t)
    return entry


def fit_reference(bundle, config, profile_name: str = "qsdhcp"):
    """Profile fit to the configuration's CMDS mode shifts (the reference A_ref), or None."""
    if config.cmds is None:
        return None
    return fit_line(
        [cmds_spectrum(config.cmds)], profile_name, doppler_of(bundle.sample), bundle.sample.nu0_hz
    )


@dataclass(frozen=True)
class LineAnalysis:
    """The line area of one configuration from one method and t_cut, and its CMDS comparison.

    SI inside: ``line_fit.line_area`` in Hz/m; :attr:`line_area` and :meth:`to_dict` give
    cm^-2 at the edge, labelled.
    """

    configuration: str
    method: str
    window: str | None
    t_cut_s: float | None  # None for spectrum-level input
    profile: str
    line_fit: LineFit
    reference_fit: LineFit | None
    spectrum: SpectrumData
    number_density_m3: float
    temperature_k: float
    n_points: int
    clipped_points: int
    unconverged_points: int
    record_short_points: int
    calibration: object | None = None
    noise: object | None = None  # the NoiseDiagnosis of the ring-downs (fit.noise)
    input_note: str | None = None  # what the input was, when not ring-down records
    ringdown_fits: RingdownFits | None = field(default=None, repr=False)  # decay times behind it
    h_params: object | None = None  # the H the decay times were fitted at (TFParams), tf-crds
    line_area_u_h_si: float | None = None  # H's part of u(A) (Hz/m); None: not propagated

    @property
    def line_area_u_si(self) -> float:
        """u(A) (Hz/m): the line fit's, and H's part in quadrature when it was propagated."""
        u_h = 0.0 if self.line_area_u_h_si is None else self.line_area_u_h_si
        return float(np.hypot(self.line_fit.line_area_u, u_h))

    @property
    def u_note(self) -> str:
        """What u(A) holds: ``fit`` (decay-time noise) or ``fit + H`` (H's posterior too)."""
        return "fit" if self.line_area_u_h_si is None else "fit + H"

    def with_h_uncertainty(self, u_h_si: float) -> LineAnalysis:
        """The analysis with H's part of u(A) (Hz/m) added (see ``uncertainty.line_area``)."""
        return replace(self, line_area_u_h_si=float(u_h_si))

    @property
    def line_area(self) -> Quantity:
        """A (cm^-2) with its u (:attr:`u_note`: the fit's, and H's when propagated)."""
        return Quantity(
            float(line_area_to_cm2(self.line_fit.line_area)),
            float(line_area_to_cm2(self.line_area_u_si)),
            "cm^-2",
        )

    @property
    def reference_area(self) -> Quantity | None:
        """A_ref (cm^-2) from the CMDS fit, or None without CMDS."""
        ref = self.reference_fit
        if ref is None:
            return None
        return Quantity(
            float(line_area_to_cm2(ref.line_area)),
            float(line_area_to_cm2(ref.line_area_u)),
            "cm^-2",
        )

    @property
    def ratio(self) -> Quantity | None:
        """A/A_ref with its first-order u (A's as :attr:`line_area`, A_ref's fit u), or None."""
        ref = self.reference_fit
        if ref is None:
            return None
        r, u = ratio(self.line_fit.line_area, self.line_area_u_si, ref.line_area, ref.line_area_u)
        return Quantity(float(r), float(u), "")

    @property
    def chi2_red(self) -> float:
        """Reduced chi-square of the CRDS spectrum fit."""
        return float(self.line_fit.chi2_red)

    @property
    def unphysical_shape(self) -> list:
        """Shape estimates below 0 (Gamma2, nu_VC): fitted on the profile's continuation."""
        return list(self.line_fit.unphysical)

    @property
    def shape_at_bound(self) -> list:
        """Shape parameters held at 0 by ``physical_bounds`` (not free at the solution: u = 0)."""
        return [n for n in self.line_fit.at_bound if n in PHYSICAL_NONNEGATIVE]

    def summary(self) -> str:
        """Plain text: A, A_ref, A/A_ref, S(296 K) with units, chi2_red, points left out."""
        from bayes_tfcrds.fit.views import line_analysis_text

        return line_analysis_text(self)

    def _repr_html_(self) -> str:
        from bayes_tfcrds.fit.views import line_analysis_html

        return line_analysis_html(self)

    def plot(self, ax=None):
        """The CRDS spectrum (and the CMDS reference) with the fitted profile and residuals."""
        from bayes_tfcrds.fit.views import plot_line_analysis

        return plot_line_analysis(self, ax)

    def to_dict(self) -> dict:
        """The JSON record of ``bayes-tfcrds linefit`` (and of the demo's ``results.json``)."""
        lf, ref, n = self.line_fit, self.reference_fit, self.number_density_m3
        out = {
            "configuration": self.configuration,
            "method": self.method,
            "window": self.window,
            "t_cut_s": None if self.t_cut_s is None else float(self.t_cut_s),
            "profile": self.profile,
            "line_area": dict(
                edge_entry(lf.line_area, self.line_area_u_si, "Hz/m"),
                u_holds=self.u_note,
                u_fit_si=float(lf.line_area_u),
                u_h_si=self.line_area_u_h_si,
            ),
            "intensity": intensity_entry(
                lf.line_area, self.line_area_u_si, n, self.temperature_k, self.u_note
            ),
            "parameters": {  # A in cm^-2 as above (SI in value_si, u_si), the rest in SI
                name: edge_entry(v, np.sqrt(lf.cov[i, i]), parameter_unit(name, "absorption"))
                for i, (name, v) in enumerate(zip(lf.names, lf.values))
            },
            "correlation": {
                "names": list(lf.names),
                # null where undefined: a parameter held at a bound has u = 0 (NaN is not JSON)
                "matrix": [
                    [float(r) if np.isfinite(r) else None for r in row]
                    for row in np.round(lf.correlation, 6)
                ],
            },
            "chi2_red": self.chi2_red,
            "unphysical_shape": self.unphysical_shape,
            "shape_at_bound": self.shape_at_bound,
            "n_points": self.n_points,
            "clipped_points": self.clipped_points,
            "unconverged_points": self.unconverged_points,
            "record_short_points": self.record_short_points,
        }
        if self.input_note is not None:
            out["input"] = self.input_note
        if self.calibration is not None:
            p = self.h_params if self.h_params is not None else self.calibration.params
            out["transfer_function"] = {
                "f_c_hz": p.f_c_hz,
                "a_r": p.a_r,
                "f_r_hz": p.f_r_hz,
                "gamma_r": p.gamma_r,
                "n_r": p.n_r,
                "variant": p.variant,
                "refined": self.calibration.refined is not None,
                "at": "calibration" if self.h_params is None else "posterior centre",
            }
        if self.noise is not None:
            out["noise"] = self.noise.to_dict()
        if ref is None:
            out["reference_area"] = None
            out["ratio"] = None
        else:
            out["reference_area"] = edge_entry(ref.line_area, ref.line_area_u, "Hz/m")
            out["ratio"] = {"value": self.ratio.value, "u": self.ratio.u}
            out["reference_chi2_red"] = float(ref.chi2_red)
            out["reference_unphysical_shape"] = list(ref.unphysical)
        return out


def analyse_line(
    bundle,
    config,
    method: str = "tf-crds",
    window: str = "extinction",
    t_cut_s: float = 4e-6,
    profile_name: str = "qsdhcp",
    calibration=None,
    physical_bounds: bool = False,
    noise=None,
    tf=None,
) -> LineAnalysis:
    """Fit decay times at ``t_cut_s`` (s), the line profile to 1/(c tau), and CMDS; compare.

    ``physical_bounds`` keeps Gamma2, nu_VC >= 0 in the CRDS line fit (see ``fit.line.fit_line``).
    The ring-down noise's colour is diagnosed and accounted for first
    (:func:`~bayes_tfcrds.fit.h_calibration.account_for_noise_colour`), unless ``noise`` gives
    the NoiseDiagnosis of a ``config`` already returned by it (many analyses of one config).

    Parameters
    ----------
    bundle : Bundle
        The measurement (its sample gives T, p, x and the Doppler width).
    config : Configuration
        The configuration analysed (``bundle.configs["D2"]``).
    method : str
        ``crds`` or ``tf-crds``.
    window : str
        ``extinction`` or ``letter`` (tf-crds).
    t_cut_s : float
        Truncation time (s) from laser extinction.
    profile_name : str
        Line profile (``qsdhcp``, ``sdvp``, ``voigt``, ...).
    calibration : Calibration, optional
        H for tf-crds (made here when not given).
    physical_bounds : bool
        Keep Gamma2, nu_VC >= 0 in the CRDS line fit.
    noise : NoiseDiagnosis, optional
        The noise colour of ``config`` if already diagnosed.
    tf : TFParams, optional
        The H at which tf-crds fits the decay times (default ``calibration.params``);
        :func:`~bayes_tfcrds.uncertainty.line_area.analyse_line_with_h` gives the centre of H's
        posterior and adds H's part of u(A).

    Returns
    -------
    LineAnalysis
        A (cm^-2 via ``.line_area``), A_ref, A/A_ref, the line fit with its residuals, the ring-down
        fits behind it; ``summary()``, ``to_dict()``, ``plot()``.
    """
    gd = doppler_of(bundle.sample)
    check_t_cuts(config, [t_cut_s])
    check_overlap(config)
    try:
        beat = None
        if noise is None:
            config, noise, beat = account_for_noise_colour(config, window)
        if method == "tf-crds" and calibration is None:
            calibration = calibrate(config, window=window, beat=beat)
        fits = fit_config(
            config, [t_cut_s], method=method, window=window, calibration=calibration, tf=tf
        )
    except AnalysisError as exc:
        raise LineFitError(str(exc)) from exc
    # a decay time whose fit did not converge is not a measurement: left out and counted
    kept = fits.converged_only()
    unconverged = kept.unconverged[:, 0]
    spec = crds_spectrum(kept.nu_hz, kept.tau_s[:, 0], kept.tau_u_s[:, 0])
    if spec.nu_hz.size < 8:
        raise LineFitError(
            f"only {spec.nu_hz.size} usable decay times in configuration {config.name!r}"
        )
    lf = fit_line([spec], profile_name, gd, bundle.sample.nu0_hz, physical_bounds=physical_bounds)
    sample = bundle.sample
    return LineAnalysis(
        configuration=config.name,
        method=method,
        window=window if method == "tf-crds" else None,
        t_cut_s=float(t_cut_s),
        profile=profile_name,
        line_fit=lf,
        reference_fit=fit_reference(bundle, config, profile_name),
        spectrum=spec,
        number_density_m3=float(
            number_density(sample.pressure_pa, sample.temperature_k, sample.mole_fraction)
        ),
        temperature_k=sample.temperature_k,
        n_points=int(spec.nu_hz.size),
        clipped_points=int(np.sum(fits.clipped)),
        unconverged_points=int(np.sum(unconverged)),
        # decays with less than two decay times of record after t_cut (offset and tau nearly
        # degenerate)
        record_short_points=int(
            sum(fits.status(i, 0) == "record-short" for i in range(fits.nu_hz.size))
        ),
        calibration=calibration,
        noise=noise,
        ringdown_fits=fits,
        h_params=tf if method == "tf-crds" else None,
    )


SPECTRUM_LEVEL = "spectrum-level input: no transfer-function rows"


def analyse_spectrum(
    spectrum, profile_name: str = "qsdhcp", physical_bounds: bool = False
) -> LineAnalysis:
    """Line fit of a spectrum a lab kept instead of ring-down records: tau(nu) or alpha(nu).

    ``spectrum`` has the fields of ``bundle.labfolder.LabSpectrum``: ``sample``, ``nu_hz`` (Hz),
    ``quantity`` (``tau`` in s or ``alpha`` in 1/m), ``values``, ``u`` (standard
    uncertainties, same unit) and ``source`` (the file). Decay times become 1/(c tau); alpha
    is fitted as given, the empty-cavity loss (or any constant) in the fitted baseline. No
    detection chain was modelled: the result says so (``input_note``), has no transfer-function
    entry and no t_cut, and its u(A) holds the fit only.
    """
    nu = np.asarray(spectrum.nu_hz, float)
    y, u = np.asarray(spectrum.values, float), np.asarray(spectrum.u, float)
    bad = ~(np.isfinite(nu) & np.isfinite(y) & np.isfinite(u) & (u > 0))
    if spectrum.quantity == "tau":
        bad |= ~(y > 0)
    if bad.any():
        i = int(np.argmax(bad))
        raise LineFitError(
            f"{spectrum.source}: row {i + 1} of the data (nu = {nu[i]:.12g} Hz) has "
            f"{spectrum.quantity} = {y[i]!r}, u = {u[i]!r}: values must be finite"
            + (" and > 0" if spectrum.quantity == "tau" else "")
            + " and uncertainties > 0; remove or fix the row"
        )
    label = f"{spectrum.quantity}(nu) from {spectrum.source}"
    try:
        if spectrum.quantity == "tau":
            spec = crds_spectrum(nu, y, u, label=label)
        else:
            check_repeats(nu, y, u, label)
            spec = SpectrumData("absorption", nu, y, u, label)
    except ValueError as exc:
        raise LineFitError(str(exc)) from exc
    if nu.size < 8:
        raise LineFitError(f"{spectrum.source}: only {nu.size} points; a line fit needs >= 8")
    sample = spectrum.sample
    lf = fit_line(
        [spec], profile_name, doppler_of(sample), sample.nu0_hz, physical_bounds=physical_bounds
    )
    return LineAnalysis(
        configuration=str(spectrum.source),
        method="spectrum",
        window=None,
        t_cut_s=None,
        profile=profile_name,
        line_fit=lf,
        reference_fit=None,
        spectrum=spec,
        number_density_m3=float(
            number_density(sample.pressure_pa, sample.temperature_k, sample.mole_fraction)
        ),
        temperature_k=sample.temperature_k,
        n_points=int(nu.size),
        clipped_points=0,
        unconverged_points=0,
        record_short_points=0,
        input_note=SPECTRUM_LEVEL,
    )
