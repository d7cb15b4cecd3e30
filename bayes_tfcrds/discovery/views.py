"""Notebook views of a :class:`~bayes_tfcrds.discovery.workflow.DiscoveryResult`.

Rendering only: the steps as plain text and an HTML table, and the figure of every gap's |z|
after each step (the gaps shrinking as effects are added).
"""

from __future__ import annotations

import numpy as np

from bayes_tfcrds.output.notebook import LEGEND_ABOVE, html_table, new_figure, text_table
from bayes_tfcrds.output.plotting import house_style

STEP_HEADER = ("step", "effect added", "evidence (Delta BIC)", "block", "fitted parameters")


def effect_with_form(step: dict) -> str:
    """A step's effect with its family's chosen member: "extinction_tail (2 exponentials)".

    Effects the data cannot tell from it follow: "... or hard_collisions (soft collisions)".
    """
    out = step["effect"] + (f" ({step['form']})" if step.get("form") else "")
    for alt in step.get("alternatives") or ():
        out += f" or {alt['effect']}" + (f" ({alt['form']})" if alt.get("form") else "")
    return out


def _params(params: dict) -> str:
    return "; ".join(
        f"{k} = {v['value']:.4g} ± {v['u']:.2g} {v['unit']}".strip() for k, v in params.items()
    )


def _step_rows(result) -> list:
    return [
        [i + 1, effect_with_form(s), f"{s['evidence']:.1f}", s["block"], _params(s["params"])]
        for i, s in enumerate(result.steps)
    ] or [["-", "nothing added", "", "", ""]]


def _head(result) -> str:
    final = result.evaluations[-1].state.model.label()
    return (
        f"discovery on configuration {result.config}: {result.start.label()} -> {final} "
        f"(threshold Delta BIC {result.threshold:g}, {result.seconds:.1f} s); stopped: "
        f"{result.stop_reason}"
    )


GAP_HEADER = ("gap", "calibrated z", "null band of z", "open", "where")


def _gap_rows(result) -> list:
    return [
        [
            k,
            f"{v.get('z_cal', v['z']):.2f}",
            f"[{v['band'][0]:.2f}, {v['band'][1]:.2f}]" if "band" in v else "",
            "OPEN" if v.get("open") else "closed",
            v.get("where", ""),
        ]
        for k, v in result.evaluations[-1].gaps.items()
    ]


def discovery_text(result) -> str:
    """The steps and the gaps the final model leaves, as plain text."""
    out = [_head(result), text_table(STEP_HEADER, _step_rows(result))]
    out.append(
        "gaps of the final model (calibrated z: about N(0, 1) when the model explains the data "
        "block; open when outside the null band of the analytic z):"
    )
    out.append(text_table(GAP_HEADER, _gap_rows(result)))
    if result.noise is not None:
        out.append(result.noise.summary_line())
    return "\n".join(out)


def discovery_html(result) -> str:
    """The steps and the final gaps as two small HTML tables."""
    return html_table(STEP_HEADER, _step_rows(result), caption=_head(result)) + html_table(
        GAP_HEADER, _gap_rows(result), caption="gaps of the final model"
    )


@house_style
def plot_discovery(result, ax=None):
    """Calibrated z of every gap after each step (log scale); a matplotlib Figure."""
    if ax is None:
        fig, axes = new_figure(1, 1)
        ax = axes[0, 0]
    else:
        fig = ax.figure
    xs = np.arange(len(result.evaluations))
    for g in result.evaluations[0].gaps:
        zs = [e.gaps[g].get("z_cal", np.nan) if g in e.gaps else np.nan for e in result.evaluations]
        ax.plot(xs, np.maximum(zs, 1e-2), "o-", label=g)
    ax.set_yscale("log")
    ax.set_xticks(xs, ["start", *result.effects_added], rotation=20)
    ax.set_xlabel("model after each step (effect added)")
    ax.set_ylabel("calibrated z of each gap (1)")
    ax.legend(ncols=3, frameon=False, fontsize="small", **LEGEND_ABOVE)
    return fig
