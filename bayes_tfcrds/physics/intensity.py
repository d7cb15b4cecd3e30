"""Temperature dependence of a line intensity: the partition function Q(T) and S(T) <-> S(T_ref).

A line intensity is quoted at a reference temperature (HITRAN's T_ref = 296 K) but measured at
the sample's T. In the HITRAN convention (Simeckova et al., JQSRT 98, 130 (2006), Eq. 11; the
formula of hitran-api's ``EnvironmentDependency_Intensity``)

    S(T) = S(T_ref) Q(T_ref)/Q(T) exp(-E''/(k_B T)) / exp(-E''/(k_B T_ref))
           [1 - exp(-h nu0/(k_B T))] / [1 - exp(-h nu0/(k_B T_ref))]

with Q the total internal partition sum, E'' the lower-state energy and nu0 the line position.
In spectroscopic units E''/(k_B T) = c2 E''[cm^-1]/T with c2 = hc/k_B = 1.4387769 cm K.

SI inside: E'' in J, nu0 in Hz, T in K; Q is dimensionless. The intensity itself is only ever
scaled by these dimensionless factors, so it keeps whatever unit the caller holds it in.

Q(T) is interpolated in a shipped table (bayes_tfcrds/data/tips2021_<isotopologue>.csv, TIPS-2021,
Gamache et al., JQSRT 271, 107713 (2021)) by a cubic spline in ln Q against ln T, which is
nearly linear for a rotor (Q ~ k_B T/(h c B)); temperatures outside the table are refused, never
extrapolated.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from importlib import resources

import numpy as np
from scipy.interpolate import CubicSpline

from bayes_tfcrds.core.constants import H_PLANCK, K_B

__all__ = [
    "PartitionTable",
    "partition_table",
    "partition_function",
    "intensity_ratio",
    "intensity_log_derivative",
]


@dataclass(frozen=True)
class PartitionTable:
    """Total internal partition sum Q(T) of one isotopologue, tabulated by a cited source.

    isotopologue: e.g. "12C16O"; temperature_k: the table's nodes (K, increasing);
    q: Q at the nodes (dimensionless, HITRAN convention); source: the citation of the values.
    Calling the table interpolates Q; outside [t_min_k, t_max_k] it raises ValueError, because a
    partition sum extrapolated past its table is not a measurement model anyone can cite.
    """

    isotopologue: str
    temperature_k: np.ndarray
    q: np.ndarray
    source: str
    _spline: CubicSpline = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        t = np.array(self.temperature_k, dtype=float)
        q = np.array(self.q, dtype=float)
        if t.ndim != 1 or t.shape != q.shape or t.size < 4:
            raise ValueError(f"{self.isotopologue}: need >= 4 (T, Q) nodes of equal length")
        if not (np.all(np.diff(t) > 0) and t[0] > 0 and np.all(q > 0)):
            raise ValueError(f"{self.isotopologue}: need increasing T > 0 and Q > 0")
        t.flags.writeable = q.flags.writeable = False
        object.__setattr__(self, "temperature_k", t)
        object.__setattr__(self, "q", q)
        object.__setattr__(self, "_spline", CubicSpline(np.log(t), np.log(q)))

    @property
    def t_min_k(self) -> float:
        """Lowest tabulated temperature (K)."""
        return float(self.temperature_k[0])

    @property
    def t_max_k(self) -> float:
        """Highest tabulated temperature (K)."""
        return float(self.temperature_k[-1])

    def _log_t(self, temperature_k) -> np.ndarray:
        """ln T, after refusing any T outside the table (or not finite)."""
        t = np.asarray(temperature_k, dtype=float)
        if not np.all((t >= self.t_min_k) & (t <= self.t_max_k)):
            raise ValueError(
                f"Q({self.isotopologue}) is tabulated for {self.t_min_k:g}-{self.t_max_k:g} K "
                f"only; got T = {t} K (a partition sum is never extrapolated)"
            )
        return np.log(t)

    def __call__(self, temperature_k):
        """Q(T), dimensionless; T in K (broadcasts)."""
        return _scalar(np.exp(self._spline(self._log_t(temperature_k))))

    def log_derivative(self, temperature_k):
        """d ln Q/dT in 1/K (the spline's d ln Q/d ln T over T); T in K (broadcasts)."""
        log_t = self._log_t(temperature_k)
        return _scalar(self._spline(log_t, 1) / np.exp(log_t))


def _scalar(x):
    """A 0-d result as float, arrays unchanged."""
    return float(x) if np.ndim(x) == 0 else x


@functools.cache
def partition_table(isotopologue: str = "12C16O") -> PartitionTable:
    """The shipped TIPS-2021 table of ``isotopologue`` (data/tips2021_<isotopologue>.csv)."""
    name = f"tips2021_{isotopologue}.csv"
    entry = resources.files("bayes_tfcrds").joinpath("data", name)
    if not entry.is_file():
        raise ValueError(f"no partition-function table for {isotopologue!r} ({name})")
    lines = entry.read_text(encoding="utf-8").splitlines()
    source = " ".join(ln[1:].strip() for ln in lines if ln.startswith("#"))
    header, *rows = [ln for ln in lines if ln.strip() and not ln.startswith("#")]
    if header.replace(" ", "") != "temperature_k,q":
        raise ValueError(f"{name}: expected the columns 'temperature_k,q', got {header!r}")
    data = np.array([[float(v) for v in row.split(",")] for row in rows])
    return PartitionTable(isotopologue, data[:, 0], data[:, 1], source)


def partition_function(temperature_k, isotopologue: str = "12C16O"):
    """Total internal partition sum Q(T) (dimensionless) from TIPS-2021; T in K (broadcasts)."""
    return partition_table(isotopologue)(temperature_k)


def _stimulated_emission(nu0_hz, temperature_k):
    """1 - exp(-h nu0/(k_B T)), dimensionless: the fraction of absorption not undone by emission."""
    return -np.expm1(-H_PLANCK * np.asarray(nu0_hz, float) / (K_B * np.asarray(temperature_k)))


def intensity_ratio(
    temperature_k, t_ref_k, nu0_hz, lower_state_energy_j, isotopologue: str = "12C16O"
):
    """S(T)/S(T_ref), dimensionless: the HITRAN temperature conversion of a line intensity.

    temperature_k, t_ref_k: T and T_ref (K, inside the partition table); nu0_hz: line position
    (Hz); lower_state_energy_j: E'' (J). The product of the partition-sum ratio Q(T_ref)/Q(T),
    the Boltzmann factor of the lower state exp(-E''/k_B (1/T - 1/T_ref)) and the
    stimulated-emission ratio. Multiply S(T_ref) by it for S(T); divide S(T) by it for S(T_ref).
    """
    t = np.asarray(temperature_k, dtype=float)
    t_ref = np.asarray(t_ref_k, dtype=float)
    q = partition_table(isotopologue)
    boltzmann = np.exp(-np.asarray(lower_state_energy_j, float) / K_B * (1.0 / t - 1.0 / t_ref))
    emission = _stimulated_emission(nu0_hz, t) / _stimulated_emission(nu0_hz, t_ref)
    return _scalar(q(t_ref) / q(t) * boltzmann * emission)


def intensity_log_derivative(
    temperature_k, nu0_hz, lower_state_energy_j, isotopologue: str = "12C16O"
):
    """d ln S(T)/dT at fixed S(T_ref), in 1/K.

    = -d ln Q/dT + E''/(k_B T^2) - (h nu0/(k_B T^2)) / (exp(h nu0/(k_B T)) - 1): the analytic
    derivative of :func:`intensity_ratio`. The sensitivity of an intensity referred to T_ref to
    the measured T is minus this (plus the 1/T of the number density in S = A/N).
    """
    t = np.asarray(temperature_k, dtype=float)
    x = H_PLANCK * np.asarray(nu0_hz, float) / (K_B * t)
    d_q = partition_table(isotopologue).log_derivative(t)
    d_boltzmann = np.asarray(lower_state_energy_j, float) / (K_B * t * t)
    d_emission = x / t / np.expm1(x)
    return _scalar(-d_q + d_boltzmann - d_emission)
