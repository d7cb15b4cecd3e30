"""Spectra from fitted decay times, CMDS mode shifts and CMWS mode widths.

Absorption in 1/m from 1/(c tau) or 4 pi Gamma / c; dispersion as mode shifts in Hz.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from bayes_tfcrds.core.constants import C

REPEAT_P_MIN = 1e-6  # repeats at one frequency whose chi2 is less probable than this disagree
REPEAT_TOL_HZ = 1.0  # frequencies closer than this are one cavity mode measured again


class RepeatError(ValueError):
    """Points at one frequency (a repeated measurement) that disagree beyond their uncertainty."""


def check_repeats(nu_hz, y, u, label: str = "") -> None:
    """Refuse repeated frequencies whose values disagree; accept consistent repeats.

    Labs repeat modes, and the line fit treats each repeat as an independent point, which is the
    right combination when they agree. When they do not (chi2 of the group about its weighted
    mean below probability REPEAT_P_MIN), a frequency was mislabelled or a record copied: the
    indices and values are named.
    """
    nu = np.asarray(nu_hz, float)
    if nu.size < 2 or u is None:
        return
    order = np.argsort(nu, kind="stable")
    new_group = np.diff(nu[order]) > REPEAT_TOL_HZ
    starts = np.concatenate([[0], np.nonzero(new_group)[0] + 1])
    ends = np.concatenate([starts[1:], [nu.size]])
    y, u = np.asarray(y, float), np.asarray(u, float)
    usable = np.isfinite(y) & np.isfinite(u) & (u > 0)
    for a, b in zip(starts, ends):
        idx = order[a:b][usable[order[a:b]]]
        if idx.size < 2:
            continue
        w = 1.0 / u[idx] ** 2
        mean = np.sum(w * y[idx]) / np.sum(w)
        chi2 = float(np.sum(w * (y[idx] - mean) ** 2))
        p = float(stats.chi2.sf(chi2, idx.size - 1))
        if not p >= REPEAT_P_MIN:
            values = ", ".join(f"[{i}] {y[i]:.6g} +/- {u[i]:.2g}" for i in idx)
            raise RepeatError(
                f"{label or 'spectrum'}: {idx.size} points at nu = {nu[idx[0]]:.6f} Hz "
                f"(indices {', '.join(map(str, idx))}) disagree: {values}; chi2 = {chi2:.3g} for "
                f"{idx.size - 1} dof (p = {p:.2g}). A repeated measurement must agree within its "
                "uncertainty: check nu_hz of those records"
            )


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

    def __post_init__(self):
        check_repeats(self.nu_hz, self.y, self.u, self.label)


def crds_spectrum(nu_hz, tau_s, tau_u_s, label="CRDS") -> SpectrumData:
    """Absorption spectrum 1/(c tau) (1/m) from fitted decay times; NaN fits are dropped.

    Repeated frequencies must agree (:func:`check_repeats`, indices are the records').
    """
    check_repeats(nu_hz, tau_s, tau_u_s, f"{label} decay times (ring-down records)")
    ok = np.isfinite(tau_s) & np.isfinite(tau_u_s) & (np.asarray(tau_u_s) > 0)
    a, u = absorption_from_tau(np.asarray(tau_s)[ok], np.asarray(tau_u_s)[ok])
    return SpectrumData("absorption", np.asarray(nu_hz, float)[ok], a, u, label)


def cmds_spectrum(cmds, label="CMDS") -> SpectrumData:
    """Dispersion spectrum (mode shifts, Hz) from a bundle's CMDS group (repeats must agree)."""
    return SpectrumData(
        "dispersion",
        np.asarray(cmds.nu_hz, float),
        np.asarray(cmds.shift_hz, float),
        np.asarray(cmds.shift_u_hz, float),
        f"{label} mode shifts (/cmds)" if label == "CMDS" else label,
    )


def cmws_spectrum(cmds, label="CMWS") -> SpectrumData | None:
    """Absorption spectrum 4 pi Gamma / c (1/m) from CMDS mode widths, if present."""
    if cmds.width_hz is None or cmds.width_u_hz is None:
        return None
    a, u = absorption_from_width(cmds.width_hz, cmds.width_u_hz)
    return SpectrumData("absorption", np.asarray(cmds.nu_hz, float), a, u, label)
