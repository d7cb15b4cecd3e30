"""Wall time of the MCMC coverage study, 200 campaigns on 2 cores (issue 16): target <= 60 min.

Runs exactly the command that makes the committed report,

    bayes-tfcrds study studies/coverage.toml -o OUTDIR --workers 2

from an empty OUTDIR (finished campaigns are reused on a rerun, which would time nothing), and
prints PASS/FAIL with the campaigns' count, the failed ones and the mean wall time per campaign.
With ``-o reports/coverage`` the timed run is the committed report. Takes about an hour.

Usage:  python benchmarks/coverage_speed.py [-o OUTDIR] [--study studies/coverage.toml]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

TARGET_MIN = 60.0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-o", "--output", help="report folder (default: a temporary one)")
    ap.add_argument("--study", default="studies/coverage.toml")
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(args.output or os.path.join(tmp, "coverage"))
        done = out / "campaigns"
        if done.exists() and any(done.iterdir()):
            print(f"{done} holds finished campaigns: a rerun would reuse them; use an empty -o")
            return 2
        cmd = [sys.executable, "-m", "bayes_tfcrds.cli", "study", args.study, "-o", str(out)]
        cmd += ["--workers", str(args.workers)]
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True)
        minutes = (time.perf_counter() - t0) / 60.0
        numbers = json.loads((out / "numbers.json").read_text())
    n, ok = numbers["n_campaigns"], numbers["n_ok"]
    verdict = "PASS" if minutes <= TARGET_MIN else "FAIL"
    print(
        f"{verdict}  coverage study ({numbers['posterior']} posterior, {n} campaigns, "
        f"{args.workers} workers): {minutes:.1f} min (target <= {TARGET_MIN:.0f} min); "
        f"{ok} analysed, {n - ok} failed; {60 * minutes / n:.1f} s per campaign"
    )
    return 0 if verdict == "PASS" else 1


if __name__ == "__main__":
    sys.exit(main())
