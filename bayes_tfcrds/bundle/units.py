"""Lab units at the import edge: a value and its unit name -> SI (Hz, s, V, Pa, K, m).

Labs keep ring-downs in microseconds and millivolts, beat notes in MHz, pressures in Torr and
line positions in cm^-1; a bundle holds SI only. Each quantity kind has its own table, so
"cm^-1" is a frequency (wavenumber x 100 c) for a line position and an absorption coefficient
(x 100 1/m) for alpha. Temperatures in degC are offset for absolute values only: an
uncertainty (a difference) in degC equals the one in K.
"""

from __future__ import annotations

from bayes_tfcrds.core.constants import ATM, TORR
from bayes_tfcrds.core.constants import C as C_M_PER_S

#: unit name -> factor to SI, per quantity kind (aliases: "us" and "µs", "1/cm" and "cm^-1")
UNITS: dict[str, dict[str, float]] = {
    "time": {"s": 1.0, "ms": 1e-3, "us": 1e-6, "µs": 1e-6, "ns": 1e-9, "ps": 1e-12},
    "frequency": {
        "Hz": 1.0,
        "kHz": 1e3,
        "MHz": 1e6,
        "GHz": 1e9,
        "THz": 1e12,
        "cm^-1": 100.0 * C_M_PER_S,  # wavenumber -> frequency: x 100 c
        "1/cm": 100.0 * C_M_PER_S,
    },
    "voltage": {"V": 1.0, "mV": 1e-3, "uV": 1e-6, "µV": 1e-6},
    "pressure": {
        "Pa": 1.0,
        "hPa": 100.0,
        "kPa": 1e3,
        "mbar": 100.0,
        "bar": 1e5,
        "Torr": TORR,
        "mTorr": TORR * 1e-3,
        "atm": ATM,
    },
    "temperature": {"K": 1.0, "degC": 1.0, "°C": 1.0},
    "length": {"m": 1.0, "cm": 1e-2, "mm": 1e-3},
    "fraction": {"1": 1.0, "%": 1e-2, "ppm": 1e-6, "ppb": 1e-9},
    "mass": {"u": 1.0},
    "absorption": {"1/m": 1.0, "m^-1": 1.0, "1/cm": 100.0, "cm^-1": 100.0},
    "count": {"1": 1.0},
}
#: the SI unit a bare number (no unit) is read in, per kind
SI_UNIT = {
    "time": "s",
    "frequency": "Hz",
    "voltage": "V",
    "pressure": "Pa",
    "temperature": "K",
    "length": "m",
    "fraction": "1",
    "mass": "u",
    "absorption": "1/m",
    "count": "1",
}
_CELSIUS = ("degC", "°C")
ZERO_CELSIUS_K = 273.15


class UnitError(ValueError):
    """A unit name that is not known for the quantity (the message lists the known ones)."""


def factor(unit: str | None, kind: str) -> float:
    """Factor from ``unit`` to SI for quantities of ``kind`` (None: the SI unit itself)."""
    table = UNITS[kind]
    name = SI_UNIT[kind] if unit is None else str(unit).strip()
    if name not in table:
        raise UnitError(
            f"unknown {kind} unit {name!r}; known: {', '.join(table)} (SI {SI_UNIT[kind]})"
        )
    return table[name]


def offset(unit: str | None, kind: str, difference: bool = False) -> float:
    """Additive offset to SI after scaling: 273.15 K for an absolute temperature in degC."""
    if kind == "temperature" and not difference and unit is not None and unit in _CELSIUS:
        return ZERO_CELSIUS_K
    return 0.0


def to_si(values, unit: str | None, kind: str, difference: bool = False):
    """``values`` (number or numpy array) in ``unit`` -> SI; ``difference`` for uncertainties."""
    f, o = factor(unit, kind), offset(unit, kind, difference)
    return values * f + o if o else values * f


def from_si(values, unit: str | None, kind: str, difference: bool = False):
    """SI ``values`` -> ``unit`` (the inverse of :func:`to_si`; used to write lab folders)."""
    f, o = factor(unit, kind), offset(unit, kind, difference)
    return (values - o) / f if o else values / f
