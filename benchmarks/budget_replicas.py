"""Does the budget's stated u(A) match the scatter of A over simulated campaigns? (60 replicas)

The first check's small version in CI is the coverage study's test
(``tests/studies/test_coverage_study.py``, 40 campaigns); the second runs here only (20 replicas
took 2.5-3 min of one CI worker). Each replica simulates the letter's chain
D4 on a small campaign (21 modes, 4096 samples, 25 averages) with new noise and runs the budget
(Laplace posterior, t_cut 4 and 8 us), the path the two tests check:

* stated u: sd(A) over replicas / mean u_stat(A) inside the chi distribution's 3-sigma band
  (0.73-1.28 for 60 replicas; the sample sd is known to 9 %), and the mean pull within 3 of its
  standard errors of zero;
* noise rows: with the same beat note in every replica, sd(A) between the ring-down-noise rows
  and the whole u_stat, each bound widened by the same band.

PASS/FAIL per check. About 7 s per replica on one core; ``--workers 2`` halves the time.

Usage:  python benchmarks/budget_replicas.py [--replicas 60] [--workers 2]
"""

from __future__ import annotations

import argparse
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the tests' replica helpers
from tests.uncertainty.replicas import (  # noqa: E402
    FAST,
    TINY,
    noise_rows_bracket_scatter,
    replicate,
    scatter_matches_u,
)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--replicas", type=int, default=60)
    ap.add_argument("--seed", type=int, default=5, help="seed of the first check (+1: second)")
    ap.add_argument("--workers", type=int, default=1)
    args = ap.parse_args(argv)
    pool = ProcessPoolExecutor(args.workers) if args.workers > 1 else None
    ok = True
    try:
        t0 = time.perf_counter()
        rep = replicate(args.replicas, args.seed, "letter-D4", TINY, FAST, progress=True, pool=pool)
        c = scatter_matches_u(rep)
        good = c["ratio_ok"] and c["unbiased"]
        ok &= good
        print(
            f"{'PASS' if good else 'FAIL'}  stated u: sd(A)/mean u_stat = {c['ratio']:.3f} "
            f"(band {c['band'][0]:.3f}-{c['band'][1]:.3f}), mean pull {c['mean_pull']:+.3f}; "
            f"{args.replicas} replicas, seed {args.seed}, {time.perf_counter() - t0:.0f} s",
            flush=True,
        )
        t0 = time.perf_counter()
        rep = replicate(
            args.replicas,
            args.seed + 1,
            "letter-D4",
            TINY,
            FAST,
            fixed_beat=True,
            progress=True,
            pool=pool,
        )
        c = noise_rows_bracket_scatter(rep)
        ok &= c["ok"]
        print(
            f"{'PASS' if c['ok'] else 'FAIL'}  noise rows: sd(A) = {c['scatter']:.4g} Hz/m within "
            f"{c['bounds'][0]:.4g}-{c['bounds'][1]:.4g} Hz/m (band x mean noise rows, band x mean "
            f"u_stat); {args.replicas} replicas, seed {args.seed + 1}, "
            f"{time.perf_counter() - t0:.0f} s"
        )
    finally:
        if pool is not None:
            pool.shutdown()
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
