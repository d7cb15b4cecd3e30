"""What every study kind shares: the campaign it analyses and a map over an optional pool."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from bayes_tfcrds.output.progress import progress_bar
from bayes_tfcrds.studies.spec import Study, StudyError

#: study kinds that compare every configuration with its CMDS reference (A/A_ref); a simulated
#: campaign always has one, a measured bundle may not
NEEDS_CMDS = ("tcut", "window_history", "budgets")


def stored_record(path, fingerprint: str) -> dict | None:
    """A finished task's JSON record at ``path`` if it was made with these settings, else None.

    Studies keep one record per task (campaign, seed) so that an interrupted run resumes; a
    record of other settings, or one left unreadable by a kill, is run again.
    """
    import json

    path = Path(path)
    if not path.exists():
        return None
    try:
        rec = json.loads(path.read_text())
    except (json.JSONDecodeError, OSError):
        return None
    return rec if rec.get("fingerprint") == fingerprint else None


def configuration_of(bundle, name):
    """The configuration ``name`` of ``bundle`` (the only one when None); ValueError otherwise."""
    if name is None:
        if len(bundle.configs) != 1:
            raise ValueError(
                f"the bundle has configurations {list(bundle.configs)}; choose one with --config"
            )
        return next(iter(bundle.configs.values()))
    if name not in bundle.configs:
        raise ValueError(f"no configuration {name!r} in the bundle (it has {list(bundle.configs)})")
    return bundle.configs[name]


def load_study_bundle(study: Study):
    """The measurement bundle a study names, refused (StudyError) if the study cannot use it.

    Called before the report folder is made, so a missing, damaged or unsuitable bundle costs
    nothing and leaves nothing behind; the error names the study file's key and the bundle.
    """
    from bayes_tfcrds.bundle.reader import load_bundle
    from bayes_tfcrds.bundle.records import BundleError

    try:
        bundle = load_bundle(study.bundle)
    except BundleError as exc:
        raise StudyError(f"{study.path}: campaign.bundle: {exc.one_line()}") from None
    missing = [name for name, cfg in bundle.configs.items() if cfg.cmds is None]
    if study.kind in NEEDS_CMDS and missing:
        raise StudyError(
            f"{study.path}: a {study.kind} study compares each configuration with its CMDS "
            f"reference, and campaign.bundle {study.bundle} has no /cmds in {missing}"
        )
    return bundle


def campaign_of(study: Study, outdir: Path, bundle=None):
    """Simulate the study's campaign into OUTDIR/campaign.h5 (or load the named bundle).

    ``bundle`` is the named bundle when the caller has loaded it already
    (:func:`load_study_bundle`).
    """
    from bayes_tfcrds.bundle.reader import load_bundle, load_truth
    from bayes_tfcrds.bundle.writer import save_bundle
    from bayes_tfcrds.simulate.campaign import Campaign, parse_effect, simulate_campaign

    if study.bundle is not None:
        return bundle or load_study_bundle(study), None, Path(study.bundle)
    effects = dict(parse_effect(e) for e in study.effects)
    camp = replace(Campaign(), n_points=study.points, n_samples=study.samples, n_avg=study.averages)
    bundle, truth = simulate_campaign(
        list(study.presets), np.random.default_rng(study.seed), camp, effects
    )
    path = outdir / "campaign.h5"
    save_bundle(bundle, path, truth=truth)
    return load_bundle(path), load_truth(path), path


def parallel_map(pool, fn, items, progress: bool = False, label: str = "tasks"):
    """``[fn(i) for i in items]``, through ``pool.map`` when a pool (any executor) is given.

    ``progress``: count the results as they arrive, with the time left at the mean rate
    (:func:`bayes_tfcrds.output.progress.progress_bar`).
    """
    items = list(items)
    results = (fn(i) for i in items) if pool is None else pool.map(fn, items)
    if progress:
        results = progress_bar(results, total=len(items), desc=label)
    return list(results)
