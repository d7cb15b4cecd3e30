"""Declarative studies: a short TOML file says what to simulate (or load) and analyse; the runner
does it and writes a self-contained report.

Study file layout (every key optional unless marked)::

    [study]
    name = "letter_tcut"          # required
    title = "..."                 # shown on the report
    kind = "tcut"                 # required: tcut | figures | window_history | budgets | coverage
    seed = 7                      # the simulation and sampling seed

    [campaign]                    # simulate (default) ...
    presets = ["letter-D1", "letter-D2"]
    points = 101                  # spectral points
    samples = 16384               # samples per transient
    averages = 100                # acquisitions per transient
    effects = ["etalon:amplitude_per_m=1e-7"]
    # bundle = "data/campaign.h5" # ... or load a measurement bundle instead
    campaigns = 200               # coverage: simulated campaigns (truths drawn per campaign)

    [analysis]
    methods = ["crds", "tf-crds"]
    t_cuts_us = [2, 3, 4, 5, 6, 8]
    t_cut_us = 4                  # the t_cut of single-t_cut results
    profile = "qsdhcp"
    shape_bounds = "free"         # free | physical (Gamma2, nu_VC >= 0, as the letter reads its fits)
    windows = ["extinction"]
    mcmc_steps = 3000             # budgets: MCMC steps per ensemble before the gates are checked
    posterior = "laplace"         # coverage: the budget's posterior, laplace | mcmc
    mcmc_campaigns = 20           # coverage: the first N campaigns again with MCMC (cross-check)

An invalid file is refused with the offending key named.
"""
from __future__ import annotations

import difflib
import tomllib
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

SCHEMA = {
    "study": {"name": str, "title": str, "description": str, "kind": str, "seed": int},
    "campaign": {"presets": [str], "points": int, "samples": int, "averages": int, "effects": [str], "bundle": str,
                 "campaigns": int},
    "analysis": {"methods": [str], "t_cuts_us": [float], "t_cut_us": float, "profile": str, "shape_bounds": str,
                 "windows": [str], "mcmc_steps": int, "posterior": str, "mcmc_campaigns": int},
}
KINDS = ("tcut", "figures", "window_history", "budgets", "coverage")
LETTER_BIAS = {"D1": (0.06, 41), "D2": (0.03, 87), "D3": (0.15, 74), "D4": (0.28, 43)}   # % and factor


class StudyError(ValueError):
    """The study file is invalid: the message names the key and what is wrong."""


@dataclass(frozen=True)
class Study:
    name: str
    kind: str
    title: str
    description: str
    seed: int
    presets: tuple
    points: int
    samples: int
    averages: int
    effects: tuple
    bundle: str | None
    methods: tuple
    t_cuts_s: tuple
    t_cut_s: float
    profile: str
    windows: tuple
    mcmc_steps: int
    path: str
    text: str
    n_campaigns: int = 0
    posterior: str = "mcmc"
    mcmc_campaigns: int = 0
    shape_bounds: str = "free"


def _check_type(where, value, kind):
    if isinstance(kind, list):
        if not isinstance(value, list):
            raise StudyError(f"{where}: key must be a list, got {type(value).__name__}")
        for i, v in enumerate(value):
            _check_type(f"{where}[{i}]", v, kind[0])
        return
    if kind is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
    elif kind is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    else:
        ok = isinstance(value, kind)
    if not ok:
        raise StudyError(f"{where}: expected {kind.__name__}, got {value!r}")


def load_study(path) -> Study:
    """Parse and validate a study file; raise :class:`StudyError` naming the bad key."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
        raw = tomllib.loads(text)
    except FileNotFoundError:
        raise StudyError(f"{path}: no such study file")
    except tomllib.TOMLDecodeError as exc:
        raise StudyError(f"{path}: not valid TOML ({exc})")
    for section, body in raw.items():
        if section not in SCHEMA:
            hint = difflib.get_close_matches(section, SCHEMA, n=1)
            raise StudyError(f"{path}: unknown section [{section}]" + (f" (did you mean [{hint[0]}]?)" if hint else ""))
        if not isinstance(body, dict):
            raise StudyError(f"{path}: {section} must be a table [{section}]")
        for key, value in body.items():
            if key not in SCHEMA[section]:
                hint = difflib.get_close_matches(key, SCHEMA[section], n=1)
                raise StudyError(f"{path}: unknown key {section}.{key}" + (f" (did you mean {section}.{hint[0]}?)" if hint else ""))
            _check_type(f"{path}: {section}.{key}", value, SCHEMA[section][key])
    st, cp, an = raw.get("study", {}), raw.get("campaign", {}), raw.get("analysis", {})
    for key in ("name", "kind"):
        if key not in st:
            raise StudyError(f"{path}: missing required key study.{key}")
    if st["kind"] not in KINDS:
        raise StudyError(f"{path}: study.kind must be one of {KINDS}, got {st['kind']!r}")
    from .simulate import PRESETS, parse_effect
    for i, p in enumerate(cp.get("presets", [])):
        if p not in PRESETS:
            raise StudyError(f"{path}: campaign.presets[{i}] = {p!r} is not a preset ({sorted(PRESETS)})")
    for i, e in enumerate(cp.get("effects", [])):
        try:
            parse_effect(e)
        except ValueError as exc:
            raise StudyError(f"{path}: campaign.effects[{i}]: {exc}")
    for key, lo, hi in (("points", 8, 2000), ("samples", 256, 1 << 20), ("averages", 1, 100000),
                        ("campaigns", 1, 100000)):
        if key in cp and not lo <= cp[key] <= hi:
            raise StudyError(f"{path}: campaign.{key} = {cp[key]} is outside [{lo}, {hi}]")
    if an.get("posterior", "mcmc") not in ("mcmc", "laplace"):
        raise StudyError(f"{path}: analysis.posterior must be 'mcmc' or 'laplace', got {an['posterior']!r}")
    if an.get("mcmc_campaigns", 0) < 0:
        raise StudyError(f"{path}: analysis.mcmc_campaigns must be >= 0")
    if st["kind"] == "coverage" and ("bundle" in cp or "effects" in cp):
        raise StudyError(f"{path}: a coverage study simulates its own campaigns: campaign.bundle and "
                         "campaign.effects do not apply")
    for i, m in enumerate(an.get("methods", [])):
        if m not in ("crds", "tf-crds"):
            raise StudyError(f"{path}: analysis.methods[{i}] = {m!r} must be 'crds' or 'tf-crds'")
    for i, w in enumerate(an.get("windows", [])):
        if w not in ("extinction", "letter"):
            raise StudyError(f"{path}: analysis.windows[{i}] = {w!r} must be 'extinction' or 'letter'")
    if an.get("shape_bounds", "free") not in ("free", "physical"):
        raise StudyError(f"{path}: analysis.shape_bounds must be 'free' or 'physical', got {an['shape_bounds']!r}")
    from .lineshape import PROFILES
    if an.get("profile", "qsdhcp") not in PROFILES:
        raise StudyError(f"{path}: analysis.profile must be one of {sorted(PROFILES)}")
    t_cuts = tuple(float(v) * 1e-6 for v in an.get("t_cuts_us", [2, 3, 4, 5, 6, 8]))
    if any(t <= 0 for t in t_cuts):
        raise StudyError(f"{path}: analysis.t_cuts_us must be positive")
    if "bundle" in cp and ("presets" in cp or "effects" in cp):
        raise StudyError(f"{path}: campaign.bundle excludes campaign.presets and campaign.effects")
    bundle = cp.get("bundle")
    if bundle is not None and not Path(bundle).is_absolute():
        bundle = str((path.parent / bundle).resolve())
    return Study(name=st["name"], kind=st["kind"], title=st.get("title", st["name"]),
                 description=st.get("description", ""), seed=st.get("seed", 7),
                 presets=tuple(cp.get("presets", ["letter-D1", "letter-D2", "letter-D3", "letter-D4"])),
                 points=cp.get("points", 101), samples=cp.get("samples", 16384), averages=cp.get("averages", 100),
                 effects=tuple(cp.get("effects", [])), bundle=bundle,
                 methods=tuple(an.get("methods", ["crds", "tf-crds"])), t_cuts_s=t_cuts,
                 t_cut_s=float(an.get("t_cut_us", 4)) * 1e-6, profile=an.get("profile", "qsdhcp"),
                 windows=tuple(an.get("windows", ["extinction"])), mcmc_steps=an.get("mcmc_steps", 3000),
                 path=str(path), text=text, n_campaigns=cp.get("campaigns", 200),
                 posterior=an.get("posterior", "mcmc"), mcmc_campaigns=an.get("mcmc_campaigns", 0),
                 shape_bounds=an.get("shape_bounds", "free"))


def campaign_of(study: Study, outdir: Path):
    """Simulate the study's campaign into OUTDIR/campaign.h5 (or load the named bundle)."""
    from .bundle import load_bundle, load_truth, save_bundle
    from .simulate import Campaign, parse_effect, simulate_campaign
    if study.bundle is not None:
        return load_bundle(study.bundle), None, Path(study.bundle)
    effects = dict(parse_effect(e) for e in study.effects)
    camp = replace(Campaign(), n_points=study.points, n_samples=study.samples, n_avg=study.averages)
    bundle, truth = simulate_campaign(list(study.presets), np.random.default_rng(study.seed), camp, effects)
    path = outdir / "campaign.h5"
    save_bundle(bundle, path, truth=truth)
    return load_bundle(path), load_truth(path), path


def run_study(path, outdir, progress: bool = False, pool=None, seed: int | None = None):
    """Run the study file at ``path`` and write its report into ``outdir``; returns the report paths.

    ``seed`` (if given) replaces the file's ``[study] seed``.
    """
    from .report import Report, provenance
    study = load_study(path)
    if seed is not None:
        study = replace(study, seed=int(seed))
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    rep = Report(title=study.title)
    if study.description:
        rep.add_text(study.description)
    if study.kind == "coverage":
        # many campaigns, each simulated inside its own task: no single bundle
        from .calibration_study import coverage_study
        numbers = coverage_study(study, rep, out, progress=progress, pool=pool)
        rep.provenance = provenance(seeds={"study": study.seed, "campaign i": f"SeedSequence({study.seed}, "
                                           "spawn_key=(i,))"}, study_text=study.text)
    else:
        bundle, truth, bundle_path = campaign_of(study, out)
        runner = {"tcut": _study_tcut, "figures": _study_figures, "window_history": _study_window_history,
                  "budgets": _study_budgets}[study.kind]
        numbers = runner(study, bundle, truth, rep, out, progress=progress, pool=pool)
        rep.provenance = provenance(seeds={"study": study.seed}, inputs=[bundle_path], study_text=study.text,
                                    extra={"bundle description": bundle.description or ""})
    import json
    from .cli import atomic_write_text
    atomic_write_text(out / "numbers.json", json.dumps(numbers, indent=2, default=float) + "\n")
    return rep.write(out, stem=study.name)


def _map(pool, fn, items):
    if pool is None:
        return [fn(i) for i in items]
    return list(pool.map(fn, items))


# ----------------------------------------------------------------------------------- t_cut


def _tcut_config(args):
    bundle_path, name, methods, t_cuts, profile, window, physical = args
    from .analysis import calibrate
    from .bundle import load_bundle
    from .linefit import analyse_line
    bundle = load_bundle(bundle_path)
    cfg = bundle.configs[name]
    cal = calibrate(cfg, window=window) if "tf-crds" in methods else None
    rows = []
    for m in methods:
        for tc in t_cuts:
            r = analyse_line(bundle, cfg, method=m, window=window, t_cut_s=tc, profile_name=profile,
                             calibration=cal if m == "tf-crds" else None, physical_bounds=physical)
            rows.append({"config": name, "method": m, "t_cut_s": tc, "ratio": r["ratio"]["value"],
                         "ratio_u": r["ratio"]["u"], "area_si": r["line_area"]["value_si"],
                         "ref_si": r["reference_area"]["value_si"], "chi2_red": r["chi2_red"],
                         "shape_at_bound": r["shape_at_bound"], "unphysical_shape": r["unphysical_shape"]})
    return rows


def _study_tcut(study, bundle, truth, rep, out, progress=False, pool=None):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    bpath = str(out / "campaign.h5") if study.bundle is None else study.bundle
    window = study.windows[0]
    jobs = [(bpath, name, study.methods, study.t_cuts_s, study.profile, window, study.shape_bounds == "physical")
            for name in bundle.configs]
    rows = [r for part in _map(pool, _tcut_config, jobs) for r in part]
    names = list(bundle.configs)
    refs = np.array([next(r["ref_si"] for r in rows if r["config"] == n) for n in names])
    band = (refs.min() / refs.mean() - 1, refs.max() / refs.mean() - 1)
    numbers = {"rows": rows, "cmds_spread": [float(b) for b in band], "configs": {}}
    fig, (ax_top, ax_all) = plt.subplots(2, 1, figsize=(7.5, 7.5), sharex=True,
                                         gridspec_kw={"height_ratios": [1, 1.3]})
    colors = dict(zip(names, plt.cm.tab10(np.arange(len(names)))))
    for ax in (ax_top, ax_all):
        ax.axhspan(1 + band[0], 1 + band[1], color="0.85", label="CMDS A_ref spread")
        ax.axhline(1.0, color="0.4", lw=0.8)
    table = []
    for n in names:
        cfg_rows = {m: [r for r in rows if r["config"] == n and r["method"] == m] for m in study.methods}
        entry = {}
        for m, mk in (("crds", "+"), ("tf-crds", "o")):
            if m not in cfg_rows:
                continue
            t = np.array([r["t_cut_s"] for r in cfg_rows[m]]) * 1e6
            y = np.array([r["ratio"] for r in cfg_rows[m]])
            u = np.array([r["ratio_u"] for r in cfg_rows[m]])
            ax_all.errorbar(t, y, u, fmt=mk, color=colors[n], ms=6, label=f"{n} {m.upper()}")
            if m == "tf-crds":
                ax_top.errorbar(t, y, u, fmt=mk, color=colors[n], ms=5, label=f"{n}")
            entry[m] = float(np.mean(np.abs(y - 1)))
        if "crds" in entry and "tf-crds" in entry:
            entry["factor"] = entry["crds"] / entry["tf-crds"]
        numbers["configs"][n] = entry
        lb, lf = LETTER_BIAS.get(n, (float("nan"), float("nan")))
        table.append([n, f"{100 * entry.get('crds', np.nan):.2f}", f"{100 * entry.get('tf-crds', np.nan):.3f}",
                      f"{lb:.2f}", f"{entry.get('factor', np.nan):.0f}", f"{lf:.0f}"])
    ax_top.set_ylabel("A/A_ref (TF-CRDS)")
    ax_all.set_ylabel("A/A_ref")
    ax_all.set_xlabel("t_cut (us)")
    ax_all.legend(fontsize=7, ncol=2)
    ax_top.legend(fontsize=7, ncol=4)
    ax_top.set_title("Line area relative to CMDS against t_cut (letter Fig. 5)")
    rep.add_figure(fig, "A/A_ref against t_cut for every configuration: CRDS (+) and TF-CRDS (o); grey: the spread "
                        "of the configurations' CMDS references. Top: TF-CRDS magnified.")
    rep.add_heading("Bias reduction (mean |A/A_ref - 1| over the t_cut range)")
    rep.add_table(["config", "CRDS bias (%)", "TF-CRDS bias (%)", "letter TF-CRDS bias (%)", "reduction factor",
                   "letter factor"], table)
    for n in names:
        e = numbers["configs"][n]
        rep.add_summary(f"{n}: TF-CRDS mean |A/A_ref - 1|", f"{100 * e.get('tf-crds', np.nan):.3f} %",
                        f"letter {LETTER_BIAS.get(n, ('?',))[0]} %; CRDS {100 * e.get('crds', np.nan):.2f} %")
        rep.add_diagnostic(f"{n}: TF-CRDS bias below 0.1 %", e.get("tf-crds", 1) < 1e-3,
                           f"{100 * e.get('tf-crds', np.nan):.3f} %")
    rep.add_summary("CMDS A_ref spread across configurations", f"{100 * (band[1] - band[0]):.3f} %", "letter: < 0.06 %")
    for r in rows:
        if r["method"] == "tf-crds":
            rep.add_diagnostic(f"{r['config']} TF-CRDS t_cut {r['t_cut_s'] * 1e6:g} us: line-fit chi2_red < 2",
                               r["chi2_red"] < 2, f"{r['chi2_red']:.2f}")
    rep.add_text("The comparison with CMDS is limited by the reference's own noise (the grey band); the table "
                 "against the simulation's truth below separates the two.")
    if study.shape_bounds == "physical":
        rep.add_text("Line fits hold Gamma2 and nu_VC at >= 0 (analysis.shape_bounds = 'physical'), reading the "
                     "CRDS spectra as physical line shapes as the letter does. On a spectrum distorted by an "
                     "uncorrected H the free estimator would follow the distortion below 0 and give a different "
                     "(larger) CRDS bias; the TF-CRDS fits do not reach the bounds.")
    else:
        rep.add_text("Line fits leave Gamma2 and nu_VC free on the qSDHCP continuation (unbiased when the model is "
                     "right); a fit that ends below 0 is named in the last column of the table below.")
    if truth is not None:
        a_true = truth["line"]["line_area_hz_per_m"]
        rep.add_heading("Against the simulation's truth")
        rep.add_table(["config", "method", "t_cut (us)", "A/A_true - 1 (%)", "A_ref/A_true - 1 (%)",
                       "line-fit chi2_red", "shape held at 0 / below 0"],
                      [[r["config"], r["method"], f"{r['t_cut_s'] * 1e6:g}", f"{100 * (r['area_si'] / a_true - 1):+.3f}",
                        f"{100 * (r['ref_si'] / a_true - 1):+.3f}", f"{r['chi2_red']:.1f}",
                        ", ".join(r["shape_at_bound"] + [n + " < 0" for n in r["unphysical_shape"]]) or "-"]
                       for r in rows])
    return numbers


def _study_figures(study, bundle, truth, rep, out, progress=False, pool=None):
    from .study_figures import letter_figures
    return letter_figures(study, bundle, truth, rep)


def _study_window_history(study, bundle, truth, rep, out, progress=False, pool=None):
    from .study_figures import window_history
    return window_history(study, bundle, truth, rep)


def _study_budgets(study, bundle, truth, rep, out, progress=False, pool=None):
    from .study_figures import budgets
    return budgets(study, bundle, truth, rep, out, progress=progress, pool=pool)
