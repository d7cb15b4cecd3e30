"""Matplotlib for files: the Agg backend and the toolkit's one figure style, set in one place.

Every figure the toolkit draws goes to a PNG, an SVG, a PDF or an HTML report, never to a
window, so the backend is set before pyplot is first imported (it also keeps CI and workers
headless). :func:`pyplot` also applies :data:`STYLE`, the house style a journal accepts:
TrueType (Type 42) fonts in PDF and PostScript (many journals refuse Type 3), 200 dpi raster
output, fonts of at least 8 pt at the drawn size (figures are drawn at the printed width, about
7.5 in for a full page), constrained layout (titles and labels never run into neighbours) and
error bars with caps.
"""

from __future__ import annotations

import textwrap

import numpy as np

MICROSECOND = "µs"  # the unit symbol for microseconds in every label (never "us")

# the smallest font any figure uses (pt at the drawn size): journals ask for >= 7-8 pt in print
MIN_FONT_PT = 8.0
RASTER_DPI = 200  # PNG resolution; >= 200 dpi is what journals ask of line art in raster form

STYLE = {
    "pdf.fonttype": 42,  # TrueType, not Type 3
    "ps.fonttype": 42,
    "svg.fonttype": "path",  # glyphs as outlines: the SVG looks the same without the font
    "svg.hashsalt": "bayes-tfcrds",  # stable element ids: the same figure gives the same bytes
    "savefig.dpi": RASTER_DPI,
    "figure.dpi": 100,
    "font.size": 9,
    "axes.titlesize": 9,
    "axes.labelsize": 9,
    "xtick.labelsize": MIN_FONT_PT,
    "ytick.labelsize": MIN_FONT_PT,
    "legend.fontsize": MIN_FONT_PT,
    "legend.title_fontsize": MIN_FONT_PT,
    "figure.titlesize": 10,
    "figure.constrained_layout.use": True,
    "errorbar.capsize": 2.5,
    "lines.markersize": 4,
    "legend.framealpha": 0.9,
    "axes.formatter.useoffset": False,  # tick labels show the values, not "+1.542e1"
}


def house_style(draw):
    """Decorator: ``draw`` runs with :data:`STYLE` in force; the caller's rcParams come back after.

    For the notebook views, which build Figure objects without pyplot: they get the house style's
    fonts, caps and layout without changing the backend or the user's global settings.
    """
    import functools

    @functools.wraps(draw)
    def styled(*args, **kwargs):
        import matplotlib

        with matplotlib.rc_context(STYLE):
            return draw(*args, **kwargs)

    return styled


def pyplot():
    """``matplotlib.pyplot`` with the Agg backend selected and :data:`STYLE` applied."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    matplotlib.rcParams.update(STYLE)
    return plt


def literal(text: str) -> str:
    r"""``text`` shown as it is in a matplotlib label or title, never read as mathtext.

    Names in figures come from files (configuration names); matplotlib parses text between two
    ``$`` as mathtext, so a configuration named ``$\frac{1}$`` stopped a study with a parse error
    after all its work. An escaped ``\$`` is drawn as a dollar sign.
    """
    return str(text).replace("$", r"\$")


def dodge(n_series: int, spacing: float) -> np.ndarray:
    """Horizontal offsets that set ``n_series`` series at the same x side by side.

    Four configurations measured at the same t_cut would otherwise hide each other's error bars;
    the offsets are centred on 0 and ``spacing`` apart (in the units of x), so the group stays
    centred on the true x.
    """
    return (np.arange(n_series) - (n_series - 1) / 2) * spacing


def legend_outside(ax, ncol: int = 1, **kwargs):
    """A legend to the right of ``ax``, off the data (constrained layout makes room for it)."""
    return ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), ncol=ncol, **kwargs)


def legend_above(ax, ncol: int, **kwargs):
    """A legend in one band above ``ax``, off the data (for wide axes with many series)."""
    return ax.legend(loc="lower left", bbox_to_anchor=(0.0, 1.01, 1.0, 0.1), ncol=ncol, **kwargs)


def caption_lines(caption: str, width_in: float, font_pt: float = 8.5) -> str:
    """``caption`` wrapped to lines that fit a figure ``width_in`` inches wide.

    An average glyph of a sans-serif font is about half its size wide, so a line holds about
    ``72 width / (0.5 font_pt)`` characters; 0.95 of that leaves a margin.
    """
    chars = max(int(0.95 * 72 * width_in / (0.5 * font_pt)), 20)
    return "\n".join(textwrap.wrap(caption, chars))


def draw_caption(fig, caption: str, number: int | None = None, font_pt: float = 8.5):
    """Draw ``caption`` under ``fig`` (as in a paper: "Figure n. ..."); returns the text artist.

    The text is placed under everything already drawn (tick labels and legends below the axes
    included); save with ``bbox_inches="tight"`` so the page grows to hold it.
    """
    head = f"Figure {number}. " if number is not None else ""
    text = caption_lines(head + caption, fig.get_figwidth(), font_pt)
    fig.canvas.draw()  # runs the layout, so the extent below is where things really are
    bottom_in = fig.get_tightbbox(fig.canvas.get_renderer()).y0
    y = (bottom_in - 0.08) / fig.get_figheight()  # a 0.08 in gap under the lowest artist
    # captions hold names from files: drawn as they are, never parsed as mathtext ("$")
    return fig.text(0.01, y, text, ha="left", va="top", fontsize=font_pt, parse_math=False)
