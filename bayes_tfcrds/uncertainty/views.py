"""Notebook views of a budget (:class:`~bayes_tfcrds.uncertainty.line_budget.BudgetResult`).

Rendering only: plain text, a JSON-ready dict, an HTML table and the bar chart of the budget
shares, all read from the result (its ``budget.json`` summary and its GUM budgets).
"""

from __future__ import annotations

import math
import textwrap

import numpy as np

from bayes_tfcrds.core.constants import edge_budget, line_area_to_cm2
from bayes_tfcrds.output.notebook import fmt, html_table, new_figure, text_table
from bayes_tfcrds.output.plotting import house_style

COMPONENT_HEADER = ("component of u_c(A)", "u (cm^-2)", "share of u_c^2 (%)")


def _head(summary: dict) -> str:
    window = f", {summary['window']} window" if summary.get("window") else ""
    post = summary.get("posterior") or {}
    approx = " (an APPROXIMATION: Gaussians at the least-squares fits)"
    posterior = ""
    if post:
        posterior = f"; posterior: {post['method']}" + (approx if post["approximation"] else "")
    return (
        f"budget of configuration {summary['configuration']}: {summary['method']}{window}, "
        f"t_cut = {summary['t_cut_s'] * 1e6:g} µs, {summary['profile']}; status "
        f"{summary['status']}{posterior}"
    )


def _result_rows(summary: dict) -> list:
    rows = []
    for key, label in (
        ("line_area", "A"),
        ("reference_area", "A_ref (CMDS)"),
        ("ratio", "A/A_ref"),
        ("intensity", "S(T_ref)"),
    ):
        e = summary.get(key)
        if e is None:
            continue
        if key == "intensity":
            label = f"S({e['t_ref_k']:g} K)"
        rows.append([label, fmt(e["value"], e["u"]), e.get("unit", "1")])
    if summary.get("en") is not None:
        rows.append(["E_n (A vs A_ref, k = 2)", fmt(summary["en"], digits=3), "1"])
    return rows


def _component_rows(summary: dict) -> list:
    return [
        [
            c["name"],
            fmt(c["u"], digits=3),
            fmt(None if c["share"] is None else 100 * c["share"], digits=3),
        ]
        for c in summary.get("components", [])
    ]


def budget_text(summary: dict) -> str:
    """The budget as plain text: results with u_c and units, then u_c(A) by component."""
    out = [_head(summary)]
    if summary["status"] != "ok":
        out.append("FAILED: no result (convergence gates not met); see summary['diagnostics']")
        return "\n".join(out)
    out.append(text_table(("quantity", "value ± u_c", "unit"), _result_rows(summary)))
    out.append(text_table(COMPONENT_HEADER, _component_rows(summary)))
    return "\n".join(out)


def budget_html(summary: dict) -> str:
    """Results and the components of u_c(A) as two small HTML tables."""
    if summary["status"] != "ok":
        return html_table(("status",), [[summary["status"]]], caption=_head(summary))
    return html_table(
        ("quantity", "value ± u_c", "unit"), _result_rows(summary), caption=_head(summary)
    ) + html_table(COMPONENT_HEADER, _component_rows(summary))


def _strict(x):
    """Nested data with NaN/inf floats (numpy scalars too) as None: strict JSON."""
    if isinstance(x, dict):
        return {str(k): _strict(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_strict(v) for v in x]
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(x) else None
    return x


def budget_dict(result) -> dict:
    """The ``budget.json`` summary plus the three GUM budgets (A in cm^-2 as in the summary)."""
    out = dict(result.summary)
    shown = [
        None if b is None else edge_budget(b).to_dict()
        for b in (result.budget_a, result.budget_s, result.budget_ratio)
    ]
    out["budgets"] = dict(zip(("line_area", "intensity", "ratio"), shown))
    return _strict(out)


@house_style
def plot_budget(result, ax=None):
    """Horizontal bars: each component's share of u_c^2(A) (%), its u in cm^-2 beside it.

    Shares of correlated components can be negative (an input that lowers u_c); they sum to
    100 %.
    """
    b = result.budget_a
    shares = b.shares()
    names = [c.name for c in b.components]
    values = np.array([100 * shares[n] for n in names])
    if ax is None:
        fig, axes = new_figure(1, 1)
        ax = axes[0, 0]
        fig.set_size_inches(7.5, 1.4 + 0.5 * len(names))
    else:
        fig = ax.figure
    y = np.arange(len(names))[::-1]
    ax.barh(y, np.nan_to_num(values), color=["C0" if v >= 0 else "C3" for v in values])
    ax.set_yticks(y, [textwrap.fill(n, 32) for n in names], fontsize="small")
    for yi, c, v in zip(y, b.components, values):
        u = line_area_to_cm2(c.contribution)
        ax.annotate(
            f" {u:.2g} cm⁻²",
            (max(np.nan_to_num(v), 0), yi),
            va="center",
            fontsize="small",
        )
    ax.axvline(0, color="0.3", lw=0.6)
    ax.set_xlim(min(0, np.nanmin(values) * 1.1), max(100, np.nanmax(values)) * 1.3)
    ax.set_xlabel("share of u_c²(A) (%)")
    uc = line_area_to_cm2(b.combined_u)
    ax.set_title(
        f"{result.summary['configuration']}: u_c(A) = {uc:.3g} cm⁻²\n"
        f"({100 * b.combined_u / abs(b.value):.3g} % of A)",
        loc="left",
        fontsize="small",
    )
    return fig
