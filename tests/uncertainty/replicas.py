"""Repeated simulations to check that stated uncertainties match the scatter they claim.

Each replica simulates a campaign with a new seed, runs the budget pipeline on it and records
the line area with its statistical uncertainty (ring-down noise and H) and its noise row. With
``fixed_beat`` the beat-note measurement (hence the H posterior) is the same in every replica
and only the ring-down noise changes: the scatter of A then checks the noise row alone.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import stats

from bayes_tfcrds.core.constants import line_area_from_cm2
from bayes_tfcrds.core.gum import Budget
from bayes_tfcrds.simulate.campaign import Campaign, simulate_campaign
from bayes_tfcrds.uncertainty.line_budget import BudgetOptions, run_budget

# the replicas' campaign (the letter's chain D4 is simulated on it) and budget options
TINY = replace(Campaign(), n_points=21, n_samples=4096, n_avg=25)
FAST = BudgetOptions(posterior="laplace", t_cuts_s=(4e-6, 8e-6))


@dataclass(frozen=True)
class Replicas:
    """Per replica: A (Hz/m), u_stat (Hz/m), the ring-down-noise rows combined (Hz/m: the line fit
    given H and the multi-ring-down refinement of H), and the true A (Hz/m)."""

    area: np.ndarray
    u_stat: np.ndarray
    u_noise: np.ndarray
    area_true: float

    @property
    def pulls(self) -> np.ndarray:
        return (self.area - self.area_true) / self.u_stat

    def ratio_scatter_to_u(self) -> float:
        """Scatter of A over replicas divided by the mean stated statistical u(A)."""
        return float(np.std(self.area, ddof=1) / np.mean(self.u_stat))


def sd_ratio_band(n: int, k_sigma: float = 3.0) -> tuple[float, float]:
    """Where the sample sd of ``n`` normal values over their true sd falls, two-sided, with the
    tail probability of a ``k_sigma`` normal deviate on each side (chi distribution, n - 1 dof).

    For 20 replicas at 3 sigma: 0.545 to 1.502; for 60: 0.732 to 1.282.
    """
    p = stats.norm.sf(k_sigma)
    return tuple(float(np.sqrt(stats.chi2.ppf(q, n - 1) / (n - 1))) for q in (p, 1.0 - p))


def scatter_matches_u(rep: Replicas, k_sigma: float = 3.0) -> dict:
    """Do replicas scatter as the stated u_stat says? Both checks at ``k_sigma``.

    ``ratio``: sd(A) / mean u_stat inside :func:`sd_ratio_band`; ``unbiased``: the mean pull
    within k_sigma of its standard error sd(pulls) / sqrt(n).
    """
    n = rep.area.size
    lo, hi = sd_ratio_band(n, k_sigma)
    ratio = rep.ratio_scatter_to_u()
    mean, se = float(np.mean(rep.pulls)), float(np.std(rep.pulls, ddof=1) / np.sqrt(n))
    return {
        "ratio": ratio,
        "band": (lo, hi),
        "ratio_ok": lo < ratio < hi,
        "mean_pull": mean,
        "unbiased": abs(mean) < k_sigma * se,
    }


def noise_rows_bracket_scatter(rep: Replicas, k_sigma: float = 3.0) -> dict:
    """With the beat note fixed, sd(A) between the ring-down-noise rows and the whole u_stat.

    Since the joint H posterior weighs the beat-note draws by the ring-down likelihood, ring-down
    noise also moves the other H parameters: the noise-only scatter lies between the rows it
    drives directly and the whole statistical u (whose beat-note part does not vary here). Each
    bound is widened by the sampling spread of a sample sd (:func:`sd_ratio_band`).
    """
    lo, hi = sd_ratio_band(rep.area.size, k_sigma)
    scatter = float(np.std(rep.area, ddof=1))
    low, high = lo * float(np.mean(rep.u_noise)), hi * float(np.mean(rep.u_stat))
    return {"scatter": scatter, "bounds": (low, high), "ok": low < scatter < high}


def replicate(
    n: int,
    seed: int,
    preset: str = "letter-D2",
    campaign: Campaign = Campaign(),
    options: BudgetOptions = BudgetOptions(posterior="laplace"),
    fixed_beat: bool = False,
    progress: bool = False,
    pool=None,
) -> Replicas:
    """Run ``n`` replicas of simulate + budget; seeds derive from ``seed`` (reproducible).

    Replica i draws from child i of ``SeedSequence(seed)`` whatever ``n`` is, so the first
    replicas of a longer run are those of a shorter one (with ``fixed_beat`` the shared beat
    note is child n's, so it changes with ``n``); ``pool`` (an Executor) runs them in parallel
    with the same results.
    """
    jobs = [(seed, i, n, preset, campaign, options, fixed_beat) for i in range(n)]
    runs = pool.map(_replica, jobs) if pool is not None else map(_replica, jobs)
    if progress:
        from tqdm import tqdm

        runs = tqdm(runs, total=n, desc=f"replicas {preset}")
    rows = list(runs)
    area, u_stat, u_noise, truth = (np.array([r[k] for r in rows]) for k in range(4))
    return Replicas(area=area, u_stat=u_stat, u_noise=u_noise, area_true=float(truth[-1]))


def _replica(job) -> tuple:
    """(A, u_stat, u of the ring-down-noise rows, true A) of replica ``i`` (Hz/m)."""
    seed, i, n, preset, campaign, options, fixed_beat = job
    children = np.random.SeedSequence(seed).spawn(n + 1)
    rng = np.random.default_rng(children[i])
    streams = None
    if fixed_beat:
        # the same beat-note draws in every replica: a fresh copy of the fixed stream
        streams = {
            "beat": np.random.default_rng(
                np.random.SeedSequence(children[-1].entropy, spawn_key=children[-1].spawn_key)
            )
        }
    bundle, truth = simulate_campaign([preset], rng, campaign, streams=streams)
    cfg = next(iter(bundle.configs.values()))
    res = run_budget(bundle, cfg, options, np.random.default_rng([seed, i]))
    s = res.summary
    area = s["line_area"]["value_si"] if s["line_area"] else np.nan
    u_stat = float(line_area_from_cm2(s["line_area"]["u_statistical"]))
    # everything ring-down noise drives: the line fit given H and the refinement of H, with the
    # correlation the budget gives them (GUM Eq. 16 on that subset of rows)
    bud = res.budget_a
    sub = tuple(
        c
        for c in bud.components
        if c.name.startswith("ring-down noise") or c.name.endswith("(refined on ring-downs)")
    )
    names = {c.name for c in sub}
    corr = {k: v for k, v in bud.correlations.items() if k[0] in names and k[1] in names}
    u_noise = Budget(
        quantity="ring-down noise",
        value=bud.value,
        unit=bud.unit,
        components=sub,
        correlations=corr,
    ).combined_u
    return area, u_stat, u_noise, truth["line"]["line_area_hz_per_m"]
