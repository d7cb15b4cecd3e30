"""Confusion table of the discovery workflow: hide one effect, ask discovery what is missing.

For every canonical effect (and ``window_history``), and for nothing hidden, simulate a reduced
letter-D2 campaign with that effect on (base truth: ideal detector, Voigt line, so exactly the
hidden effect is there), run :func:`bayes_tfcrds.discover` from the case's start model
without telling it, and tabulate the first effect it names against the hidden one, with the time
each discovery took. One two-effect case (``baseline_drift`` + ``etalon``) checks that both are
found. Writes ``reports/discovery/confusion.md`` and ``confusion.json``.

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

CAMPAIGN = replace(Campaign(), n_points=21, n_samples=4096)
CASES = {"nothing": ({}, None), **HIDDEN_CASES}
TWO_EFFECTS = ("baseline_drift+etalon", ({"baseline_drift": {}, "etalon": {}}, None))


def run_case(args):
    """Simulate one hidden case with one seed and discover; returns a JSON-ready dict."""
    name, effects, start, seed = args
    bundle, _ = simulate_campaign(
        ["letter-D2"], np.random.default_rng(seed), CAMPAIGN, effects, line_effects_default=False
    )
    t0 = time.perf_counter()
    res = discover(bundle, "D2", start)
    dt = time.perf_counter() - t0
    fin = res.evaluations[-1].gaps
    return {
        "hidden": name,
        "seed": seed,
        "start": start or "crds+voigt",
        "effects_added": res.effects_added,
        "first": res.effects_added[0] if res.effects_added else "nothing",
        "seconds": dt,
        "evidence": [s["evidence"] for s in res.steps],
        "final_z": {k: round(v["z"], 2) for k, v in fin.items()},
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--seed", type=int, default=11, help="first seed; seeds are seed, seed+1, ...")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--cases", default=None, help="comma-separated subset of cases (default all)")
    ap.add_argument("-o", "--output", default="reports/discovery")
    a = ap.parse_args(argv)
    names = list(CASES) if a.cases is None else a.cases.split(",")
    jobs = [(n, *CASES[n], a.seed + s) for n in names for s in range(a.seeds)]
    if a.cases is None:
        jobs += [(TWO_EFFECTS[0], *TWO_EFFECTS[1], a.seed + s) for s in range(a.seeds)]
    results = []
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=a.workers) as pool:
        for i, r in enumerate(pool.map(run_case, jobs)):
            results.append(r)
            print(
                f"[{i + 1}/{len(jobs)}] {r['hidden']:22s} seed {r['seed']}: {r['effects_added']} "
                f"({r['seconds']:.0f} s)",
                flush=True,
            )
    wall = time.perf_counter() - t0
    cols = ["nothing", *CANDIDATES]
    lines = [
        "# Discovery confusion table",
        "",
        f"Reduced letter-D2 campaign ({CAMPAIGN.n_points} requested modes, {CAMPAIGN.n_samples} "
        f"samples), seeds {a.seed}..{a.seed + a.seeds - 1}; rows: hidden effect; columns: first "
        f"effect named. Wall time {wall / 60:.1f} min with {a.workers} workers.",
        "",
        "| hidden \\ named first | "
        + " | ".join(cols)
        + " | correct | time per discovery (s, median [max]) |",
        "|---|" + "---|" * (len(cols) + 2),
    ]
    summary = {}
    for n in names:
        rs = [r for r in results if r["hidden"] == n]
        counts = {c: sum(r["first"] == c for r in rs) for c in cols}
        ok = counts.get(n, 0)
        times = [r["seconds"] for r in rs]
        summary[n] = {
            "counts": counts,
            "correct": ok,
            "runs": len(rs),
            "median_s": float(np.median(times)),
            "max_s": float(np.max(times)),
        }
        lines.append(
            f"| {n} | "
            + " | ".join(str(counts[c]) if counts[c] else "." for c in cols)
            + f" | {ok}/{len(rs)} | {np.median(times):.0f} [{np.max(times):.0f}] |"
        )
    two = [r for r in results if r["hidden"] == TWO_EFFECTS[0]]
    if two:
        want = set(TWO_EFFECTS[0].split("+"))
        found = sum(want <= set(r["effects_added"]) for r in two)
        lines += [
            "",
            f"Two effects hidden ({TWO_EFFECTS[0]}): both found in {found}/{len(two)} runs; added "
            "per run: "
            + "; ".join(
                f"seed {r['seed']}: {', '.join(r['effects_added']) or 'none'}" for r in two
            ),
        ]
        summary[TWO_EFFECTS[0]] = {"both_found": found, "runs": len(two)}
    lines += ["", "Every run (effects added in order, final |z| of the gaps):", ""]
    for r in results:
        lines.append(
            f"* {r['hidden']} seed {r['seed']}: {', '.join(r['effects_added']) or 'none'}; "
            f"{r['seconds']:.0f} s; final z "
            + ", ".join(f"{k} {v:+.1f}" for k, v in r["final_z"].items())
        )
    out = Path(a.output)
    out.mkdir(parents=True, exist_ok=True)
    (out / "confusion.md").write_text("\n".join(lines) + "\n")
    (out / "confusion.json").write_text(
        json.dumps(
            {
                "campaign": {"n_points": CAMPAIGN.n_points, "n_samples": CAMPAIGN.n_samples},
                "seeds": [a.seed + s for s in range(a.seeds)],
                "summary": summary,
                "runs": results,
                "wall_s": wall,
            },
            indent=2,
        )
        + "\n"
    )
    print("\n".join(lines[: len(names) + 6]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
