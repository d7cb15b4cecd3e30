"""Spectra from fitted decay times, CMDS mode shifts and CMWS mode widths.

Absorption in 1/m from 1/(c tau) or 4 pi Gamma / c; dispersion as mode shifts in Hz.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bayes_tfcrds.core.constants import C


def absorption_from_tau(tau_s, tau_u_s=None):
    """Total loss 1/(c tau) (1/m) and its standard uncertainty tau_u/(c tau^2) (1/m)."""
    tau = np.asarray(tau_s, float)
    alpha = 1.0 / (C * tau)
    if tau_u_s is None:
        return alpha, None
    return alpha, np.asarray(tau_u_s, float) / (C * tau**2)


def absorption_from_width(width_hz, width_u_hz=None):
    """Total loss 4 pi Gamma / c (1/m) from mode half widths Gamma (Hz) (CMWS)."""
    a = 4 * np.pi * np.asarray(width_hz, float) / C
    return a, (None if width_u_hz is None else 4 * np.pi * np.asarray(width_u_hz, float) / C)


@dataclass(frozen=True)
class SpectrumData:
    """One spectrum to fit.

    ``kind`` is ``absorption`` (y = 1/(c tau) or 4 pi Gamma/c, 1/m) or ``dispersion`` (y = mode
    shift, Hz); ``nu_hz`` absolute frequencies, ``u`` standard uncertainties in y's unit.
    """

    kind: str
    nu_hz: np.ndarray
    y: np.ndarray
    u: np.ndarray
    label: str = ""


def crds_spectrum(nu_hz, tau_s, tau_u_s, label="CRDS") -> SpectrumData:
    """Absorption spectrum 1/(c tau) (1/m) from fitted decay times; NaN fits are dropped."""
    ok = np.isfinite(tau_s) & np.isfinite(tau_u_s) & (np.asarray(tau_u_s) > 0)
    a, u = absorption_from_tau(np.asarray(tau_s)[ok], np.asarray(tau_u_s)[ok])
    return SpectrumData("absorption", np.asarray(nu_hz, float)[ok], a, u, label)


def cmds_spectrum(cmds, label="CMDS") -> SpectrumData:
    """Dispersion spectrum (mode shifts, Hz) from a bundle's CMDS group."""
    return SpectrumData(
        "dispersion",
        np.asarray(cmds.nu_hz, float),
        np.asarray(cmds.shift_hz, float),
        np.asarray(cmds.shift_u_hz, float),
        label,
    )


def cmws_spectrum(cmds, label="CMWS") -> SpectrumData | None:
    """Absorption spectrum 4 pi Gamma / c (1/m) from CMDS mode widths, if present."""
    if cmds.width_hz is None or cmds.width_u_hz is None:
        return None
    a, u = absorption_from_width(cmds.width_hz, cmds.width_u_hz)
    return SpectrumData("absorption", np.asarray(cmds.nu_hz, float), a, u, label)
