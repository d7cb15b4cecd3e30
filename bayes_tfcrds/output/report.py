"""Self-contained reports: one HTML file (figures embedded, nothing fetched) plus a PDF of figures.

A report opens with a summary table of the key numbers, then figures and tables, every
diagnostic with pass/fail, and provenance (package version, git commit, input-file hashes,
seeds, the study file itself). All text that came from outside (bundle attributes, study
files) is HTML-escaped: a bundle's description may hold anything, including markup.
"""

from __future__ import annotations

import base64
import hashlib
import html
import io
import json
import platform
import subprocess
import sys
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

from bayes_tfcrds._version import __version__
from bayes_tfcrds.output.files import atomic_path, atomic_write_text
from bayes_tfcrds.output.plotting import RASTER_DPI, draw_caption, pyplot

SVG_LIMIT_BYTES = 1_000_000  # above this an embedded figure becomes a PNG (report size)


def figure_image(fig) -> tuple[str, bytes]:
    """(MIME type, bytes) of ``fig`` for an HTML report: SVG, or a PNG when the SVG is too big."""
    buf = io.BytesIO()
    # dense traces drawn with rasterized=True are embedded as RASTER_DPI images in the SVG
    fig.savefig(buf, format="svg", dpi=RASTER_DPI, bbox_inches="tight", metadata={"Date": None})
    if buf.tell() <= SVG_LIMIT_BYTES:
        return "image/svg+xml", buf.getvalue()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=RASTER_DPI, bbox_inches="tight", metadata={"Software": None})
    return "image/png", buf.getvalue()


@dataclass
class Report:
    """A report being assembled: call the ``add_*`` methods in reading order, then ``write``."""

    title: str
    summary_rows: list = field(default_factory=list)  # (label, value, note)
    blocks: list = field(default_factory=list)  # ("h2"|"p"|"table"|"figure"|"pre", payload)
    diagnostics: list = field(default_factory=list)  # (name, passed, detail)
    provenance: dict = field(default_factory=dict)
    figures: list = field(default_factory=list)  # matplotlib figures, for the PDF

    def add_summary(self, label, value, note=""):
        self.summary_rows.append((str(label), str(value), str(note)))

    def add_heading(self, text):
        self.blocks.append(("h2", str(text)))

    def add_text(self, text):
        self.blocks.append(("p", str(text)))

    def add_pre(self, text):
        self.blocks.append(("pre", str(text)))

    def add_table(self, header, rows, caption=""):
        self.blocks.append(
            ("table", ([str(h) for h in header], [[str(c) for c in r] for r in rows], str(caption)))
        )

    def add_figure(self, fig, caption=""):
        """Embed a matplotlib figure as vector SVG (and keep it for the PDF).

        A figure whose SVG would exceed :data:`SVG_LIMIT_BYTES` (long ring-down traces) is
        embedded as a :data:`RASTER_DPI` dpi PNG instead, so the report stays small enough to open.
        """
        fmt, data = figure_image(fig)
        self.blocks.append(("figure", (fmt, base64.b64encode(data).decode("ascii"), str(caption))))
        self.figures.append((fig, str(caption)))

    def add_diagnostic(self, name, passed: bool, detail=""):
        self.diagnostics.append((str(name), bool(passed), str(detail)))

    def to_html(self) -> str:
        e = html.escape
        parts = [
            "<!DOCTYPE html><html lang='en'><head><meta "
            f"charset='utf-8'><title>{e(self.title)}</title>",
            "<style>"
            "body{font-family:sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;color:#222}"
            "table{border-collapse:collapse;margin:1em 0;font-size:90%}"
            "td,th{border:1px solid #bbb;padding:3px 7px;text-align:left}"
            "th{background:#eee}img{max-width:100%}.pass{color:#060}"
            ".fail{color:#b00;font-weight:bold}"
            "pre{background:#f6f6f6;padding:.6em;overflow-x:auto;font-size:85%}"
            "figcaption{font-size:90%;color:#444}"
            "</style></head><body>",
            f"<h1>{e(self.title)}</h1>",
        ]
        if self.summary_rows:
            parts.append(
                "<h2>Summary</h2><table><tr><th>quantity</th><th>value</th><th>note</th></tr>"
            )
            parts += [
                f"<tr><td>{e(a)}</td><td>{e(b)}</td><td>{e(c)}</td></tr>"
                for a, b, c in self.summary_rows
            ]
            parts.append("</table>")
        for kind, payload in self.blocks:
            if kind == "h2":
                parts.append(f"<h2>{e(payload)}</h2>")
            elif kind == "p":
                parts.append(f"<p>{e(payload)}</p>")
            elif kind == "pre":
                parts.append(f"<pre>{e(payload)}</pre>")
            elif kind == "table":
                header, rows, caption = payload
                parts.append("<table>" + (f"<caption>{e(caption)}</caption>" if caption else ""))
                parts.append("<tr>" + "".join(f"<th>{e(h)}</th>" for h in header) + "</tr>")
                parts += ["<tr>" + "".join(f"<td>{e(c)}</td>" for c in r) + "</tr>" for r in rows]
                parts.append("</table>")
            elif kind == "figure":
                fmt, data, caption = payload
                parts.append(
                    f"<figure><img alt='{e(caption)}' "
                    f"src='data:{fmt};base64,{data}'>"
                    f"<figcaption>{e(caption)}</figcaption></figure>"
                )
        parts.append(
            "<h2>Diagnostics</h2><table><tr><th>check</th><th>result</th><th>detail</th></tr>"
        )
        for name, ok, detail in self.diagnostics:
            cls, word = ("pass", "PASS") if ok else ("fail", "FAIL")
            parts.append(
                f"<tr><td>{e(name)}</td><td class='{cls}'>{word}</td><td>{e(detail)}</td></tr>"
            )
        parts.append("</table><h2>Provenance</h2><table>")
        for k, v in self.provenance.items():
            if k == "study_file":
                continue
            parts.append(f"<tr><td>{e(str(k))}</td><td>{e(str(v))}</td></tr>")
        parts.append("</table>")
        if "study_file" in self.provenance:
            parts.append(f"<h3>Study file</h3><pre>{e(self.provenance['study_file'])}</pre>")
        # mark the page once every embedded image has decoded (checked by the rendering test)
        parts.append(
            "<script>window.addEventListener('load',function(){"
            "var i=document.images,ok=true;"
            "for(var k=0;k<i.length;k++){if(!i[k].complete||i[k].naturalWidth===0){ok=false;}}"
            "document.body.setAttribute('data-images-ok',ok?'true':'false');"
            "document.body.setAttribute('data-image-count',String(i.length));});</script>"
        )
        parts.append("</body></html>")
        return "\n".join(parts)

    def write(self, outdir, stem="report") -> tuple:
        """Write ``stem.html`` and ``stem.pdf`` (figures) atomically; returns their paths."""
        plt = pyplot()
        from matplotlib.backends.backend_pdf import PdfPages

        out = Path(outdir)
        out.mkdir(parents=True, exist_ok=True)
        html_path = out / f"{stem}.html"
        atomic_write_text(html_path, self.to_html())
        pdf_path = out / f"{stem}.pdf"
        with atomic_path(pdf_path) as tmp_pdf:
            meta = {
                "Title": self.title,
                "Subject": "; ".join(
                    f"Figure {i + 1}: {c}" for i, (_, c) in enumerate(self.figures)
                ),
                "CreationDate": None,
                "ModDate": None,
            }
            with PdfPages(tmp_pdf, metadata=meta) as pdf:
                for i, (fig, caption) in enumerate(self.figures):
                    # the caption a reader sees, under the figure as in a paper; the page grows
                    # to hold it (bbox_inches="tight")
                    text = draw_caption(fig, caption, number=i + 1) if caption else None
                    pdf.savefig(fig, bbox_inches="tight", pad_inches=0.1)
                    if text is not None:
                        text.remove()
        for fig, _ in self.figures:
            plt.close(fig)
        return html_path, pdf_path


def file_sha256(path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def git_commit(path=None) -> str:
    """The checkout's commit (with ``+dirty`` when it has uncommitted changes), or ``unknown``.

    Changes under ``reports/`` do not count: regenerating several reports in one clone writes
    them there, and the code that made the later ones is still the commit's.
    """
    cwd = Path(path or Path(__file__).resolve().parent)
    try:
        rev = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=cwd, capture_output=True, text=True, timeout=10
        )
        if rev.returncode != 0:
            return "unknown"
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"]
            + ["--", ":(top)", ":(top,exclude)reports"],
            cwd=cwd,
            capture_output=True,
            text=True,
            timeout=10,
        )
        return rev.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def provenance(seeds=None, inputs=(), study_text=None, extra=None) -> dict:
    """Package version, git commit, Python and library versions, input hashes, seeds."""
    import numpy
    import scipy

    prov = {
        "package": f"bayes-tfcrds {__version__}",
        "git_commit": git_commit(),
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "numpy": numpy.__version__,
        "scipy": scipy.__version__,
        "generated_utc": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
    }
    for p in inputs:
        prov[f"sha256 {Path(p).name}"] = file_sha256(p)
    if seeds is not None:
        prov["seeds"] = json.dumps(seeds)
    if extra:
        prov.update(extra)
    if study_text is not None:
        prov["study_file"] = study_text
    return prov
