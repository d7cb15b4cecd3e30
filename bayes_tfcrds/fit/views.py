"""Notebook views of the fit results: plain text, JSON-ready dicts, HTML tables and figures.

Rendering only: every number comes from the result object (``RingdownFits``, ``Calibration``,
``LineFit``, ``LineAnalysis``), whose ``summary()``, ``to_dict()``, ``_repr_html_()`` and
``plot()`` call these functions. SI inside; time axes in µs, spectra in cm^-1 (absorption) or
kHz (CMDS mode shifts) and detuning in GHz, every axis labelled with its unit.
"""

from __future__ import annotations

import math

import numpy as np

from bayes_tfcrds.core.constants import edge_entry, line_area_to_cm2
from bayes_tfcrds.output.notebook import (
    LEGEND_ABOVE,
    data_and_residual_axes,
    fmt,
    html_table,
    new_figure,
    text_table,
)
from bayes_tfcrds.output.plotting import house_style
from bayes_tfcrds.physics.transfer_function import PARAM_NAMES, transfer_function

H_UNITS = {"f_c_hz": "Hz", "a_r": "1", "f_r_hz": "Hz", "gamma_r": "1", "n_r": "1", "scale": "1"}
SI_PREFIX = {-12: "p", -9: "n", -6: "µ", -3: "m", 0: "", 3: "k", 6: "M", 9: "G"}
POWER = {-12: "10⁻¹²", -9: "10⁻⁹", -6: "10⁻⁶", -3: "10⁻³", 0: "", 3: "10³", 6: "10⁶"}


def _json(x):
    """A float for JSON: NaN and inf become None."""
    x = float(x)
    return x if math.isfinite(x) else None


def _strict_entry(value, u, unit: str) -> dict:
    """:func:`~bayes_tfcrds.core.constants.edge_entry` with NaN and inf as None (JSON)."""
    return {
        k: _json(v) if isinstance(v, float) else v for k, v in edge_entry(value, u, unit).items()
    }


def _json_array(a):
    """Nested lists of floats, NaN as None (strict JSON)."""
    a = np.asarray(a, float)
    if a.ndim == 0:
        return _json(a)
    return [_json_array(r) for r in a]


def _exponent(values) -> int:
    """The power of 1000 that brings the largest finite |value| into [1, 1000)."""
    v = np.abs(np.asarray(values, float))
    v = v[np.isfinite(v) & (v > 0)]
    if v.size == 0:
        return 0
    return int(np.clip(3 * math.floor(math.log10(v.max()) / 3), -12, 6))


def _legend(ax, title: str) -> None:
    """One legend row above the data panel (off the data), ``title`` on the line above it."""
    ax.legend(
        ncols=3,
        frameon=False,
        title=title or None,
        title_fontsize="small",
        alignment="left",
        **LEGEND_ABOVE,
    )


# --------------------------------------------------------------------------- ring-down fits


def _status_counts(fits, j) -> dict:
    counts = {}
    for i in range(fits.nu_hz.size):
        s = fits.status(i, j)
        counts[s] = counts.get(s, 0) + 1
    return counts


def _ringdown_rows(fits) -> list:
    rows = []
    for j, tc in enumerate(fits.t_cut_s):
        tau = fits.tau_s[:, j]
        ok = np.isfinite(tau)
        rel = fits.tau_u_s[ok, j] / tau[ok]
        counts = _status_counts(fits, j)
        rows.append(
            [
                f"{tc * 1e6:g}",
                f"{np.nanmin(tau) * 1e6:.4g}-{np.nanmax(tau) * 1e6:.4g}" if ok.any() else "-",
                f"{np.median(rel) * 1e6:.3g}" if ok.any() else "-",
                fmt(np.nanmedian(fits.chi2_red[:, j]) if ok.any() else None, digits=4),
                ", ".join(f"{k} {v}" for k, v in sorted(counts.items())),
            ]
        )
    return rows


RINGDOWN_HEADER = ("t_cut (µs)", "tau (µs)", "median u(tau)/tau (ppm)", "median chi2_red", "status")


def _ringdown_head(fits) -> str:
    window = f", {fits.window} window" if fits.window else ""
    noise = "noise estimated from the residuals" if fits.noise_estimated else "stated noise"
    if fits.noise_kappa is not None:
        k = fits.kappa_per_point
        noise += (
            f", coloured: weighted with noise_v sqrt(kappa), kappa {np.min(k):.3g}-{np.max(k):.3g}"
            " (chi2_red at the stated noise)"
        )
    return f"{fits.method} fits{window}: {fits.nu_hz.size} transients, {noise}"


def ringdowns_text(fits) -> str:
    """Summary of :class:`~bayes_tfcrds.fit.ringdown.RingdownFits`, one row per t_cut."""
    return _ringdown_head(fits) + "\n" + text_table(RINGDOWN_HEADER, _ringdown_rows(fits))


def ringdowns_html(fits) -> str:
    """The summary of :func:`ringdowns_text` as an HTML table."""
    return html_table(RINGDOWN_HEADER, _ringdown_rows(fits), caption=_ringdown_head(fits))


def ringdowns_dict(fits) -> dict:
    """Every fit as JSON: arrays (points x t_cuts) with their units, NaN as null.

    ``tau_u`` is the standard uncertainty of tau, its noise and H parts in quadrature as in the
    CSV (:meth:`~bayes_tfcrds.fit.ringdown.RingdownFits.to_csv`); ``tau_u_noise`` the fit's own.
    """
    m, c = fits.tau_s.shape
    u_h = np.sqrt(fits.tau_u_total_s**2 - fits.tau_u_s**2)
    return {
        "method": fits.method,
        "window": fits.window,
        "noise_estimated": bool(fits.noise_estimated),
        "nu": {"values": _json_array(fits.nu_hz), "unit": "Hz"},
        "t_cut": {"values": _json_array(fits.t_cut_s), "unit": "s"},
        "tau": {"values": _json_array(fits.tau_s), "unit": "s"},
        "tau_u": {"values": _json_array(fits.tau_u_total_s), "unit": "s"},
        "tau_u_noise": {"values": _json_array(fits.tau_u_s), "unit": "s"},
        "tau_u_h": {"values": _json_array(u_h), "unit": "s"},
        "amplitude": {"values": _json_array(fits.amplitude_v), "unit": "V"},
        "offset": {"values": _json_array(fits.offset_v), "unit": "V"},
        "chi2_red": {"values": _json_array(fits.chi2_red), "unit": "1"},
        "noise_kappa": {"values": _json_array(fits.kappa_per_point), "unit": "1"},
        "status": [[fits.status(i, j) for j in range(c)] for i in range(m)],
    }


@house_style
def plot_ringdown(fits, i=None, j: int = 0, ax=None):
    """Transient ``i`` at t_cut index ``j``: data, fitted model and residuals against t (µs).

    ``i`` defaults to the fitted transient with the shortest decay time (the line centre, where
    the detection chain distorts most). Returns the Figure.
    """
    if i is None:
        i = int(np.nanargmin(np.where(np.isfinite(fits.tau_s[:, j]), fits.tau_s[:, j], np.inf)))
    tr = fits.trace(i, j)
    fig, ax_d, ax_r = data_and_residual_axes(ax)
    t_us = tr["time_s"] * 1e6
    ax_d.plot(t_us, tr["signal_v"] * 1e3, color="0.6", lw=0.8, label="data")
    ax_d.plot(t_us, tr["model_v"] * 1e3, color="C3", lw=1.2, label=f"{fits.method} fit")
    for a in (ax_d, ax_r):
        a.axvline(fits.t_cut_s[j] * 1e6, color="0.3", ls=":", lw=1)
    ax_d.set_ylabel("signal (mV)")
    _legend(
        ax_d,
        f"ν = {fits.nu_hz[i] / 1e12:.6f} THz, t_cut = {fits.t_cut_s[j] * 1e6:g} µs (dotted), "
        f"τ = {fits.tau_s[i, j] * 1e6:.5g} µs",
    )
    e = _exponent(tr["residual_v"]) if np.any(np.isfinite(tr["residual_v"])) else -3
    ax_r.plot(t_us, tr["residual_v"] / 10.0**e, color="C0", lw=0.6)
    ax_r.axhline(0, color="0.3", lw=0.6)
    ax_r.set_ylabel(f"residual ({SI_PREFIX[e]}V)")
    ax_r.set_xlabel("t (µs)")
    return fig


# --------------------------------------------------------------------------- H calibration


def _beat_values(beat) -> dict:
    err = beat.stderr
    out = {n: (float(getattr(beat.params, n)), err.get(n)) for n in PARAM_NAMES}
    out["scale"] = (float(beat.scale), err.get("scale"))
    return out


def _refined_values(refined) -> dict:
    if refined is None:
        return {}
    err = refined.stderr
    return {n: (float(getattr(refined.params, n)), err[n]) for n in refined.free}


def _calibration_rows(cal) -> list:
    beat, ref = _beat_values(cal.beat), _refined_values(cal.refined)
    z = (
        {}
        if cal.refined is None or cal.refined.z is None
        else dict(zip(cal.refined.free, cal.refined.z))
    )
    rows = []
    for n in (*PARAM_NAMES, "scale"):
        v, u = beat[n]
        rows.append(
            [
                n,
                fmt(v, u) if u is not None else f"{v:.6g} (held)",
                fmt(*ref[n]) if n in ref else "-",
                H_UNITS[n],
                fmt(z.get(n), digits=3),
            ]
        )
    return rows


CAL_HEADER = ("parameter", "beat note", "refined on ring-downs", "unit", "tension z")


def _calibration_head(cal) -> str:
    b = cal.beat
    head = (
        f"H calibration ({b.params.variant} Eq. 2): beat-note fit of {b.f_hz.size} frequencies, "
        f"chi2_red {b.chi2_red:.3g} ({b.dof} dof)"
    )
    r = cal.refined
    if r is not None:
        head += (
            f"; refined ({', '.join(r.free)}) on the ring-downs, chi2_red {r.chi2_red:.3g}, "
            f"{'converged' if r.converged else 'NOT converged'}"
        )
    return head


def calibration_text(cal) -> str:
    """Summary of a :class:`~bayes_tfcrds.fit.h_calibration.Calibration`."""
    return _calibration_head(cal) + "\n" + text_table(CAL_HEADER, _calibration_rows(cal))


def calibration_html(cal) -> str:
    """The summary of :func:`calibration_text` as an HTML table."""
    return html_table(CAL_HEADER, _calibration_rows(cal), caption=_calibration_head(cal))


def _entries(values: dict) -> dict:
    return {
        n: {"value": v, "u": None if u is None else _json(u), "unit": H_UNITS[n]}
        for n, (v, u) in values.items()
    }


def calibration_dict(cal) -> dict:
    """JSON-ready calibration: beat-note fit, refinement (with its tension), the H used."""
    b, r = cal.beat, cal.refined
    out = {
        "variant": b.params.variant,
        "beat_note": {
            "parameters": _entries(_beat_values(b)),
            "free": list(b.free),
            "chi2": _json(b.chi2),
            "dof": int(b.dof),
            "chi2_red": _json(b.chi2_red),
            "frequency_range": {
                "values": [_json(b.f_hz.min()), _json(b.f_hz.max())],
                "unit": "Hz",
            },
            "n_frequencies": int(b.f_hz.size),
        },
        "refined": None,
        "used": {
            n: {"value": float(getattr(cal.params, n)), "unit": H_UNITS[n]} for n in PARAM_NAMES
        },
    }
    if r is not None:
        c2, dof, p = r.tension_chi2
        out["refined"] = {
            "parameters": _entries(_refined_values(r)),
            "chi2": _json(r.chi2),
            "dof": int(r.dof),
            "chi2_red": _json(r.chi2_red),
            "converged": bool(r.converged),
            "composite_weight": _json(r.weight),
            "tension": {
                n: {k: (None if v is None else _json(v)) for k, v in d.items()}
                for n, d in r.tension().items()
            },
            "tension_chi2": _json(c2),
            "tension_dof": int(dof),
            "tension_p": _json(p),
        }
    return out


@house_style
def plot_calibration(cal, ax=None):
    """Measured |H| (beat note, with its u) and K |H(f)| fitted, and refined, against f (Hz).

    The refined H is drawn with the beat note's scale K, so the two curves differ only where the
    ring-downs moved H. Residuals are (data - fit)/u for a weighted beat note.
    """
    b = cal.beat
    fig, ax_d, ax_r = data_and_residual_axes(ax)
    f = np.asarray(b.f_hz, float)
    grid = np.geomspace(f.min(), f.max(), 400)
    u = np.asarray(b.h_mag_u, float)
    ax_d.errorbar(
        f,
        b.h_mag,
        yerr=u if np.all(np.isfinite(u)) else None,
        fmt="o",
        ms=3,
        capsize=2,
        color="0.3",
        label="beat note",
    )
    ax_d.plot(
        grid, b.scale * np.abs(transfer_function(grid, b.params)), color="C0", label="beat-note fit"
    )
    if cal.refined is not None:
        ax_d.plot(
            grid,
            b.scale * np.abs(transfer_function(grid, cal.refined.params)),
            color="C3",
            ls="--",
            label=f"refined ({', '.join(cal.refined.free)})",
        )
    ax_d.set_xscale("log")
    ax_d.set_ylabel("K |H(f)| (1)")
    _legend(ax_d, "")
    # TFFit.residuals are (model - data)/u: drawn as data - fit
    ax_r.plot(f, -np.asarray(b.residuals), "o", ms=3, color="C0")
    ax_r.axhline(0, color="0.3", lw=0.6)
    ax_r.set_ylabel("(data − fit)/u (1)" if b.weighted else "data − fit (1)")
    ax_r.set_xlabel("f (Hz)")
    return fig


# --------------------------------------------------------------------------- line fits


def parameter_unit(name: str, kind: str) -> str:
    """Unit of a line-fit parameter (SI): A in Hz/m, widths and positions in Hz."""
    if name == "line_area":
        return "Hz/m"
    if name.startswith("baseline"):
        return "1/m" if kind == "absorption" else "Hz"
    if name.startswith("slope"):
        return "1/(m Hz)" if kind == "absorption" else "1"
    return "Hz"


def _kind_of(lf, name: str) -> str:
    digits = name.removeprefix("baseline").removeprefix("slope")
    k = int(digits) if digits.isdigit() else 0
    return lf.spectra[k].kind if lf.spectra else "absorption"


def _line_rows(lf) -> list:
    rows = []
    for n in lf.names:
        flag = " (held at 0)" if n in lf.at_bound else " (< 0)" if n in lf.unphysical else ""
        rows.append([n, fmt(lf.value(n), lf.stderr(n)) + flag, parameter_unit(n, _kind_of(lf, n))])
    a, ua = lf.line_area_cm2()
    rows.append(["line_area (spectroscopic unit)", fmt(a, ua), "cm^-2"])
    return rows


def _line_head(lf) -> str:
    return (
        f"{lf.profile} fit to {len(lf.spectra)} spectrum(s): chi2_red {lf.chi2_red:.4g} "
        f"({lf.dof} dof), Doppler HWHM {lf.doppler_hwhm_hz / 1e6:.4g} MHz (fixed), "
        f"nu_ref {lf.nu_ref_hz:.1f} Hz" + ("; covariance scaled by chi2_red" if lf.scaled else "")
    )


LINE_HEADER = ("parameter", "value ± u", "unit")


def line_fit_text(lf) -> str:
    """Summary of a :class:`~bayes_tfcrds.fit.line.LineFit`: parameters with units."""
    return _line_head(lf) + "\n" + text_table(LINE_HEADER, _line_rows(lf))


def line_fit_html(lf) -> str:
    """The summary of :func:`line_fit_text` as an HTML table."""
    return html_table(LINE_HEADER, _line_rows(lf), caption=_line_head(lf))


def line_fit_dict(lf) -> dict:
    """JSON-ready line fit: parameters (value, u, unit), A in cm^-2, chi2, flags."""
    a, ua = lf.line_area_cm2()
    return {
        "profile": lf.profile,
        "parameters": {  # A in cm^-2 (SI twin in value_si, u_si), the rest in SI
            n: _strict_entry(lf.value(n), lf.stderr(n), parameter_unit(n, _kind_of(lf, n)))
            for n in lf.names
        },
        "line_area_cm2": {"value": _json(a), "u": _json(ua), "unit": "cm^-2"},
        "fixed": {n: {"value": _json(v), "unit": "Hz"} for n, v in lf.fixed.items()},
        "nu_ref": {"value": lf.nu_ref_hz, "unit": "Hz"},
        "doppler_hwhm": {"value": lf.doppler_hwhm_hz, "unit": "Hz"},
        "chi2": _json(lf.chi2),
        "dof": int(lf.dof),
        "chi2_red": _json(lf.chi2_red),
        "scaled": bool(lf.scaled),
        "at_bound": list(lf.at_bound),
        "unphysical": list(lf.unphysical),
        "spectra": [
            {"kind": s.kind, "label": s.label, "n_points": int(s.nu_hz.size)} for s in lf.spectra
        ],
    }


# y in the plotted unit per SI unit, and its name
_Y_UNITS = {"absorption": (1e-2, "cm⁻¹"), "dispersion": (1.0, "Hz")}


def _draw_spectrum(lf, k, ax_d, ax_r, title: str = "") -> None:
    """Spectrum ``k`` of a line fit with error bars, the fitted model and data - fit."""
    s = lf.spectra[k]
    to_unit, unit = _Y_UNITS[s.kind]
    x = (np.asarray(s.nu_hz) - lf.nu_ref_hz) / 1e9
    grid = np.linspace(np.min(s.nu_hz), np.max(s.nu_hz), 1200)
    e = _exponent(np.asarray(s.y) * to_unit)
    ax_d.errorbar(
        x,
        s.y * to_unit / 10.0**e,
        yerr=s.u * to_unit / 10.0**e,
        fmt="o",
        ms=2.5,
        capsize=2,
        color="0.3",
        label=s.label or s.kind,
    )
    ax_d.plot(
        (grid - lf.nu_ref_hz) / 1e9,
        lf.model(grid, k) * to_unit / 10.0**e,
        color="C3",
        label=f"{lf.profile} fit",
    )
    name = "1/(cτ)" if s.kind == "absorption" else "mode shift"
    ax_d.set_ylabel(f"{name} ({_scaled_unit(e, unit)})")
    ref = f"ν_ref = {lf.nu_ref_hz / 1e12:.6f} THz"
    _legend(ax_d, f"{title}; {ref}" if title else ref)
    # LineFit.residuals are model - data (y unit): drawn as data - fit
    resid = -np.asarray(lf.residuals[k]) * to_unit
    er = _exponent(resid)
    ax_r.errorbar(
        x, resid / 10.0**er, yerr=s.u * to_unit / 10.0**er, fmt="o", ms=2.5, capsize=2, color="C0"
    )
    ax_r.axhline(0, color="0.3", lw=0.6)
    ax_r.set_ylabel(f"data − fit ({_scaled_unit(er, unit)})")
    ax_r.set_xlabel("ν − ν_ref (GHz)")


def _scaled_unit(e: int, unit: str) -> str:
    """``unit`` times 10^e: an SI prefix for Hz, a power of ten otherwise."""
    if e == 0:
        return unit
    if unit == "Hz":
        return f"{SI_PREFIX[e]}Hz"
    return f"{POWER[e]} {unit}"


@house_style
def plot_line_fit(lf, ax=None):
    """Every spectrum of the fit (one column each) with the profile and the residuals."""
    n = len(lf.spectra)
    if ax is not None or n == 1:
        fig, ax_d, ax_r = data_and_residual_axes(ax)
        _draw_spectrum(lf, 0, ax_d, ax_r, f"chi2_red {lf.chi2_red:.3g}")
        return fig
    fig, axes = new_figure(2, n, height_ratios=(3, 1))
    for k in range(n):
        _draw_spectrum(lf, k, axes[0, k], axes[1, k])
    return fig


# --------------------------------------------------------------------------- line analysis


def _line_analysis_rows(la) -> list:
    d = la.to_dict()
    rows = [
        ["A", fmt(d["line_area"]["value"], d["line_area"]["u"]), "cm^-2", f"{la.u_note} u"],
    ]
    if d["reference_area"] is not None:
        ref = d["reference_area"]
        rows.append(["A_ref (CMDS)", fmt(ref["value"], ref["u"]), "cm^-2", "fit u"])
        rows.append(["A/A_ref", fmt(d["ratio"]["value"], d["ratio"]["u"]), "1", f"{la.u_note} u"])
    s = d["intensity"]
    rows.append(
        [
            f"S({s['t_ref_k']:g} K)",
            fmt(s["value"], s["u"]),
            s["unit"],
            f"{la.u_note} u only (the budget adds p, T, x"
            + (", H)" if la.line_area_u_h_si is None else ")"),
        ]
    )
    rows.append(["chi2_red", fmt(la.chi2_red, digits=4), "1", "CRDS spectrum fit"])
    return rows


def _line_analysis_head(la) -> str:
    window = f", {la.window} window" if la.window else ""
    left = (
        f"{la.clipped_points} clipped, {la.unconverged_points} not converged, "
        f"{la.record_short_points} record-short"
    )
    head = (
        f"configuration {la.configuration}: {la.method}{window}, t_cut = {la.t_cut_s * 1e6:g} µs, "
        f"{la.profile}; {la.n_points} points ({left})"
    )
    if la.shape_at_bound:
        head += f"; held at 0: {', '.join(la.shape_at_bound)}"
    if la.unphysical_shape:
        head += f"; below 0: {', '.join(la.unphysical_shape)}"
    return head


LA_HEADER = ("quantity", "value ± u", "unit", "note")


def line_analysis_text(la) -> str:
    """Summary of a :class:`~bayes_tfcrds.fit.line_analysis.LineAnalysis`."""
    out = _line_analysis_head(la) + "\n" + text_table(LA_HEADER, _line_analysis_rows(la))
    if la.noise is not None:
        out += "\n" + la.noise.summary_line()
    return out


def line_analysis_html(la) -> str:
    """The summary of :func:`line_analysis_text` as an HTML table."""
    return html_table(LA_HEADER, _line_analysis_rows(la), caption=_line_analysis_head(la))


@house_style
def plot_line_analysis(la, ax=None):
    """The CRDS spectrum with its fit and residuals, beside the CMDS reference fit if any."""
    a = line_area_to_cm2(la.line_fit.line_area)
    title = f"{la.configuration} {la.method}, t_cut {la.t_cut_s * 1e6:g} µs: A = {a:.5g} cm⁻²"
    if ax is not None or la.reference_fit is None:
        fig, ax_d, ax_r = data_and_residual_axes(ax)
        _draw_spectrum(la.line_fit, 0, ax_d, ax_r, title)
        return fig
    fig, axes = new_figure(2, 2, height_ratios=(3, 1))
    _draw_spectrum(la.line_fit, 0, axes[0, 0], axes[1, 0], title)
    r = la.ratio
    _draw_spectrum(
        la.reference_fit, 0, axes[0, 1], axes[1, 1], f"A/A_ref = {r.value:.5f} ± {r.u:.2g}"
    )
    return fig
