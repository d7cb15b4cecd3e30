"""Study kinds that draw the letter's figures, compare windows, and run the D1-D4 budgets."""

from __future__ import annotations

import numpy as np

from bayes_tfcrds.fit.h_calibration import account_for_noise_colour, calibrate
from bayes_tfcrds.fit.line import fit_line
from bayes_tfcrds.fit.line_analysis import analyse_line, doppler_of
from bayes_tfcrds.fit.ringdown import fit_ringdowns
from bayes_tfcrds.fit.spectrum import crds_spectrum
from bayes_tfcrds.output.plotting import (
    MICROSECOND as US,
)
from bayes_tfcrds.output.plotting import (
    dodge,
    legend_outside,
    literal,
    pyplot,
)
from bayes_tfcrds.physics.transfer_function import transfer_function


def _figure_transfer_function(plt, rep, name, cfg, cal, tf, extremes, tc) -> None:
    """Letter Fig. 2a: beat-note |H|, Eq. 2 fitted to it and refined, ring-down spectra."""
    rd = cfg.ringdowns
    i_long, i_short = extremes
    fig, ax = plt.subplots(figsize=(7.5, 4.2))
    t_data = cfg.transfer_function
    f = np.asarray(t_data.f_hz)
    ax.errorbar(
        f,
        t_data.h_mag / cal.beat.scale,
        t_data.h_mag_u / cal.beat.scale,
        fmt=".",
        color="0.3",
        label="beat note |H| (normalised)",
    )
    ff = np.logspace(np.log10(f[0]), np.log10(f[-1]), 400)
    ax.semilogx(
        ff,
        np.abs(transfer_function(ff, cal.beat.params)),
        "k-",
        label="Eq. 2 fitted to the beat note",
    )
    ax.semilogx(
        ff,
        np.abs(transfer_function(ff, cal.params)),
        "-",
        color="tab:orange",
        label="refined on ring-downs (f_c)",
    )
    ax2 = ax.twinx()
    t = rd.time_s
    for i, col in ((i_long, "tab:blue"), (i_short, "tab:red")):
        sel = t >= tc
        spec = np.abs(np.fft.rfft(rd.signal_v[i, sel] - np.mean(rd.signal_v[i, sel][-200:])))
        fs = np.fft.rfftfreq(sel.sum(), rd.dt_s)
        ax2.fill_between(
            fs[1:],
            spec[1:] / spec[1:].max(),
            color=col,
            alpha=0.15,
            rasterized=True,  # thousands of samples: pixels in the SVG/PDF, text stays vector
            label=f"ring-down spectrum, τ = {tf.tau_s[i, 0] * 1e6:.1f} {US}",
        )
    ax2.set_yscale("log")
    ax2.set_ylim(1e-4, 2)
    ax2.set_ylabel("ring-down Fourier amplitude (normalised to peak)")
    ax.set_xlabel("frequency f (Hz)")
    ax.set_ylabel("|H(f)| / |H(0)| (dimensionless)")
    ax.set_xlim(f[0], f[-1])
    # one legend for both axes, below the plot: the curves fill the whole frequency range
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = ax2.get_legend_handles_labels()
    ax.legend(h1 + h2, l1 + l2, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2)
    ax.set_title(f"{literal(name)}: detection transfer function (letter Fig. 2a)")
    rep.add_figure(
        fig,
        f"{name}: measured |H| (dots), Eq. 2 fitted to it (black), refined by the multi-ring-down "
        "fit (orange); shaded: Fourier spectra of the long and short ring-downs.",
    )


def _figure_ringdowns(plt, rep, numbers, name, rd, crds, tf, extremes, tc) -> None:
    """Letter Fig. 2b: the longest and shortest ring-downs with CRDS and TF-CRDS residuals."""
    i_long, i_short = extremes
    t = rd.time_s
    fig, axes = plt.subplots(
        3, 1, figsize=(7.5, 6.5), sharex=True, gridspec_kw={"height_ratios": [2, 1, 1]}
    )
    sel = t >= tc
    for i, col in ((i_long, "tab:blue"), (i_short, "tab:red")):
        axes[0].plot(
            t[sel] * 1e6,
            rd.signal_v[i, sel] * 1e3,
            color=col,
            lw=0.8,
            rasterized=True,  # thousands of samples: pixels in the SVG/PDF, text stays vector
            label=f"τ = {tf.tau_s[i, 0] * 1e6:.1f} {US}",
        )
        rc = crds.residuals_v[i, 0, sel] * 1e3
        rt = tf.residuals_v[i, 0, sel] * 1e3
        axes[1 if i == i_long else 2].plot(
            t[sel] * 1e6,
            rc,
            color=col,
            lw=0.5,
            rasterized=True,  # thousands of samples: pixels in the SVG/PDF, text stays vector
            label=f"CRDS residual (RMS {np.sqrt(np.mean(rc**2)):.3f} mV)",
        )
        axes[1 if i == i_long else 2].plot(
            t[sel] * 1e6,
            rt,
            color="k",
            lw=0.5,
            rasterized=True,  # thousands of samples: pixels in the SVG/PDF, text stays vector
            label=f"TF-CRDS residual (RMS {np.sqrt(np.mean(rt**2)):.3f} mV)",
        )
        numbers[f"{name}_residual_rms_mv_tau{tf.tau_s[i, 0] * 1e6:.0f}us"] = {
            "crds": float(np.sqrt(np.mean(rc**2))),
            "tf-crds": float(np.sqrt(np.mean(rt**2))),
        }
    axes[0].set_ylabel("signal (mV)")
    legend_outside(axes[0])
    for a in axes[1:]:
        a.set_ylabel("residual (mV)")
        legend_outside(a)
    axes[0].set_xlim(tc * 1e6, min(t[-1], 8 * tf.tau_s[i_long, 0]) * 1e6)
    axes[-1].set_xlabel(f"time after extinction t ({US})")
    axes[0].set_title(
        f"{literal(name)}: ring-downs truncated at t_cut = {tc * 1e6:g} {US} (letter Fig. 2b)"
    )
    rep.add_figure(
        fig,
        f"{name}: ring-downs with the longest and shortest decay times, and the residuals of CRDS "
        "(colour) and TF-CRDS with the refined H (black).",
    )


def _figure_spectra(plt, rep, name, study, bundle, crds, tf, gd, tc):
    """Letter Fig. 3: CRDS and TF-CRDS spectra with line fits, residuals, the tau correction.

    Returns (relative tau correction in %, CRDS line fit, TF-CRDS line fit).
    """
    sp_c = crds_spectrum(crds.nu_hz, crds.tau_s[:, 0], crds.tau_u_s[:, 0])
    sp_t = crds_spectrum(tf.nu_hz, tf.tau_s[:, 0], tf.tau_u_s[:, 0])
    fc = fit_line([sp_c], study.profile, gd, bundle.sample.nu0_hz)
    ft = fit_line([sp_t], study.profile, gd, bundle.sample.nu0_hz)
    det = (sp_t.nu_hz - bundle.sample.nu0_hz) / 1e9
    order = np.argsort(det)
    fig, axes = plt.subplots(
        4, 1, figsize=(7.5, 8), sharex=True, gridspec_kw={"height_ratios": [2, 1, 1, 1]}
    )
    axes[0].plot(det, sp_c.y * 1e4, "s", ms=3, color="tab:blue", label="CRDS 1/(c τ)")
    axes[0].plot(det, sp_t.y * 1e4, ".", ms=4, color="k", label="TF-CRDS 1/(c τ)")
    model_c = sp_c.y - fc.residuals[0]
    model_t = sp_t.y - ft.residuals[0]
    axes[0].plot(
        det[order],
        model_c[order] * 1e4,
        "--",
        color="tab:blue",
        lw=0.8,
        label=f"{study.profile} fit (CRDS)",
    )
    axes[0].plot(
        det[order],
        model_t[order] * 1e4,
        "-",
        color="tab:red",
        lw=0.8,
        label=f"{study.profile} fit (TF-CRDS)",
    )
    axes[0].set_ylabel("loss 1/(c τ) (10⁻⁶ cm⁻¹)")  # 1/m x 1e-2 -> 1/cm, x 1e6
    legend_outside(axes[0])
    axes[1].plot(det, fc.residuals[0] / sp_c.u, "s", ms=3, color="tab:blue")
    axes[1].set_ylabel("CRDS residual\n(units of u)")
    axes[2].plot(det, ft.residuals[0] / sp_t.u, ".", ms=4, color="k")
    axes[2].set_ylabel("TF-CRDS residual\n(units of u)")
    for a in axes[1:3]:
        a.axhline(0, color="0.5", lw=0.6)
    rel = 100 * (tf.tau_s[:, 0] - crds.tau_s[:, 0]) / crds.tau_s[:, 0]
    axes[3].plot((tf.nu_hz - bundle.sample.nu0_hz) / 1e9, rel, ".", color="tab:purple")
    axes[3].set_ylabel("(τ_TF − τ)/τ (%)")
    axes[3].set_xlabel("detuning ν − ν₀ (GHz)")
    axes[0].set_title(f"{literal(name)}: spectra at t_cut = {tc * 1e6:g} {US} (letter Fig. 3)")
    rep.add_figure(
        fig,
        f"{name}: CRDS and TF-CRDS spectra with {study.profile} fits, normalised residuals, and "
        "the relative difference of TF-corrected and apparent decay times across the line.",
    )
    return rel, fc, ft


def letter_figures(study, bundle, truth, rep, out=None, progress=False, pool=None):
    """Fig. 2a (beat note and models), Fig. 2b (ring-downs and residuals), Fig. 3 (spectra)."""
    plt = pyplot()
    numbers = {}
    tc = study.t_cut_s
    gd = doppler_of(bundle.sample)
    for name, cfg in bundle.configs.items():
        cal = calibrate(cfg, t_cuts_s=study.t_cuts_s, window=study.windows[0])
        rd = cfg.ringdowns
        crds = fit_ringdowns(rd, [tc], "crds", keep_residuals=True)
        tf = fit_ringdowns(rd, [tc], "tf-crds", cal.params, study.windows[0], keep_residuals=True)
        extremes = int(np.nanargmax(tf.tau_s[:, 0])), int(np.nanargmin(tf.tau_s[:, 0]))
        _figure_transfer_function(plt, rep, name, cfg, cal, tf, extremes, tc)
        _figure_ringdowns(plt, rep, numbers, name, rd, crds, tf, extremes, tc)
        rel, fc, ft = _figure_spectra(plt, rep, name, study, bundle, crds, tf, gd, tc)
        numbers[name] = {
            "tau_difference_pct_min": float(np.nanmin(rel)),
            "tau_difference_pct_max": float(np.nanmax(rel)),
            "chi2_red_crds": fc.chi2_red,
            "chi2_red_tf": ft.chi2_red,
            "refined_f_c_hz": cal.params.f_c_hz,
            "beat_f_c_hz": cal.beat.params.f_c_hz,
        }
        rep.add_summary(
            f"{name}: tau correction across the line",
            f"{np.nanmin(rel):+.2f} % to {np.nanmax(rel):+.2f} %",
            "letter: D2 -0.04 % to -2.4 %, D4 -0.6 % to -16 %",
        )
        rep.add_summary(
            f"{name}: spectrum fit chi2_red CRDS / TF-CRDS",
            f"{fc.chi2_red:.1f} / {ft.chi2_red:.2f}",
        )
        rep.add_diagnostic(
            f"{name}: TF-CRDS spectrum residuals consistent with noise",
            ft.chi2_red < 2,
            f"chi2_red = {ft.chi2_red:.2f}",
        )
    return numbers


def window_history(study, bundle, truth, rep, out=None, progress=False, pool=None):
    """TF-CRDS with the letter window against the extinction window, across t_cut and chains."""
    plt = pyplot()
    numbers = {"rows": []}
    a_true = truth["line"]["line_area_hz_per_m"] if truth is not None else None
    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    rows = []
    names = list(bundle.configs)
    # the configurations share every t_cut: set them side by side so no marker hides another
    t_us = np.array(study.t_cuts_s) * 1e6
    step = np.min(np.diff(np.unique(t_us))) if np.unique(t_us).size > 1 else 1.0
    shift = dict(zip(names, dodge(len(names), 0.5 * step / max(len(names), 1))))
    colours = dict(zip(names, plt.cm.tab10(np.arange(len(names)) % 10)))
    for name, raw in bundle.configs.items():
        for window, mk in (("letter", "s"), ("extinction", "o")):
            cfg, noise, beat = account_for_noise_colour(raw, window)
            # each pipeline refines H with its own window, as the letter does: the refinement
            # can absorb part of a window's misrepresentation into f_c
            cal = calibrate(cfg, t_cuts_s=study.t_cuts_s, window=window, beat=beat)
            numbers[f"{name}_{window}_refined_f_c_hz"] = cal.params.f_c_hz
            vals = []
            for tc in study.t_cuts_s:
                r = analyse_line(
                    bundle,
                    cfg,
                    method="tf-crds",
                    window=window,
                    t_cut_s=tc,
                    profile_name=study.profile,
                    calibration=cal,
                    noise=noise,
                )
                ref = a_true if a_true is not None else float(r.reference_fit.line_area)
                vals.append(float(r.line_fit.line_area) / ref - 1)
                rows.append(
                    [name, window, f"{tc * 1e6:g}", f"{100 * vals[-1]:+.3f}", f"{r.chi2_red:.2f}"]
                )
                numbers["rows"].append(
                    {
                        "config": name,
                        "window": window,
                        "t_cut_s": tc,
                        "bias": vals[-1],
                        "chi2_red": r.chi2_red,
                    }
                )
            ax.plot(
                t_us + shift[name],
                100 * np.array(vals),
                mk + ("--" if window == "letter" else "-"),
                color=colours[name],
                mfc="none" if window == "letter" else colours[name],
                label=f"{literal(name)} {window}",
            )
        worst = max(
            abs(r["bias"])
            for r in numbers["rows"]
            if r["config"] == name and r["window"] == "extinction"
        )
        rep.add_diagnostic(
            f"{name}: extinction window bias below 0.1 %",
            worst < 1e-3,
            f"max |bias| {100 * worst:.3f} %",
        )
    ax.axhline(0, color="0.5", lw=0.8)
    ax.set_xticks(np.unique(t_us))  # a tick at each t_cut, the centre of its group
    ax.set_xlabel(f"t_cut ({US}); configurations offset side by side")
    ax.set_ylabel("A/A_true − 1 (%)" if a_true is not None else "A/A_ref − 1 (%)")
    legend_outside(ax)
    ax.set_title("TF-CRDS line area: letter window (open squares) vs extinction window (circles)")
    rep.add_figure(
        fig,
        "Each pipeline refines f_c with its own window, then fits every t_cut. The letter's "
        "window models the history before t_cut as flat; with a chain whose memory lasts "
        "microseconds that misrepresents the signal the chain has seen, and the refined f_c "
        "absorbs only part of it. The extinction window models the history that really was there. "
        "The configurations are drawn side by side around each t_cut.",
    )
    rep.add_table(["config", "window", "t_cut (us)", "A/A_true - 1 (%)", "chi2_red"], rows)
    for name in bundle.configs:
        for w in ("letter", "extinction"):
            b = [r["bias"] for r in numbers["rows"] if r["config"] == name and r["window"] == w]
            rep.add_summary(
                f"{name}: {w} window bias range", f"{100 * min(b):+.3f} % to {100 * max(b):+.3f} %"
            )
    return numbers
