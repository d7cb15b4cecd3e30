"""Run a declared study: the registry of study kinds and the runner that writes the report."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

from bayes_tfcrds.output.files import atomic_write_text
from bayes_tfcrds.studies.common import campaign_of, load_study_bundle
from bayes_tfcrds.studies.spec import KINDS, load_study


def _runner(kind: str):
    """The function that runs a study of ``kind`` (imported on use: each needs its own layers)."""
    if kind == "tcut":
        from bayes_tfcrds.studies.tcut import study_tcut

        return study_tcut
    if kind == "figures":
        from bayes_tfcrds.studies.figures import letter_figures

        return letter_figures
    if kind == "window_history":
        from bayes_tfcrds.studies.figures import window_history

        return window_history
    if kind == "budgets":
        from bayes_tfcrds.studies.budgets import budgets

        return budgets
    if kind == "coverage":
        from bayes_tfcrds.studies.coverage import coverage_study

        return coverage_study
    raise ValueError(f"unknown study kind {kind!r} (one of {KINDS})")


def run_study(path, outdir, progress: bool = False, pool=None, seed: int | None = None):
    """Run the study file at ``path`` and write its report into ``outdir``.

    Returns the report's paths (HTML, PDF).

    ``seed`` (if given) replaces the file's ``[study] seed``.
    """
    from bayes_tfcrds.output.report import Report, provenance

    study = load_study(path)
    if seed is not None:
        study = replace(study, seed=int(seed))
    # a named bundle is checked before the report folder exists (nothing is left on a refusal)
    given = load_study_bundle(study) if study.bundle is not None else None
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    rep = Report(title=study.title)
    if study.description:
        rep.add_text(study.description)
    runner = _runner(study.kind)
    if study.kind == "tcut" and study.n_seeds > 1:
        # many campaigns, each simulated inside its own task; seed 0's bundle is kept
        from bayes_tfcrds.studies.tcut_seeds import SEED_SCHEME, tcut_seeds_study

        numbers = tcut_seeds_study(study, rep, out, progress=progress, pool=pool)
        seed0 = out / "campaign.h5"
        rep.provenance = provenance(
            seeds={"study": study.seed, "campaign i": SEED_SCHEME.replace("seed", str(study.seed))},
            inputs=[seed0] if seed0.exists() else [],
            study_text=study.text,
        )
    elif study.kind == "coverage":
        # many campaigns, each simulated inside its own task: no single bundle
        numbers = runner(study, rep, out, progress=progress, pool=pool)
        rep.provenance = provenance(
            seeds={
                "study": study.seed,
                "campaign i": f"SeedSequence({study.seed}, spawn_key=(i,))",
            },
            study_text=study.text,
        )
    else:
        bundle, truth, bundle_path = campaign_of(study, out, given)
        numbers = runner(study, bundle, truth, rep, out, progress=progress, pool=pool)
        rep.provenance = provenance(
            seeds={"study": study.seed},
            inputs=[bundle_path],
            study_text=study.text,
            extra={"bundle description": bundle.description or ""},
        )
    atomic_write_text(out / "numbers.json", json.dumps(numbers, indent=2, default=float) + "\n")
    return rep.write(out, stem=study.name)
