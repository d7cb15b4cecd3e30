"""The files of a budget run: budget.json, GUM tables, decay-time posteriors, netCDF, corners.

One unit per quantity in every file: line areas A, A_ref in cm^-2 (SI Hz/m only as labelled
twins: ``*_si`` fields and columns, a prior's ``unit_si``, a netCDF variable's ``units_sampled``),
S(T_ref) in cm/molecule, A/A_ref in 1. budget.json's structure (for a budget that
imports this one, see :func:`component_from_result`) is described in data/FORMAT.md, section
"Outputs of `budget`".
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math
import os
from dataclasses import replace
from pathlib import Path

import numpy as np

from bayes_tfcrds.core.constants import EDGE_UNITS, edge_budget, edge_unit, line_area_to_cm2
from bayes_tfcrds.core.gum import Budget, Component, format_uncertainty, format_value
from bayes_tfcrds.output.files import atomic_path, atomic_write_text, clean_dead_writers
from bayes_tfcrds.output.plotting import RASTER_DPI, pyplot
from bayes_tfcrds.uncertainty.line_budget import POSTERIORS, BudgetResult

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


#: draws histogrammed in a corner plot's panels (every walker at every n-th step, for speed)
CORNER_DRAWS = 20_000


def thin_steps(flat, shape, most: int):
    """The rows of ``flat`` at every n-th step, with all walkers and ensembles kept.

    ``flat`` is in ensemble, step, walker order and ``shape`` gives those three sizes; n is the
    smallest stride that leaves at most ``most`` rows.
    """
    n_ens, n_steps, n_walk = shape
    stride = max(1, -(-n_ens * n_steps * n_walk // most))
    return flat.reshape(n_ens, n_steps, n_walk, -1)[:, ::stride].reshape(-1, flat.shape[-1])


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
    # the panels histogram at most CORNER_DRAWS draws: every walker at every n-th step (whole
    # steps, so no walker is left out; deterministic). Contours and histograms are as smooth; the
    # titles and quantile lines use every draw
    shown = thin_steps(data, run.samples.shape[:3], CORNER_DRAWS)
    corner.corner(
        shown,
        fig=fig,
        labels=labels,
        truths=None if all(t is None for t in truths) else truths,
        truth_color="tab:orange",
        show_titles=False,
        quantiles=None,
        label_kwargs={"fontsize": 9},
        labelpad=0.1,
        max_n_ticks=4,
        use_math_text=False,
        # the 2-d panels show the density (grey, fading to white in empty bins) and its contours;
        # individual draws beyond the outer contour are not drawn, so a sparse tail or a minor
        # mode of ~1 % of the draws is faint there (the 1-d histograms on the diagonal show it).
        # The markers and the white fill that hid the inner ones were half of the PNG's drawing
        # (1.3 s of 2.6 s per plot, 9 parameters) and tripled its size
        plot_datapoints=False,
        no_fill_contours=True,
    )
    for ax in fig.axes:
        ax.tick_params(labelsize=8)
    for i in range(k):  # the 16/50/84 % quantiles of all draws, dashed, as corner draws them
        for q in np.percentile(data[:, i], [16.0, 50.0, 84.0]):
            fig.axes[i * (k + 1)].axvline(q, ls="dashed", color="k")
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


def write_corner(key: str, run, truth, config, path) -> Path:
    """Draw the corner plot of posterior run ``key`` and save it at ``path`` (atomically)."""
    plt = pyplot()
    fig = corner_figure(key, run, truth, config)
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=RASTER_DPI)
    plt.close(fig)
    return Path(path)


def write_outputs(
    result: BudgetResult,
    outdir,
    seed: int | None = None,
    truth: dict | None = None,
    workers: int = 1,
    started: dict | None = None,
) -> list:
    """budget.json, budget tables (Markdown, CSV), posteriors (arviz netCDF) and corner plots.

    Every file goes through a temporary name and a rename, so none is ever half-written.
    ``truth`` (the bundle's /truth, from bayes_tfcrds.bundle.reader.load_truth) adds truth lines
    to the corner plots of a simulated bundle. With ``workers`` > 1 the corner plots (seconds
    each) are drawn in that many processes while this one writes the rest; the files are the
    same. ``started`` (from :func:`corner_job`) holds the corner plots already submitted to a
    pool while the budget ran: one still waiting there is taken back and drawn here once the
    rest is written.
    """
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    # temporary files left by an earlier run that was killed while writing (a live run's stay)
    clean_dead_writers(out)
    written = []
    summary = dict(result.summary)
    if seed is not None:
        summary["seed"] = seed
    if "posterior" in summary:
        summary["posterior"] = posterior_record(summary["posterior"]["method"])
    atomic_write_text(out / "budget.json", json.dumps(summary, indent=2, default=float) + "\n")
    written.append(out / "budget.json")
    tables = [result.budget_a, result.budget_s] + (
        [result.budget_ratio] if result.budget_ratio is not None else []
    )
    mcs = _monte_carlo_results(result)
    md = "\n\n".join(
        f"## {b.quantity}\n\n{edge_budget(b).to_markdown()}"
        + monte_carlo_markdown(mc, *edge_unit(b.unit))
        for b, mc in zip(tables, mcs)
    )
    if "posterior" in summary:
        md = f"{posterior_markdown(summary['posterior'])}\n\n{md}"
    banner = failed_banner(result)
    if banner:
        md = f"# {banner}\n\n{md}"
    refinement = (result.summary.get("transfer_function") or {}).get("refinement")
    if refinement:
        md += "\n\n" + refinement_markdown(refinement)
    ident = (result.summary.get("transfer_function") or {}).get("identification")
    if ident:
        md += "\n\n" + identification_markdown(ident)
    if result.summary.get("noise"):
        md += "\n\n" + noise_markdown(result.summary["noise"])
    if result.summary.get("instrument"):
        md += "\n\n" + instrument_markdown(result.summary["instrument"])
    if result.summary.get("line_shape_models"):
        md += "\n\n" + line_shape_markdown(result.summary["line_shape_models"])
    md += "\n\n" + priors_markdown(result.summary.get("priors") or {})
    atomic_write_text(out / "budget.md", md + "\n")
    mark = f"# {banner}\n" if banner else ""
    atomic_write_text(out / "budget.csv", mark + budget_csv(result))
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
    config = result.summary.get("configuration")
    started = started or {}
    corners = [
        (key, run, truth, config, out / f"corner_{key}.png")
        for key, run in result.runs.items()
        if key not in started
    ]
    if started:
        return written + _finish_started(result, out, started, corners)
    pool = None
    if workers > 1 and len(corners) > 1:
        from concurrent.futures import ProcessPoolExecutor

        pool = ProcessPoolExecutor(max_workers=min(int(workers), len(corners)))
    try:
        drawn = [pool.submit(write_corner, *c) for c in corners] if pool else []
        written += write_posteriors(result, out)
        written += [f.result() for f in drawn] if pool else [write_corner(*c) for c in corners]
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
    return written


def write_posteriors(result, out: Path) -> list:
    """Each posterior run as arviz netCDF, ``posterior_KEY.nc`` in ``out``; the paths."""
    written = []
    for key, run in result.runs.items():
        path = out / f"posterior_{key}.nc"
        run.save_netcdf(path, EDGE_UNITS)  # line areas in cm^-2, as every other file
        written.append(path)
    return written


def corner_job(pool, out, truth, config):
    """Corner plots drawn in ``pool`` while the budget runs: ``on_run`` for ``run_budget``.

    ``on_run(key, run)`` (for :func:`~bayes_tfcrds.uncertainty.line_budget.run_budget`) submits
    each posterior's corner plot to ``pool`` as soon as the run is sampled. The pool draws it
    under a pending name (``corner_KEY.pending.png``); :func:`write_outputs` gives it its name,
    so a run that fails later leaves no plot beside an earlier run's budget
    (:func:`discard_started`).

    Returns (on_run, started): ``started`` fills with {key: (future, write_corner arguments)}.
    """
    started = {}

    def on_run(key, run):
        args = (key, run, truth, config, Path(out) / f"corner_{key}.png")
        pending = _pending(args[4])
        started[key] = (pool.submit(write_corner, *args[:4], pending), args)

    return on_run, started


def _pending(path: Path) -> Path:
    return path.with_name(path.stem + ".pending.png")


def discard_started(started: dict | None) -> None:
    """Cancel the corner plots a failed run started and remove those drawn (after the pool)."""
    for fut, args in (started or {}).values():
        fut.cancel()
        with contextlib.suppress(FileNotFoundError):
            _pending(args[4]).unlink()


def _finish_started(result, out: Path, started: dict, corners: list) -> list:
    """The netCDF files, then every corner plot: those the pool has not begun are drawn here.

    ``corners`` are the write_corner arguments of the runs nobody started; a started plot still
    waiting in the pool is cancelled there and drawn here, the latest submitted first.
    """
    written = write_posteriors(result, out)
    todo = list(corners)
    todo += [args for fut, args in reversed(list(started.values())) if fut.cancel()]
    written += [write_corner(*c) for c in todo]
    for fut, args in started.values():
        if not fut.cancelled():
            os.replace(fut.result(), args[4])
            written.append(args[4])
    return written


#: the coverage study of the Laplace posterior (studies/coverage_laplace.toml), as committed in
#: the source repository; the shipped MCMC path has its own, reports/coverage
COVERAGE_NUMBERS = Path("reports") / "coverage_laplace" / "numbers.json"
COVERAGE_QUANTITIES = ("A", "A/A_ref", "A (u_c)", "A/A_ref (u_c)")


#: the same figures shipped with the package (an installed package has no reports/); a test
#: keeps it equal to laplace_coverage(reports/coverage_laplace/numbers.json)
PACKAGED_COVERAGE = Path(__file__).resolve().parents[1] / "data" / "laplace_coverage.json"


def laplace_coverage(path=None) -> dict | None:
    """The measured coverage of the Laplace posterior, read from the coverage study's numbers.

    ``path``: a coverage study's numbers.json; by default the copy shipped with the package
    (``data/laplace_coverage.json``, extracted from reports/coverage_laplace/numbers.json).
    None when the file is absent or is not a Laplace coverage study. Returns the file, the
    number of campaigns,
    and per quantity the fraction of campaigns whose 68 % and 95 % intervals held the truth.
    """
    if path is None:
        try:
            return json.loads(PACKAGED_COVERAGE.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return None
    path = Path(path)
    try:
        numbers = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if numbers.get("posterior") != "laplace":
        return None
    sums = numbers.get("summaries", {})
    return {
        "source": str(COVERAGE_NUMBERS),
        "n_campaigns": numbers.get("n_campaigns"),
        "coverage": {
            q: {"68": sums[q]["coverage_68"], "95": sums[q]["coverage_95"]}
            for q in COVERAGE_QUANTITIES
            if q in sums
        },
        "mcmc_cross_check_campaigns": (numbers.get("mcmc_check") or {}).get("n"),
    }


def posterior_record(method: str, coverage_path=None) -> dict:
    """budget.json's ``posterior``: the method and whether it is an approximation.

    For the Laplace approximation, also its measured coverage (:func:`laplace_coverage`).
    """
    record = {
        "method": method,
        "approximation": method == "laplace",
        "description": POSTERIORS[method],
    }
    if method == "laplace":
        record["measured_coverage"] = laplace_coverage(coverage_path) or {
            "source": f"{COVERAGE_NUMBERS} of the source repository (not beside this installation)"
        }
    return record


def posterior_line(record: dict) -> str:
    """One line naming the posterior; for Laplace, the approximation and its measured coverage."""
    if not record["approximation"]:
        return f"posterior: {record['method']} ({record['description']})"
    cov = record.get("measured_coverage", {})
    figures = "; ".join(
        f"{q} {100 * c['68']:.1f} % / {100 * c['95']:.1f} %"
        for q, c in cov.get("coverage", {}).items()
    )
    measured = (
        f"measured coverage of the 68 % / 95 % intervals over {cov['n_campaigns']} simulated "
        f"campaigns: {figures} ({cov['source']})"
        if figures
        else f"measured coverage: {cov.get('source')}"
    )
    return f"posterior: APPROXIMATION, {record['description']}; {measured}"


def posterior_markdown(record: dict) -> str:
    """The posterior section at the top of budget.md."""
    if not record["approximation"]:
        return f"Posterior: **{record['method']}**, {record['description']}."
    cov = record.get("measured_coverage", {})
    rows = [
        "## Posterior: Laplace approximation",
        "",
        f"{record['description'][0].upper()}{record['description'][1:]}.",
        "",
    ]
    if cov.get("coverage"):
        rows += [
            f"Measured coverage over {cov['n_campaigns']} simulated campaigns ({cov['source']}): "
            "A and A/A_ref are the posterior's own intervals (ring-down noise and H); the (u_c) "
            "rows are those of the full GUM u_c, Type B rows included.",
            "",
            "| quantity | 68 % interval holds the truth | 95 % interval holds the truth |",
            "|---|---|---|",
        ]
        rows += [
            f"| {q} | {100 * c['68']:.1f} % | {100 * c['95']:.1f} % |"
            for q, c in cov["coverage"].items()
        ]
    else:
        rows.append(f"Measured coverage: {cov.get('source')}.")
    return "\n".join(rows)


def failed_banner(result: BudgetResult) -> str:
    """The line every output of a budget that failed its gates starts with ('' when it passed)."""
    if result.passed:
        return ""
    return (
        f"FAILED: {result.status}. These numbers did not pass the convergence gates and must not "
        "be used; rerun with more steps (--steps, --max-steps) to resume the chains"
    )


def instrument_markdown(instrument: dict) -> str:
    """The 'Instrument rows' section: what sized each data-sized instrument row of u(A)."""
    lines = [
        "## Instrument rows",
        "",
        "Each row asks the data how large an effect the analysis model leaves out could be "
        "(static nonlinearity V' = V + beta V^2/1 V fitted on the ring-downs; baseline slope and "
        "etalon by the BIC weight w of the line fit with them). A finding means the data ask for "
        "the effect.",
        "",
        "| row | sized by | change of A (cm^-2) | finding |",
        "|---|---|---|---|",
    ]
    for name, d in instrument.items():
        if "beta" in d:
            by = f"beta = {d['beta']:.3g} +/- {d['u_beta']:.2g}"
        else:
            by = f"w = {d['weight_extended']:.3g}"
        lines.append(f"| {name} | {by} | {d['delta_a_cm2']:+.3g} | {d.get('finding') or '-'} |")
    return "\n".join(lines)


def noise_markdown(noise: dict) -> str:
    """The ring-down noise section of budget.md: whiteness tests and the tau variance factor."""
    bp = noise["box_pierce"]
    weighted = (
        "every ring-down fit and likelihood weights a record with noise_v sqrt(kappa), so "
        "u(tau) is that of the correlated noise"
    )
    if not noise.get("kappa_applied", not noise["white"]):
        verdict = "white: decay-time uncertainties from the stated noise"
    elif noise["white"]:
        verdict = (
            "white at the 1e-3 tests, but a 1/f term improves the low band by dchi2 = "
            f"{noise['flicker_dchi2']:.1f} (Akaike's criterion keeps it): " + weighted
        )
    else:
        verdict = "**coloured**: " + weighted
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
    if refinement.get("region"):  # why H was not refined about the least-squares beat note
        rows += ["", f"Where H was refined: {refinement['region']}."]
    return "\n".join(rows)


def identification_markdown(ident: dict) -> str:
    """Which H parameters the data identify, with the other descriptions of the same H(f)."""
    rows = ["## H: parameters the data identify", ""]
    if not ident["not_identified"]:
        rows.append(
            "Every sampled H parameter: no other description of Eq. 2 gives the same H(f) within "
            f"its uncertainty (largest |H - H*|/u(H) allowed: {ident['threshold_max_z']:.2f})."
        )
        return "\n".join(rows)
    rows.append(
        f"**Not identified: {', '.join(ident['not_identified'])}.** The beat note and the "
        "ring-downs see H(f) only; these descriptions of Eq. 2 give the reported H(f) within its "
        "uncertainty, with the poles shared out differently between the two paths. H(f), the "
        "decay times and A do not depend on the choice; the u of the parameters named describes "
        "the reported description only."
    )
    rows.append("")
    names = [k for k in ident["descriptions"][0] if k not in ("max_z", "differs_in")]
    rows.append("| " + " | ".join(names) + " | max abs(H - H*)/u(H) | differs in |")
    rows.append("|" + "---|" * (len(names) + 2))
    for d in ident["descriptions"]:
        vals = " | ".join(format(d[n], ".6g") for n in names)
        rows.append(f"| {vals} | {d['max_z']:.2f} | {', '.join(d['differs_in'])} |")
    return "\n".join(rows)


def _monte_carlo_results(result: BudgetResult) -> list:
    """The MC results in the order of the budget tables (A, S, A/A_ref), None where absent."""
    mc = result.monte_carlo
    if mc is None:
        return [None, None, None]
    return [mc.line_area, mc.intensity, mc.ratio]


def monte_carlo_markdown(mc, unit: str, scale: float = 1.0) -> str:
    """The JCGM 101 line under a budget table: y, u, 95 % interval, k, trials, stability.

    ``mc`` in the budget's SI unit; shown in ``unit`` (= ``scale`` x SI).
    """
    if mc is None:
        return ""
    mc = replace(
        mc,
        value=mc.value * scale,
        u=mc.u * scale,
        interval=(mc.interval[0] * scale, mc.interval[1] * scale),
        tolerance=mc.tolerance * scale,
    )
    state = "stabilised" if mc.stabilised else "**not stabilised** (trial cap reached)"
    return (
        f"\nJCGM 101 adaptive Monte Carlo ({mc.trials} trials, {state} at delta = "
        f"{mc.tolerance:.1g} {unit}): y = {format_value(mc.value, mc.u)} {unit}, u = "
        f"{format_uncertainty(mc.u)} {unit}, 95 % interval [{format_value(mc.interval[0], mc.u)}"
        f", {format_value(mc.interval[1], mc.u)}] {unit}, k = half-width/u = {mc.k:.3f} "
        "(beside the GUM k = 2 and k = t_95(nu_eff)).\n"
    )


# budget.csv: one unit per quantity, as budget.json (A in cm^-2), SI beside it
CSV_COLUMNS = (
    "measurand",
    "row",
    "kind",
    "value",
    "standard_uncertainty",
    "unit",
    "sensitivity_coefficient",
    "contribution",
    "contribution_unit",
    "share",
    "dof",
    "k",
    "interval_low",
    "interval_high",
    "value_si",
    "standard_uncertainty_si",
    "unit_si",
    "note",
)


def _budget_rows(budget: Budget, mc) -> list:
    """The rows of one budget in budget.json's units: inputs, the GUM result, the MC result."""
    out_unit, f_out = edge_unit(budget.unit)
    rows = []
    shares = budget.shares()
    for c in budget.components:
        unit, f_in = edge_unit(c.unit)
        rows.append(
            {
                "row": c.name,
                "kind": "input",
                "value": None if c.value is None else c.value * f_in,
                "standard_uncertainty": c.u * f_in,
                "unit": unit,
                "sensitivity_coefficient": c.sensitivity * f_out / f_in,
                "contribution": c.contribution * f_out,
                "contribution_unit": out_unit,
                "share": shares[c.name],
                "dof": c.dof,
                "value_si": c.value if f_in != 1.0 else None,
                "standard_uncertainty_si": c.u if f_in != 1.0 else None,
                "unit_si": c.unit if f_in != 1.0 else None,
                "note": c.note,
            }
        )
    nu = budget.effective_dof
    k95 = budget.coverage_factor(0.95)
    y, u = budget.value, budget.combined_u
    si = f_out != 1.0
    rows.append(
        {
            "row": "GUM combined (k = t_95(nu_eff))",
            "kind": "combined",
            "value": y * f_out,
            "standard_uncertainty": u * f_out,
            "unit": out_unit,
            "dof": nu,
            "k": k95,
            "interval_low": (y - k95 * u) * f_out,
            "interval_high": (y + k95 * u) * f_out,
            "value_si": y if si else None,
            "standard_uncertainty_si": u if si else None,
            "unit_si": budget.unit if si else None,
            "note": "GUM Eq. 16, Welch-Satterthwaite nu_eff (G.2b); U (k = 2) = 2 u",
        }
    )
    if mc is not None:
        rows.append(
            {
                "row": "JCGM 101 Monte Carlo",
                "kind": "monte_carlo",
                "value": mc.value * f_out,
                "standard_uncertainty": mc.u * f_out,
                "unit": out_unit,
                "k": mc.k,
                "interval_low": mc.interval[0] * f_out,
                "interval_high": mc.interval[1] * f_out,
                "value_si": mc.value if si else None,
                "standard_uncertainty_si": mc.u if si else None,
                "unit_si": budget.unit if si else None,
                "note": f"adaptive, {mc.trials} trials, "
                + ("stabilised" if mc.stabilised else "not stabilised"),
            }
        )
    return [{"measurand": budget.quantity, **r} for r in rows]


def _cell(v) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return "" if math.isnan(v) else ("inf" if math.isinf(v) else repr(v))
    return str(v)


def budget_csv(result: BudgetResult) -> str:
    """budget.csv: every row of the A, S(T_ref) and A/A_ref budgets, A_ref, the GUM and MC results.

    Units as budget.json (A and A_ref in cm^-2, S in cm/molecule), SI (Hz/m) in the *_si columns
    where converted; full precision; inf dof written 'inf'.
    """
    rows = []
    tables = [result.budget_a, result.budget_s, result.budget_ratio]
    for budget, mc in zip(tables, _monte_carlo_results(result)):
        if budget is not None:
            rows += _budget_rows(budget, mc)
    if result.budget_ratio is not None:
        ref = result.budget_ratio.components[1]
        f = float(line_area_to_cm2(1.0))
        rows.append(
            {
                "measurand": "reference area A_ref (CMDS)",
                "row": "CMDS posterior",
                "kind": "combined",
                "value": ref.value * f,
                "standard_uncertainty": ref.u * f,
                "unit": "cm^-2",
                "dof": ref.dof,
                "value_si": ref.value,
                "standard_uncertainty_si": ref.u,
                "unit_si": ref.unit,
                "note": ref.note,
            }
        )
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    for r in rows:
        w.writerow([_cell(r.get(k)) for k in CSV_COLUMNS])
    return buf.getvalue()


def component_from_result(entry: dict, name: str, sensitivity: float, note: str = "") -> Component:
    """A row of another GUM budget from one quantity of a budget.json (``line_area``, ...).

    ``entry``: e.g. ``json.load(f)["intensity"]`` with ``value``, ``u``, ``unit`` and
    ``effective_dof`` ("inf" for infinite); ``sensitivity``: c_i of the importing budget per
    that unit. The importing budget then carries u and nu_eff on (GUM G.4), and its Monte Carlo
    can use ``entry["monte_carlo"]`` (y, u, interval) as the input's summary.
    """
    if "u_holds" in entry:  # linefit.json: its u is the line fit's (and H's), not a u_c
        raise ValueError(
            f"the entry for {name!r} is a line fit's (its u holds: {entry['u_holds']}), not a "
            "budget's combined u: import budget.json (bayes-tfcrds budget) instead"
        )
    missing = [k for k in ("value", "u", "unit") if entry.get(k) is None]
    if missing:
        raise ValueError(
            f"budget.json entry for {name!r} lacks {missing}: was the budget run failed? "
            "(its numbers are then under 'unconverged_estimates' and must not be used)"
        )
    dof = entry.get("effective_dof", "inf")
    return Component(
        name,
        float(entry["value"]),
        float(entry["u"]),
        float(sensitivity),
        entry["unit"],
        dof=math.inf if dof in ("inf", None) else float(dof),
        note=note or "imported from budget.json (combined u and effective dof of that budget)",
    )


PRIOR_COLUMNS = ("posterior", "parameter", "prior", "lower", "upper", "unit", "condition")


def prior_rows(priors: dict) -> list:
    """Rows (PRIOR_COLUMNS) of the ``priors`` of budget.json; an unbounded side reads -inf/inf."""
    bound = lambda v, side: side if v is None else format(v, ".6g")  # noqa: E731
    return [
        [run["posterior"], p["parameter"], p["family"], bound(p["lower"], "-inf")]
        + [bound(p["upper"], "inf"), p["unit"], p["condition"] or p["note"]]
        for run in priors.values()
        for p in run["parameters"]
    ]


def priors_markdown(priors: dict) -> str:
    """The Priors section of budget.md: every sampled parameter's prior family, bounds and unit."""
    if not priors:
        return "## Priors\n\nNone: Laplace posteriors (Gaussians about the least-squares fits)."
    rows = ["## Priors", "", "| " + " | ".join(PRIOR_COLUMNS) + " |", "|---" * 7 + "|"]
    rows += ["| " + " | ".join(c.replace("|", "\\|") for c in r) + " |" for r in prior_rows(priors)]
    rows += ["", "log-uniform priors are sampled as the logarithm of the parameter."]
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
