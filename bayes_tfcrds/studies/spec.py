"""Declarative studies.

A short TOML file says what to simulate (or load) and analyse; the runner does it and writes a
self-contained report.

Study file layout (every key optional unless marked)::

    [study]
    name = "letter_tcut"          # required
    title = "..."                 # shown on the report
    kind = "tcut"                 # required: tcut | figures | window_history | budgets | coverage
    seed = 7                      # the simulation and sampling seed
    seeds = 20                    # tcut: independent simulated campaigns (default 1)

    [campaign]                    # simulate (default) ...
    presets = ["letter-D1", "letter-D2"]
    points = 101                  # spectral points
    samples = 16384               # samples per transient
    averages = 100                # acquisitions per transient
    effects = ["etalon:amplitude_per_m=1e-7"]
    # bundle = "data/campaign.h5" # ... or load a measurement bundle instead
    campaigns = 200               # coverage: simulated campaigns (truths drawn per campaign)
    chains = ["preset", "zoo"]    # coverage strata: chains about the presets and/or the zoo's
    noise = ["white", "coloured"] # coverage strata: white and/or coloured detector noise

    [analysis]
    methods = ["crds", "tf-crds"]
    t_cuts_us = [2, 3, 4, 5, 6, 8]
    t_cut_us = 4                  # the t_cut of single-t_cut results
    profile = "qsdhcp"
    shape_bounds = "free"         # free | physical (Gamma2, nu_VC >= 0, as the letter reads fits)
    windows = ["extinction"]
    mcmc_steps = 3000             # budgets: MCMC steps per ensemble before the gates are checked
    posterior = "laplace"         # coverage: the budget's posterior, laplace | mcmc
    mcmc_campaigns = 20           # coverage: the first N campaigns again with MCMC (cross-check)

An invalid file is refused with the offending key named.
"""

from __future__ import annotations

import difflib
import math
import re
import tomllib
from dataclasses import dataclass
from pathlib import Path

SCHEMA = {
    "study": {
        "name": str,
        "title": str,
        "description": str,
        "kind": str,
        "seed": int,
        "seeds": int,
    },
    "campaign": {
        "presets": [str],
        "points": int,
        "samples": int,
        "averages": int,
        "effects": [str],
        "bundle": str,
        "campaigns": int,
        "chains": [str],
        "noise": [str],
    },
    "analysis": {
        "methods": [str],
        "t_cuts_us": [float],
        "t_cut_us": float,
        "profile": str,
        "shape_bounds": str,
        "windows": [str],
        "mcmc_steps": int,
        "posterior": str,
        "mcmc_campaigns": int,
    },
}

KINDS = ("tcut", "figures", "window_history", "budgets", "coverage")


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
    n_seeds: int = 1
    chain_kinds: tuple = ("preset",)
    noise_kinds: tuple = ("white",)


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


def _read(path: Path) -> tuple[str, dict]:
    """The file's text and its TOML tables; a missing or invalid file is refused."""
    try:
        text = path.read_text(encoding="utf-8")
        raw = tomllib.loads(text)
    except FileNotFoundError:
        raise StudyError(f"{path}: no such study file") from None
    except IsADirectoryError:
        raise StudyError(f"{path}: is a folder, not a study file") from None
    except UnicodeDecodeError as exc:
        raise StudyError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    except tomllib.TOMLDecodeError as exc:
        raise StudyError(f"{path}: not valid TOML ({exc})") from None
    return text, raw


def _check_schema(path: Path, raw: dict) -> None:
    """Every section and key known (with a hint for a near miss), every value of its type."""
    for section, body in raw.items():
        if section not in SCHEMA:
            hint = difflib.get_close_matches(section, SCHEMA, n=1)
            raise StudyError(
                f"{path}: unknown section [{section}]"
                + (f" (did you mean [{hint[0]}]?)" if hint else "")
            )
        if not isinstance(body, dict):
            raise StudyError(f"{path}: {section} must be a table [{section}]")
        for key, value in body.items():
            if key not in SCHEMA[section]:
                hint = difflib.get_close_matches(key, SCHEMA[section], n=1)
                raise StudyError(
                    f"{path}: unknown key {section}.{key}"
                    + (f" (did you mean {section}.{hint[0]}?)" if hint else "")
                )
            _check_type(f"{path}: {section}.{key}", value, SCHEMA[section][key])


NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")


def _check_study_and_campaign(path: Path, st: dict, cp: dict) -> None:
    """Required keys, the study kind, presets, effects and the campaign's sizes."""
    for key in ("name", "kind"):
        if key not in st:
            raise StudyError(f"{path}: missing required key study.{key}")
    if st["kind"] not in KINDS:
        raise StudyError(f"{path}: study.kind must be one of {KINDS}, got {st['kind']!r}")
    if not NAME_PATTERN.fullmatch(st["name"]):
        # the name is the report's file stem: no path separators, no '..', nothing a shell or
        # a file system could read as something else
        raise StudyError(
            f"{path}: study.name = {st['name']!r} must be 1-64 letters, digits, '.', '_' or '-', "
            "starting with a letter or digit (it names the report files)"
        )
    if "seed" in st and not 0 <= st["seed"] < 2**63:
        raise StudyError(f"{path}: study.seed must be an integer >= 0, got {st['seed']!r}")
    from bayes_tfcrds.simulate.campaign import PRESETS, parse_effect

    for i, p in enumerate(cp.get("presets", [])):
        if p not in PRESETS:
            raise StudyError(
                f"{path}: campaign.presets[{i}] = {p!r} is not a preset ({sorted(PRESETS)})"
            )
    for i, e in enumerate(cp.get("effects", [])):
        try:
            parse_effect(e)
        except ValueError as exc:
            raise StudyError(f"{path}: campaign.effects[{i}]: {exc}") from None
    for key, allowed in (("chains", ("preset", "zoo")), ("noise", ("white", "coloured"))):
        if key not in cp:
            continue
        if st.get("kind") != "coverage":
            raise StudyError(f"{path}: campaign.{key} sets the strata of a coverage study only")
        values = cp[key]
        if not values or len(set(values)) != len(values) or not set(values) <= set(allowed):
            raise StudyError(
                f"{path}: campaign.{key} = {values!r} must list different values from {allowed}"
            )
    for key, lo, hi in (
        ("points", 8, 2000),
        ("samples", 256, 1 << 20),
        ("averages", 1, 100000),
        ("campaigns", 1, 100000),
    ):
        if key in cp and not lo <= cp[key] <= hi:
            raise StudyError(f"{path}: campaign.{key} = {cp[key]} is outside [{lo}, {hi}]")


def _check_analysis(path: Path, st: dict, cp: dict, an: dict) -> tuple:
    """The analysis choices; returns the t_cuts in s."""
    if an.get("posterior", "mcmc") not in ("mcmc", "laplace"):
        raise StudyError(
            f"{path}: analysis.posterior must be 'mcmc' or 'laplace', got {an['posterior']!r}"
        )
    if an.get("mcmc_campaigns", 0) < 0:
        raise StudyError(f"{path}: analysis.mcmc_campaigns must be >= 0")
    if st["kind"] == "coverage" and ("bundle" in cp or "effects" in cp):
        raise StudyError(
            f"{path}: a coverage study simulates its own campaigns: campaign.bundle and "
            "campaign.effects do not apply"
        )
    for i, m in enumerate(an.get("methods", [])):
        if m not in ("crds", "tf-crds"):
            raise StudyError(f"{path}: analysis.methods[{i}] = {m!r} must be 'crds' or 'tf-crds'")
    for i, w in enumerate(an.get("windows", [])):
        if w not in ("extinction", "letter"):
            raise StudyError(
                f"{path}: analysis.windows[{i}] = {w!r} must be 'extinction' or 'letter'"
            )
    if an.get("shape_bounds", "free") not in ("free", "physical"):
        raise StudyError(
            f"{path}: analysis.shape_bounds must be 'free' or 'physical', got "
            f"{an['shape_bounds']!r}"
        )
    from bayes_tfcrds.physics.lineshape import PROFILES

    if an.get("profile", "qsdhcp") not in PROFILES:
        raise StudyError(f"{path}: analysis.profile must be one of {sorted(PROFILES)}")
    t_cuts = tuple(float(v) * 1e-6 for v in an.get("t_cuts_us", [2, 3, 4, 5, 6, 8]))
    # a ring-down record lasts microseconds to milliseconds: t_cut beyond 1 ms is a unit error
    for key, values in (("t_cuts_us", t_cuts), ("t_cut_us", (an.get("t_cut_us", 4) * 1e-6,))):
        if not values or not all(math.isfinite(t) and 0 < t <= 1e-3 for t in values):
            raise StudyError(
                f"{path}: analysis.{key} must be one or more numbers in (0, 1000] us, got "
                f"{an.get(key)!r}"
            )
    for key in ("methods", "windows"):
        if key in an and not an[key]:
            raise StudyError(f"{path}: analysis.{key} is empty; leave it out for the default")
    if "presets" in cp and not cp["presets"]:
        raise StudyError(f"{path}: campaign.presets is empty; leave it out for the default")
    if "mcmc_steps" in an and not 1 <= an["mcmc_steps"] <= 10**7:
        raise StudyError(f"{path}: analysis.mcmc_steps must be in [1, 1e7], got {an['mcmc_steps']}")
    if st.get("seeds", 1) != 1 and (st["kind"] != "tcut" or "bundle" in cp):
        raise StudyError(
            f"{path}: study.seeds repeats a simulated tcut study over independent campaigns; "
            "leave it out for other kinds and for a campaign.bundle"
        )
    if not 1 <= st.get("seeds", 1) <= 10000:
        raise StudyError(f"{path}: study.seeds must be in [1, 10000], got {st['seeds']}")
    if "bundle" in cp and ("presets" in cp or "effects" in cp):
        raise StudyError(f"{path}: campaign.bundle excludes campaign.presets and campaign.effects")
    return t_cuts


def load_study(path) -> Study:
    """Parse and validate a study file; raise :class:`StudyError` naming the bad key."""
    path = Path(path)
    text, raw = _read(path)
    _check_schema(path, raw)
    st, cp, an = raw.get("study", {}), raw.get("campaign", {}), raw.get("analysis", {})
    _check_study_and_campaign(path, st, cp)
    t_cuts = _check_analysis(path, st, cp, an)
    bundle = cp.get("bundle")
    if bundle is not None and not Path(bundle).is_absolute():
        bundle = str((path.parent / bundle).resolve())
    return Study(
        name=st["name"],
        kind=st["kind"],
        title=st.get("title", st["name"]),
        description=st.get("description", ""),
        seed=st.get("seed", 7),
        presets=tuple(cp.get("presets", ["letter-D1", "letter-D2", "letter-D3", "letter-D4"])),
        points=cp.get("points", 101),
        samples=cp.get("samples", 16384),
        averages=cp.get("averages", 100),
        effects=tuple(cp.get("effects", [])),
        bundle=bundle,
        methods=tuple(an.get("methods", ["crds", "tf-crds"])),
        t_cuts_s=t_cuts,
        t_cut_s=float(an.get("t_cut_us", 4)) * 1e-6,
        profile=an.get("profile", "qsdhcp"),
        windows=tuple(an.get("windows", ["extinction"])),
        mcmc_steps=an.get("mcmc_steps", 3000),
        path=str(path),
        text=text,
        n_campaigns=cp.get("campaigns", 200),
        posterior=an.get("posterior", "mcmc"),
        mcmc_campaigns=an.get("mcmc_campaigns", 0),
        shape_bounds=an.get("shape_bounds", "free"),
        n_seeds=st.get("seeds", 1),
        chain_kinds=tuple(cp.get("chains", ["preset"])),
        noise_kinds=tuple(cp.get("noise", ["white"])),
    )
