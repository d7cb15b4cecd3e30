"""The committed discovery example: baseline drift and an etalon hidden in a reduced letter-D2
campaign (ideal detector, Voigt line), discovered from plain CRDS + Voigt.

Writes ``reports/discovery/example/`` (discovery.json, discovery.html, discovery.pdf).

Usage:  python benchmarks/discovery_example.py [--seed 11] [-o reports/discovery/example]
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace

import numpy as np

from bayes_tfcrds.discovery.report import write_report
from bayes_tfcrds.discovery.workflow import discover
from bayes_tfcrds.simulate.campaign import Campaign, simulate_campaign

#: the confusion benchmark's reduced campaign (21 requested modes, 4096 samples)
CAMPAIGN = replace(Campaign(), n_points=21, n_samples=4096)
HIDDEN = {"baseline_drift": {}, "etalon": {}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("-o", "--output", default="reports/discovery/example")
    args = ap.parse_args(argv)
    bundle, _ = simulate_campaign(
        ["letter-D2"],
        np.random.default_rng(args.seed),
        CAMPAIGN,
        HIDDEN,
        line_effects_default=False,
    )
    result = discover(bundle, "D2", None, progress=lambda line: print(line, file=sys.stderr))
    json_path, html_path = write_report(result, args.output, seed=args.seed)
    added = ", ".join(result.effects_added) or "none"
    print(f"effects added: {added}; wrote {json_path}, {html_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
