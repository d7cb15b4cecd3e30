"""Confusion table of the discovery workflow: hide one effect, ask discovery what is missing.

Two families of hidden-effect shapes: family A writes each effect in the form our candidates
assume; family B (``tests/discovery/hidden_cases_b.py``) writes it from the physics in another
form, at 306 K (a hyperbolic laser leak after extinction, a transverse mode with its own losses
and frequency, a tanh-saturating amplifier, a thermally relaxing offset, a chirped beat that
decays at the mean rate of two modes, a cascade detector integrated in the time domain, a
power-law speed dependence, soft collisions (Galatry), an Airy etalon, a line of another
molecule). For every effect and for nothing hidden, simulate a reduced letter-D2 campaign with
that effect on (base truth: ideal detector, Voigt line), run
:func:`bayes_tfcrds.discover` from the case's start model without telling it, and tabulate:

* the first effect named against the hidden one;
* spurious additions: any effect added that is not the hidden one (for a hidden chain, H and the
  extinction window are both right: the simulated chain sees the whole ring-down history);
* runs that end with "unexplained structure" (gaps left open that no candidate explains);
* the time of each discovery.

One two-effect case (``baseline_drift`` + ``etalon``, family A) checks that both are found.
Writes ``confusion.md`` and ``confusion.json`` to the output folder.

Usage:  nice python benchmarks/discovery_confusion.py --seeds 5 --seed 11 [--workers 2]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

from bayes_tfcrds.discovery.workflow import CANDIDATES, discover
from bayes_tfcrds.simulate.campaign import Campaign, simulate_campaign

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the tests' fixtures
from tests.discovery.hidden_cases import HIDDEN_CASES  # noqa: E402
from tests.discovery.hidden_cases_b import HIDDEN_CASES_B  # noqa: E402
from tests.discovery.hidden_cases_b import nothing as nothing_b  # noqa: E402

CAMPAIGN = replace(Campaign(), n_points=21, n_samples=4096)
FAMILIES = {
    "A": {"nothing": ({}, None), **HIDDEN_CASES},
    "B": {"nothing": (nothing_b, None), **HIDDEN_CASES_B},
}
#: family B's noise comes from another stream than family A's at the same seed (independent runs)
FAMILY_B_STREAM = 2
TWO_EFFECTS = ("baseline_drift+etalon", ({"baseline_drift": {}, "etalon": {}}, None))
#: effects that are right when the named case is hidden (besides the case itself)
ALSO_RIGHT = {"transfer_function": {"window_history"}}


def right_effects(hidden: str) -> set:
    """The effects whose addition is correct when ``hidden`` is hidden."""
    if hidden == "nothing":
        return set()
    names = set(hidden.split("+"))
    for n in list(names):
        names |= ALSO_RIGHT.get(n, set())
    return names


def run_case(args):
    """Simulate one hidden case with one seed and discover; returns a JSON-ready dict."""
    family, name, effects, start, seed = args
    rng = np.random.default_rng(seed)
    if callable(effects):  # family B: a builder that writes the effect itself, its own noise
        bundle, _ = effects(np.random.default_rng([FAMILY_B_STREAM, seed]), CAMPAIGN)
    else:
        bundle, _ = simulate_campaign(
            ["letter-D2"], rng, CAMPAIGN, effects, line_effects_default=False
        )
    t0 = time.perf_counter()
    res = discover(bundle, "D2", start, rng=np.random.default_rng(seed))
    dt = time.perf_counter() - t0
    fin = res.evaluations[-1].gaps
    right = right_effects(name)
    # a step names its effect and those the data cannot tell from it (its alternatives): the
    # set is right when it holds a right effect, and the named one then adds nothing spurious
    sets = [{s["effect"], *(a["effect"] for a in s.get("alternatives") or ())} for s in res.steps]
    named_any = set().union(*sets) if sets else set()
    return {
        "family": family,
        "hidden": name,
        "seed": seed,
        "start": start or "crds+voigt",
        "effects_added": res.effects_added,
        "first": res.effects_added[0] if res.effects_added else "nothing",
        "named": name == "nothing" or set(name.split("+")) <= named_any,
        # strict: only the effects added count (an alternative names nothing)
        "named_strict": name == "nothing" or set(name.split("+")) <= set(res.effects_added),
        "spurious": [s["effect"] for s, st in zip(res.steps, sets) if not st & right],
        "spurious_strict": [e for e in res.effects_added if e not in right],
        "ambiguous": [sorted(st) for st in sets if len(st) > 1],
        "unexplained": [u["gap"] for u in res.unexplained],
        "stop_reason": res.stop_reason,
        "seconds": dt,
        "evidence": [s["evidence"] for s in res.steps],
        "final_z_cal": {k: round(v.get("z_cal", v["z"]), 2) for k, v in fin.items()},
    }


def _jobs(families, names, seeds, first_seed) -> list:
    jobs = []
    for fam in families:
        cases = FAMILIES[fam]
        for n in names or list(cases):
            jobs += [(fam, n, *cases[n], first_seed + s) for s in range(seeds)]
    if names is None and "A" in families:
        jobs += [("A", TWO_EFFECTS[0], *TWO_EFFECTS[1], first_seed + s) for s in range(seeds)]
    return jobs


def _family_table(results, fam) -> tuple[list, dict]:
    """Markdown rows and the summary of one family."""
    cols = ["nothing", *CANDIDATES]
    lines = [
        "| hidden \\ named first | "
        + " | ".join(cols)
        + " | named | named strictly | spurious | spurious strictly | unexplained "
        "| time (s, median [max]) |",
        "|---|" + "---|" * (len(cols) + 6),
    ]
    summary = {}
    rs_f = [r for r in results if r["family"] == fam]
    for n in dict.fromkeys(r["hidden"] for r in rs_f):
        rs = [r for r in rs_f if r["hidden"] == n]
        counts = {c: sum(r["first"] == c for r in rs) for c in cols}
        named = sum(r["named"] for r in rs)
        spur = sum(bool(r["spurious"]) for r in rs)
        unex = sum(bool(r["unexplained"]) for r in rs)
        strict = sum(r.get("named_strict", r["named"]) for r in rs)
        spur_s = sum(bool(r.get("spurious_strict", r["spurious"])) for r in rs)
        times = [r["seconds"] for r in rs]
        summary[n] = {
            "counts": counts,
            "named": named,
            "named_strict": strict,
            "spurious_strict": spur_s,
            "spurious": spur,
            "unexplained": unex,
            "runs": len(rs),
            "median_s": float(np.median(times)),
            "max_s": float(np.max(times)),
        }
        lines.append(
            f"| {n} | "
            + " | ".join(str(counts.get(c, 0)) if counts.get(c, 0) else "." for c in cols)
            + f" | {named}/{len(rs)} | {strict}/{len(rs)} | {spur}/{len(rs)} | {spur_s}/{len(rs)} "
            f"| {unex}/{len(rs)} | "
            f"{np.median(times):.0f} [{np.max(times):.0f}] |"
        )
    return lines, summary


def _totals(results) -> dict:
    hidden = [r for r in results if r["hidden"] != "nothing"]
    clean = [r for r in results if r["hidden"] == "nothing"]
    return {
        "runs": len(results),
        "named_fraction": float(np.mean([r["named"] for r in hidden])) if hidden else None,
        "named_strict_fraction": float(np.mean([r.get("named_strict", r["named"]) for r in hidden]))
        if hidden
        else None,
        "spurious_fraction": float(np.mean([bool(r["spurious"]) for r in results])),
        "spurious_strict_fraction": float(
            np.mean([bool(r.get("spurious_strict", r["spurious"])) for r in results])
        ),
        "clean_runs_adding_something": int(sum(bool(r["effects_added"]) for r in clean)),
        "clean_runs": len(clean),
        "max_seconds": float(max(r["seconds"] for r in results)),
        "median_seconds": float(np.median([r["seconds"] for r in results])),
    }


def _totals_line(label, tot) -> str:
    return (
        f"{label}: hidden effect named in {100 * tot['named_fraction']:.1f} % of the runs that "
        f"hide one ({100 * tot['named_strict_fraction']:.1f} % counting only effects added); a "
        f"spurious addition in {100 * tot['spurious_fraction']:.1f} % "
        f"({100 * tot['spurious_strict_fraction']:.1f} % counting an indistinguishable alternative "
        "as spurious); clean runs "
        f"adding something: {tot['clean_runs_adding_something']}/{tot['clean_runs']}; time per "
        f"discovery median {tot['median_seconds']:.0f} s, max {tot['max_seconds']:.0f} s."
    )


def _markdown(results, families, a, wall) -> tuple[list, dict]:
    tot = _totals(results)
    lines = [
        "# Discovery confusion table",
        "",
        f"Reduced letter-D2 campaign ({CAMPAIGN.n_points} requested modes, {CAMPAIGN.n_samples} "
        f"samples), seeds {a.seed}..{a.seed + a.seeds - 1}; rows: hidden effect; columns: first "
        "effect added; named: the hidden effect is among those added, or named beside an added "
        "one as an effect the data cannot tell from it (within Delta BIC 2, tried and not "
        "rejected); named strictly: among those added; spurious: an effect added whose step "
        "names no hidden effect; spurious strictly: an effect added that is not hidden; "
        "unexplained: the run ended with gaps open that no candidate explains. Wall time "
        f"{wall / 60:.1f} min with {a.workers} workers.",
        "",
        _totals_line("All runs", tot),
    ]
    summary = {"totals": tot}
    for fam in families:
        rows, summary[fam] = _family_table(results, fam)
        fam_tot = _totals([r for r in results if r["family"] == fam])
        summary[fam]["totals"] = fam_tot
        lines += ["", f"## Family {fam}", "", _totals_line(f"Family {fam}", fam_tot), "", *rows]
    lines += ["", "Every run (family, effects added in order, stop, final calibrated z):", ""]
    for r in results:
        lines.append(
            f"* {r['family']} {r['hidden']} seed {r['seed']}: "
            f"{', '.join(r['effects_added']) or 'none'}"
            + "".join(f" ({' or '.join(st)} indistinguishable)" for st in r.get("ambiguous", []))
            + f"; {r['seconds']:.0f} s; {r['stop_reason']}; "
            "z_cal " + ", ".join(f"{k} {v:+.1f}" for k, v in r["final_z_cal"].items())
        )
    return lines, summary


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--seed", type=int, default=11, help="first seed; seeds are seed, seed+1, ...")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--families", default="A,B", help="shape families, A and/or B")
    ap.add_argument("--cases", default=None, help="comma-separated subset of cases (default all)")
    ap.add_argument("-o", "--output", default="reports/discovery")
    ap.add_argument(
        "--render", default=None, help="re-render confusion.md from a stored confusion.json"
    )
    a = ap.parse_args(argv)
    if a.render is not None:
        return _render(a)
    families = a.families.split(",")
    names = None if a.cases is None else a.cases.split(",")
    jobs = _jobs(families, names, a.seeds, a.seed)
    results = []
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=a.workers) as pool:
        for i, r in enumerate(pool.map(run_case, jobs)):
            results.append(r)
            print(
                f"[{i + 1}/{len(jobs)}] {r['family']} {r['hidden']:22s} seed {r['seed']}: "
                f"{r['effects_added']} spurious {r['spurious']} ({r['seconds']:.0f} s)",
                flush=True,
            )
    wall = time.perf_counter() - t0
    lines, summary = _markdown(results, families, a, wall)
    out = Path(a.output)
    out.mkdir(parents=True, exist_ok=True)
    (out / "confusion.md").write_text("\n".join(lines) + "\n")
    record = {
        "campaign": {"n_points": CAMPAIGN.n_points, "n_samples": CAMPAIGN.n_samples},
        "seeds": [a.seed + s for s in range(a.seeds)],
        "families": families,
        "workers": a.workers,
        "summary": summary,
        "runs": results,
        "wall_s": wall,
    }
    (out / "confusion.json").write_text(json.dumps(record, indent=2) + "\n")
    print("\n".join(lines[:6]))
    return 0


def _render(a) -> int:
    """confusion.md (and the summary in confusion.json) again from the stored runs."""
    path = Path(a.render)
    record = json.loads(path.read_text())
    seeds = record["seeds"]
    a.seed, a.seeds = seeds[0], len(seeds)
    a.workers = record.get("workers", a.workers)
    lines, record["summary"] = _markdown(record["runs"], record["families"], a, record["wall_s"])
    out = Path(a.output)
    out.mkdir(parents=True, exist_ok=True)
    (out / "confusion.md").write_text("\n".join(lines) + "\n")
    (out / "confusion.json").write_text(json.dumps(record, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
