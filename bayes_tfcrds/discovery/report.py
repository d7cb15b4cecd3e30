"""The discovery report: ``discovery.json`` and ``discovery.html``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from bayes_tfcrds.discovery.views import effect_with_form
from bayes_tfcrds.discovery.workflow import DiscoveryResult
from bayes_tfcrds.output.files import atomic_write_text
from bayes_tfcrds.output.plotting import MICROSECOND, dodge, legend_outside, pyplot

# --------------------------------------------------------------------------- report


def _fmt_params(params):
    out = []
    for k, v in params.items():
        out.append(f"{k} = {v['value']:.4g} +/- {v['u']:.2g} {v['unit']}".strip())
    return "; ".join(out)


def _steps_table(rep, result) -> None:
    """One row per step: the effect added, its evidence, and every gap before and after."""
    gap_names = list(result.evaluations[0].gaps)
    rep.add_heading("Steps")
    rows = []
    for i, s in enumerate(result.steps):
        rows.append(
            [
                i + 1,
                effect_with_form(s),
                f"{s['evidence']:.1f}",
                f"{s['delta_chi2']:.1f} / {s['k']}",
                s["block"],
                _fmt_params(s["params"]),
                "; ".join(
                    f"{g}: {s['gaps_before'][g]['z']:.1f} -> {s['gaps_after'][g]['z']:.1f}"
                    for g in gap_names
                    if g in s["gaps_after"]
                ),
            ]
        )
    rep.add_table(
        [
            "step",
            "effect",
            "evidence (Delta BIC)",
            "Delta chi2 / k",
            "block",
            "fitted parameters",
            "gap z before -> after",
        ],
        rows or [["-", "nothing added", "", "", "", "", ""]],
    )


def _final_gaps_table(rep, result) -> None:
    """The gaps of the final model, each with its z and where it is largest."""
    rep.add_heading("Gaps of the final model")
    ev = result.evaluations[-1]
    rep.add_table(
        ["gap", "value", "expected", "z", "where"],
        [
            [
                k,
                f"{v['value']:.4g}",
                f"{v['expected']:.3g}" + (f" +/- {v['spread']:.2g}" if "spread" in v else ""),
                f"{v['z']:.2f}",
                v["where"],
            ]
            for k, v in ev.gaps.items()
        ],
    )


def _candidates_tables(rep, result) -> None:
    """Every candidate tried in each round, with its evidence."""
    rep.add_heading("Candidates per round")
    for r, cands in enumerate(result.candidates):
        rep.add_table(
            ["effect", "evidence", "Delta chi2", "k", "block", "note"],
            [
                [
                    c.effect,
                    f"{c.evidence:.1f}" if np.isfinite(c.evidence) else "n/a",
                    f"{c.delta_chi2:.1f}",
                    c.k,
                    c.block,
                    c.note,
                ]
                for c in cands
            ],
            caption=f"round {r + 1}",
        )


def _figures(plt, rep, result) -> None:
    """The gaps shrinking step by step; residuals of the start and final models."""
    gap_names = list(result.evaluations[0].gaps)
    fig, ax = plt.subplots(figsize=(7.5, 4))
    xs = np.arange(len(result.evaluations))
    # every gap is evaluated at every step: set them side by side so equal values stay visible
    for g, dx in zip(gap_names, dodge(len(gap_names), 0.04)):
        zs = [abs(e.gaps[g]["z"]) if g in e.gaps else np.nan for e in result.evaluations]
        ax.plot(xs + dx, np.maximum(zs, 1e-2), "o-", label=g)
    ax.axhline(3, color="k", ls=":", lw=1)
    ax.set_yscale("log")
    ax.set_xticks(xs, ["start"] + result.effects_added, rotation=20)
    ax.set_ylabel("|z| of each gap (standard deviations)")
    ax.set_xlabel("model after each step (effect added)")
    legend_outside(ax)
    rep.add_figure(fig, "Gaps shrinking: |z| of every gap metric after each step (dotted: 3 sigma)")
    fig, axes = plt.subplots(1, 2, figsize=(7.5, 3.4))
    for e, lab in ((result.evaluations[0], "start"), (result.evaluations[-1], "final")):
        lf = e.lines[0]
        order = np.argsort(e.detuning)
        axes[0].plot(e.detuning[order] / 1e9, lf.residuals_norm[order], "o-", ms=3, label=lab)
        tb = e.resid_first.mean(0)
        nbin = 64
        n = tb.size // nbin * nbin
        axes[1].plot(
            np.arange(n // nbin) * nbin * e.dt_s * 1e6,
            tb[:n].reshape(-1, nbin).mean(1) * np.sqrt(nbin * e.resid_first.shape[0]),
            label=lab,
        )
    axes[0].set_xlabel("detuning ν − ν₀ (GHz)")
    axes[0].set_ylabel("spectrum residual (units of u)")
    axes[1].set_xlabel(f"time after t_cut ({MICROSECOND})")
    axes[1].set_ylabel("stacked transient residual\n(standard deviations per bin)")
    for a in axes:
        a.axhline(0, color="0.5", lw=0.6)
    legend_outside(axes[1])
    rep.add_figure(
        fig,
        "Residuals of the start and final models: spectrum (left) and transients stacked over "
        "spectral points, 64-sample bins (right)",
    )


def _diagnostics(rep, result) -> None:
    """Pass/fail lines: what the final model leaves unexplained."""
    ev = result.evaluations[-1]
    rep.add_diagnostic(
        "final transient chi2/dof within 3 spread",
        abs(ev.gaps["transient_chi2"]["z"]) < 3,
        f"z = {ev.gaps['transient_chi2']['z']:.2f}",
    )
    rep.add_diagnostic(
        "final spectrum chi2/dof within 3 spread",
        abs(ev.gaps["spectrum_chi2"]["z"]) < 3,
        f"z = {ev.gaps['spectrum_chi2']['z']:.2f}",
    )
    if result.noise is not None:
        rep.add_diagnostic(
            "ring-down residuals white at the start (coloured noise, or transient structure no "
            "candidate explains, makes slow effects' evidence about kappa times too large)",
            result.noise.white,
            result.noise.summary_line(),
        )
    if "crds_cmds" in ev.gaps:
        rep.add_diagnostic(
            "A/A_ref consistent with 1 (k = 2)",
            ev.gaps["crds_cmds"]["z"] < 2,
            f"A/A_ref - 1 = {ev.gaps['crds_cmds']['value']:+.2e} +/- "
            f"{ev.gaps['crds_cmds']['u']:.1e}",
        )


def write_report(result: DiscoveryResult, outdir, seed=None, inputs=()):
    """``discovery.json`` and ``discovery.html`` (+ PDF of figures) in ``outdir``."""
    plt = pyplot()
    from bayes_tfcrds.output.report import Report, provenance

    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    data = result.to_json()
    atomic_write_text(out / "discovery.json", json.dumps(data, indent=2) + "\n")
    rep = Report(f"Discovery on configuration {result.config}")
    rep.add_summary("start model", result.start.label())
    rep.add_summary("final model", result.evaluations[-1].state.model.label())
    rep.add_summary("effects added", ", ".join(result.effects_added) or "none")
    rep.add_summary(
        "threshold", f"Delta BIC > {result.threshold:g}", "on the block the effect acts on"
    )
    rep.add_summary("time", f"{result.seconds:.1f} s")
    _steps_table(rep, result)
    _final_gaps_table(rep, result)
    _candidates_tables(rep, result)
    _figures(plt, rep, result)
    _diagnostics(rep, result)
    rep.provenance = provenance(seeds=seed, inputs=inputs)
    rep.write(out, stem="discovery")
    return out / "discovery.json", out / "discovery.html"
