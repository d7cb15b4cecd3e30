"""Physical constants (CODATA 2018, exact where SI defines them) and edge-unit conversions.

Everything inside the package is SI. Spectroscopic units (cm^-1, cm^-2, cm/molecule) are
produced only by the conversion helpers here, at the edges (reports, CLI output).
"""

from __future__ import annotations

import numpy as np

C = 299_792_458.0  # speed of light, m/s (exact)
K_B = 1.380_649e-23  # Boltzmann constant, J/K (exact)
H_PLANCK = 6.626_070_15e-34  # Planck constant, J s (exact)
AMU = 1.660_539_066_60e-27  # unified atomic mass unit, kg
TORR = 101_325.0 / 760.0  # Pa per Torr
ATM = 101_325.0  # Pa per standard atmosphere


def number_density(pressure_pa, temperature_k, mole_fraction=1.0):
    """Absorber number density N = p x / (k_B T), in m^-3 (p in Pa, T in K)."""
    return np.asarray(pressure_pa) * mole_fraction / (K_B * np.asarray(temperature_k))


def hz_to_wavenumber_cm(nu_hz):
    """Optical frequency (Hz) to wavenumber (cm^-1)."""
    return np.asarray(nu_hz) / (C * 100.0)


def wavenumber_cm_to_hz(sigma_cm):
    """Wavenumber (cm^-1) to optical frequency (Hz)."""
    return np.asarray(sigma_cm) * C * 100.0


def line_area_to_cm2(area_si):
    """Integrated line area from SI (alpha in m^-1 integrated over Hz: Hz/m) to cm^-2.

    A[cm^-2] = integral of alpha[cm^-1] over wavenumber[cm^-1] = A_SI / (100 * 100 c).
    """
    return np.asarray(area_si) / (1.0e4 * C)


#: {SI unit inside: (the unit every output shows it in, factor SI -> that unit)}: the one
#: quantity computed in SI that spectroscopists quote otherwise, the line area (Hz/m -> cm^-2)
EDGE_UNITS = {"Hz/m": ("cm^-2", 1.0 / (1.0e4 * C))}


def edge_unit(unit: str) -> tuple[str, float]:
    """(unit shown in every output, factor from ``unit``) of an SI unit; others unchanged."""
    return EDGE_UNITS.get(unit, (unit, 1.0))


def edge_entry(value_si, u_si, unit_si: str) -> dict:
    """{value, u, unit} in the unit every output shows the quantity in.

    A line area in cm^-2, with its SI twin in ``value_si``, ``u_si``, ``unit_si``; any other
    quantity as it is (SI).
    """
    unit, f = edge_unit(unit_si)
    out = {"value": f * float(value_si), "u": f * float(u_si), "unit": unit}
    if unit != unit_si:
        out.update(value_si=float(value_si), u_si=float(u_si), unit_si=unit_si)
    return out


def edge_budget(budget):
    """A GUM budget (:class:`~bayes_tfcrds.core.gum.Budget`) as every output shows it.

    Its line-area rows and result (Hz/m inside) in cm^-2; every other quantity as it is.
    """
    return budget.in_units(EDGE_UNITS)


def edge_keys(record: dict) -> dict:
    """``record`` for an output: each SI line-area entry (a key with ``hz_per_m``) in cm^-2.

    The key says the unit, and changes with it: ``delta_a_hz_per_m`` becomes ``delta_a_cm2``
    (cm^-2), ``da_dt_hz_per_m_per_k`` ``da_dt_cm2_per_k``; its number (or each number of a dict
    under it) is converted, None stays None. Other entries are kept as they are.
    """
    f = EDGE_UNITS["Hz/m"][1]

    def shown(v):
        if isinstance(v, dict):
            return {k: shown(x) for k, x in v.items()}
        return None if v is None else f * float(v)

    return {
        k.replace("hz_per_m", "cm2") if "hz_per_m" in k else k: shown(v) if "hz_per_m" in k else v
        for k, v in record.items()
    }


def line_area_from_cm2(area_cm2):
    """Integrated line area from cm^-2 to SI (Hz/m)."""
    return np.asarray(area_cm2) * 1.0e4 * C


def intensity_to_cm_per_molecule(area_si, number_density_m3):
    """Line intensity S = A/N in cm/molecule, from A in Hz/m and N in m^-3."""
    return line_area_to_cm2(area_si) / (np.asarray(number_density_m3) * 1.0e-6)


def intensity_from_cm_per_molecule(s_cm, number_density_m3):
    """Line area A = S N in Hz/m, from S in cm/molecule and N in m^-3."""
    return line_area_from_cm2(np.asarray(s_cm) * np.asarray(number_density_m3) * 1.0e-6)
