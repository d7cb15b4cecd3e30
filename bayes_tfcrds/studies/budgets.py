"""The ``budgets`` study: every configuration's line-area budget, their consistency and CMDS."""

from __future__ import annotations

import numpy as np

from bayes_tfcrds.core.constants import edge_budget
from bayes_tfcrds.output.plotting import legend_above, literal, pyplot
from bayes_tfcrds.studies.common import parallel_map
from bayes_tfcrds.uncertainty.outputs import PRIOR_COLUMNS, prior_rows


def _budget_config(args):
    bundle_path, name, steps, t_cut, profile, window, seed = args
    from dataclasses import replace

    from bayes_tfcrds.bundle.reader import load_bundle
    from bayes_tfcrds.uncertainty.line_budget import BudgetOptions, run_budget

    bundle = load_bundle(bundle_path)
    opts = replace(
        BudgetOptions(),
        t_cut_s=t_cut,
        profile=profile,
        window=window,
        n_steps=steps,
        max_steps=max(8 * steps, 24000),
    )
    rng = np.random.default_rng([seed, sum(map(ord, name))])
    res = run_budget(bundle, bundle.configs[name], opts, rng)
    # the GUM tables with A in cm^-2, as the report's summary and budget.json show it
    a, s = (edge_budget(b).to_dict() for b in (res.budget_a, res.budget_s))
    return name, res.summary, a, s


def _budget_table(rep, bd):
    """A GUM budget (``Budget.to_dict()``) as an HTML table with the JCGM 100 columns."""

    def g(x, n=3):
        return "" if x is None else (x if isinstance(x, str) else f"{x:.{n}g}")

    rows = [
        [
            c["name"],
            g(c["value"], 7),
            g(c["u"], 2),
            c["unit"],
            g(c["sensitivity"], 4),
            g(c["contribution"], 2),
            "" if c["share"] is None else f"{100 * c['share']:.1f} %",
            g(c["dof"]),
            c["note"],
        ]
        for c in bd["components"]
    ]
    corr = "; ".join(f"r({c['a']}, {c['b']}) = {c['r']:.2f}" for c in bd["correlations"])
    rep.add_table(
        [
            "quantity",
            "value",
            "standard uncertainty",
            "unit",
            "sensitivity coefficient",
            f"contribution to u ({bd['unit']})",
            "share",
            "dof",
            "note",
        ],
        rows,
        caption=f"{bd['quantity']} = {bd['value']:.7g} {bd['unit']}; u_c = {bd['combined_u']:.2g} "
        f"{bd['unit']}; U (k = 2) = {bd['expanded_k2']:.2g} {bd['unit']}",
    )
    if corr:
        rep.add_text("Correlations: " + corr)


def _refinement_table(rep, name: str, s: dict) -> None:
    """How the ring-downs updated the beat note: values and tension z (|z| > 3: a finding)."""
    ref = (s.get("transfer_function") or {}).get("refinement")
    if not ref:
        return
    rows = []
    for par, t in ref["parameters"].items():
        rows.append(
            [
                par,
                "-"
                if t["beat_note"] is None
                else f"{t['beat_note']:.6g} +/- {t['beat_note_u']:.2g}",
                f"{t['refined']:.6g} +/- {t['refined_u']:.2g}",
                "-" if t["z"] is None else f"{t['z']:+.2f}",
            ]
        )
    rep.add_table(["H parameter", "beat note", "refined on ring-downs", "tension z"], rows)
    rep.add_diagnostic(
        f"{name}: beat note and ring-downs agree on H (|z| <= 3)",
        not ref["in_tension"],
        f"joint chi2 {ref['tension_chi2']:.2f} ({ref['tension_dof']} dof, p = "
        f"{ref['tension_p']:.3g}); refined: {', '.join(s['transfer_function']['refined'])}",
    )


def _priors_table(rep, results) -> None:
    """The priors of the budgets' posteriors (from each summary), each distinct row once."""
    rows = {}
    for name, s, *_ in results:
        for row in prior_rows(s.get("priors") or {}):
            rows.setdefault(tuple(row), []).append(name)
    if rows:
        rep.add_heading("Priors")
        rep.add_table(["configs", *PRIOR_COLUMNS], [[", ".join(c), *r] for r, c in rows.items()])


def _consistency(rep, ok: list) -> dict:
    """Weighted mean of A over configurations and its Birge ratio.

    Consistency is judged on what is independent between configurations (ring-down noise and
    each chain's H); the Type B rows (t_cut, line-shape model) are shared systematics and are
    added to the mean's uncertainty once, not averaged down.
    """
    a = np.array([s["line_area"]["value"] for _, s in ok])
    u_ind = np.array([s["line_area"]["u_statistical"] for _, s in ok])
    u_tot = np.array([s["line_area"]["u"] for _, s in ok])
    w = 1 / u_ind**2
    mean = np.sum(w * a) / np.sum(w)
    u_mean_ind = 1 / np.sqrt(np.sum(w))
    u_shared = float(np.mean(np.sqrt(np.maximum(u_tot**2 - u_ind**2, 0.0))))
    u_mean = float(np.hypot(u_mean_ind, u_shared))
    birge = np.sqrt(np.sum(w * (a - mean) ** 2) / (len(a) - 1))
    numbers_mean = {
        "value": mean,
        "u": u_mean,
        "u_independent": u_mean_ind,
        "u_shared": u_shared,
        "unit": "cm^-2",
        "birge_ratio": birge,
    }
    rep.add_summary(
        "weighted mean of A over configurations",
        f"{mean:.6e} +/- {u_mean:.1e} cm^-2",
        f"independent part {u_mean_ind:.1e}, shared Type B {u_shared:.1e}",
    )
    rep.add_summary(
        "Birge ratio (independent uncertainties)", f"{birge:.2f}", f"{len(a)} configurations"
    )
    rep.add_diagnostic(
        "configurations mutually consistent (Birge ratio < 1 + 2 sqrt(1/(2(n-1))))",
        birge < 1 + 2 * np.sqrt(1 / (2 * (len(a) - 1))),
        f"R_B = {birge:.2f}",
    )
    return numbers_mean


def _comparison_figure(plt, rep, ok: list) -> None:
    """A/A_ref per configuration, and S against the reference intensity."""
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(7.5, 3.6))
    x = np.arange(len(ok))
    ax1.errorbar(x, [s["ratio"]["value"] for _, s in ok], [s["ratio"]["u"] for _, s in ok], fmt="o")
    ax1.axhline(1, color="0.5")
    ax1.set_xticks(x, [literal(n) for n, _ in ok])
    ax1.set_ylabel("A/A_ref, TF-CRDS (dimensionless)")
    ax1.set_xlabel("configuration")
    unit = 1e-25  # S drawn in 10^-25 cm/molecule: no "1e-25" offset text above the axes
    svals = [s["intensity"]["value"] / unit for _, s in ok]
    ax2.errorbar(x, svals, [s["intensity"]["u"] / unit for _, s in ok], fmt="o")
    ref = ok[0][1]["intensity"]
    ax2.axhspan(
        (ref["reference"] - ref["reference_u"]) / unit,
        (ref["reference"] + ref["reference_u"]) / unit,
        color="0.85",
        label="reference S, Cygan et al. 2025",
    )
    ax2.set_xticks(x, [literal(n) for n, _ in ok])
    ax2.set_ylabel("S(296 K) (10⁻²⁵ cm/molecule)")
    ax2.set_xlabel("configuration")
    legend_above(ax2, ncol=1)
    rep.add_figure(
        fig,
        "TF-CRDS line areas relative to CMDS (left) and line intensities against the reference "
        "value 8.0603(70) × 10⁻²⁵ cm/molecule (Cygan et al. 2025; grey band, right), both at "
        "296 K, with standard uncertainties from the budgets.",
    )


def _ratio_lines(rep, ok: list) -> None:
    """Each configuration's A/A_ref as a summary line and a 0.1 % diagnostic."""
    for name, s in ok:
        rep.add_summary(
            f"{name}: A/A_ref (TF-CRDS)",
            f"{s['ratio']['value']:.5f} +/- {s['ratio']['u']:.5f}",
            f"E_n = {s['en']:+.2f}; bias {100 * (s['ratio']['value'] - 1):+.3f} %",
        )
        rep.add_diagnostic(
            f"{name}: |A/A_ref - 1| < 0.1 %",
            abs(s["ratio"]["value"] - 1) < 1e-3,
            f"{100 * (s['ratio']['value'] - 1):+.3f} %",
        )


def budgets(study, bundle, truth, rep, out, progress=False, pool=None):
    """Every configuration's budget, their consistency (weighted mean, Birge ratio), and CMDS."""
    plt = pyplot()
    bpath = str(out / "campaign.h5") if study.bundle is None else study.bundle
    jobs = [
        (bpath, n, study.mcmc_steps, study.t_cut_s, study.profile, study.windows[0], study.seed)
        for n in bundle.configs
    ]
    results = parallel_map(pool, _budget_config, jobs, progress, "configuration budgets")
    numbers = {"configs": {}}
    rows = []
    ok = []
    for name, s, bd_a, bd_s in results:
        numbers["configs"][name] = s
        passed = s["diagnostics"]["passed"]
        rep.add_diagnostic(
            f"{name}: MCMC gates (R-hat < 1.01, ESS > 400, > 50 tau_int)",
            passed,
            f"R-hat max {s['diagnostics']['rhat_max']:.4f}, ESS min "
            f"{s['diagnostics']['ess_min']:.0f}",
        )
        if not passed:
            rows.append([name, "FAILED", "", "", "", "", ""])
            continue
        ok.append((name, s))
        rows.append(
            [
                name,
                f"{s['line_area']['value']:.6e}",
                f"{s['line_area']['u']:.2e}",
                f"{s['ratio']['value']:.5f} +/- {s['ratio']['u']:.5f}",
                f"{s['en']:+.2f}",
                f"{s['intensity']['value']:.5e} +/- {s['intensity']['u']:.1e}",
                f"{s['intensity']['en']:+.2f}",
            ]
        )
        rep.add_heading(f"{name}: budget")
        _budget_table(rep, bd_a)
        _budget_table(rep, bd_s)
        _refinement_table(rep, name, s)
    rep.add_heading("Line areas, CMDS comparison and intensities")
    rep.add_table(
        [
            "config",
            "A (cm^-2)",
            "u(A) (cm^-2)",
            "A/A_ref",
            "E_n (k=2)",
            "S(296 K) (cm/molecule)",
            "E_n vs 8.0603(70)e-25 (296 K)",
        ],
        rows,
    )
    if len(ok) >= 2:
        numbers["weighted_mean"] = _consistency(rep, ok)
        _comparison_figure(plt, rep, ok)
    _ratio_lines(rep, ok)
    _priors_table(rep, results)
    return numbers
