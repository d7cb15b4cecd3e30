"""The files of a budget run: budget.json, GUM tables, decay-time posteriors, netCDF, corners."""

from __future__ import annotations

import json
from pathlib import Path

from bayes_tfcrds.output.files import atomic_path, atomic_write_text, clean_dead_writers
from bayes_tfcrds.output.plotting import pyplot
from bayes_tfcrds.uncertainty.line_budget import BudgetResult


def write_outputs(result: BudgetResult, outdir, seed: int | None = None) -> list:
    """budget.json, budget tables (Markdown, CSV), posteriors (arviz netCDF) and corner plots.

    Every file goes through a temporary name and a rename, so none is ever half-written.
    """
    import corner

    plt = pyplot()

    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    # temporary files left by an earlier run that was killed while writing (a live run's stay)
    clean_dead_writers(out)
    written = []
    summary = dict(result.summary)
    if seed is not None:
        summary["seed"] = seed
    atomic_write_text(out / "budget.json", json.dumps(summary, indent=2, default=float) + "\n")
    written.append(out / "budget.json")
    tables = [result.budget_a, result.budget_s] + (
        [result.budget_ratio] if result.budget_ratio is not None else []
    )
    md = "\n\n".join(f"## {b.quantity}\n\n{b.to_markdown()}" for b in tables)
    banner = failed_banner(result)
    if banner:
        md = f"# {banner}\n\n{md}"
    refinement = (result.summary.get("transfer_function") or {}).get("refinement")
    if refinement:
        md += "\n\n" + refinement_markdown(refinement)
    if result.summary.get("noise"):
        md += "\n\n" + noise_markdown(result.summary["noise"])
    if result.summary.get("line_shape_models"):
        md += "\n\n" + line_shape_markdown(result.summary["line_shape_models"])
    atomic_write_text(out / "budget.md", md + "\n")
    mark = f"# {banner}\n" if banner else ""
    atomic_write_text(out / "budget.csv", mark + result.budget_a.to_csv())
    lines = (
        ([mark.rstrip()] if mark else [])
        + ["nu_hz,t_cut_s,tau_s,u_noise_s,u_h_s,u_s"]
        + [
            f"{nu:.9f},{tc:.6e},{tau:.10e},{un:.4e},{uh:.4e},{u:.4e}"
            for nu, tc, tau, un, uh, u in result.tau_table
        ]
    )
    atomic_write_text(out / "tau_posterior.csv", "\n".join(lines) + "\n")
    written += [out / "budget.md", out / "budget.csv", out / "tau_posterior.csv"]
    for key, run in result.runs.items():
        path = out / f"posterior_{key}.nc"
        run.save_netcdf(path)
        written.append(path)
        fig = corner.corner(run.flat(), labels=list(run.names), show_titles=True, title_fmt=".3g")
        with atomic_path(out / f"corner_{key}.png", suffix=".png") as tmp:
            fig.savefig(tmp, dpi=70)
        plt.close(fig)
        written.append(out / f"corner_{key}.png")
    return written


def failed_banner(result: BudgetResult) -> str:
    """The line every output of a budget that failed its gates starts with ('' when it passed)."""
    if result.passed:
        return ""
    return (
        f"FAILED: {result.status}. These numbers did not pass the convergence gates and must not "
        "be used; rerun with more steps (--steps, --max-steps) to resume the chains"
    )


def noise_markdown(noise: dict) -> str:
    """The ring-down noise section of budget.md: whiteness tests and the tau variance factor."""
    bp = noise["box_pierce"]
    verdict = (
        "white: decay-time uncertainties from the stated noise"
        if noise["white"]
        else "**coloured**: every ring-down fit and likelihood weights a record with "
        "noise_v sqrt(kappa), so u(tau) is that of the correlated noise"
    )
    return (
        "## Ring-down noise\n\n"
        f"Box-Pierce over {bp['lags']} lags p = {bp['p_value']:.3g} (rho(1) = "
        f"{noise['rho_1']:+.3f}); variance factor of tau kappa = {noise['kappa_median']:.3g} "
        f"(records {noise['kappa_min']:.3g}-{noise['kappa_max']:.3g}, z = "
        f"{noise['z_kappa']:+.1f} against white); residuals of {noise['residual_model']} at "
        f"t_cut = {noise['t_cut_s'] * 1e6:g} us. Verdict: {verdict}."
    )


def refinement_markdown(refinement: dict) -> str:
    """The H update table of budget.md: beat note, refined value, shift and tension z."""
    rows = [
        "## H: beat note updated by the ring-downs",
        "",
        "| parameter | beat note | u | refined | u | shift (beat-note u) | tension z |",
        "|---|---|---|---|---|---|---|",
    ]
    fmt = lambda v, f: "-" if v is None else format(v, f)  # noqa: E731
    for name, t in refinement["parameters"].items():
        rows.append(
            f"| {name} | {fmt(t['beat_note'], '.6g')} | {fmt(t['beat_note_u'], '.2g')} | "
            f"{t['refined']:.6g} | {t['refined_u']:.2g} | {fmt(t['shift_in_beat_u'], '+.2f')} | "
            f"{fmt(t['z'], '+.2f')} |"
        )
    rows.append("")
    finding = "; **finding: beat note and ring-downs disagree (|z| > 3)**"
    rows.append(
        f"Joint tension chi2 = {refinement['tension_chi2']:.2f} ({refinement['tension_dof']} dof, "
        f"p = {refinement['tension_p']:.3g})" + (finding if refinement["in_tension"] else "")
    )
    return "\n".join(rows)


def line_shape_markdown(models: dict) -> str:
    """The line-shape model section of budget.md: each candidate's fit, AIC, weight and A."""
    rows = [
        "## Line-shape model: candidate profiles",
        "",
        "| candidate | free shape parameters | chi2_red | AIC - AIC_min | weight | A (cm^-2) |",
        "|---|---|---|---|---|---|",
    ]
    for c in models["candidates"]:
        fit = (
            "fit failed | - | 0 | -"  # the reason is in budget.json
            if c["failed"]
            else f"{c['chi2_red']:.3g} | {c['delta_aic']:.3g} | {c['weight']:.3g} | "
            f"{c['line_area']:.7g}"
        )
        rows.append(f"| {c['label']} | {', '.join(c['shape_free'])} | {fit} |")
    rows += [
        "",
        f"Model-averaged A = {models['line_area']:.7g} cm^-2, between-model sd "
        f"{models['u_between']:.2g} cm^-2 ({models['method']}); A of the budget's profile "
        f"{models['line_area_of_profile']:.7g} cm^-2.",
    ]
    return "\n".join(rows)
