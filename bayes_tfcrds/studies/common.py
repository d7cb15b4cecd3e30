"""What every study kind shares: the campaign it analyses and a map over an optional pool."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from bayes_tfcrds.studies.spec import Study


def campaign_of(study: Study, outdir: Path):
    """Simulate the study's campaign into OUTDIR/campaign.h5 (or load the named bundle)."""
    from bayes_tfcrds.bundle.reader import load_bundle, load_truth
    from bayes_tfcrds.bundle.writer import save_bundle
    from bayes_tfcrds.simulate.campaign import Campaign, parse_effect, simulate_campaign

    if study.bundle is not None:
        return load_bundle(study.bundle), None, Path(study.bundle)
    effects = dict(parse_effect(e) for e in study.effects)
    camp = replace(Campaign(), n_points=study.points, n_samples=study.samples, n_avg=study.averages)
    bundle, truth = simulate_campaign(
        list(study.presets), np.random.default_rng(study.seed), camp, effects
    )
    path = outdir / "campaign.h5"
    save_bundle(bundle, path, truth=truth)
    return load_bundle(path), load_truth(path), path


def parallel_map(pool, fn, items):
    """``[fn(i) for i in items]``, through ``pool.map`` when a pool (any executor) is given."""
    if pool is None:
        return [fn(i) for i in items]
    return list(pool.map(fn, items))
