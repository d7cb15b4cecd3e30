"""Pieces shared by the notebook views of results: plain-text and HTML tables, figures.

The views (``fit/views.py``, ``uncertainty/views.py``, ``discovery/views.py``) render result
objects; the result classes only delegate to them (lmfit style: computation and rendering
apart).

Figures are built as :class:`matplotlib.figure.Figure` objects, not through ``pyplot``: a view
returns its figure to the caller and leaves pyplot's global state (its figure list and its
backend) alone, so in Jupyter the inline backend the user has stays in charge, and a loop
drawing hundreds of figures keeps no reference to any of them.
"""

from __future__ import annotations

import html

import numpy as np

LEGEND_ABOVE = {"loc": "lower left", "bbox_to_anchor": (0.0, 1.02), "borderaxespad": 0.0}


def text_table(header, rows) -> str:
    """Rows of cells as aligned plain text (cells formatted by the caller), header first."""
    cells = [[str(c) for c in header]] + [[str(c) for c in r] for r in rows]
    width = [max(len(r[i]) for r in cells) for i in range(len(header))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, width)).rstrip() for r in cells]
    lines.insert(1, "  ".join("-" * w for w in width))
    return "\n".join(lines)


def html_table(header, rows, caption: str | None = None) -> str:
    """A small HTML table (every cell escaped), with an optional caption."""
    head = "".join(f"<th>{html.escape(str(c))}</th>" for c in header)
    body = "".join(
        "<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in r) + "</tr>" for r in rows
    )
    cap = "" if caption is None else f"<caption>{html.escape(caption)}</caption>"
    return f"<table>{cap}<thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def fmt(value, u=None, digits: int = 6) -> str:
    """``value`` (and ``u``) for a table: ``g`` format, or ``-`` for None/NaN."""
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return "-"
    if u is None:
        return f"{value:.{digits}g}"
    return f"{value:.{digits}g} ± {u:.2g}"


def new_figure(nrows: int = 1, ncols: int = 1, height_ratios=None, width: float = 6.4):
    """(Figure, axes array of shape (nrows, ncols)): constrained layout, columns share x."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width * ncols**0.5, 2.0 + 2.2 * nrows), layout="constrained")
    axes = fig.subplots(
        nrows,
        ncols,
        squeeze=False,
        sharex="col",
        gridspec_kw=None if height_ratios is None else {"height_ratios": height_ratios},
    )
    return fig, axes


def data_and_residual_axes(ax=None):
    """(Figure, data Axes, residual Axes) for a fit plot.

    ``ax`` None draws a new figure; one Axes gets a residual panel appended below it; a pair of
    Axes is used as (data, residuals).
    """
    if ax is None:
        fig, axes = new_figure(2, 1, height_ratios=(3, 1))
        return fig, axes[0, 0], axes[1, 0]
    if isinstance(ax, (tuple, list, np.ndarray)):
        data_ax, resid_ax = ax
        return data_ax.figure, data_ax, resid_ax
    from mpl_toolkits.axes_grid1 import make_axes_locatable

    resid_ax = make_axes_locatable(ax).append_axes("bottom", size="35%", pad=0.35, sharex=ax)
    return ax.figure, ax, resid_ax
