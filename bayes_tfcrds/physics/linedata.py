"""Spectroscopic line parameters shipped with the package, converted to SI on loading.

The data files (bayes_tfcrds/data/*.toml) keep the spectroscopic units of their sources in
the key names (cm^-1, cm^-1/atm, cm/molecule) and cite a source for every number; this
module is the one place where they become SI (Hz, Hz/Pa, J). The line intensity stays in
cm/molecule, the only edge-unit field, because that is the unit in which it is reported
and compared (constants.intensity_from_cm_per_molecule converts it to an area). It is given
at the reference temperature temperature_k; :meth:`LineData.intensity_ratio` converts it to
any other T (physics.intensity: Q(T) from TIPS-2021, E'', stimulated emission).
"""

from __future__ import annotations

import functools
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass
from importlib import resources
from types import MappingProxyType

import numpy as np

from bayes_tfcrds.core.constants import (
    ATM,
    H_PLANCK,
    C,
    intensity_to_cm_per_molecule,
    number_density,
)
from bayes_tfcrds.physics import intensity
from bayes_tfcrds.physics.lineshape import doppler_hwhm_hz

__all__ = ["Source", "LineData", "load_line", "available_lines"]

_HZ_PER_CM = 100.0 * C  # 1 cm^-1 in Hz
_HZ_PER_PA_PER_CM_PER_ATM = _HZ_PER_CM / ATM
_J_PER_CM = H_PLANCK * _HZ_PER_CM  # an energy of 1 cm^-1 in J

# numeric keys every line file must define (each also needs a [sources] entry)
_REQUIRED = (
    "temperature_k",
    "mass_u",
    "nu0_cm",
    "nu0_u_cm",
    "lower_state_energy_cm",
    "intensity_cm_per_molecule",
    "intensity_u_cm_per_molecule",
    "gamma0_self_cm_per_atm",
    "delta0_self_cm_per_atm",
    "nu_vc_self_cm_per_atm",
    "gamma0_air_cm_per_atm",
    "n_gamma0_air",
    "delta0_air_cm_per_atm",
    "nu_vc_air_cm_per_atm",
    "gamma2_ratio",
    "delta2_ratio",
)


@dataclass(frozen=True)
class Source:
    """Where a number comes from; estimate = True means it is not a measurement of the line."""

    reference: str
    estimate: bool


@dataclass(frozen=True)
class LineData:
    """One line's parameters in SI at the reference temperature temperature_k (K).

    Pressure coefficients are per pascal of the perturber: *_hz_per_pa without a suffix are
    self (absorber-absorber) values, *_air_* are for an air/N2 buffer. HWHM and shifts in
    Hz/Pa; gamma2_ratio = Gamma2/Gamma0, delta2_ratio = Delta2/Delta0 (dimensionless);
    n_gamma0_air is the temperature exponent of the air width. intensity_* in cm/molecule at
    temperature_k (HITRAN's T_ref); lower_state_energy_j is E'' (J), which with the partition
    function of ``isotopologue`` (e.g. "12C16O") gives the intensity at other temperatures.
    """

    name: str
    isotopologue: str
    nu0_hz: float
    nu0_u_hz: float
    lower_state_energy_j: float
    intensity_cm_per_molecule: float
    intensity_u_cm_per_molecule: float
    gamma0_hz_per_pa: float
    delta0_hz_per_pa: float
    nu_vc_hz_per_pa: float
    gamma0_air_hz_per_pa: float
    n_gamma0_air: float
    delta0_air_hz_per_pa: float
    nu_vc_air_hz_per_pa: float
    gamma2_ratio: float
    delta2_ratio: float
    mass_u: float
    temperature_k: float
    sources: Mapping[str, Source]

    @property
    def estimates(self) -> tuple[str, ...]:
        """Keys of the data file whose values are estimates rather than measurements."""
        return tuple(k for k, s in self.sources.items() if s.estimate)

    def doppler_hwhm_hz(self, temperature_k):
        """Doppler HWHM (Hz) of this line at temperature_k (K)."""
        return doppler_hwhm_hz(self.nu0_hz, temperature_k, self.mass_u)

    def intensity_ratio(self, temperature_k):
        """S(T)/S(T_ref), dimensionless, T in K (T_ref = temperature_k of the data).

        Q(T_ref)/Q(T) exp(-E''/k_B (1/T - 1/T_ref)) times the stimulated-emission ratio
        (physics.intensity.intensity_ratio); refuses T outside the partition-function table.
        """
        return intensity.intensity_ratio(
            temperature_k,
            self.temperature_k,
            self.nu0_hz,
            self.lower_state_energy_j,
            self.isotopologue,
        )

    def intensity_cm_per_molecule_at(self, temperature_k):
        """The line intensity S(T) in cm/molecule at temperature_k (K)."""
        return self.intensity_cm_per_molecule * self.intensity_ratio(temperature_k)

    def intensity_log_derivative(self, temperature_k):
        """d ln S(T)/dT in 1/K at temperature_k (K), S(T_ref) held fixed.

        -d ln Q/dT + E''/(k_B T^2) minus the stimulated-emission term: +0.014 /K for the
        CO (3-0) R(23) line at 296 K, whose E'' = 1059 cm^-1 is five times k_B T.
        """
        return intensity.intensity_log_derivative(
            temperature_k, self.nu0_hz, self.lower_state_energy_j, self.isotopologue
        )

    def reference_intensity_from_area(
        self, area_hz_per_m, pressure_pa, temperature_k, mole_fraction=1.0
    ):
        """S(T_ref) in cm/molecule from a measured line area, the measurement model of a budget.

        area_hz_per_m: A (Hz/m) measured at pressure_pa (Pa), temperature_k (K) and absorber
        mole_fraction; S(T) = A/N with N = p x/(k_B T), then S(T_ref) = S(T)/intensity_ratio(T):
        A k_B T/(p x) Q(T)/Q(T_ref) exp(E''/k_B (1/T - 1/T_ref)) times the stimulated-emission
        ratio. T_ref is temperature_k of the line data (296 K).
        """
        n = number_density(pressure_pa, temperature_k, mole_fraction)
        s_t = intensity_to_cm_per_molecule(area_hz_per_m, n)
        return s_t / self.intensity_ratio(temperature_k)

    def shape_at(self, pressure_pa, temperature_k, mole_fraction=1.0) -> dict:
        """Collisional shape parameters (HWHM, shifts, rates in Hz) for lineshape.profile.

        pressure_pa: total pressure (Pa); temperature_k: gas temperature (K);
        mole_fraction: absorber fraction, the rest being air. Each coefficient is the
        mole-fraction-weighted self/air mixture times the pressure. Only the air width has
        a temperature exponent in the data, (T_ref/T)^n_air; the self coefficients, shifts
        and nu_VC are used at their reference-temperature values. Gamma2 and Delta2 follow
        from the ratios. Returns a dict keyed like lineshape.SHAPE_PARAMETERS.
        """
        p = np.asarray(pressure_pa, dtype=float)
        t = np.asarray(temperature_k, dtype=float)
        x = np.asarray(mole_fraction, dtype=float)
        if np.any(p < 0) or np.any(t <= 0) or np.any((x < 0) | (x > 1)):
            raise ValueError("need pressure_pa >= 0, temperature_k > 0, 0 <= mole_fraction <= 1")
        air_width = self.gamma0_air_hz_per_pa * (self.temperature_k / t) ** self.n_gamma0_air
        gamma0 = p * (x * self.gamma0_hz_per_pa + (1.0 - x) * air_width)
        delta0 = p * (x * self.delta0_hz_per_pa + (1.0 - x) * self.delta0_air_hz_per_pa)
        nu_vc = p * (x * self.nu_vc_hz_per_pa + (1.0 - x) * self.nu_vc_air_hz_per_pa)
        shape = {
            "gamma0_hz": gamma0,
            "gamma2_hz": self.gamma2_ratio * gamma0,
            "delta0_hz": delta0,
            "delta2_hz": self.delta2_ratio * delta0,
            "nu_vc_hz": nu_vc,
        }
        return {k: (float(v) if np.ndim(v) == 0 else v) for k, v in shape.items()}


def _parse(text: str, origin: str) -> LineData:
    """Build LineData from one TOML document, checking every number has a cited source."""
    raw = tomllib.loads(text)
    missing = [k for k in ("name", "molecule", *_REQUIRED) if k not in raw]
    if missing:
        raise ValueError(f"{origin}: missing keys {missing}")
    cited = raw.get("sources", {})
    if raw.get("schema") != 1:
        raise ValueError(f"{origin}: unsupported schema {raw.get('schema')!r}")
    numeric = [
        k
        for k, v in raw.items()
        if isinstance(v, (int, float)) and not isinstance(v, bool) and k != "schema"
    ]
    uncited = [k for k in numeric if k not in cited]
    if uncited:
        raise ValueError(f"{origin}: no [sources] entry for {uncited}")
    sources = {}
    for key, entry in cited.items():
        if not isinstance(entry.get("reference"), str) or not isinstance(
            entry.get("estimate"), bool
        ):
            raise ValueError(
                f"{origin}: sources.{key} needs a 'reference' string and an 'estimate' boolean"
            )
        sources[key] = Source(entry["reference"], entry["estimate"])
    per_pa = _HZ_PER_PA_PER_CM_PER_ATM
    return LineData(
        name=raw["name"],
        isotopologue=str(raw["molecule"]),
        nu0_hz=raw["nu0_cm"] * _HZ_PER_CM,
        nu0_u_hz=raw["nu0_u_cm"] * _HZ_PER_CM,
        lower_state_energy_j=raw["lower_state_energy_cm"] * _J_PER_CM,
        intensity_cm_per_molecule=float(raw["intensity_cm_per_molecule"]),
        intensity_u_cm_per_molecule=float(raw["intensity_u_cm_per_molecule"]),
        gamma0_hz_per_pa=raw["gamma0_self_cm_per_atm"] * per_pa,
        delta0_hz_per_pa=raw["delta0_self_cm_per_atm"] * per_pa,
        nu_vc_hz_per_pa=raw["nu_vc_self_cm_per_atm"] * per_pa,
        gamma0_air_hz_per_pa=raw["gamma0_air_cm_per_atm"] * per_pa,
        n_gamma0_air=float(raw["n_gamma0_air"]),
        delta0_air_hz_per_pa=raw["delta0_air_cm_per_atm"] * per_pa,
        nu_vc_air_hz_per_pa=raw["nu_vc_air_cm_per_atm"] * per_pa,
        gamma2_ratio=float(raw["gamma2_ratio"]),
        delta2_ratio=float(raw["delta2_ratio"]),
        mass_u=float(raw["mass_u"]),
        temperature_k=float(raw["temperature_k"]),
        sources=MappingProxyType(sources),
    )


@functools.cache
def _catalogue() -> dict:
    """All line files in bayes_tfcrds/data, keyed by their 'name'."""
    lines = {}
    for entry in sorted(
        resources.files("bayes_tfcrds").joinpath("data").iterdir(), key=lambda e: e.name
    ):
        if entry.name.endswith(".toml"):
            line = _parse(entry.read_text(encoding="utf-8"), entry.name)
            lines[line.name] = line
    return lines


def available_lines() -> tuple[str, ...]:
    """Names accepted by load_line."""
    return tuple(_catalogue())


def load_line(name: str = "CO (3-0) R(23)") -> LineData:
    """Parameters of the named line (see available_lines), SI except the intensity."""
    try:
        return _catalogue()[name]
    except KeyError:
        raise ValueError(f"unknown line {name!r}; available: {available_lines()}") from None
