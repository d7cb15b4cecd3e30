"""Simulation-based calibration: does the stated uncertainty cover the truth as often as it says.

Many reduced-size campaigns are simulated, each from parameters drawn from the distribution
:class:`TruthDistribution` states, and the full budget pipeline (:func:`run_budget`) runs on
each. For the line area A, the ratio A/A_ref, the decay time at the spectral point nearest the
line centre and the H cutoff f_c we record the truth, the estimate, its standard uncertainty u,
whether ``estimate +/- z u`` (z for 68.27 % and 95 %) holds the truth, and the posterior CDF at
the truth (the normalised rank of the truth among posterior draws; uniform if the posterior is
calibrated, Talts et al. 2018, arXiv:1804.06788).

Prior and truth distribution. SBC needs the truth drawn from the analysis prior. The analysis
priors here are all flat or log-flat on wide physical bounds (inference/posteriors.py: A > 0,
0 <= Gamma2 <= 2/3 Gamma0, nu_VC >= 0; log-uniform f_c, f_r, Gamma_r over 1 Hz to 10 GHz), and the
Laplace posterior uses none: no prior is informative, so truths are drawn inside the bounds from
physically sensible ranges, and the check is frequentist coverage averaged over those truths.

Each campaign is an independent task whose random numbers come from
``SeedSequence(seed, spawn_key=(index,))`` alone, so results do not depend on the worker count;
each writes one small JSON file, and a rerun skips the campaigns already done.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
from scipy import stats

from bayes_tfcrds.output.files import atomic_write_text
from bayes_tfcrds.output.plotting import pyplot
from bayes_tfcrds.output.progress import progress_bar
from bayes_tfcrds.output.report import git_commit
from bayes_tfcrds.physics.linedata import load_line
from bayes_tfcrds.physics.transfer_function import TFParams
from bayes_tfcrds.simulate.campaign import (
    PRESETS,
    Campaign,
    LineTruth,
    line_truth,
    simulate_campaign,
)
from bayes_tfcrds.simulate.noise import NoiseColour
from bayes_tfcrds.simulate.zoo import ZOO_REGIMES, draw_chain
from bayes_tfcrds.studies.common import stored_record

LEVELS = (0.68, 0.95)
Z = {p: float(stats.norm.ppf(0.5 + p / 2)) for p in LEVELS}  # 0.994, 1.960
QUANTITIES = ("A", "A/A_ref", "tau_centre", "f_c")
LABELS = {
    "A": "line area A",
    "A/A_ref": "A/A_ref",
    "tau_centre": "line-centre tau",
    "f_c": "H cutoff f_c",
    "A (u_c)": "A, full GUM u_c",
    "A/A_ref (u_c)": "A/A_ref, full GUM u_c",
    "S (u_c)": "S(296 K), full GUM u_c",
}
#: the full-budget quantities (u_c with the Type B rows)
UC_QUANTITIES = ("A (u_c)", "A/A_ref (u_c)", "S (u_c)")
#: the unit of each quantity's truth, estimate and u in the records (numbers.json "units"); A in
#: SI throughout this study's outputs, S(296 K) as the budget states it
UNITS = {
    "A": "Hz/m",
    "A/A_ref": "1",
    "tau_centre": "s",
    "f_c": "Hz",
    "A (u_c)": "Hz/m",
    "A/A_ref (u_c)": "1",
    "S (u_c)": "cm/molecule",
}
# 2: drawn T, gauge reading errors, S (u_c); 3: chain and noise strata; 4: f_c identified or not;
# 5: h_region (where the ring-downs refined H)
RECORD_VERSION = 5
#: the chain regime of a letter preset (the issue's strata: D1/D2-like, D3/D4-like, chain zoo)
PRESET_REGIME = {
    "letter-D1": "D1/D2-like",
    "letter-D2": "D1/D2-like",
    "letter-D3": "D3/D4-like",
    "letter-D4": "D3/D4-like",
}
#: coloured detector noise of a 'coloured' stratum: one of these shapes, drawn per campaign
COLOURED_KINDS = ("lowpass", "chain", "pink")


@dataclass(frozen=True)
class TruthDistribution:
    """Where each campaign's truth is drawn from (SI). ``U(a, b)``: uniform; ``logU``: log-uniform.

    Ranges straddle the letter's campaign (5 Torr, the line data, the presets): intensity S ~
    S_ref U(0.9, 1.1); pressure ~ U(400, 933) Pa (3-7 Torr); temperature ~ U(280, 310) K; the
    gauges' reading errors drawn from their stated Type B distributions (pressure: normal with
    the campaign's u(p); temperature: rectangular with the campaign's u(T)), so the budget's
    Type B rows are tested too; Gamma0 ~ (line data at p) U(0.9, 1.1);
    Gamma2/Gamma0 ~ U(0.05, 0.20); nu_VC/Gamma0 ~ U(0.2, 0.7); base chain uniform over the presets,
    then f_c ~ f_c,preset logU(0.7, 1.4), A_r ~ A_r,preset U(0.85, 1.15), f_r ~ U(4, 8) MHz,
    Gamma_r ~ U(0.6, 0.8); single-acquisition noise ~ noise_preset U(0.75, 1.5).
    """

    intensity_factor: tuple = (0.9, 1.1)
    pressure_pa: tuple = (400.0, 933.0)
    temperature_k: tuple = (280.0, 310.0)
    gamma0_factor: tuple = (0.9, 1.1)
    gamma2_ratio: tuple = (0.05, 0.20)
    nu_vc_ratio: tuple = (0.2, 0.7)
    f_c_factor: tuple = (0.7, 1.4)
    a_r_factor: tuple = (0.85, 1.15)
    f_r_hz: tuple = (4.0e6, 8.0e6)
    gamma_r: tuple = (0.6, 0.8)
    noise_factor: tuple = (0.75, 1.5)

    def describe(self) -> list:
        """(parameter, distribution) rows for the report."""
        u = lambda r: f"U({r[0]:g}, {r[1]:g})"  # noqa: E731
        return [
            (
                "line intensity S",
                f"S_ref x {u(self.intensity_factor)}, S_ref = 8.0603e-25 cm/molecule",
            ),
            ("pressure p (Pa)", u(self.pressure_pa)),
            ("temperature T (K)", u(self.temperature_k)),
            ("pressure reading error (Pa)", "N(0, u(p)^2), u(p) of the campaign"),
            ("temperature reading error (K)", "rectangular, sd u(T) of the campaign"),
            ("Gamma0", f"(line data at p) x {u(self.gamma0_factor)}"),
            ("Gamma2/Gamma0", u(self.gamma2_ratio)),
            ("nu_VC/Gamma0", u(self.nu_vc_ratio)),
            ("base chain", "uniform over the study's presets"),
            ("f_c", f"preset f_c x logU({self.f_c_factor[0]:g}, {self.f_c_factor[1]:g})"),
            ("A_r", f"preset A_r x {u(self.a_r_factor)}"),
            ("f_r (Hz)", u(self.f_r_hz)),
            ("Gamma_r", u(self.gamma_r)),
            ("noise per acquisition", f"preset noise x {u(self.noise_factor)}"),
        ]


@dataclass(frozen=True)
class CampaignDraw:
    """One campaign's truth (SI; intensity S(T_ref) in cm/molecule, the line data's unit)."""

    preset: str
    intensity_cm_per_molecule: float
    pressure_pa: float
    gamma0_factor: float
    gamma2_ratio: float
    nu_vc_ratio: float
    tf: TFParams
    noise_v: float
    temperature_k: float = 296.0
    pressure_error_pa: float = 0.0  # the gauges' realised reading errors (Type B inputs)
    temperature_error_k: float = 0.0
    chain: str = "preset"  # "preset" (drawn about the base preset's chain) or "zoo-<regime>"
    noise: NoiseColour = NoiseColour()  # PSD shape of the detector noise

    @property
    def stratum(self) -> dict:
        """The campaign's stratum: chain regime and noise kind."""
        regime = "zoo" if self.chain.startswith("zoo") else PRESET_REGIME.get(self.preset, "preset")
        return {"chain": regime, "noise": "white" if self.noise.is_white else "coloured"}


def random_colour(rng: np.random.Generator) -> NoiseColour:
    """A coloured detector-noise shape, one of three kinds with probability 1/3 each.

    Low-pass (corner logU(1, 15) MHz, order 1, 2 or 3), through the detection chain, or
    1/f^alpha on a white floor (knee logU(5, 300) kHz, alpha U(0.7, 1.5)).
    """
    kind = COLOURED_KINDS[int(rng.integers(len(COLOURED_KINDS)))]
    if kind == "lowpass":
        f = float(np.exp(rng.uniform(np.log(1e6), np.log(15e6))))
        return NoiseColour("lowpass", f_hz=f, order=float(rng.choice([1.0, 2.0, 3.0])))
    if kind == "pink":
        knee = float(np.exp(rng.uniform(np.log(5e3), np.log(3e5))))
        return NoiseColour("pink", f_knee_hz=knee, alpha=float(rng.uniform(0.7, 1.5)))
    return NoiseColour("chain")


def draw_truth(
    rng: np.random.Generator,
    presets,
    dist: TruthDistribution = TruthDistribution(),
    campaign: Campaign = Campaign(),
    chain_kind: str = "preset",
    noise_kind: str = "white",
) -> CampaignDraw:
    """Draw one campaign's truth from ``dist`` (see :class:`TruthDistribution`).

    The reading errors use the campaign's stated u(p) and u(T). ``chain_kind`` 'zoo' replaces
    the chain drawn about the preset by a chain-zoo chain (regime tail or pole, equally likely;
    :mod:`bayes_tfcrds.simulate.zoo`); ``noise_kind`` 'coloured' draws a noise shape
    (:func:`random_colour`). Those draws come after the others, so the white, preset-chain
    campaigns are drawn as before.
    """
    line = load_line()
    preset = str(presets[int(rng.integers(len(presets)))])
    base = PRESETS[preset]
    uni = lambda r: float(rng.uniform(*r))  # noqa: E731
    s = line.intensity_cm_per_molecule * uni(dist.intensity_factor)
    p = uni(dist.pressure_pa)
    g0f, g2r, nvr = uni(dist.gamma0_factor), uni(dist.gamma2_ratio), uni(dist.nu_vc_ratio)
    f_c = base.tf.f_c_hz * float(np.exp(rng.uniform(*np.log(dist.f_c_factor))))
    tf = replace(
        base.tf,
        f_c_hz=f_c,
        a_r=base.tf.a_r * uni(dist.a_r_factor),
        f_r_hz=uni(dist.f_r_hz),
        gamma_r=uni(dist.gamma_r),
    )
    draw = CampaignDraw(
        preset=preset,
        intensity_cm_per_molecule=s,
        pressure_pa=p,
        gamma0_factor=g0f,
        gamma2_ratio=g2r,
        nu_vc_ratio=nvr,
        tf=tf,
        noise_v=base.noise_v * uni(dist.noise_factor),
        temperature_k=uni(dist.temperature_k),
        pressure_error_pa=float(campaign.pressure_u_pa * rng.standard_normal()),
        temperature_error_k=float(campaign.temperature_u_k * np.sqrt(3.0) * rng.uniform(-1, 1)),
    )
    if chain_kind == "zoo":
        regime = ZOO_REGIMES[int(rng.integers(len(ZOO_REGIMES)))]
        draw = replace(draw, tf=draw_chain(rng, regime), chain=f"zoo-{regime}")
    elif chain_kind != "preset":
        raise ValueError(f"chain kind {chain_kind!r}: 'preset' or 'zoo'")
    if noise_kind == "coloured":
        draw = replace(draw, noise=random_colour(rng))
    elif noise_kind != "white":
        raise ValueError(f"noise kind {noise_kind!r}: 'white' or 'coloured'")
    return draw


def preset_draw(preset: str, campaign: Campaign = Campaign()) -> CampaignDraw:
    """The draw that reproduces ``simulate_campaign([preset])`` (letter line data, preset chain)."""
    line = load_line()
    shape = line.shape_at(campaign.pressure_pa, campaign.temperature_k)
    return CampaignDraw(
        preset=preset,
        intensity_cm_per_molecule=line.intensity_cm_per_molecule,
        pressure_pa=campaign.pressure_pa,
        gamma0_factor=1.0,
        gamma2_ratio=line.gamma2_ratio,
        nu_vc_ratio=shape["nu_vc_hz"] / shape["gamma0_hz"],
        tf=PRESETS[preset].tf,
        noise_v=PRESETS[preset].noise_v,
        temperature_k=campaign.temperature_k,
    )


def drawn_line(draw: CampaignDraw, campaign: Campaign) -> LineTruth:
    """The letter's line (speed dependence and hard collisions on) with the drawn parameters.

    The drawn Gamma0 scale, Gamma2/Gamma0, nu_VC/Gamma0 and intensity (S at T_ref, converted to
    the campaign's T), at the campaign's pressure.
    """
    lt0 = line_truth(
        campaign,
        {"speed_dependence": {}, "hard_collisions": {}},
        intensity_ref_cm_per_molecule=draw.intensity_cm_per_molecule,
    )
    g0 = lt0.gamma0_hz * draw.gamma0_factor
    return replace(
        lt0,
        gamma0_hz=g0,
        gamma2_hz=draw.gamma2_ratio * g0,
        nu_vc_hz=draw.nu_vc_ratio * g0,
    )


def simulate_draw(draw: CampaignDraw, rng: np.random.Generator, campaign: Campaign = Campaign()):
    """One-configuration campaign with the drawn truth.

    :func:`simulate_campaign` for the draw's base preset, with the drawn line, chain and noise.
    Returns ``(Bundle, truth_dict)`` like it.
    """
    camp = replace(
        campaign,
        pressure_pa=draw.pressure_pa,
        temperature_k=draw.temperature_k,
        pressure_error_pa=draw.pressure_error_pa,
        temperature_error_k=draw.temperature_error_k,
        noise=draw.noise,
    )
    return simulate_campaign(
        [draw.preset],
        rng,
        camp,
        {"transfer_function": {}},
        line_effects_default=False,
        line=drawn_line(draw, camp),
        chain_tf={draw.preset: draw.tf},
        noise_v={draw.preset: draw.noise_v},
        description=f"simulation-based calibration draw (base {draw.preset})",
    )


# ----------------------------------------------------------------------------- one campaign


def _entry(truth, estimate, u, cdf):
    z = (truth - estimate) / u if u > 0 else float("nan")
    return {
        "truth": float(truth),
        "estimate": float(estimate),
        "u": float(u),
        "pull": float(z),
        "cdf": float(cdf),
        **{f"in{int(100 * p)}": bool(abs(z) < Z[p]) for p in LEVELS},
    }


def _from_draws(truth, estimate, draws):
    """Entry with u = sd of the posterior draws and their CDF at the truth (the normalised rank)."""
    d = np.asarray(draws, float)
    return _entry(truth, estimate, float(np.std(d)), float(np.mean(d < truth)))


def _gaussian(truth, estimate, u):
    """Entry for a Gaussian result N(estimate, u^2).

    Its CDF at the truth is the rank in the limit of many draws.
    """
    return _entry(
        truth, estimate, u, float(stats.norm.cdf((truth - estimate) / u)) if u > 0 else float("nan")
    )


def _f_c_identification(ident, f_c_true: float, entry: dict) -> dict:
    """Whether the budget identified f_c; if not, the other descriptions' f_c and the truth's place.

    Where another description of Eq. 2 gives the same H(f), the budget reports f_c as not
    identified: its u then describes one description only, and the coverage of f_c is counted
    over the campaigns where it is identified. ``truth_in_a_description``: the truth inside the
    95 % interval (1.96 u) of the reported f_c (u from its draws) or of another description's
    (in log f_c, u from H(f)'s uncertainty): a count of where the truth lies, not a coverage.
    """
    if ident is None or ident.identified("f_c_hz"):
        return {"identified": True}
    k = ident.names.index("f_c_hz")
    near = [abs(entry["pull"]) < Z[0.95]]
    for d in ident.descriptions:
        u_log = max(d.u_sample[k], 1e-12)
        near.append(abs(np.log(d.params.f_c_hz / f_c_true)) < Z[0.95] * u_log)
    return {
        "identified": False,
        "descriptions_f_c_hz": [float(d.params.f_c_hz) for d in ident.descriptions],
        "truth_in_a_description": bool(any(near)),
    }


def counted(record: dict, quantity: str) -> bool:
    """Whether a quantity of an analysed campaign counts in the coverage (f_c: where identified)."""
    e = record.get("quantities", {}).get(quantity)
    return e is not None and e.get("identified", True)


def analyse_campaign(bundle, truth, options, rng: np.random.Generator) -> dict:
    """Run the budget on a one-configuration bundle and compare its results with the truth.

    The quantities are A, A/A_ref, the line-centre tau and f_c.

    A, A/A_ref and f_c use the posterior draws the budget made (A: ring-down noise and H; A_ref:
    CMDS); line-centre tau is Gaussian (fit u and H, first order). The ``(u_c)`` entries use the
    full GUM combined u, Type B rows included, for coverage only.
    """
    from bayes_tfcrds.fit.h_calibration import BEAT_FREE
    from bayes_tfcrds.uncertainty.line_budget import run_budget

    cfg = next(iter(bundle.configs.values()))
    res = run_budget(bundle, cfg, options, rng)
    s = res.summary
    out = {
        "status": s["status"],
        "diagnostics": {k: v for k, v in s["diagnostics"].items() if k != "runs"},
    }
    if s["status"] != "ok":
        return out
    a_true = truth["line"]["line_area_hz_per_m"]
    a_tot, a_ref = res.samples["a_total"], res.samples["a_ref"]
    a_hat = s["line_area"]["value_si"]
    # independent pairing of the A and A_ref posteriors (separate measurements)
    ratio_draws = a_tot / a_ref[rng.permutation(a_ref.size)[np.arange(a_tot.size) % a_ref.size]]
    q = {
        "A": _from_draws(a_true, a_hat, a_tot),
        "A/A_ref": _from_draws(
            1.0, s["ratio"]["value"], ratio_draws
        ),  # CMDS measures the same line: truth 1
        "A (u_c)": _gaussian(a_true, a_hat, s["line_area"]["u_si"]),
        "A/A_ref (u_c)": _gaussian(1.0, s["ratio"]["value"], s["ratio"]["u"]),
        # S(T_ref) through the whole measurement model: A, the gauges' readings (with their
        # drawn errors), Q(T), E'', at the campaign's drawn temperature
        "S (u_c)": _gaussian(
            truth["line"]["intensity_ref_cm_per_molecule"],
            s["intensity"]["value"],
            s["intensity"]["u"],
        ),
    }
    mc = s["intensity"].get("monte_carlo")
    if mc is not None:
        lo, hi = mc["interval"]
        s_true = truth["line"]["intensity_ref_cm_per_molecule"]
        # the JCGM 101 95 % interval of S (k from the Monte Carlo), checked as an interval
        q["S (U, MC)"] = {"in95": bool(lo <= s_true <= hi), "k": mc["k"]}
    rows = [r for r in res.tau_table if np.isclose(r[1], options.t_cut_s)]
    nu = np.array([r[0] for r in rows])
    k = int(np.argmin(np.abs(nu - bundle.sample.nu0_hz)))
    tau_true_all = np.asarray(next(iter(truth["configs"].values()))["tau_s"])
    i_true = int(np.argmin(np.abs(np.asarray(cfg.ringdowns.nu_hz) - nu[k])))
    q["tau_centre"] = _gaussian(tau_true_all[i_true], rows[k][2], rows[k][5])
    ifc = BEAT_FREE.index("f_c_hz")
    f_c_true = next(iter(truth["configs"].values()))["f_c_hz"]
    q["f_c"] = _from_draws(
        f_c_true, s["transfer_function"]["f_c_hz"], res.samples["h_draws"][:, ifc]
    )
    q["f_c"].update(_f_c_identification(res.identification, f_c_true, q["f_c"]))
    out["quantities"] = q
    out["detuning_centre_hz"] = float(nu[k] - bundle.sample.nu0_hz)
    # why H was not refined about the least-squares beat note (None: it was; posterior_steps)
    out["h_region"] = (s["transfer_function"].get("refinement") or {}).get("region")
    return out


@dataclass(frozen=True)
class CoverageSettings:
    """Everything a campaign task depends on (its JSON records a fingerprint of it)."""

    seed: int
    campaign: Campaign
    options: object  # BudgetOptions
    presets: tuple
    dist: TruthDistribution = TruthDistribution()
    chains: tuple = ("preset",)  # the strata: chain kinds x noise kinds, in turn by index
    noises: tuple = ("white",)

    @property
    def strata(self) -> list:
        """(chain kind, noise kind) of each stratum; campaign i is in stratum i mod len."""
        return [(c, n) for c in self.chains for n in self.noises]

    def draw(self, index: int):
        """Campaign ``index``: its truth and the generators of its simulation and analysis."""
        ss = np.random.SeedSequence(self.seed, spawn_key=(index,))
        g_draw, g_sim, g_fit = (np.random.default_rng(c) for c in ss.spawn(3))
        chain, noise = self.strata[index % len(self.strata)]
        draw = draw_truth(g_draw, self.presets, self.dist, self.campaign, chain, noise)
        return draw, g_sim, g_fit

    def fingerprint(self) -> str:
        text = json.dumps(
            [
                RECORD_VERSION,
                self.seed,
                asdict(self.campaign),
                asdict(self.options),
                list(self.presets),
                asdict(self.dist),
                list(self.chains),
                list(self.noises),
            ],
            sort_keys=True,
            default=str,
        )
        return hashlib.sha256(text.encode()).hexdigest()[:16]


def run_campaign(settings: CoverageSettings, index: int) -> dict:
    """Draw, simulate and analyse campaign ``index``; its numbers depend on (settings, index)."""
    draw, g_sim, g_fit = settings.draw(index)
    bundle, truth = simulate_draw(draw, g_sim, settings.campaign)
    rec = {
        "index": index,
        "fingerprint": settings.fingerprint(),
        "posterior": settings.options.posterior,
        "stratum": draw.stratum,
        "draw": {
            **{k: v for k, v in asdict(draw).items() if k not in ("tf", "noise")},
            **{f"tf_{k}": v for k, v in asdict(draw.tf).items()},
            "noise": draw.noise.describe(),
        },
        "line_area_true_hz_per_m": truth["line"]["line_area_hz_per_m"],
        "code": git_commit(),
    }
    try:
        rec.update(analyse_campaign(bundle, truth, settings.options, g_fit))
    except Exception as exc:  # a campaign the pipeline cannot analyse is counted, never dropped
        import traceback

        where = [
            f"{Path(f.filename).name}:{f.lineno} {f.name}"
            for f in traceback.extract_tb(exc.__traceback__)[-4:]
        ]
        rec.update({"status": f"error: {type(exc).__name__}: {exc}", "trace": where})
    return rec


def campaign_task(args) -> dict:
    """Pool task: campaign ``index``, read from OUTDIR/campaigns if done, else run and stored."""
    settings, index, folder = args
    path = Path(folder) / f"c{index:04d}_{settings.options.posterior}.json"
    done = stored_record(path, settings.fingerprint())
    if done is not None:
        return done
    rec = run_campaign(settings, index)
    atomic_write_text(path, json.dumps(rec, indent=1, default=float) + "\n")
    return rec


def run_campaigns(
    settings: CoverageSettings, indices, folder, pool=None, progress=False, label="campaigns"
) -> list:
    """All campaign records (by index), through ``pool`` when given; finished ones are reused."""
    jobs = [(settings, int(i), str(folder)) for i in indices]
    if pool is None:
        it = jobs
        if progress:
            it = progress_bar(jobs, desc=label)
        recs = [campaign_task(j) for j in it]
    else:
        from concurrent.futures import as_completed

        futs = [pool.submit(campaign_task, j) for j in jobs]
        it = as_completed(futs)
        if progress:
            it = progress_bar(it, total=len(futs), desc=label)
        for _ in it:
            pass
        recs = [f.result() for f in futs]
    return sorted(recs, key=lambda r: r["index"])


# ----------------------------------------------------------------------------- statistics


def binomial_se(p: float, n: int) -> float:
    """Standard error of a coverage fraction over n independent campaigns with coverage p."""
    return float(np.sqrt(p * (1 - p) / n)) if n > 0 else float("nan")


def summarise(records, quantity: str, u_scale: float = 1.0, bins: int = 10) -> dict:
    """Coverage of the 68 % and 95 % intervals and the rank histogram of one quantity.

    The rank histogram comes with its chi-square test of uniformity.

    ``u_scale`` rescales every stated u (and, Gaussian-approximated, the posterior) to show
    how the checks react to a mis-stated uncertainty.
    """
    ok = [r for r in records if r.get("status") == "ok" and counted(r, quantity)]
    pulls = np.array([r["quantities"][quantity]["pull"] for r in ok]) / u_scale
    if u_scale == 1.0:
        cdf = np.array([r["quantities"][quantity]["cdf"] for r in ok])
    else:
        cdf = stats.norm.cdf(pulls)
    n = pulls.size
    out = {"quantity": quantity, "n": n, "bins": bins}
    for p in LEVELS:
        c = float(np.mean(np.abs(pulls) < Z[p])) if n else float("nan")
        out[f"coverage_{int(100 * p)}"] = c
        out[f"se_{int(100 * p)}"] = binomial_se(c, n)
        out[f"se_nominal_{int(100 * p)}"] = binomial_se(p, n)
    counts = np.histogram(np.clip(cdf, 0, 1), bins=bins, range=(0, 1))[0]
    expected = n / bins
    chi2 = float(np.sum((counts - expected) ** 2 / expected)) if n else float("nan")
    out.update(
        {
            "rank_counts": counts.tolist(),
            "rank_chi2": chi2,
            "rank_dof": bins - 1,
            "rank_p": float(stats.chi2.sf(chi2, bins - 1)),
            "mean_pull": float(np.mean(pulls)),
            "sd_pull": float(np.std(pulls, ddof=1)) if n > 1 else float("nan"),
            "median_pull": float(np.median(pulls)) if n else float("nan"),
            "robust_sd_pull": robust_sd(pulls),
        }
    )
    return out


#: the quantities each stratum is summarised for (the posterior's, and S with its full u_c)
STRATUM_QUANTITIES = (*QUANTITIES, "S (u_c)")


def stratum_label(stratum: dict) -> str:
    return f"{stratum['chain']}, {stratum['noise']} noise"


def in_band(coverage: float, p: float, n: int, k: float = 2.0) -> bool:
    """Coverage within ``k`` binomial standard deviations sqrt(p(1-p)/n) of nominal ``p``."""
    return bool(n > 0 and abs(coverage - p) <= k * binomial_se(p, n))


def chance_exit(p: float, n: int, k: float = 2.0) -> float:
    """Probability that a calibrated coverage leaves its ``k``-sigma band by chance.

    Exact, from Binomial(n, p): the share of hit counts in ``n`` campaigns whose coverage
    :func:`in_band` refuses.
    """
    if n <= 0:
        return float("nan")
    hits = np.arange(n + 1)
    outside = np.abs(hits / n - p) > k * binomial_se(p, n)
    return float(stats.binom.pmf(hits[outside], n, p).sum())


def band_exits(rows: list) -> dict:
    """How many (stratum, quantity, level) coverages left their band, against chance.

    Each band is a 2-sigma test, so even a calibrated budget leaves some: with 6 strata, 5
    quantities and 2 levels about 3 of the 60. ``expected`` sums the exact binomial exit
    probabilities; ``p_value`` is P(at least ``observed`` exits) for independent tests (the
    tests are positively correlated - A and A/A_ref, 68 and 95 % of one quantity - which widens
    the true distribution, so this p-value is a lower bound on the real one).
    """
    probs, observed = [], 0
    for row in rows:
        for e in row["quantities"].values():
            for p in LEVELS:
                key = int(100 * p)
                if e["n"] > 0:
                    probs.append(chance_exit(p, e["n"]))
                    observed += not e[f"in_band_{key}"]
    probs = np.array(probs)
    # P(at least `observed`) for a sum of independent Bernoulli(probs): Poisson-binomial by
    # convolution of the tests' distributions
    dist = np.array([1.0])
    for q in probs:
        dist = np.convolve(dist, [1.0 - q, q])
    return {
        "tests": int(probs.size),
        "observed": int(observed),
        "expected": float(probs.sum()),
        "p_value": float(dist[observed:].sum()) if probs.size else float("nan"),
    }


def strata_table(records) -> list:
    """Coverage per stratum (chain regime x noise kind) and quantity, with its 2-sigma band.

    A stratum's quantity is in band when both its 68 % and 95 % coverage lie within two binomial
    standard deviations of nominal for that stratum's number of campaigns.
    """
    ok = [r for r in records if r.get("status") == "ok" and "stratum" in r]
    labels = sorted({stratum_label(r["stratum"]) for r in records if "stratum" in r})
    rows = []
    for label in labels:
        mine = [r for r in ok if stratum_label(r["stratum"]) == label]
        n_all = sum(1 for r in records if "stratum" in r and stratum_label(r["stratum"]) == label)
        qs = {}
        for q in STRATUM_QUANTITIES:
            pulls = np.array([r["quantities"][q]["pull"] for r in mine if counted(r, q)])
            n = pulls.size
            entry = {"n": n, "sd_pull": float(np.std(pulls, ddof=1)) if n > 1 else None}
            for p in LEVELS:
                key = int(100 * p)
                c = float(np.mean(np.abs(pulls) < Z[p])) if n else float("nan")
                entry[f"coverage_{key}"] = c
                entry[f"band_{key}"] = [p - 2 * binomial_se(p, n), p + 2 * binomial_se(p, n)]
                entry[f"in_band_{key}"] = in_band(c, p, n)
            qs[q] = entry
        rows.append({"stratum": label, "campaigns": n_all, "analysed": len(mine), "quantities": qs})
    return rows


def _strata_report(rows: list, post: str, rep) -> None:
    """The strata table: per stratum and quantity, 68/95 % coverage and whether in band."""
    if len(rows) < 2:
        return
    rep.add_heading("Coverage by stratum")
    table = []
    for row in rows:
        for q, e in row["quantities"].items():
            mark = "in band" if e["in_band_68"] and e["in_band_95"] else "**out of band**"
            table.append(
                [
                    row["stratum"],
                    LABELS[q],
                    e["n"],
                    f"{100 * e['coverage_68']:.1f}",
                    f"{100 * e['coverage_95']:.1f}",
                    "-" if e["sd_pull"] is None else f"{e['sd_pull']:.2f}",
                    mark,
                ]
            )
    rep.add_table(
        ["stratum", "quantity", "campaigns", "68 % (%)", "95 % (%)", "sd of pulls", "verdict"],
        table,
        caption=f"{post} posterior. Campaign i is in stratum i mod (number of strata). In band: "
        "both coverages within two binomial standard deviations sqrt(p(1-p)/n) of nominal for the "
        "stratum's n. Chain regimes: D1/D2-like and D3/D4-like are chains drawn about those "
        "presets; zoo chains are drawn from both regimes of Eq. 2 (simulate/zoo.py). Coloured "
        "noise is low-pass, through the detection chain, or 1/f, drawn per campaign.",
    )
    ex = band_exits(rows)
    rep.add_summary(
        "strata: coverages out of their 2-sigma band",
        f"{ex['observed']} of {ex['tests']} (chance alone: {ex['expected']:.1f})",
        f"P(>= {ex['observed']} by chance) = {ex['p_value']:.2g} for independent tests",
    )
    rep.add_text(
        f"Each band is a two-sigma test, so a perfectly calibrated budget still leaves some: of "
        f"these {ex['tests']} (stratum, quantity, level) coverages, {ex['expected']:.1f} are "
        f"expected out of band by chance (exact binomial), and {ex['observed']} are. The "
        f"probability of at least {ex['observed']} by chance is {ex['p_value']:.2g} if the tests "
        "were independent; they are positively correlated (A and A/A_ref, the two levels of one "
        "quantity), which makes clusters of exits likelier, so that figure is a lower bound."
    )


def beat_note_mode(settings: CoverageSettings, index: int) -> dict:
    """Re-simulate campaign ``index`` and refit its beat note.

    Gives A_r as fitted, and the fit started at the truth.

    |H| alone cannot tell A_r from its mirror -A_r/(1 + 2 A_r): both give the same gain above f_c
    and nearly the same |H| near it, so a fit may land on the mirror; the ring-downs (which see
    the phase) then disagree with it. This says whether that happened to a campaign.
    """
    from bayes_tfcrds.fit.beat_note import fit_beat_note
    from bayes_tfcrds.fit.h_calibration import BEAT_FREE, beat_note_fit

    draw, g_sim, _ = settings.draw(index)
    bundle, _ = simulate_draw(draw, g_sim, settings.campaign)
    cfg = next(iter(bundle.configs.values()))
    fit = beat_note_fit(cfg, free=BEAT_FREE)
    at_truth = fit_beat_note(
        cfg.transfer_function, variant=fit.params.variant, free=BEAT_FREE, start=draw.tf
    )
    return {
        "a_r_true": draw.tf.a_r,
        "a_r_fit": fit.params.a_r,
        "chi2_fit": float(fit.chi2),
        "a_r_from_truth": at_truth.params.a_r,
        "chi2_from_truth": float(at_truth.chi2),
        "mirror": bool(np.sign(fit.params.a_r) != np.sign(draw.tf.a_r)),
    }


def robust_sd(x) -> float:
    """1.4826 x the median absolute deviation: the sd of Gaussian data, blind to gross outliers."""
    x = np.asarray(x, float)
    return float(1.4826 * np.median(np.abs(x - np.median(x)))) if x.size else float("nan")


def check(summary: dict, k_sigma: float = 3.0, alpha: float = 0.01) -> dict:
    """Pass/fail of one quantity.

    Each coverage within ``k_sigma`` binomial sd of nominal, ranks uniform at level ``alpha``.
    """
    res = {}
    for p in LEVELS:
        key = int(100 * p)
        res[f"coverage_{key}"] = (
            abs(summary[f"coverage_{key}"] - p) <= k_sigma * summary[f"se_nominal_{key}"]
        )
    res["ranks_uniform"] = summary["rank_p"] > alpha
    return res


# ----------------------------------------------------------------------------- the study


def settings_of(study) -> CoverageSettings:
    from bayes_tfcrds.uncertainty.line_budget import BudgetOptions

    camp = replace(Campaign(), n_points=study.points, n_samples=study.samples, n_avg=study.averages)
    opts = replace(
        BudgetOptions(),
        posterior=study.posterior,
        t_cut_s=study.t_cut_s,
        t_cuts_s=tuple(sorted(set(study.t_cuts_s))),
        profile=study.profile,
        window=study.windows[0],
        n_steps=study.mcmc_steps,
        max_steps=max(8 * study.mcmc_steps, 24000),
    )
    return CoverageSettings(
        seed=study.seed,
        campaign=camp,
        options=opts,
        presets=tuple(study.presets),
        chains=tuple(study.chain_kinds),
        noises=tuple(study.noise_kinds),
    )


def _rank_figure(rep, sums, n, title):
    plt = pyplot()
    keys = list(sums)
    fig, axes = plt.subplots(1, len(keys), figsize=(max(1.9 * len(keys), 3.0), 3.2), sharey=True)
    for ax, k in zip(np.atleast_1d(axes), keys):
        s = sums[k]
        b = s["bins"]
        lo, hi = stats.binom.ppf([0.005, 0.995], s["n"], 1 / b)
        ax.bar(
            (np.arange(b) + 0.5) / b,
            s["rank_counts"],
            width=1 / b,
            color="tab:blue",
            alpha=0.55,
            edgecolor="k",
            lw=0.4,
        )
        ax.axhspan(lo, hi, color="0.5", alpha=0.3, zorder=3)
        ax.axhline(s["n"] / b, color="0.2", lw=0.8, zorder=3)
        ax.set_title(f"{LABELS[k]}\nchi2 p = {s['rank_p']:.2f}")
        ax.set_xlim(0, 1)
    np.atleast_1d(axes)[0].set_ylabel("campaigns per bin (count)")
    # one x label for the row (four copies ran into each other); the grey band is explained in
    # the caption (a legend inside hid the first histogram's low bins)
    fig.supxlabel("normalised rank of the truth in the posterior (0-1)", fontsize=9)
    fig.suptitle(title)
    rep.add_figure(
        fig,
        f"Rank histograms over {n} campaigns: the posterior CDF at the truth, in "
        f"{sums[keys[0]]['bins']} bins. Calibrated posteriors give a flat histogram; grey: where "
        "99 % of the bin counts of a uniform rank fall (binomial). A U shape means u is too "
        "small, a hump too large, a slope a bias.",
    )


def _coverage_figure(rep, sums):
    plt = pyplot()
    keys = list(sums)
    fig, axes = plt.subplots(1, 2, figsize=(7.5, 3.4), sharey=True)
    for ax, p in zip(axes, LEVELS):
        key = int(100 * p)
        y = np.arange(len(keys))
        c = [100 * sums[k][f"coverage_{key}"] for k in keys]
        e = [100 * sums[k][f"se_{key}"] for k in keys]
        se0 = 100 * sums[keys[0]][f"se_nominal_{key}"]
        ax.axvspan(
            100 * p - 2 * se0, 100 * p + 2 * se0, color="0.88", label="nominal ± 2 binomial sd"
        )
        ax.axvline(100 * p, color="0.3", lw=0.8)
        ax.errorbar(c, y, xerr=e, fmt="o", color="tab:blue", label="observed ± 1 binomial se")
        ax.set_yticks(y, [LABELS[k] for k in keys])
        ax.set_xlabel(f"coverage of the {key} % interval (%)")
    # one legend above both panels, off the points
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside upper center", ncol=2)
    rep.add_figure(
        fig,
        "Coverage of estimate +/- z u (z = 0.994 for 68 %, 1.960 for 95 %) over the campaigns, "
        "with binomial standard errors.",
    )


def _describe(study, settings, rep) -> None:
    """What was simulated and analysed, and the truth distribution."""
    post = settings.options.posterior
    rep.add_text(
        f"{study.n_campaigns} campaigns, each with its own truth drawn from the distribution "
        f"below, simulated at reduced size ({study.points} spectral points, {study.samples} "
        f"samples of 20 ns, {study.averages} averages; one configuration) and analysed by the "
        f"full budget pipeline (TF-CRDS, {settings.options.window} window, {study.profile}, t_cut "
        f"= {study.t_cut_s * 1e6:g} us, {post} posterior). The analysis priors are flat or "
        "log-flat on wide physical bounds, so no prior is informative: truths are drawn inside "
        "the bounds, and what is checked is frequentist coverage averaged over those truths "
        "(simulation-based calibration with a flat prior)."
    )
    if post == "laplace":
        rep.add_text(
            "Posterior: 'laplace' (Gaussian posteriors from the least-squares fits, the beat-note "
            "fit and the refinement's sandwich covariance): the approximation of `budget "
            "--posterior laplace`, whose output quotes these figures. What `budget` ships by "
            "default, emcee, is calibrated on the same campaigns by studies/coverage.toml "
            "(reports/coverage)."
        )
    else:
        rep.add_text(
            "Posterior: 'mcmc', what `budget` ships: emcee posteriors of H, the line and A_ref "
            f"with the budget's priors, {settings.options.n_steps} steps per ensemble to start "
            "(its default) and its gates (R-hat < 1.01, bulk and tail ESS > 400, > 50 "
            "autocorrelation times), extended until they pass. A campaign that misses a gate is "
            "counted as failed, never as covered. The Laplace approximation is calibrated on the "
            "same campaigns by studies/coverage_laplace.toml."
        )
    if len(settings.strata) > 1:
        rep.add_text(
            "Strata: campaign i takes the i-th (mod "
            f"{len(settings.strata)}) of the chain kinds x noise kinds "
            + ", ".join(f"({c}, {n})" for c, n in settings.strata)
            + ". 'preset' chains are drawn about the base preset's (below), 'zoo' chains from "
            "the chain zoo (both regimes of Eq. 2: a slow tail beside a fast resonance, or a fast "
            "pole beside a slow resonance; simulate/zoo.py); 'coloured' noise is low-pass (corner "
            "1-15 MHz, order 1-3), through the detection chain, or 1/f^alpha (knee 5-300 kHz, "
            "alpha 0.7-1.5), drawn per campaign with the same per-sample sd as white."
        )
    rep.add_heading("Truth distribution")
    rep.add_table(["parameter", "drawn from"], settings.dist.describe())


def _coverage_table(sums: dict, n: int, post: str, rep) -> None:
    """The coverage table with its figures."""
    main_keys = list(QUANTITIES)
    rep.add_heading("Coverage")
    rows = []
    for k, s in sums.items():
        rows.append(
            [
                LABELS[k],
                s["n"],
                f"{100 * s['coverage_68']:.1f} +/- {100 * s['se_68']:.1f}",
                f"{100 * s['coverage_95']:.1f} +/- {100 * s['se_95']:.1f}",
                f"{s['mean_pull']:+.3g}",
                f"{s['sd_pull']:.3g}",
                f"{s['median_pull']:+.3f}",
                f"{s['robust_sd_pull']:.3f}",
                f"{s['rank_chi2']:.1f} ({s['rank_dof']})",
                f"{s['rank_p']:.3f}",
            ]
        )
    rep.add_table(
        [
            "quantity",
            "campaigns",
            "68 % coverage (%)",
            "95 % coverage (%)",
            "mean pull",
            "sd of pulls",
            "median pull",
            "robust sd of pulls (1.4826 MAD)",
            "rank chi2 (dof)",
            "p",
        ],
        rows,
        caption="Coverage +/- binomial standard error sqrt(c(1-c)/n). Pull = (truth - "
        "estimate)/u; the mean and sd are dominated by any gross outlier (listed below), the "
        "median and MAD are not. The first four rows use the posterior (ring-down noise and H, "
        "the budget's statistical u); the u_c rows use the full GUM budget: its t_cut row and its "
        "data-sized rows (line-shape model average, H model form, instrument rows) describe "
        "choices and effects the simulation does not vary (its truth is the fitted qSDHCP, its "
        "detector linear), so they may cover more than nominal; S also carries the gauges' "
        "Type B rows, whose errors the simulation does draw. f_c counts the campaigns whose "
        "budget identifies it (see 'f_c not identified' below for the others).",
    )
    _coverage_figure(rep, sums)
    _rank_figure(rep, {k: sums[k] for k in main_keys}, n, f"Rank histograms ({post} posterior)")


def _mc_coverage(ok: list) -> float | None:
    """Share of campaigns whose JCGM 101 95 % interval of S(296 K) holds the truth."""
    mc = [r["quantities"]["S (U, MC)"]["in95"] for r in ok if "S (U, MC)" in r["quantities"]]
    return float(np.mean(mc)) if mc else None


def _coverage_checks(sums: dict, checks: dict, recs: list, bad: list, n: int, rep) -> None:
    """Summary lines and pass/fail diagnostics of the coverage (targets of issue #9)."""
    main_keys = list(QUANTITIES)
    a = sums["A"]
    rep.add_summary(
        "A: 95 % interval coverage",
        f"{100 * a['coverage_95']:.1f} +/- {100 * a['se_95']:.1f} %",
        f"{n} campaigns; target 95 +/- 3 %",
    )
    rep.add_summary(
        "A: 68 % interval coverage",
        f"{100 * a['coverage_68']:.1f} +/- {100 * a['se_68']:.1f} %",
        f"{n} campaigns; target 68 +/- 5 %",
    )
    for k in main_keys[1:]:
        s = sums[k]
        rep.add_summary(
            f"{LABELS[k]}: 68 % / 95 % coverage",
            f"{100 * s['coverage_68']:.1f} / {100 * s['coverage_95']:.1f} %",
            f"rank chi2 p = {s['rank_p']:.3f}",
        )
    s_ref = sums["S (u_c)"]
    rep.add_summary(
        "S(296 K): 68 % / 95 % coverage (full u_c)",
        f"{100 * s_ref['coverage_68']:.1f} / {100 * s_ref['coverage_95']:.1f} %",
        "T drawn over 280-310 K, the gauges' reading errors drawn from their Type B u",
    )
    rep.add_diagnostic(
        "S(296 K): 95 % coverage within 95 +/- 3 % (issue #17)",
        abs(s_ref["coverage_95"] - 0.95) <= 0.03,
        f"{100 * s_ref['coverage_95']:.1f} %",
    )
    mc = [r["quantities"]["S (U, MC)"] for r in recs if "S (U, MC)" in r.get("quantities", {})]
    c95 = _mc_coverage([r for r in recs if r.get("status") == "ok"])
    if mc:
        rep.add_diagnostic(
            "S(296 K): the Monte Carlo 95 % interval (k from JCGM 101) covers 95 +/- 3 %",
            abs(c95 - 0.95) <= 0.03,
            f"{100 * c95:.1f} % of {len(mc)} campaigns; k from "
            f"{min(m['k'] for m in mc):.2f} to {max(m['k'] for m in mc):.2f}",
        )
    rep.add_diagnostic(
        "every campaign analysed",
        not bad,
        f"{len(bad)} of {len(recs)} failed" + (f": {bad[0]['status']}" if bad else ""),
    )
    rep.add_diagnostic(
        "A: 95 % coverage within 95 +/- 3 % (issue #9)",
        abs(a["coverage_95"] - 0.95) <= 0.03,
        f"{100 * a['coverage_95']:.1f} %",
    )
    rep.add_diagnostic(
        "A: 68 % coverage within 68 +/- 5 % (issue #9)",
        abs(a["coverage_68"] - 0.68) <= 0.05,
        f"{100 * a['coverage_68']:.1f} %",
    )
    for k in main_keys:
        for p in LEVELS:
            key = int(100 * p)
            s = sums[k]
            rep.add_diagnostic(
                f"{LABELS[k]}: {key} % coverage within 3 binomial sd of nominal",
                checks[k][f"coverage_{key}"],
                f"{100 * s[f'coverage_{key}']:.1f} % (3 sd = {300 * s[f'se_nominal_{key}']:.1f} %)",
            )
        rep.add_diagnostic(
            f"{LABELS[k]}: ranks uniform (chi-square, p > 0.01)",
            checks[k]["ranks_uniform"],
            f"chi2 = {sums[k]['rank_chi2']:.1f}, {sums[k]['rank_dof']} dof, p = "
            f"{sums[k]['rank_p']:.3f}",
        )


def _outliers(settings, recs: list, ok: list, bad: list, n: int, rep) -> dict:
    """Failed and far-off campaigns, each with a beat-note mode check; returns those by index."""
    main_keys = list(QUANTITIES)
    if bad:
        rep.add_heading("Campaigns the pipeline could not analyse")
        rep.add_text(
            "They are left out of the coverage above and counted here; each can be rerun alone "
            "with bayes_tfcrds.studies.coverage.run_campaign(settings, index)."
        )
        rep.add_table(
            ["campaign", "base chain", "status", "where"],
            [
                [
                    r["index"],
                    r["draw"]["preset"],
                    r["status"],
                    " <- ".join(reversed(r.get("trace", []))),
                ]
                for r in bad
            ],
        )
    far = [
        (r["index"], k, r["quantities"][k]["pull"])
        for r in ok
        for k in main_keys
        if counted(r, k) and abs(r["quantities"][k]["pull"]) > 4
    ]
    if far:
        rep.add_heading("Pulls beyond 4")
        rep.add_text(
            f"Expected about {n * len(main_keys) * 2 * stats.norm.sf(4):.2f} for Gaussian pulls."
        )
        rep.add_table(
            ["campaign", "quantity", "pull"], [[i, LABELS[k], f"{z:+.3g}"] for i, k, z in far]
        )
    suspects = sorted({r["index"] for r in bad} | {i for i, _, _ in far})
    modes = {i: beat_note_mode(settings, i) for i in suspects}
    if modes:
        rep.add_heading("Beat-note check of the failed and far-off campaigns")
        rep.add_text(
            "Each is simulated again and its beat note refitted. |H| alone cannot tell A_r from "
            "its mirror -A_r/(1 + 2 A_r) (the same gain above f_c, nearly the same |H| near it); "
            "when the fit lands on the mirror, the ring-downs disagree with H and the refinement "
            "either fails or moves f_c far to compensate, with a small stated u."
        )
        rep.add_table(
            [
                "campaign",
                "A_r true",
                "A_r beat fit",
                "chi2 beat fit",
                "A_r fit started at truth",
                "chi2 started at truth",
                "mirror solution",
            ],
            [
                [
                    i,
                    f"{m['a_r_true']:.3f}",
                    f"{m['a_r_fit']:.3f}",
                    f"{m['chi2_fit']:.2f}",
                    f"{m['a_r_from_truth']:.3f}",
                    f"{m['chi2_from_truth']:.2f}",
                    "yes" if m["mirror"] else "no",
                ]
                for i, m in modes.items()
            ],
        )
        n_mirror = sum(m["mirror"] for m in modes.values())
        rep.add_diagnostic(
            "no campaign's beat-note fit on the mirror A_r solution",
            n_mirror == 0,
            f"{n_mirror} of {len(recs)} campaigns",
        )
    return modes


def _mcmc_cross_check(study, settings, ok: list, folder, pool, progress, rep):
    """The first ``study.mcmc_campaigns`` campaigns again with the MCMC posterior.

    Same draws, data and analysis seeds; returns (numbers, records).
    """
    main_keys = list(QUANTITIES)
    m = min(study.mcmc_campaigns, study.n_campaigns)
    ms = replace(settings, options=replace(settings.options, posterior="mcmc"))
    mrecs = run_campaigns(ms, range(m), folder, pool, progress, "MCMC cross-check")
    mok = [r for r in mrecs if r.get("status") == "ok"]
    mfail = [r for r in mrecs if r.get("status") != "ok"]
    rep.add_heading(f"MCMC cross-check ({m} of the campaigns)")
    rep.add_text(
        "The first campaigns again, with emcee posteriors for H, the line and A_ref (convergence "
        "gates R-hat < 1.01, ESS > 400, > 50 autocorrelation times). A campaign that misses a "
        "gate is listed as failed and left out; it is never counted as covered."
    )
    mb = 5 if len(mok) >= 25 else max(2, len(mok) // 5)
    msums = {k: summarise(mrecs, k, bins=mb) for k in main_keys} if mok else {}
    lap = {r["index"]: r for r in ok}
    rows = []
    for k in main_keys:
        if not mok:
            break
        s = msums[k]
        both = [
            (lap[r["index"]]["quantities"][k], r["quantities"][k]) for r in mok if r["index"] in lap
        ]
        du = np.median([b["u"] / a_["u"] for a_, b in both]) if both else float("nan")
        rows.append(
            [
                LABELS[k],
                s["n"],
                f"{100 * s['coverage_68']:.0f} +/- {100 * s['se_68']:.0f}",
                f"{100 * s['coverage_95']:.0f} +/- {100 * s['se_95']:.0f}",
                f"{s['sd_pull']:.2f}",
                f"{du:.3f}",
            ]
        )
    if rows:
        rep.add_table(
            [
                "quantity",
                "campaigns",
                "68 % coverage (%)",
                "95 % coverage (%)",
                "sd of pulls",
                "median u(MCMC)/u(Laplace)",
            ],
            rows,
        )
    if mfail:
        rep.add_table(
            ["campaign", "status", "where"],
            [[r["index"], r["status"], " <- ".join(reversed(r.get("trace", [])))] for r in mfail],
        )
    rep.add_diagnostic(
        "MCMC cross-check: every campaign sampled and its convergence gates met",
        not mfail,
        f"{len(mfail)} of {len(mrecs)} failed" + (f": {mfail[0]['status']}" if mfail else ""),
    )
    return {
        "n": m,
        "n_ok": len(mok),
        "failed": [r["status"] for r in mfail],
        "summaries": msums,
    }, mrecs


def _not_identified_report(ok: list, rep) -> dict:
    """The campaigns whose budget reported f_c as not identified, and where their truth lay.

    They are left out of f_c's coverage: its u describes one description only.
    """
    mine = [r for r in ok if "f_c" in r["quantities"] and not counted(r, "f_c")]
    held = sum(r["quantities"]["f_c"]["truth_in_a_description"] for r in mine)
    every = [r["quantities"]["f_c"] for r in ok if "f_c" in r["quantities"]]
    unconditional = {
        f"coverage_{int(100 * p)}": float(np.mean([abs(e["pull"]) < Z[p] for e in every]))
        for p in LEVELS
    }
    if mine:
        rep.add_summary(
            "f_c not identified by the data (left out of f_c's coverage)",
            f"{len(mine)} of {len(ok)} campaigns",
            f"truth's f_c in the 95 % interval of a reported description in {held} of "
            f"{len(mine)}; f_c's coverage over all {len(every)} campaigns (the reported "
            f"description only): 68 %: {100 * unconditional['coverage_68']:.1f} %, 95 %: "
            f"{100 * unconditional['coverage_95']:.1f} %",
        )
        rep.add_table(
            ["campaign", "stratum", "f_c true (Hz)", "reported (Hz)", "other descriptions (Hz)"],
            [
                [
                    r["index"],
                    stratum_label(r["stratum"]),
                    f"{r['quantities']['f_c']['truth']:.4g}",
                    f"{r['quantities']['f_c']['estimate']:.4g}",
                    ", ".join(f"{v:.4g}" for v in r["quantities"]["f_c"]["descriptions_f_c_hz"]),
                ]
                for r in mine
            ],
            caption="The budget found another description of Eq. 2 (the poles shared out "
            "differently between the main and the resonant path) that gives the same H(f) within "
            "its uncertainty, and reported f_c as not identified (budget.md, 'H: parameters the "
            "data identify'). A, A/A_ref and the decay times depend on H(f) only and are counted.",
        )
    return {
        "campaigns": [r["index"] for r in mine],
        "truth_in_a_description": int(held),
        "f_c_all_campaigns": {"n": len(every), **unconditional},
    }


def coverage_study(study, rep, out, progress=False, pool=None) -> dict:
    """The ``coverage`` study: draw, simulate, analyse ``study.n_campaigns`` campaigns; report."""
    settings = settings_of(study)
    folder = Path(out) / "campaigns"
    recs = run_campaigns(
        settings, range(study.n_campaigns), folder, pool, progress, "coverage campaigns"
    )
    ok = [r for r in recs if r.get("status") == "ok"]
    bad = [r for r in recs if r.get("status") != "ok"]
    bins = 10 if len(ok) >= 100 else 5
    main_keys = list(QUANTITIES)
    sums = {k: summarise(recs, k, bins=bins) for k in main_keys + list(UC_QUANTITIES)}
    checks = {k: check(sums[k]) for k in main_keys}
    n = len(ok)
    post = settings.options.posterior
    _describe(study, settings, rep)
    _coverage_table(sums, n, post, rep)
    strata = strata_table(recs)
    _strata_report(strata, post, rep)
    _coverage_checks(sums, checks, recs, bad, n, rep)
    modes = _outliers(settings, recs, ok, bad, n, rep)
    not_identified = _not_identified_report(ok, rep)
    n_all = len(recs)
    a95_all = sum(r["quantities"]["A"]["in95"] for r in ok) / n_all
    a68_all = sum(r["quantities"]["A"]["in68"] for r in ok) / n_all
    rep.add_summary(
        "A: coverage counting failed campaigns as misses",
        f"68 %: {100 * a68_all:.1f} %, 95 %: {100 * a95_all:.1f} %",
        f"{n_all} campaigns, {len(bad)} failed",
    )
    numbers = {
        "posterior": post,
        "n_campaigns": study.n_campaigns,
        "units": UNITS,  # of the records' truth, estimate and u
        "n_ok": n,
        "failed": [r["status"] for r in bad],
        "truth_distribution": asdict(settings.dist),
        "summaries": sums,
        "checks": checks,
        "settings_fingerprint": settings.fingerprint(),
        "beat_note_modes": modes,
        "a_coverage_failures_as_misses": {"68": a68_all, "95": a95_all},
        "s_monte_carlo_coverage_95": _mc_coverage(ok),
        "strata": strata,
        "strata_band_exits": band_exits(strata),
        "f_c_not_identified": not_identified,
    }
    m = min(study.mcmc_campaigns, study.n_campaigns)
    mrecs = []
    if m and post != "mcmc":
        numbers["mcmc_check"], mrecs = _mcmc_cross_check(
            study, settings, ok, folder, pool, progress, rep
        )
        numbers["mcmc_check"]["strata"] = strata_table(mrecs)
    codes = sorted({r.get("code", "not recorded") for r in recs + mrecs})
    rep.add_text(
        "Campaign records are reused on a rerun whatever the code version; they were computed "
        "with: "
        + ", ".join(codes)
        + ". Delete the campaigns/ folder to recompute them with the current code."
    )
    numbers["campaign_code"] = codes
    numbers["records"] = [
        {k: r[k] for k in ("index", "status", "stratum", "draw", "quantities") if k in r}
        for r in recs
    ]
    return numbers
