"""The ``tcut`` study over many seeds: the letter's bias reduction with intervals.

One seed is one full simulated campaign (every configuration's ring-downs, beat note and CMDS
reference), analysed at every t_cut with every method as the one-seed study does
(:func:`bayes_tfcrds.studies.tcut._tcut_config`). Per seed, configuration and method the bias is
averaged over the t_cut range as the letter does, against two references:

* the simulation's truth, ``A/A_true - 1``: the error of the line area itself;
* the configuration's simulated CMDS reference, ``A/A_ref - 1``: the letter's comparison, which
  carries the reference's own noise (u(A_ref) = 0.015 %, :func:`simulate.campaign.cmds_noise`).

Both the signed mean over t_cut and the mean of ``|.|`` (the letter's "average residual bias")
are kept. Over seeds: the mean with a 95 % Student-t interval. The bias reduction factor is
``mean_seeds(|CRDS bias|) / mean_seeds(|TF-CRDS bias|)`` (a ratio of means: a per-seed ratio
explodes where one seed's TF-CRDS bias is near 0), with a 95 % percentile bootstrap interval
that resamples seeds (numerator and denominator together).

Seed ``i`` draws from ``SeedSequence(seed, spawn_key=(i,))`` alone, so results do not depend on
the worker count; each seed writes one JSON file in OUTDIR/seeds, and a rerun skips the seeds
already done with the same settings. Seed 0's bundle is kept as OUTDIR/campaign.h5 (its Fig. 5
look-alike is drawn); the others are deleted after their analysis (about 50 MB each).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
from scipy import stats

from bayes_tfcrds.output.files import atomic_write_text
from bayes_tfcrds.output.plotting import literal, pyplot
from bayes_tfcrds.simulate.campaign import Campaign, parse_effect, simulate_campaign
from bayes_tfcrds.studies.common import stored_record
from bayes_tfcrds.studies.tcut import LETTER_BIAS, _tcut_config, _tcut_figure

RECORD_VERSION = 2  # 2: TF-CRDS at the centre of H's posterior, u with H's part
SEED_SCHEME = (
    "SeedSequence(seed, spawn_key=(i,)); H's posterior draws of configuration k: "
    "spawn_key=(i, 1 + k)"
)
# the bootstrap's own stream: a spawn key no seed index reaches (study.seeds <= 10000)
BOOTSTRAP_KEY = 1_000_000
N_BOOTSTRAP = 4000
LEVEL = 0.95
AGAINST = ("truth", "cmds")
LETTER_SPREAD = 6e-4  # the letter's "spread below 0.06 %" of the four CMDS references


@dataclass(frozen=True)
class SeedSettings:
    """Everything one seed's numbers depend on (each record holds a fingerprint of it)."""

    seed: int
    campaign: Campaign
    presets: tuple
    effects: tuple
    methods: tuple
    t_cuts_s: tuple
    profile: str
    window: str
    physical: bool

    def fingerprint(self) -> str:
        text = json.dumps(
            [RECORD_VERSION, asdict(self)], sort_keys=True, default=str
        )  # the Campaign's fields, cmds_area_rel_u among them
        return hashlib.sha256(text.encode()).hexdigest()[:16]


def settings_of(study) -> SeedSettings:
    """The seed settings a study file declares."""
    camp = replace(Campaign(), n_points=study.points, n_samples=study.samples, n_avg=study.averages)
    return SeedSettings(
        seed=study.seed,
        campaign=camp,
        presets=tuple(study.presets),
        effects=tuple(study.effects),
        methods=tuple(study.methods),
        t_cuts_s=tuple(study.t_cuts_s),
        profile=study.profile,
        window=study.windows[0],
        physical=study.shape_bounds == "physical",
    )


def run_seed(settings: SeedSettings, index: int, folder: Path) -> dict:
    """Simulate and analyse seed ``index``; its numbers depend on (settings, index) only."""
    from bayes_tfcrds.bundle.writer import save_bundle
    from bayes_tfcrds.output.report import git_commit

    rng = np.random.default_rng(np.random.SeedSequence(settings.seed, spawn_key=(index,)))
    effects = dict(parse_effect(e) for e in settings.effects)
    bundle, truth = simulate_campaign(list(settings.presets), rng, settings.campaign, effects)
    path = folder.parent / "campaign.h5" if index == 0 else folder / f"s{index:04d}.h5"
    save_bundle(bundle, path, truth=truth)
    rows = []
    for i, name in enumerate(bundle.configs):
        job = (
            str(path),
            name,
            settings.methods,
            settings.t_cuts_s,
            settings.profile,
            settings.window,
            settings.physical,
            np.random.SeedSequence(settings.seed, spawn_key=(index, 1 + i)),
        )
        rows.extend(_tcut_config(job))
    if index != 0:
        path.unlink()
    return {
        "index": index,
        "fingerprint": settings.fingerprint(),
        "a_true_si": truth["line"]["line_area_hz_per_m"],
        "rows": rows,
        "code": git_commit(),
    }


def seed_task(args) -> dict:
    """Pool task: seed ``index``, read from FOLDER if done with these settings, else run."""
    settings, index, folder = args
    folder = Path(folder)
    path = folder / f"s{index:04d}.json"
    done = stored_record(path, settings.fingerprint())
    if done is not None:
        return done
    rec = run_seed(settings, index, folder)
    atomic_write_text(path, json.dumps(rec, indent=1, default=float) + "\n")
    return rec


def run_seeds(settings: SeedSettings, n_seeds: int, folder, pool=None, progress=False) -> list:
    """All seed records (by index), through ``pool`` when given; finished ones are reused."""
    Path(folder).mkdir(parents=True, exist_ok=True)
    jobs = [(settings, i, str(folder)) for i in range(n_seeds)]
    if pool is None:
        it = jobs
        if progress:
            from tqdm import tqdm

            it = tqdm(jobs, desc="tcut seeds")
        return [seed_task(j) for j in it]
    from concurrent.futures import as_completed

    futs = [pool.submit(seed_task, j) for j in jobs]
    it = as_completed(futs)
    if progress:
        from tqdm import tqdm

        it = tqdm(it, total=len(futs), desc="tcut seeds")
    for _ in it:
        pass
    return sorted((f.result() for f in futs), key=lambda r: r["index"])


# ----------------------------------------------------------------------------- statistics


def seed_biases(rec: dict, names, methods) -> np.ndarray:
    """One seed's biases averaged over t_cut.

    Shape (config, method, against (truth, cmds), signed | abs): ``mean_t (A/A_x - 1)`` and
    ``mean_t |A/A_x - 1|`` (dimensionless).
    """
    out = np.full((len(names), len(methods), len(AGAINST), 2), np.nan)
    for i, n in enumerate(names):
        for j, m in enumerate(methods):
            rows = [r for r in rec["rows"] if r["config"] == n and r["method"] == m]
            area = np.array([r["area_si"] for r in rows])
            ref = np.array([r["ref_si"] for r in rows])
            for k, dev in enumerate((area / rec["a_true_si"] - 1, area / ref - 1)):
                out[i, j, k] = np.mean(dev), np.mean(np.abs(dev))
    return out


@dataclass(frozen=True)
class Interval:
    """A mean over seeds with its interval (dimensionless); ``sd`` the seed-to-seed sd."""

    mean: float
    lo: float
    hi: float
    sd: float
    n: int


def t_interval(x, level: float = LEVEL) -> Interval:
    """Mean of ``x`` with its Student-t interval (n - 1 degrees of freedom)."""
    x = np.asarray(x, float)
    n = x.size
    m = float(np.mean(x))
    sd = float(np.std(x, ddof=1)) if n > 1 else float("nan")
    half = stats.t.ppf(0.5 + level / 2, n - 1) * sd / np.sqrt(n) if n > 1 else float("nan")
    return Interval(m, m - half, m + half, sd, n)


def bootstrap_ratio(num, den, rng: np.random.Generator, n_boot=N_BOOTSTRAP, level=LEVEL):
    """``mean(num) / mean(den)`` and its percentile bootstrap interval, seeds resampled jointly."""
    num, den = np.asarray(num, float), np.asarray(den, float)
    value = float(np.mean(num) / np.mean(den))
    idx = rng.integers(0, num.size, size=(n_boot, num.size))
    ratios = num[idx].mean(axis=1) / den[idx].mean(axis=1)
    lo, hi = np.quantile(ratios, [0.5 - level / 2, 0.5 + level / 2])
    return Interval(value, float(lo), float(hi), float(np.std(ratios, ddof=1)), num.size)


@dataclass(frozen=True)
class SeedSummary:
    """The letter comparison over seeds.

    ``bias[(config, method, against, kind)]`` (kind: signed | abs) and
    ``factor[(config, against)]`` are :class:`Interval`; ``cmds_sd[config]`` the sd of
    A_ref/A_true over seeds, ``cmds_spread`` each seed's (max - min)/mean of the configurations'
    A_ref, ``stated_u[(config, method)]`` the fits' mean stated u(A/A_ref) (all dimensionless).
    """

    names: tuple
    methods: tuple
    n_seeds: int
    bias: dict
    factor: dict
    cmds_sd: dict
    cmds_spread: np.ndarray
    stated_u: dict
    at_calibration: dict  # TF-CRDS rows per config whose H posterior failed (calibration's H)


def summarise_seeds(records, names, methods, rng: np.random.Generator) -> SeedSummary:
    """Biases, reduction factors and the CMDS reference's scatter over all seed records."""
    b = np.array([seed_biases(r, names, methods) for r in records])  # (seed, cfg, m, ag, kind)
    bias, factor = {}, {}
    for i, n in enumerate(names):
        for j, m in enumerate(methods):
            for k, ag in enumerate(AGAINST):
                for q, kind in enumerate(("signed", "abs")):
                    bias[(n, m, ag, kind)] = t_interval(b[:, i, j, k, q])
        if "crds" in methods and "tf-crds" in methods:
            jc, jt = methods.index("crds"), methods.index("tf-crds")
            for k, ag in enumerate(AGAINST):
                factor[(n, ag)] = bootstrap_ratio(b[:, i, jc, k, 1], b[:, i, jt, k, 1], rng)
    ref = np.array(
        [
            [next(r["ref_si"] for r in rec["rows"] if r["config"] == n) for n in names]
            for rec in records
        ]
    )
    a_true = np.array([rec["a_true_si"] for rec in records])
    cmds_sd = {n: float(np.std(ref[:, i] / a_true - 1, ddof=1)) for i, n in enumerate(names)}
    spread = np.ptp(ref, axis=1) / ref.mean(axis=1)
    stated_u = {
        (n, m): float(
            np.mean(
                [
                    r["ratio_u"]
                    for rec in records
                    for r in rec["rows"]
                    if r["config"] == n and r["method"] == m
                ]
            )
        )
        for n in names
        for m in methods
    }
    at_calibration = {
        n: sum(
            r.get("h_at") == "calibration"
            for rec in records
            for r in rec["rows"]
            if r["config"] == n
        )
        for n in names
    }
    return SeedSummary(
        tuple(names), tuple(methods), len(records), bias, factor, cmds_sd, spread, stated_u,
        at_calibration,
    )  # fmt: skip


LETTER_FACTOR_MEANING = (
    "the average over t_cut of |A/A_ref - 1| for TF-CRDS, and the ratio of that average for "
    "CRDS to it for TF-CRDS, both against the measured CMDS reference of the same "
    "configuration (one measurement campaign, no interval)"
)


def summary_to_dict(s: SeedSummary) -> dict:
    """The summary as numbers.json holds it, every entry labelled by its reference."""
    configs = {}
    for n in s.names:
        entry = {}
        for m in s.methods:
            entry[m] = {
                f"bias_against_{ag}": {
                    "signed_mean_over_t_cut": asdict(s.bias[(n, m, ag, "signed")]),
                    "abs_mean_over_t_cut": asdict(s.bias[(n, m, ag, "abs")]),
                }
                for ag in AGAINST
            }
        if s.factor:
            entry["reduction_factor"] = {
                f"against_{ag}": asdict(s.factor[(n, ag)]) for ag in AGAINST
            }
        lb, lf = LETTER_BIAS.get(n, (None, None))
        entry["letter"] = {
            "tf_crds_abs_bias_against_cmds": None if lb is None else round(lb / 100, 6),
            "reduction_factor_against_cmds": lf,
            "meaning": LETTER_FACTOR_MEANING,
        }
        entry["cmds_a_ref_sd_over_seeds"] = s.cmds_sd[n]
        entry["stated_u_ratio_mean"] = {m: s.stated_u[(n, m)] for m in s.methods}
        entry["tf_crds_rows_at_calibration_h"] = s.at_calibration[n]
        configs[n] = entry
    return {
        "n_seeds": s.n_seeds,
        "seed_scheme": SEED_SCHEME,
        "unit": "biases, sd and spreads are fractions (0.001 = 0.1 %); factors are ratios",
        "interval": {
            "level": LEVEL,
            "bias": "mean over seeds, Student-t interval (n_seeds - 1 degrees of freedom)",
            "reduction_factor": (
                "mean over seeds of CRDS abs bias / mean over seeds of TF-CRDS abs bias; "
                f"percentile bootstrap over seeds, {N_BOOTSTRAP} resamples, "
                f"SeedSequence(seed, spawn_key=({BOOTSTRAP_KEY},)); its sd is that of the "
                "bootstrap ratios"
            ),
        },
        "configs": configs,
        "cmds_reference": {
            "spread_per_seed": [float(v) for v in s.cmds_spread],
            "spread_mean": float(np.mean(s.cmds_spread)),
            "fraction_of_seeds_below_letter_spread": float(np.mean(s.cmds_spread < LETTER_SPREAD)),
            "letter_spread_below": LETTER_SPREAD,
        },
    }


# ----------------------------------------------------------------------------- rendering


def _pct(iv: Interval, digits=3) -> str:
    return f"{100 * iv.mean:.{digits}f} [{100 * iv.lo:.{digits}f}, {100 * iv.hi:.{digits}f}]"


def _fac(iv: Interval) -> str:
    return f"{iv.mean:.0f} [{iv.lo:.0f}, {iv.hi:.0f}]"


def seeds_figure(plt, rep, s: SeedSummary) -> None:
    """Reduction factor and TF-CRDS bias per configuration, against truth and against CMDS.

    The letter's values (against its CMDS references) are drawn beside them.
    """
    fig, (ax_f, ax_b) = plt.subplots(1, 2, figsize=(9.5, 4.2))
    x = np.arange(len(s.names))
    style = {"truth": ("o", "C0", -0.12), "cmds": ("s", "C1", 0.12)}
    for ag, (mk, col, dx) in style.items():
        if s.factor:
            f = [s.factor[(n, ag)] for n in s.names]
            ax_f.errorbar(
                x + dx,
                [v.mean for v in f],
                [[v.mean - v.lo for v in f], [v.hi - v.mean for v in f]],
                fmt=mk,
                color=col,
                label=f"ours, against {'truth' if ag == 'truth' else 'CMDS'}",
            )
        bi = [s.bias[(n, "tf-crds", ag, "abs")] for n in s.names]
        ax_b.errorbar(
            x + dx,
            [100 * v.mean for v in bi],
            [[100 * (v.mean - v.lo) for v in bi], [100 * (v.hi - v.mean) for v in bi]],
            fmt=mk,
            color=col,
            label=f"ours, against {'truth' if ag == 'truth' else 'CMDS'}",
        )
    letter = [LETTER_BIAS.get(n, (np.nan, np.nan)) for n in s.names]
    ax_f.plot(x, [lf for _, lf in letter], "k*", ms=10, label="letter, against CMDS")
    ax_b.plot(x, [lb for lb, _ in letter], "k*", ms=10, label="letter, against CMDS")
    ax_f.set_yscale("log")
    ax_f.set_ylabel("bias reduction factor CRDS / TF-CRDS")
    ax_b.set_ylabel("TF-CRDS mean |A/A_x - 1| over t_cut (%), x: true | ref")
    for ax in (ax_f, ax_b):
        ax.set_xticks(x, [literal(n) for n in s.names])
        ax.legend(fontsize=7)
    fig.suptitle(f"{s.n_seeds} seeds: mean and 95 % interval")
    fig.tight_layout()
    rep.add_figure(
        fig,
        "Left: bias reduction factor (CRDS mean |bias| over TF-CRDS mean |bias|, both averaged "
        "over t_cut and over seeds; 95 % bootstrap interval over seeds), against the "
        "simulation's truth (A/A_true) and against the configuration's simulated CMDS "
        "reference (A/A_ref); stars: the letter's factors, which are against its measured CMDS "
        "references. Right: the TF-CRDS bias itself (t interval).",
    )


def bias_tables(rep, s: SeedSummary) -> None:
    """The biases (signed and |.|, against truth and against CMDS) and the factors."""
    rep.add_heading(f"Bias averaged over the t_cut range: mean over {s.n_seeds} seeds [95 % t]")
    rows = []
    for n in s.names:
        for m in s.methods:
            lb = LETTER_BIAS.get(n, (np.nan,))[0] if m == "tf-crds" else np.nan
            rows.append(
                [
                    n,
                    m.upper(),
                    _pct(s.bias[(n, m, "truth", "signed")]),
                    _pct(s.bias[(n, m, "truth", "abs")]),
                    _pct(s.bias[(n, m, "cmds", "signed")]),
                    _pct(s.bias[(n, m, "cmds", "abs")]),
                    "-" if np.isnan(lb) else f"{lb:.2f}",
                    f"{100 * s.stated_u[(n, m)]:.3f}",
                    f"{100 * s.bias[(n, m, 'truth', 'signed')].sd:.3f}",
                ]
            )
    rep.add_table(
        [
            "config",
            "method",
            "A/A_true - 1 (%)",
            "|A/A_true - 1| (%)",
            "A/A_ref - 1 (%)",
            "|A/A_ref - 1| (%)",
            "letter |A/A_ref - 1| (%)",
            "stated u(A/A_ref) (%)",
            "sd over seeds of A/A_true - 1 (%)",
        ],
        rows,
    )
    rep.add_text(
        "Stated u: the mean over seeds and t_cut of the u each analysis states for A/A_ref: the "
        "line fits' for CRDS; for TF-CRDS the line fit's and that of H's posterior (A fitted at "
        "its centre, as `linefit` does); the CMDS reference's fit in both. Beside it the sd over "
        "seeds of the t_cut-averaged A/A_true - 1. For TF-CRDS, if its u is right, that sd is "
        "about sqrt(stated u^2 - u(A_ref)^2) (u(A_ref)/A_ref = 0.015 %) or somewhat less "
        "(averaging over t_cut removes part of the noise, not H's part); for CRDS the bias "
        "dominates, and its u does not hold it."
        + "".join(
            f" {n}: {k} TF-CRDS rows had no posterior of H (fitted at the calibration's H, u "
            "without H's part), in these means."
            for n, k in s.at_calibration.items()
            if k
        )
    )
    if not s.factor:
        return
    rep.add_heading("Bias reduction factor CRDS / TF-CRDS [95 % bootstrap over seeds]")
    rep.add_table(
        [
            "config",
            "ours, against truth (A/A_true)",
            "ours, against CMDS (A/A_ref)",
            "letter, against CMDS",
        ],
        [
            [
                n,
                _fac(s.factor[(n, "truth")]),
                _fac(s.factor[(n, "cmds")]),
                f"{LETTER_BIAS.get(n, (np.nan, np.nan))[1]:.0f}",
            ]
            for n in s.names
        ],
    )
    rep.add_text(
        "What each factor is a ratio of. Ours against truth: the mean over seeds of the CRDS "
        "|A/A_true - 1| averaged over t_cut, divided by the same for TF-CRDS; it says by how "
        "much TF-CRDS reduces the error of the line area. Ours against CMDS: the same with the "
        "configuration's simulated CMDS reference A_ref in place of the truth, the letter's "
        "definition; its TF-CRDS term holds the reference's own noise (u(A_ref) = 0.015 % per "
        "configuration), which bounds the factor. The letter's bias and factor are "
        + LETTER_FACTOR_MEANING
        + "; they compare with ours against CMDS, and a single campaign of ours scatters "
        "within the interval shown. The |.| columns are means of a positive quantity: with few "
        "seeds their t interval may reach below 0. The last column is the fits' own stated "
        "u(A/A_ref) (A's noise and A_ref's), the scale of the |.| of an unbiased method."
    )


def cmds_lines(rep, s: SeedSummary) -> None:
    """The simulated CMDS reference's scatter beside the letter's spread."""
    sd = max(s.cmds_sd.values())
    rep.add_summary(
        "CMDS A_ref: sd over seeds (largest configuration)",
        f"{100 * sd:.3f} %",
        "letter: the four references spread < 0.06 %",
    )
    rep.add_summary(
        "CMDS A_ref spread across configurations (max - min)",
        f"mean {100 * np.mean(s.cmds_spread):.3f} %, largest {100 * np.max(s.cmds_spread):.3f} %",
        f"below 0.06 % in {np.sum(s.cmds_spread < LETTER_SPREAD)} of {s.n_seeds} seeds",
    )
    rep.add_diagnostic(
        "CMDS A_ref sd over seeds below the letter's 0.06 % spread",
        sd < LETTER_SPREAD,
        f"{100 * sd:.3f} %",
    )
    for n in s.names:
        if "tf-crds" in s.methods:
            iv = s.bias[(n, "tf-crds", "truth", "abs")]
            rep.add_diagnostic(
                f"{n}: TF-CRDS mean |A/A_true - 1| below 0.1 %",
                iv.mean < 1e-3,
                _pct(iv),
            )
        if s.factor:
            f_t, f_c = s.factor[(n, "truth")], s.factor[(n, "cmds")]
            rep.add_summary(
                f"{n}: reduction factor against truth / against CMDS",
                f"{_fac(f_t)} / {_fac(f_c)}",
                f"letter (against CMDS): {LETTER_BIAS.get(n, (np.nan, np.nan))[1]:.0f}",
            )


def tcut_seeds_study(study, rep, out, progress=False, pool=None) -> dict:
    """The ``tcut`` study over ``study.n_seeds`` simulated campaigns; report and numbers."""
    settings = settings_of(study)
    folder = Path(out) / "seeds"
    recs = run_seeds(settings, study.n_seeds, folder, pool, progress)
    names = list(dict.fromkeys(r["config"] for r in recs[0]["rows"]))
    rng = np.random.default_rng(np.random.SeedSequence(study.seed, spawn_key=(BOOTSTRAP_KEY,)))
    s = summarise_seeds(recs, names, list(settings.methods), rng)
    plt = pyplot()
    rep.add_text(
        f"{s.n_seeds} independent simulated campaigns (seed i: {SEED_SCHEME}), each analysed at "
        "every t_cut with every method. The bias is averaged over the t_cut range as the letter "
        "does, against the simulation's truth and against the configuration's simulated CMDS "
        "reference."
    )
    seeds_figure(plt, rep, s)
    bias_tables(rep, s)
    cmds_lines(rep, s)
    rep.add_heading("Seed 0: one campaign (letter Fig. 5)")
    rows0 = recs[0]["rows"]
    refs = np.array([next(r["ref_si"] for r in rows0 if r["config"] == n) for n in names])
    band = (refs.min() / refs.mean() - 1, refs.max() / refs.mean() - 1)
    seed0_configs, _ = _tcut_figure(plt, rep, study, rows0, names, band)
    codes = sorted({r.get("code", "not recorded") for r in recs})
    rep.add_text(
        "Seed records (OUTDIR/seeds) are reused on a rerun with the same settings whatever the "
        "code version; they were computed with: "
        + ", ".join(codes)
        + ". Delete the seeds/ folder to recompute them with the current code."
    )
    numbers = summary_to_dict(s)
    numbers["seed_code"] = codes
    numbers["per_seed"] = [
        {"index": r["index"], "a_true_si": r["a_true_si"], "rows": r["rows"]} for r in recs
    ]
    numbers["seed0"] = {
        "rows": rows0,
        "cmds_spread": [float(v) for v in band],
        "configs_against_cmds": seed0_configs,
    }
    return numbers
