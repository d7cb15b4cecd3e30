"""A short human-readable summary of a bundle, and ``bayes-tfcrds validate``'s report."""

from __future__ import annotations

import os

import numpy as np

from bayes_tfcrds.bundle.reader import validate_file
from bayes_tfcrds.bundle.records import FORMAT_NAME, FORMAT_VERSION, Bundle
from bayes_tfcrds.core.constants import TORR, hz_to_wavenumber_cm

# --------------------------------------------------------------------------- summary


def _printable(text: str) -> str:
    """Text attributes may hold anything: show control characters escaped, never act on them."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def _range(a: np.ndarray, unit: str) -> str:
    return f"{a.min():.12g} .. {a.max():.12g} {unit}"


def summarize(bundle: Bundle) -> str:
    """A human-readable summary of a bundle (SI units; nu0 also in cm^-1, p also in Torr)."""
    s, c = bundle.sample, bundle.cavity
    out = [f"{FORMAT_NAME}, format version {FORMAT_VERSION}"]
    if bundle.description:
        out.append(f"  description: {_printable(bundle.description)}")
    extra = f", mole fraction {s.mole_fraction:g}"
    if s.mass_u is not None:
        extra += f", mass {s.mass_u:g} u"
    out += [
        f"sample: {_printable(s.molecule)} {_printable(s.line)}, nu0 = {s.nu0_hz:.12g} Hz "
        f"({float(hz_to_wavenumber_cm(s.nu0_hz)):.6f} cm^-1)",
        f"  p = {s.pressure_pa:.6g} +/- {s.pressure_u_pa:.2g} Pa ({s.pressure_pa / TORR:.6g} "
        f"Torr), T = {s.temperature_k:.6g} +/- {s.temperature_u_k:.2g} K{extra}",
        f"cavity: FSR = {c.fsr_hz:.10g} Hz"
        + ("" if c.finesse is None else f", finesse = {c.finesse:.6g}"),
        f"configurations: {len(bundle.configs)}",
    ]
    for name, cfg in bundle.configs.items():
        rd = cfg.ringdowns
        head = f"  {_printable(name)}"
        out.append(head + (f": {_printable(cfg.description)}" if cfg.description else ""))
        out.append(
            f"    ringdowns: {rd.n_points} points x {rd.n_samples} samples, t0 = {rd.t0_s:.6g} s, "
            f"dt = {rd.dt_s:.6g} s, record length {rd.n_samples * rd.dt_s:.6g} s; nu "
            f"{_range(rd.nu_hz, 'Hz')}"
        )
        out.append(
            "      n_avg: "
            + ("absent" if rd.n_avg is None else f"{rd.n_avg.min()} .. {rd.n_avg.max()}")
            + "; noise_v: "
            + (
                "absent"
                if rd.noise_v is None
                else "per sample (m, k)"
                if rd.noise_v.ndim == 2
                else "per transient (m,)"
            )
        )
        saturated = np.flatnonzero(rd.saturated)
        if saturated.size:
            listed = ", ".join(
                f"#{i} (nu = {rd.nu_hz[i]:.12g} Hz, flat until {rd.saturation.end_s[i]:.3g} s)"
                for i in saturated
            )
            out.append(f"      SATURATED transients ({saturated.size}): {listed}")
        clipped = np.flatnonzero(rd.clipped & ~rd.saturated)
        if clipped.size:
            listed = ", ".join(f"#{i} (nu = {rd.nu_hz[i]:.12g} Hz)" for i in clipped)
            out.append(f"      CLIPPED transients ({clipped.size}): {listed}")
        tf = cfg.transfer_function
        out.append(
            "    transfer_function: absent"
            if tf is None
            else f"    transfer_function: {tf.f_hz.size} beat frequencies, f = "
            f"{_range(tf.f_hz, 'Hz')}" + ("" if tf.b12_u_v is None else ", with b12_u_v")
        )
        cm = cfg.cmds
        out.append(
            "    cmds: absent"
            if cm is None
            else f"    cmds: {cm.nu_hz.size} points, widths "
            + ("present" if cm.width_hz is not None else "absent")
        )
    return "\n".join(out)


def main_validate(path) -> int:
    """``bayes-tfcrds validate FILE``.

    Print the summary and warnings and return 0 for a good bundle; print every violation with its
    path and return 1 otherwise.
    """
    name = os.fspath(path)
    bundle, errors, warnings = validate_file(name)
    shown = _printable(name)  # paths inside the file and the file's name: escaped like the summary
    if errors:
        print(f"{shown}: REFUSED, {len(errors)} problem(s):")
        for v in errors:
            print(f"  error: {_printable(str(v))}")
    else:
        print(summarize(bundle))
    if warnings:
        print(f"{len(warnings)} warning(s):")
        for v in warnings:
            print(f"  warning: {_printable(str(v))}")
    if not errors:
        print(f"{shown}: OK")
    return 1 if errors else 0
