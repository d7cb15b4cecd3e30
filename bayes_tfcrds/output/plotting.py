"""Matplotlib for files: the non-interactive Agg backend, chosen in one place.

Every figure the toolkit draws goes to a PNG, a PDF or an HTML report, never to a window, so
the backend is set before pyplot is first imported (it also keeps CI and workers headless).
"""

from __future__ import annotations


def pyplot():
    """``matplotlib.pyplot`` with the Agg backend selected."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def literal(text: str) -> str:
    r"""``text`` shown as it is in a matplotlib label or title, never read as mathtext.

    Names in figures come from files (configuration names); matplotlib parses text between two
    ``$`` as mathtext, so a configuration named ``$\frac{1}$`` stopped a study with a parse error
    after all its work. An escaped ``\$`` is drawn as a dollar sign.
    """
    return str(text).replace("$", r"\$")
