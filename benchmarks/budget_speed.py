"""Wall time of ``bayes-tfcrds budget`` on one full letter configuration, on 2 cores (issue 16).

Target: <= 30 s with ``--workers 2`` (MCMC, default steps; the whole command, from reading the
bundle to the written folder). The same budget with ``--workers 1`` is timed in the same run, for
the ratio, and the two budget.json files must be identical apart from their provenance (the
second process samples the CMDS reference from its own random stream and computes the
deterministic steps; it changes nothing else). Stage times come from the command's own log.

Usage:  python benchmarks/budget_speed.py [--seed 1] [--config D2]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time

TARGET_S = 30.0


def _run(cmd) -> tuple[float, str]:
    t0 = time.perf_counter()
    out = subprocess.run(cmd, check=True, capture_output=True, text=True)
    return time.perf_counter() - t0, out.stderr


def _stages(log: str) -> str:
    """The budget's stages and their times, from its log ('stage k/n NAME done in T;')."""
    return ", ".join(
        f"{m.group(1)} {m.group(2)}"
        for m in re.finditer(r"stage \d+/\d+ (.+?) done in ([^;]+);", log)
    )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--config", default="D2", help="letter configuration D1-D4")
    args = ap.parse_args(argv)
    exe = [sys.executable, "-m", "bayes_tfcrds.cli"]
    with tempfile.TemporaryDirectory() as tmp:
        bundle = os.path.join(tmp, "letter.h5")
        subprocess.run(
            exe + ["simulate", "--preset", f"letter-{args.config}", "--seed", str(args.seed)]
            + ["-o", bundle],
            check=True,
            capture_output=True,
        )  # fmt: skip
        times, docs = {}, {}
        for workers in (2, 1):
            out = os.path.join(tmp, f"w{workers}")
            cmd = exe + ["budget", bundle, "--config", args.config, "--seed", str(args.seed)]
            cmd += ["--workers", str(workers), "-o", out]
            times[workers], log = _run(cmd)
            doc = json.loads(open(os.path.join(out, "budget.json")).read())
            doc.pop("provenance", None)
            docs[workers] = doc
            print(f"--workers {workers}: {times[workers]:.1f} s; {_stages(log)}", flush=True)
    same = docs[1] == docs[2]
    ok = times[2] <= TARGET_S and same
    print(
        f"{'PASS' if times[2] <= TARGET_S else 'FAIL'}  budget, one letter configuration "
        f"({args.config}, MCMC, default steps), --workers 2: {times[2]:.1f} s (target <= "
        f"{TARGET_S:.0f} s); --workers 1: {times[1]:.1f} s (ratio {times[1] / times[2]:.2f})"
    )
    print(f"{'PASS' if same else 'FAIL'}  the two budget.json files are identical: {same}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
