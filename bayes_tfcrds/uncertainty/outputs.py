"""The files of a budget run: budget.json, GUM tables, decay-time posteriors, netCDF, corners."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from bayes_tfcrds.core.constants import line_area_to_cm2
from bayes_tfcrds.output.files import atomic_path, atomic_write_text, clean_dead_writers
from bayes_tfcrds.output.plotting import RASTER_DPI, pyplot
from bayes_tfcrds.uncertainty.line_budget import BudgetResult

# sampled parameter -> (symbol, unit, factor from SI to that unit, /truth entry or None). The
# samplers work in SI (and in log for f_c, f_r, Gamma_r); a corner plot shows what a
# spectroscopist reads: natural values in kHz, MHz, cm^-2 and cm^-1.
_CORNER_AXES = {
    "f_c_hz": ("f_c", "kHz", 1e-3, ("config", "f_c_hz")),
    "f_r_hz": ("f_r", "MHz", 1e-6, ("config", "f_r_hz")),
    "a_r": ("A_r", "", 1.0, ("config", "a_r")),
    "gamma_r": ("Γ_r", "", 1.0, ("config", "gamma_r")),
    "n_r": ("n_r", "", 1.0, ("config", "n_r")),
    "scale": ("K", "", 1.0, None),  # the beat note's scale factor
    "line_area": ("A", "cm⁻²", float(line_area_to_cm2(1.0)), ("line", "line_area_hz_per_m")),
    "position_offset_hz": ("ν − ν_ref", "MHz", 1e-6, None),
    "gamma0_hz": ("Γ0", "MHz", 1e-6, ("line", "gamma0_hz")),
    "gamma2_hz": ("Γ2", "MHz", 1e-6, ("line", "gamma2_hz")),
    "nu_vc_hz": ("ν_VC", "MHz", 1e-6, ("line", "nu_vc_hz")),
}
_SUPERSCRIPT = str.maketrans("-0123456789", "⁻⁰¹²³⁴⁵⁶⁷⁸⁹")


def _baseline_axis(name: str, run_key: str):
    """(symbol, unit, factor, truth) of a spectrum's baseline or slope parameter.

    A CRDS (absorption) baseline is the empty-cavity loss in 1/m, shown in cm^-1; a CMDS
    (dispersion) baseline is a frequency shift in Hz, shown in kHz, and its slope is Hz per Hz.
    """
    i = name.removeprefix("baseline").removeprefix("slope")
    i = "" if i == "0" else f" {i}"  # numbered only in a joint fit of several spectra
    if run_key == "cmds":
        if name.startswith("slope"):
            return (f"CMDS slope{i}", "Hz/GHz", 1e9, None)
        return (f"CMDS offset{i}", "Hz", 1.0, None)
    if name.startswith("slope"):
        return (f"loss slope{i}", "cm⁻¹/GHz", 1e-2 * 1e9, None)
    return (f"α_loss{i}", "cm⁻¹", 1e-2, ("alpha_loss_per_m",))


def corner_axes(run_key: str, names, flat, truth=None, config=None):
    """Columns, axis labels and truth values of a corner plot of one posterior run.

    ``flat`` holds draws (n, k) in the sampler's space (SI; ``log_`` names are natural logs);
    each column is returned in the unit of its label, scaled by a power of ten when its values
    are far from 1 (the label then says e.g. "A (10⁻⁷ cm⁻²)"). ``truth`` is the bundle's /truth
    (bayes_tfcrds.bundle.reader.load_truth) and ``config`` the configuration analysed; a truth
    is None where the bundle has none or the parameter has no simulated value.
    """
    cols, labels, truths = [], [], []
    for j, name in enumerate(names):
        x = np.asarray(flat[:, j], float)
        base = name.removeprefix("log_")
        if base != name:
            x = np.exp(x)
        if base in _CORNER_AXES:
            sym, unit, factor, where = _CORNER_AXES[base]
        elif base.startswith(("baseline", "slope")):
            sym, unit, factor, where = _baseline_axis(base, run_key)
        else:  # a parameter this table does not know: its own name, in SI
            sym, unit, factor, where = base, "SI", 1.0, None
        x = x * factor
        t = _truth_value(truth, config, where)
        t = None if t is None else t * factor
        med = float(np.nanmedian(np.abs(x))) if x.size else 0.0
        power = int(np.floor(np.log10(med))) if np.isfinite(med) and med > 0 else 0
        power = 0 if -2 <= power <= 3 else power
        scale = 10.0**-power
        unit_text = unit
        if power:
            unit_text = f"10{str(power).translate(_SUPERSCRIPT)} {unit}".rstrip()
        cols.append(x * scale)
        # a dimensionless quantity is labelled by its symbol alone, as in a paper
        labels.append(f"{sym} ({unit_text})" if unit_text else sym)
        truths.append(None if t is None else t * scale)
    return np.column_stack(cols), labels, truths


def _truth_value(truth, config, where):
    """The simulated value at ``where`` in /truth (config-level or line-level), or None."""
    if truth is None or where is None:
        return None
    try:
        if where[0] == "config":
            v = truth["configs"][config][where[1]]
        elif where[0] == "line":
            v = truth["line"][where[1]]
        else:
            v = truth[where[0]]
        v = float(v)
    except (KeyError, TypeError, ValueError):
        return None
    return v if np.isfinite(v) else None


def estimate_text(values) -> str:
    """Median +/- half the central 68 % width, rounded to two significant digits of the latter.

    The precision a metrologist quotes: the uncertainty to two digits and the value to the same
    decimal place (GUM 7.2.6), e.g. ``51.0 ± 1.7``.
    """
    lo, med, hi = np.percentile(values, [15.865, 50.0, 84.135])
    u = 0.5 * (hi - lo)
    if not (np.isfinite(u) and u > 0):
        return f"{med:.6g}"
    decimals = max(1 - int(np.floor(np.log10(u))), 0)
    return f"{med:.{decimals}f} ± {u:.{decimals}f}"


def corner_figure(run_key: str, run, truth=None, config=None):
    """The corner plot of one posterior run: named axes with units, GUM-rounded titles, truths.

    Drawn with the house style (bayes_tfcrds.output.plotting); each diagonal panel is titled
    with the median and the 68 % half-width (two significant digits); truth lines (orange) where
    the bundle has /truth. The caller saves and closes the figure.
    """
    import corner

    plt = pyplot()
    data, labels, truths = corner_axes(run_key, list(run.names), run.flat(), truth, config)
    k = data.shape[1]
    # corner lays the panels out itself: no constrained layout on its figure
    fig = plt.figure(figsize=(max(1.8 * k, 4.0),) * 2, layout="none")
    corner.corner(
        data,
        fig=fig,
        labels=labels,
        truths=None if all(t is None for t in truths) else truths,
        truth_color="tab:orange",
        show_titles=False,
        quantiles=[0.16, 0.5, 0.84],
        label_kwargs={"fontsize": 9},
        labelpad=0.1,
        max_n_ticks=4,
        use_math_text=False,
    )
    for ax in fig.axes:
        ax.tick_params(labelsize=8)
    for i, label in enumerate(labels):
        symbol, _, unit = label.partition(" (")
        unit, est = unit.rstrip(")"), estimate_text(data[:, i])
        # two lines (symbol, then value): one line ran into the next panel; nothing is drawn
        # above a diagonal panel, so the second line has room
        if unit.startswith("10"):  # a scaled unit: "A =\n(1.3141 ± 0.0014) × 10⁻⁷ cm⁻²"
            title = f"{symbol} =\n({est}) × {unit}"
        else:
            title = f"{symbol} =\n{est} {unit}".rstrip()
        fig.axes[i * (k + 1)].set_title(title, fontsize=8)
    fig.subplots_adjust(left=0.13, bottom=0.13, right=0.96, top=0.9, wspace=0.1, hspace=0.1)
    run_title = {"h": "H | beat note", "line": "line | ring-downs", "cmds": "A_ref | CMDS"}
    fig.suptitle(
        f"posterior {run_title.get(run_key, run_key)}"
        + (f", configuration {config}" if config else "")
        + ("; orange: simulated truth" if any(t is not None for t in truths) else "")
        + ("\nK: scale of the beat-note |H|" if "scale" in run.names else ""),
        fontsize=9,
    )
    return fig


def write_outputs(
    result: BudgetResult, outdir, seed: int | None = None, truth: dict | None = None
) -> list:
    """budget.json, budget tables (Markdown, CSV), posteriors (arviz netCDF) and corner plots.

    Every file goes through a temporary name and a rename, so none is ever half-written.
    ``truth`` (the bundle's /truth, from bayes_tfcrds.bundle.reader.load_truth) adds truth lines
    to the corner plots of a simulated bundle.
    """
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
        fig = corner_figure(key, run, truth, result.summary.get("configuration"))
        with atomic_path(out / f"corner_{key}.png", suffix=".png") as tmp:
            fig.savefig(tmp, dpi=RASTER_DPI)
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
