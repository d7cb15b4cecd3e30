"""The files of a comparison: comparison.json, .md, .csv and the degrees-of-equivalence plot.

Rendering only: every number comes from a :class:`~.comparison.Comparison`.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from bayes_tfcrds.output.files import atomic_path, atomic_write_text
from bayes_tfcrds.output.plotting import literal, pyplot
from bayes_tfcrds.uncertainty.comparison import Comparison
from bayes_tfcrds.uncertainty.comparison_inputs import si_factor


def write_comparison(comp: Comparison, results, outdir, seed: int | None = None) -> list:
    """comparison.json, comparison.md, comparison.csv and doe.png/.svg in ``outdir``.

    ``results`` are the LabResults compared (their sources and dof go into the json and md).
    Every file is written atomically.
    """
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    payload = comparison_json(comp, results, seed)
    atomic_write_text(out / "comparison.json", json.dumps(payload, indent=2) + "\n")
    atomic_write_text(out / "comparison.md", comparison_markdown(comp, results) + "\n")
    atomic_write_text(out / "comparison.csv", comparison_csv(comp))
    written = [out / "comparison.json", out / "comparison.md", out / "comparison.csv"]
    return written + plot_equivalence(comp, out / "doe")


def comparison_json(comp: Comparison, results, seed: int | None = None) -> dict:
    """The machine-readable comparison: the result objects, sources, and SI values beside."""
    payload = comp.to_dict()
    payload["sources"] = {r.lab: r.source for r in results}
    payload["dof"] = {r.lab: (r.dof if math.isfinite(r.dof) else None) for r in results}
    unit_si, factor = si_factor(comp.quantity)
    if unit_si is not None:
        payload["reference_si"] = {
            "value": comp.reference.value * factor,
            "u": comp.reference.u * factor,
            "unit": unit_si,
        }
    payload["notes"] = (
        "d = x - x_ref; u(d) from the covariance of the results (declared correlations) and "
        "their share in x_ref; U = k u with k = 2; E_n = d/U; zeta = d/u; chi2 (Cochran's Q) "
        "and Birge ratio of the results about their weighted mean"
    )
    if comp.reference.method.startswith("random effects"):
        payload["notes"] += (
            "; random-effects consensus: GLS mean under V + tau^2 I (tau = reference.tau, the "
            "dark uncertainty), and u(d) with tau^2 added to every result's variance (u(d) is not "
            "Knapp-Hartung-scaled; that scaling applies to u(x_ref) and its interval)"
        )
    if seed is not None:
        payload["seed"] = seed
    return payload


def _g(v, fmt: str = ".4g") -> str:
    return "-" if v is None else format(v, fmt)


def comparison_markdown(comp: Comparison, results) -> str:
    """Tables of the inputs, the reference value and consistency, and the degrees of equivalence."""
    unit, ref, cons = comp.unit, comp.reference, comp.consistency
    dof = {r.lab: r.dof for r in results}
    title = "Comparison" if comp.quantity == "other" else f"Comparison of {comp.quantity}"
    lines = [f"# {title} ({unit})", "", "## Results", ""]
    lines += ["| lab | value | u | dof | source |", "|---|---|---|---|---|"]
    for r in results:
        d = "inf" if math.isinf(dof[r.lab]) else f"{dof[r.lab]:g}"
        lines.append(f"| {r.lab} | {r.value:.6e} | {r.u:.2e} | {d} | {r.source} |")
    verdict = (
        "passed"
        if cons.passed
        else "**failed**: the results are not consistent"
        + (
            " (their scatter exceeds their u: `--random-effects REML` gives the consensus with a "
            "dark uncertainty)"
            if ref.method == "weighted mean"
            else ""
        )
    )
    lines += [
        "",
        "## Reference value",
        "",
        f"x_ref = {ref.value:.6e} {unit}, u(x_ref) = {ref.u:.2e} {unit} ({ref.method}); "
        f"95 % interval [{ref.interval[0]:.6e}, {ref.interval[1]:.6e}] {unit}"
        + ("." if ref.dof is None else f" (Student's t, {ref.dof:g} dof)."),
        "",
    ]
    if ref.method.startswith("random effects"):
        lines += [
            f"Dark uncertainty tau = {ref.tau:.3e} {unit}: the scatter of the results beyond "
            + (
                "their stated u; every u(d) below includes it."
                if ref.tau > 0
                else "their stated u is none here: the consensus is the weighted mean."
            ),
            "",
        ]
        if ref.kh_q is not None:
            lines += [
                "u(d) below uses the random-effects u(x_ref) before the Knapp-Hartung scaling, "
                "and U(d) = 2 u(d); the Knapp-Hartung u and its Student-t interval are those of "
                "x_ref itself.",
                "",
            ]
    if ref.kh_q is not None and ref.kh_q < 1 and "modified" not in ref.method:
        lines += [
            f"Note: the Knapp-Hartung q = {ref.kh_q:.3g} < 1 makes u(x_ref) smaller than the "
            "plain random-effects u; `--knapp-hartung modified` uses max(q, 1).",
            "",
        ]
    lines += [
        f"Consistency (about the weighted mean): chi2 = {cons.chi2:.3f}, dof = {cons.dof}, "
        f"p = {cons.p_value:.3g}, Birge ratio R_B = {cons.birge_ratio:.3f}; chi2 test at "
        f"{cons.alpha:.0%}: {verdict}.",
        "",
        f"## Degrees of equivalence (U with k = {comp.k:g})",
        "",
        f"| lab | d ({unit}) | u(d) | U(d) | E_n | zeta |",
        "|---|---|---|---|---|---|",
    ]
    for e in comp.equivalence:
        lines.append(
            f"| {e.lab} | {e.d:+.3e} | {e.u:.2e} | {e.U:.2e} | {_g(e.en, '+.2f')} | "
            f"{_g(e.zeta, '+.2f')} |"
        )
    lines += [
        "",
        "## Pairs",
        "",
        f"| a | b | d_ab ({unit}) | U(d_ab) | E_n |",
        "|---|---|---|---|---|",
    ]
    for p in comp.pairs:
        lines.append(f"| {p.lab_a} | {p.lab_b} | {p.d:+.3e} | {p.U:.2e} | {_g(p.en, '+.2f')} |")
    return "\n".join(lines)


def comparison_csv(comp: Comparison) -> str:
    """One row per result: value, u, d, u(d), U(d), E_n, zeta, in the comparison's unit."""
    rows = ["lab,value,u,d,u_d,U_d,en,zeta,unit,x_ref,u_ref,tau"]
    for v, u, e in zip(comp.values, comp.u, comp.equivalence):
        en = "" if e.en is None else f"{e.en:.6g}"
        zeta = "" if e.zeta is None else f"{e.zeta:.6g}"
        rows.append(
            f"{_csv_name(e.lab)},{v:.10e},{u:.6e},{e.d:.6e},{e.u:.6e},{e.U:.6e},{en},{zeta},"
            f"{comp.unit},{comp.reference.value:.10e},{comp.reference.u:.6e},"
            f"{comp.reference.tau:.6e}"
        )
    return "\n".join(rows) + "\n"


def _csv_name(name: str) -> str:
    return f'"{name.replace(chr(34), chr(34) * 2)}"' if any(c in name for c in ',"\n') else name


def plot_equivalence(comp: Comparison, stem: Path) -> list:
    """d_i with U(d_i) error bars (caps) about a zero line; PNG (200 dpi) and SVG at ``stem``."""
    plt = pyplot()
    scale = _power_of_ten(max(max(abs(e.d) + e.U for e in comp.equivalence), 1e-300))
    fig, ax = plt.subplots(figsize=(max(4.0, 0.8 * len(comp.labs) + 2.0), 3.6))
    pos = range(len(comp.labs))
    ax.errorbar(
        pos,
        [e.d / scale for e in comp.equivalence],
        yerr=[e.U / scale for e in comp.equivalence],
        fmt="o",
        capsize=4,
        color="C0",
    )
    ax.axhline(0.0, color="0.3", lw=0.8)
    ax.set_xlabel("laboratory")
    ax.set_xticks(list(pos), [literal(lab) for lab in comp.labs], rotation=30, ha="right")
    unit = "" if comp.unit == "1" else f" {comp.unit}"
    ax.set_ylabel(f"$d_i$ / ($10^{{{round(math.log10(scale))}}}${literal(unit)})")
    ax.set_title(
        literal(
            f"{'comparison' if comp.quantity == 'other' else comp.quantity} ({comp.unit}): d_i "
            f"to the {comp.reference.method}, U (k = {comp.k:g})"
        ),
        fontsize=9,
    )
    written = []
    for ext, dpi in ((".png", 200), (".svg", None)):
        path = stem.with_suffix(ext)
        with atomic_path(path, suffix=ext) as tmp:
            fig.savefig(tmp, dpi=dpi)
        written.append(path)
    plt.close(fig)
    return written


def _power_of_ten(x: float) -> float:
    """10^floor(log10 x): the axis scale, so tick labels stay short."""
    return 10.0 ** math.floor(math.log10(x))
