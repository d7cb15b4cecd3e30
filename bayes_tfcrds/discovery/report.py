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
                    f"{g}: {_zc(s['gaps_before'][g])} -> {_zc(s['gaps_after'][g])}"
                    for g in gap_names
                    if g in s["gaps_after"]
                ),
                _pct(s.get("explained_fraction")),
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
            "calibrated gap z before -> after (* open)",
            "share of its block's open misfit removed",
        ],
        rows or [["-", "nothing added", "", "", "", "", "", ""]],
    )


def _zc(gap: dict) -> str:
    """A gap's calibrated z, starred when outside its null band."""
    return f"{gap.get('z_cal', gap['z']):.1f}" + ("*" if gap.get("open") else "")


def _pct(frac) -> str:
    return "" if frac is None else f"{100 * frac:.0f} %"


def _final_gaps_table(rep, result) -> None:
    """The gaps of the final model, each with its z and where it is largest."""
    rep.add_heading("Gaps of the final model")
    ev = result.evaluations[-1]
    rep.add_table(
        [
            "gap",
            "value",
            "analytic z",
            "null band of z (99 % level / gaps)",
            "null",
            "calibrated z",
            "open",
            "where",
        ],
        [
            [
                k,
                f"{v['value']:.4g}",
                f"{v['z']:.2f}",
                _band(v),
                _null(v),
                f"{v['z_cal']:.2f}" if "z_cal" in v else "",
                "OPEN" if v.get("open") else "closed",
                v["where"],
            ]
            for k, v in ev.gaps.items()
        ],
        caption=f"band: the central interval of the metric's null at level {ev.level:.3g} / "
        f"{len(ev.gaps)} gaps per side (Bonferroni); a gap is open above it",
    )
    if result.unexplained:
        rep.add_text(
            "Unexplained structure: "
            + "; ".join(
                f"{u['gap']} (calibrated z {u['z_cal']:.1f}) at {u['where']}"
                for u in result.unexplained
            )
        )


def _band(v: dict) -> str:
    return f"[{v['band'][0]:.2f}, {v['band'][1]:.2f}]" if "band" in v else ""


def _null(v: dict) -> str:
    if v.get("null") == "bootstrap":
        return f"bootstrap, {v['null_n']} replicates"
    return "analytic (not resampled)" if "null" in v else ""


def _candidates_tables(rep, result) -> None:
    """Every candidate tried in each round, with its evidence."""
    rep.add_heading("Candidates per round")
    for r, cands in enumerate(result.candidates):
        rep.add_table(
            [
                "effect",
                "evidence",
                "Delta chi2",
                "k",
                "block",
                "share of open misfit removed (gaps it worsens elsewhere)",
                "note",
            ],
            [
                [
                    c.effect,
                    f"{c.evidence:.1f}" if np.isfinite(c.evidence) else "n/a",
                    f"{c.delta_chi2:.1f}",
                    c.k,
                    c.block,
                    (_pct(c.explained) if c.explained is not None else "not tried")
                    + (f"; worsens {', '.join(c.worsens)}" if c.worsens else ""),
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
        zs = [e.gaps[g].get("z_cal", np.nan) if g in e.gaps else np.nan for e in result.evaluations]
        ax.plot(xs + dx, np.maximum(zs, 1e-2), "o-", label=g)
    crit = [_critical_z(e) for e in result.evaluations]
    ax.plot(xs, crit, "k_", ms=30, mew=1.5, label="open above (this step's level)")
    ax.set_yscale("log")
    ax.set_xticks(xs, ["start"] + result.effects_added, rotation=20)
    ax.set_ylabel("calibrated z of each gap (1)")
    ax.set_xlabel("model after each step (effect added)")
    legend_outside(ax)
    rep.add_figure(
        fig,
        "Gaps closing: the calibrated z of every gap metric after each step (bootstrap null); "
        "black bars: the level above which a gap is open (values below 0.01 drawn at 0.01)",
    )
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


def _critical_z(ev) -> float:
    """The calibrated z above which a gap of ``ev`` is open (normal approximation)."""
    from scipy import stats

    return float(stats.norm.isf(ev.level / len(ev.gaps))) if ev.level else np.nan


def _diagnostics(rep, result) -> None:
    """Pass/fail lines: what the final model leaves unexplained."""
    ev = result.evaluations[-1]
    rep.add_diagnostic(
        "every gap of the final model inside its null band",
        not result.unexplained,
        result.stop_reason,
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
    rep.add_summary(
        "stop rule",
        f"family-wise alpha {result.alpha:g}",
        "an effect is added only while a gap is outside its bootstrap null band at level "
        "alpha/2^step (Bonferroni over the gaps), and only if it removes at least half of the "
        "open misfit of its data block: a complete model gains an effect with probability "
        f"<= {result.alpha:g}, so the false-discovery rate is <= {result.alpha:g}",
    )
    rep.add_summary("stopped", result.stop_reason)
    rep.add_summary("time", f"{result.seconds:.1f} s")
    _steps_table(rep, result)
    _final_gaps_table(rep, result)
    _candidates_tables(rep, result)
    _figures(plt, rep, result)
    _diagnostics(rep, result)
    rep.provenance = provenance(seeds=seed, inputs=inputs)
    rep.write(out, stem="discovery")
    return out / "discovery.json", out / "discovery.html"
