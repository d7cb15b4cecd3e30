"""Study kinds that draw the letter's figures, compare windows, and run the D1-D4 budgets."""
from __future__ import annotations

import numpy as np

from .analysis import calibrate
from .constants import C, line_area_to_cm2
from .ringdown import fit_ringdowns, fit_transients
from .spectrum import crds_spectrum, fit_line
from .linefit import analyse_line, doppler_of
from .transfer_function import transfer_function


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def letter_figures(study, bundle, truth, rep):
    """Fig. 2a (beat note and models), Fig. 2b (ring-downs and residuals), Fig. 3 (spectra)."""
    plt = _plt()
    numbers = {}
    tc = study.t_cut_s
    gd = doppler_of(bundle.sample)
    for name, cfg in bundle.configs.items():
        cal = calibrate(cfg, t_cuts_s=study.t_cuts_s, window=study.windows[0])
        rd = cfg.ringdowns
        crds = fit_ringdowns(rd, [tc], "crds", keep_residuals=True)
        tf = fit_ringdowns(rd, [tc], "tf-crds", cal.params, study.windows[0], keep_residuals=True)
        i_long, i_short = int(np.nanargmax(tf.tau_s[:, 0])), int(np.nanargmin(tf.tau_s[:, 0]))
        # Fig. 2a
        fig, ax = plt.subplots(figsize=(7.5, 4.2))
        t_data = cfg.transfer_function
        f = np.asarray(t_data.f_hz)
        ax.errorbar(f, t_data.h_mag / cal.beat.scale, t_data.h_mag_u / cal.beat.scale, fmt=".", color="0.3",
                    label="beat note |H| (normalised)")
        ff = np.logspace(np.log10(f[0]), np.log10(f[-1]), 400)
        ax.semilogx(ff, np.abs(transfer_function(ff, cal.beat.params)), "k-", label="Eq. 2 fitted to the beat note")
        ax.semilogx(ff, np.abs(transfer_function(ff, cal.params)), "-", color="tab:orange",
                    label="refined on ring-downs (f_c)")
        ax2 = ax.twinx()
        t = rd.time_s
        for i, col in ((i_long, "tab:blue"), (i_short, "tab:red")):
            sel = t >= tc
            spec = np.abs(np.fft.rfft(rd.signal_v[i, sel] - np.mean(rd.signal_v[i, sel][-200:])))
            fs = np.fft.rfftfreq(sel.sum(), rd.dt_s)
            ax2.fill_between(fs[1:], spec[1:] / spec[1:].max(), color=col, alpha=0.15,
                             label=f"ring-down spectrum, tau = {tf.tau_s[i, 0] * 1e6:.1f} us")
        ax2.set_yscale("log")
        ax2.set_ylim(1e-4, 2)
        ax2.set_ylabel("ring-down Fourier amplitude (norm.)")
        ax.set_xlabel("frequency (Hz)")
        ax.set_ylabel("|H(f)|")
        ax.set_xlim(f[0], f[-1])
        ax.legend(fontsize=7, loc="lower left")
        ax2.legend(fontsize=7, loc="center left")
        ax.set_title(f"{name}: detection transfer function (letter Fig. 2a)")
        rep.add_figure(fig, f"{name}: measured |H| (dots), Eq. 2 fitted to it (black), refined by the multi-ring-down "
                            "fit (orange); shaded: Fourier spectra of the long and short ring-downs.")
        # Fig. 2b
        fig, axes = plt.subplots(3, 1, figsize=(7.5, 6.5), sharex=True, gridspec_kw={"height_ratios": [2, 1, 1]})
        sel = t >= tc
        for i, col in ((i_long, "tab:blue"), (i_short, "tab:red")):
            axes[0].plot(t[sel] * 1e6, rd.signal_v[i, sel] * 1e3, color=col, lw=0.8,
                         label=f"tau = {tf.tau_s[i, 0] * 1e6:.1f} us")
            rc = crds.residuals_v[i, 0, sel] * 1e3
            rt = tf.residuals_v[i, 0, sel] * 1e3
            axes[1 if i == i_long else 2].plot(t[sel] * 1e6, rc, color=col, lw=0.5,
                                               label=f"CRDS residual (RMS {np.sqrt(np.mean(rc**2)):.3f} mV)")
            axes[1 if i == i_long else 2].plot(t[sel] * 1e6, rt, color="k", lw=0.5,
                                               label=f"TF-CRDS residual (RMS {np.sqrt(np.mean(rt**2)):.3f} mV)")
            numbers[f"{name}_residual_rms_mv_tau{tf.tau_s[i, 0] * 1e6:.0f}us"] = {
                "crds": float(np.sqrt(np.mean(rc**2))), "tf-crds": float(np.sqrt(np.mean(rt**2)))}
        axes[0].set_ylabel("signal (mV)")
        axes[0].legend(fontsize=7)
        for a in axes[1:]:
            a.set_ylabel("residual (mV)")
            a.legend(fontsize=7, loc="upper right")
        axes[0].set_xlim(tc * 1e6, min(t[-1], 8 * tf.tau_s[i_long, 0]) * 1e6)
        axes[-1].set_xlabel("time after extinction (us)")
        axes[0].set_title(f"{name}: ring-downs truncated at t_cut = {tc * 1e6:g} us (letter Fig. 2b)")
        rep.add_figure(fig, f"{name}: ring-downs with the longest and shortest decay times, and the residuals of "
                            "CRDS (colour) and TF-CRDS with the refined H (black).")
        # Fig. 3
        sp_c = crds_spectrum(crds.nu_hz, crds.tau_s[:, 0], crds.tau_u_s[:, 0])
        sp_t = crds_spectrum(tf.nu_hz, tf.tau_s[:, 0], tf.tau_u_s[:, 0])
        fc = fit_line([sp_c], study.profile, gd, bundle.sample.nu0_hz)
        ft = fit_line([sp_t], study.profile, gd, bundle.sample.nu0_hz)
        det = (sp_t.nu_hz - bundle.sample.nu0_hz) / 1e9
        order = np.argsort(det)
        fig, axes = plt.subplots(4, 1, figsize=(7.5, 8), sharex=True, gridspec_kw={"height_ratios": [2, 1, 1, 1]})
        axes[0].plot(det, sp_c.y * 1e4, "s", ms=3, color="tab:blue", label="CRDS 1/(c tau)")
        axes[0].plot(det, sp_t.y * 1e4, ".", ms=4, color="k", label="TF-CRDS 1/(c tau)")
        model_c = sp_c.y - fc.residuals[0]
        model_t = sp_t.y - ft.residuals[0]
        axes[0].plot(det[order], model_c[order] * 1e4, "--", color="tab:blue", lw=0.8, label=f"{study.profile} fit (CRDS)")
        axes[0].plot(det[order], model_t[order] * 1e4, "-", color="tab:red", lw=0.8, label=f"{study.profile} fit (TF-CRDS)")
        axes[0].set_ylabel("loss 1/(c tau) (1e-6 cm^-1)")   # 1/m x 1e-2 -> 1/cm, x 1e6
        axes[0].legend(fontsize=7)
        axes[1].plot(det, fc.residuals[0] / sp_c.u, "s", ms=3, color="tab:blue")
        axes[1].set_ylabel("CRDS resid./u")
        axes[2].plot(det, ft.residuals[0] / sp_t.u, ".", ms=4, color="k")
        axes[2].set_ylabel("TF-CRDS resid./u")
        rel = 100 * (tf.tau_s[:, 0] - crds.tau_s[:, 0]) / crds.tau_s[:, 0]
        axes[3].plot((tf.nu_hz - bundle.sample.nu0_hz) / 1e9, rel, ".", color="tab:purple")
        axes[3].set_ylabel("(tau_TF - tau)/tau (%)")
        axes[3].set_xlabel("detuning (GHz)")
        axes[0].set_title(f"{name}: spectra at t_cut = {tc * 1e6:g} us (letter Fig. 3)")
        rep.add_figure(fig, f"{name}: CRDS and TF-CRDS spectra with {study.profile} fits, normalised residuals, and the "
                            "relative difference of TF-corrected and apparent decay times across the line.")
        numbers[name] = {"tau_difference_pct_min": float(np.nanmin(rel)), "tau_difference_pct_max": float(np.nanmax(rel)),
                         "chi2_red_crds": fc.chi2_red, "chi2_red_tf": ft.chi2_red,
                         "refined_f_c_hz": cal.params.f_c_hz, "beat_f_c_hz": cal.beat.params.f_c_hz}
        rep.add_summary(f"{name}: tau correction across the line", f"{np.nanmin(rel):+.2f} % to {np.nanmax(rel):+.2f} %",
                        "letter: D2 -0.04 % to -2.4 %, D4 -0.6 % to -16 %")
        rep.add_summary(f"{name}: spectrum fit chi2_red CRDS / TF-CRDS", f"{fc.chi2_red:.1f} / {ft.chi2_red:.2f}")
        rep.add_diagnostic(f"{name}: TF-CRDS spectrum residuals consistent with noise", ft.chi2_red < 2,
                           f"chi2_red = {ft.chi2_red:.2f}")
    return numbers


def window_history(study, bundle, truth, rep):
    """TF-CRDS with the letter window against the extinction window, across t_cut and chains."""
    plt = _plt()
    numbers = {"rows": []}
    a_true = truth["line"]["line_area_hz_per_m"] if truth is not None else None
    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    rows = []
    for name, cfg in bundle.configs.items():
        for window, mk in (("letter", "s"), ("extinction", "o")):
            # each pipeline refines H with its own window, as the letter does: the refinement
            # can absorb part of a window's misrepresentation into f_c
            cal = calibrate(cfg, t_cuts_s=study.t_cuts_s, window=window)
            numbers[f"{name}_{window}_refined_f_c_hz"] = cal.params.f_c_hz
            vals = []
            for tc in study.t_cuts_s:
                r = analyse_line(bundle, cfg, method="tf-crds", window=window, t_cut_s=tc, profile_name=study.profile,
                                 calibration=cal)
                ref = a_true if a_true is not None else r["reference_area"]["value_si"]
                vals.append(r["line_area"]["value_si"] / ref - 1)
                rows.append([name, window, f"{tc * 1e6:g}", f"{100 * vals[-1]:+.3f}", f"{r['chi2_red']:.2f}"])
                numbers["rows"].append({"config": name, "window": window, "t_cut_s": tc, "bias": vals[-1],
                                        "chi2_red": r["chi2_red"]})
            ax.plot(np.array(study.t_cuts_s) * 1e6, 100 * np.array(vals), mk + ("--" if window == "letter" else "-"),
                    label=f"{name} {window}")
        worst = max(abs(r["bias"]) for r in numbers["rows"] if r["config"] == name and r["window"] == "extinction")
        rep.add_diagnostic(f"{name}: extinction window bias below 0.1 %", worst < 1e-3, f"max |bias| {100 * worst:.3f} %")
    ax.axhline(0, color="0.5", lw=0.8)
    ax.set_xlabel("t_cut (us)")
    ax.set_ylabel("A/A_true - 1 (%)" if a_true is not None else "A/A_ref - 1 (%)")
    ax.legend(fontsize=7, ncol=2)
    ax.set_title("TF-CRDS line area: letter window (squares) vs extinction window (circles)")
    rep.add_figure(fig, "Each pipeline refines f_c with its own window, then fits every t_cut. The letter's window "
                        "models the history before t_cut as flat; with a chain whose memory lasts microseconds "
                        "that misrepresents the signal the chain has seen, and the refined f_c absorbs only part of "
                        "it. The extinction window models the history that really was there.")
    rep.add_table(["config", "window", "t_cut (us)", "A/A_true - 1 (%)", "chi2_red"], rows)
    for name in bundle.configs:
        for w in ("letter", "extinction"):
            b = [r["bias"] for r in numbers["rows"] if r["config"] == name and r["window"] == w]
            rep.add_summary(f"{name}: {w} window bias range", f"{100 * min(b):+.3f} % to {100 * max(b):+.3f} %")
    return numbers


def _budget_config(args):
    bundle_path, name, steps, t_cut, profile, window, seed = args
    from dataclasses import replace
    from .bundle import load_bundle
    from .uncertainty import BudgetOptions, run_budget
    bundle = load_bundle(bundle_path)
    opts = replace(BudgetOptions(), t_cut_s=t_cut, profile=profile, window=window, n_steps=steps,
                   max_steps=max(8 * steps, 24000))
    rng = np.random.default_rng([seed, sum(map(ord, name))])
    res = run_budget(bundle, bundle.configs[name], opts, rng)
    return name, res.summary, res.budget_a.to_dict(), res.budget_s.to_dict()


def _budget_table(rep, bd):
    """A GUM budget (``Budget.to_dict()``) as an HTML table with the JCGM 100 columns."""
    def g(x, n=3):
        return "" if x is None else (x if isinstance(x, str) else f"{x:.{n}g}")
    rows = [[c["name"], g(c["value"], 7), g(c["u"], 2), c["unit"], g(c["sensitivity"], 4), g(c["contribution"], 2),
             "" if c["share"] is None else f"{100 * c['share']:.1f} %", g(c["dof"]), c["note"]] for c in bd["components"]]
    corr = "; ".join(f"r({c['a']}, {c['b']}) = {c['r']:.2f}" for c in bd["correlations"])
    rep.add_table(["quantity", "value", "standard uncertainty", "unit", "sensitivity coefficient",
                   f"contribution to u ({bd['unit']})", "share", "dof", "note"], rows,
                  caption=f"{bd['quantity']} = {bd['value']:.7g} {bd['unit']}; u_c = {bd['combined_u']:.2g} "
                          f"{bd['unit']}; U (k = 2) = {bd['expanded_k2']:.2g} {bd['unit']}")
    if corr:
        rep.add_text("Correlations: " + corr)


def budgets(study, bundle, truth, rep, out, progress=False, pool=None):
    """The budget of every configuration, their consistency (weighted mean, Birge ratio), and CMDS."""
    plt = _plt()
    from .study import _map
    bpath = str(out / "campaign.h5") if study.bundle is None else study.bundle
    jobs = [(bpath, n, study.mcmc_steps, study.t_cut_s, study.profile, study.windows[0], study.seed)
            for n in bundle.configs]
    results = _map(pool, _budget_config, jobs)
    numbers = {"configs": {}}
    rows = []
    ok = []
    for name, s, bd_a, bd_s in results:
        numbers["configs"][name] = s
        passed = s["diagnostics"]["passed"]
        rep.add_diagnostic(f"{name}: MCMC gates (R-hat < 1.01, ESS > 400, > 50 tau_int)", passed,
                           f"R-hat max {s['diagnostics']['rhat_max']:.4f}, ESS min {s['diagnostics']['ess_min']:.0f}")
        if not passed:
            rows.append([name, "FAILED", "", "", "", "", ""])
            continue
        ok.append((name, s))
        rows.append([name, f"{s['line_area']['value']:.6e}", f"{s['line_area']['u']:.2e}",
                     f"{s['ratio']['value']:.5f} +/- {s['ratio']['u']:.5f}", f"{s['en']:+.2f}",
                     f"{s['intensity']['value']:.5e} +/- {s['intensity']['u']:.1e}", f"{s['intensity']['en']:+.2f}"])
        rep.add_heading(f"{name}: budget")
        _budget_table(rep, bd_a)
        _budget_table(rep, bd_s)
    rep.add_heading("Line areas, CMDS comparison and intensities")
    rep.add_table(["config", "A (cm^-2)", "u(A) (cm^-2)", "A/A_ref", "E_n (k=2)", "S (cm/molecule)",
                   "E_n vs 8.0603(70)e-25"], rows)
    if len(ok) >= 2:
        a = np.array([s["line_area"]["value"] for _, s in ok])
        # consistency is judged on what is independent between configurations (ring-down noise and
        # each chain's H); the Type B rows (t_cut, line-shape model) are shared systematics and are
        # added to the mean's uncertainty once, not averaged down
        u_ind = np.array([s["line_area"]["u_statistical"] for _, s in ok])
        u_tot = np.array([s["line_area"]["u"] for _, s in ok])
        w = 1 / u_ind**2
        mean = np.sum(w * a) / np.sum(w)
        u_mean_ind = 1 / np.sqrt(np.sum(w))
        u_shared = float(np.mean(np.sqrt(np.maximum(u_tot**2 - u_ind**2, 0.0))))
        u_mean = float(np.hypot(u_mean_ind, u_shared))
        birge = np.sqrt(np.sum(w * (a - mean) ** 2) / (len(a) - 1))
        numbers["weighted_mean"] = {"value": mean, "u": u_mean, "u_independent": u_mean_ind, "u_shared": u_shared,
                                    "unit": "cm^-2", "birge_ratio": birge}
        rep.add_summary("weighted mean of A over configurations", f"{mean:.6e} +/- {u_mean:.1e} cm^-2",
                        f"independent part {u_mean_ind:.1e}, shared Type B {u_shared:.1e}")
        rep.add_summary("Birge ratio (independent uncertainties)", f"{birge:.2f}", f"{len(a)} configurations")
        rep.add_diagnostic("configurations mutually consistent (Birge ratio < 1 + 2 sqrt(1/(2(n-1))))",
                           birge < 1 + 2 * np.sqrt(1 / (2 * (len(a) - 1))), f"R_B = {birge:.2f}")
        fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(9, 3.8))
        x = np.arange(len(ok))
        ax1.errorbar(x, [s["ratio"]["value"] for _, s in ok], [s["ratio"]["u"] for _, s in ok], fmt="o")
        ax1.axhline(1, color="0.5")
        ax1.set_xticks(x, [n for n, _ in ok])
        ax1.set_ylabel("A/A_ref (TF-CRDS)")
        svals = [s["intensity"]["value"] for _, s in ok]
        ax2.errorbar(x, svals, [s["intensity"]["u"] for _, s in ok], fmt="o")
        ref = ok[0][1]["intensity"]
        ax2.axhspan(ref["reference"] - ref["reference_u"], ref["reference"] + ref["reference_u"], color="0.85",
                    label="8.0603(70)e-25 (Cygan et al. 2025)")
        ax2.set_xticks(x, [n for n, _ in ok])
        ax2.set_ylabel("S (cm/molecule)")
        ax2.legend(fontsize=7)
        fig.tight_layout()
        rep.add_figure(fig, "TF-CRDS line areas relative to CMDS (left) and line intensities against the reference "
                            "value (right), with standard uncertainties from the budgets.")
    for name, s in ok:
        rep.add_summary(f"{name}: A/A_ref (TF-CRDS)", f"{s['ratio']['value']:.5f} +/- {s['ratio']['u']:.5f}",
                        f"E_n = {s['en']:+.2f}; bias {100 * (s['ratio']['value'] - 1):+.3f} %")
        rep.add_diagnostic(f"{name}: |A/A_ref - 1| < 0.1 %", abs(s["ratio"]["value"] - 1) < 1e-3,
                           f"{100 * (s['ratio']['value'] - 1):+.3f} %")
    return numbers
