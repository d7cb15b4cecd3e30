"""Figures a journal accepts (issue #18): TrueType fonts, 200 dpi, units, captions, corners.

The study figures are checked on a small simulated bundle (D4, 9 cavity modes, 2048 samples), the
report machinery and the corner plots on synthetic figures and draws, so the file runs in
seconds.
"""

from __future__ import annotations

import re
import struct

import numpy as np
import pytest

from bayes_tfcrds.cli import main
from bayes_tfcrds.output import report as report_module
from bayes_tfcrds.output.plotting import MIN_FONT_PT, RASTER_DPI, dodge, pyplot
from bayes_tfcrds.output.report import Report, figure_image
from bayes_tfcrds.uncertainty.outputs import corner_axes, corner_figure, estimate_text

INCH_M = 0.0254


def _png_dpi(data: bytes) -> float:
    """Resolution of a PNG from its pHYs chunk (pixels per metre -> per inch); 0 without it."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos = 8
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind = data[pos + 4 : pos + 8]
        if kind == b"pHYs":
            x, _, unit = struct.unpack(">IIB", data[pos + 8 : pos + 17])
            assert unit == 1  # metres
            return x * INCH_M
        pos += 12 + length
    return 0.0


def _page_heights(pdf: bytes) -> list:
    return [float(h) for h in re.findall(rb"/MediaBox \[\s*\S+ \S+ \S+ (\S+)\s*\]", pdf)]


def _report_with_one_figure(caption):
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5, 3))
    x = np.arange(5.0)
    ax.errorbar(x, x**2, 0.5 + x, fmt="o", label="τ data")
    ax.set_xlabel("t_cut (µs)")
    ax.set_ylabel("loss (10⁻⁶ cm⁻¹)")
    ax.legend()
    rep = Report("fonts")
    rep.add_figure(fig, caption)
    return rep


def test_report_pdf_embeds_truetype_fonts_only_and_draws_the_caption(tmp_path):
    # Type 3 fonts are what matplotlib writes by default (pdf.fonttype 3); many journals refuse
    # them. With pdf.fonttype 42 every font is an embedded TrueType file (/FontFile2).
    caption = "A caption long enough to need two lines under a five inch figure, as a paper has."
    _, pdf_path = _report_with_one_figure(caption).write(tmp_path / "a", stem="r")
    pdf = pdf_path.read_bytes()
    assert b"/Subtype /Type3" not in pdf
    assert b"/FontFile2" in pdf
    assert b"Figure 1: A caption long enough" in pdf  # the PDF Subject names the caption
    _, bare = _report_with_one_figure("").write(tmp_path / "b", stem="r")
    # the caption is drawn: its page is taller than the same figure's page without one, by at
    # least two 8.5 pt lines
    (h_cap,), (h_bare,) = _page_heights(pdf), _page_heights(bare.read_bytes())
    assert h_cap > h_bare + 2 * 8.5


def test_html_report_embeds_vector_svg_and_falls_back_to_a_200_dpi_png(monkeypatch):
    rep = _report_with_one_figure("c")
    html = rep.to_html()
    assert "data:image/svg+xml;base64," in html and "data:image/png" not in html
    monkeypatch.setattr(report_module, "SVG_LIMIT_BYTES", 0)  # any figure is now "too big"
    fig, _ = rep.figures[0]
    fmt, data = figure_image(fig)
    assert fmt == "image/png"
    # pHYs stores whole pixels per metre: 200 dpi is 7874.0 /m, read back as 199.99 dpi
    assert _png_dpi(data) >= RASTER_DPI - 0.01


def test_dodge_is_centred_and_evenly_spaced():
    d = dodge(4, 0.1)
    assert d.sum() == pytest.approx(0.0, abs=1e-15)  # the group stays centred on the true x
    assert np.diff(d) == pytest.approx([0.1, 0.1, 0.1])


# ----------------------------------------------------------------------- study figures

# axis labels of quantities without a unit that say so in words
UNIT = re.compile(r"\((.+)\)\s*$|\(.+\);")


@pytest.fixture(scope="module")
def tiny_bundle(tmp_path_factory):
    path = tmp_path_factory.mktemp("fig_bundle") / "d.h5"
    argv = ["simulate", "--preset", "letter-D4", "--points", "9", "--samples", "2048"]
    argv += ["--seed", "1", "-o", str(path)]
    assert main(argv) == 0
    return path


def _study_figures(tmp_path, bundle, kind, monkeypatch):
    """The figures a small study adds to its report (kept open for inspection)."""
    kept = []
    plt = pyplot()
    monkeypatch.setattr(plt, "close", lambda *a, **k: None)
    original = Report.add_figure

    def add_figure(self, fig, caption=""):
        kept.append((fig, caption))
        return original(self, fig, caption)

    monkeypatch.setattr(Report, "add_figure", add_figure)
    study = tmp_path / "s.toml"
    study.write_text(
        f'[study]\nname = "s"\nkind = "{kind}"\n[campaign]\nbundle = "{bundle}"\n'
        "[analysis]\nt_cuts_us = [2, 4]\n"
    )
    argv = ["study", str(study), "--quiet", "--workers", "1", "-o", str(tmp_path / "r")]
    assert main(argv) == 0
    assert kept
    return kept


@pytest.mark.parametrize("kind", ["tcut", "figures", "window_history"])
def test_study_figures_have_units_readable_fonts_captions_and_legends_off_the_data(
    tiny_bundle, tmp_path, kind, monkeypatch
):
    for fig, caption in _study_figures(tmp_path, tiny_bundle, kind, monkeypatch):
        assert caption, "every figure has a caption"
        fig.canvas.draw()
        renderer = fig.canvas.get_renderer()
        labels = [a.get_xlabel() for a in fig.axes] + [a.get_ylabel() for a in fig.axes]
        labels = [s for s in labels if s]
        assert labels
        for s in labels:
            assert UNIT.search(s), f"axis label without a unit: {s!r}"
        for t in fig.findobj(lambda a: hasattr(a, "get_text") and hasattr(a, "get_fontsize")):
            if t.get_visible() and t.get_text().strip():
                assert not re.search(r"\bus\b", t.get_text()), t.get_text()  # µs, never "us"
                assert t.get_fontsize() >= MIN_FONT_PT, (t.get_text(), t.get_fontsize())
        for ax in fig.axes:
            leg = ax.get_legend()
            if leg is None:
                continue
            box, frame = leg.get_window_extent(renderer), ax.get_window_extent(renderer)
            # off the data: the legend and the axes' data area do not overlap (1 px of slack
            # for the anchor offset rounding)
            overlap_w = min(box.x1, frame.x1) - max(box.x0, frame.x0)
            overlap_h = min(box.y1, frame.y1) - max(box.y0, frame.y0)
            assert overlap_w <= 1 or overlap_h <= 1, f"legend over the data in {ax.get_title()!r}"
        pyplot().close(fig)


# ------------------------------------------------------------------------------ corners


class _Run:
    """What corner_figure reads of a sampling run: names, flat draws and the samples' layout."""

    def __init__(self, names, flat):
        self.names = tuple(names)
        self._flat = np.asarray(flat)
        # one ensemble of one walker: (ensembles, steps, walkers, ndim)
        self.samples = self._flat.reshape(1, -1, 1, self._flat.shape[-1])

    def flat(self):
        return self._flat


def _line_draws(rng, n=4000):
    names = ["line_area", "position_offset_hz", "gamma0_hz", "baseline0"]
    centre = np.array([394150.0, -1.5e6, 1.0e7, 1.0377e-4])  # Hz/m, Hz, Hz, 1/m
    return names, centre + rng.normal(size=(n, 4)) * centre * np.array([3e-4, 0.01, 2e-3, 1e-4])


def test_corner_labels_are_spectroscopic_names_with_units_and_values_in_those_units():
    rng = np.random.default_rng(3)
    names, flat = _line_draws(rng)
    truth = {"line": {"line_area_hz_per_m": 394150.0, "gamma0_hz": 1.0e7}, "configs": {}}
    truth["alpha_loss_per_m"] = 1.0377e-4
    data, labels, truths = corner_axes("line", names, flat, truth, "D2")
    assert labels == ["A (10⁻⁷ cm⁻²)", "ν − ν_ref (MHz)", "Γ0 (MHz)", "α_loss (10⁻⁶ cm⁻¹)"]
    # A: 394150 Hz/m / (1e4 c) = 1.31475e-7 cm^-2 (c in m/s, 1e4 for m^-1 Hz -> cm^-2)
    assert np.median(data[:, 0]) == pytest.approx(394150.0 / (1e4 * 299792458.0) * 1e7, rel=1e-3)
    assert truths[0] == pytest.approx(394150.0 / (1e4 * 299792458.0) * 1e7, rel=1e-12)
    assert np.median(data[:, 2]) == pytest.approx(10.0, rel=1e-3) and truths[2] == 10.0
    assert truths[1] is None  # the position has no simulated value to compare with
    assert truths[3] == pytest.approx(1.0377)  # 1/m -> cm^-1 is x 1e-2, shown in 1e-6 cm^-1


def test_corner_of_the_h_posterior_shows_natural_values_not_logs():
    rng = np.random.default_rng(4)
    f_c = np.log(52570.0) + 0.03 * rng.normal(size=3000)
    flat = np.column_stack([f_c, 24.5 + 0.3 * rng.normal(size=3000)])
    truth = {"configs": {"D2": {"f_c_hz": 52570.0, "a_r": 24.7}}}
    data, labels, truths = corner_axes("h", ["log_f_c_hz", "a_r"], flat, truth, "D2")
    assert labels == ["f_c (kHz)", "A_r"]
    assert np.median(data[:, 0]) == pytest.approx(52.57, rel=5e-3)  # exp of the log, in kHz
    assert truths == [pytest.approx(52.57), pytest.approx(24.7)]


def test_corner_titles_round_to_two_digits_of_the_uncertainty(tmp_path):
    rng = np.random.default_rng(5)
    # GUM 7.2.6: u to two significant digits, the value to the same decimal place
    assert estimate_text(51.02 + 1.7 * rng.normal(size=200000)) == "51.0 ± 1.7"
    assert estimate_text(0.70047 + 5.4e-4 * rng.normal(size=200000)) == "0.70047 ± 0.00054"
    names, flat = _line_draws(rng, 1000)
    fig = corner_figure("line", _Run(names, flat), None, "D2")
    titles = [a.get_title() for a in fig.axes if a.get_title()]
    assert titles[0].startswith("A =\n(1.3147") and titles[0].endswith("× 10⁻⁷ cm⁻²")
    assert titles[2].startswith("Γ0 =\n10.0") and titles[2].endswith(" MHz")
    png = tmp_path / "c.png"
    fig.savefig(png, dpi=RASTER_DPI)
    assert _png_dpi(png.read_bytes()) >= RASTER_DPI - 0.01
    pyplot().close(fig)
