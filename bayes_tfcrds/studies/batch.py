"""Budgets of many bundles: one task per bundle, through any executor (local processes, Dask).

Each task loads its bundle, runs the budget with the same options and seed as
``bayes-tfcrds budget BUNDLE`` would, and writes the same files into its own folder; a bundle the
budget refuses is recorded with the reason and does not stop the others.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bayes_tfcrds.studies.common import configuration_of, parallel_map


@dataclass(frozen=True)
class BudgetJob:
    """One bundle's budget: where it is read and written, which configuration, options, seed."""

    bundle_path: str
    outdir: str
    config: str | None
    options: object  # BudgetOptions
    seed: int


def batch_folders(paths, outdir) -> list[Path]:
    """Output folder of each bundle: ``outdir`` for one, ``outdir/<bundle stem>`` for several.

    Refuses two bundles with one stem (both would write into one folder), naming them.
    """
    paths = [Path(p) for p in paths]
    if len(paths) == 1:
        return [Path(outdir)]
    seen = {}
    for p in paths:
        if p.stem in seen:
            raise ValueError(
                f"{seen[p.stem]} and {p} would both write into {Path(outdir) / p.stem}; "
                "rename one, or run them in two batches"
            )
        seen[p.stem] = p
    return [Path(outdir) / p.stem for p in paths]


def budget_task(job: BudgetJob) -> dict:
    """Run one bundle's budget and write its files; a refusal is returned, not raised.

    Returns ``bundle``, ``output``, ``status`` (``ok``, ``failed: ...`` for gates not met, or
    ``error: ...`` for a refused input) and the budget's ``summary`` (None on error).
    """
    from bayes_tfcrds.bundle.reader import load_bundle, load_truth
    from bayes_tfcrds.bundle.records import BundleError
    from bayes_tfcrds.uncertainty.line_budget import run_budget
    from bayes_tfcrds.uncertainty.outputs import write_outputs

    record = {"bundle": job.bundle_path, "output": job.outdir, "status": None, "summary": None}
    try:
        bundle = load_bundle(job.bundle_path)
        config = configuration_of(bundle, job.config)
        res = run_budget(
            bundle, config, job.options, np.random.default_rng(job.seed), outdir=job.outdir
        )
        write_outputs(res, job.outdir, seed=job.seed, truth=load_truth(job.bundle_path))
    except BundleError as exc:
        record["status"] = f"error: {exc.one_line()}"
        return record
    except (ValueError, OSError) as exc:  # refused options or data, a busy or unusable folder
        record["status"] = f"error: {exc}"
        return record
    record["status"] = res.status
    record["summary"] = res.summary
    return record


def run_batch(jobs, pool=None, progress: bool = False) -> list[dict]:
    """:func:`budget_task` of every job, in order, through ``pool`` (any executor) when given."""
    return parallel_map(pool, budget_task, list(jobs), progress, "bundles")
