"""Repeated simulations to check that stated uncertainties match the scatter they claim.

Each replica simulates a campaign with a new seed, runs the budget pipeline on it and records
the line area with its statistical uncertainty (ring-down noise and H) and its noise row. With
``fixed_beat`` the beat-note measurement (hence the H posterior) is the same in every replica
and only the ring-down noise changes: the scatter of A then checks the noise row alone.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bayes_tfcrds.core.constants import line_area_from_cm2
from bayes_tfcrds.core.gum import Budget
from bayes_tfcrds.simulate.campaign import Campaign, simulate_campaign
from bayes_tfcrds.uncertainty.line_budget import BudgetOptions, run_budget


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

    def ratio_scatter_to_noise_row(self) -> float:
        return float(np.std(self.area, ddof=1) / np.mean(self.u_noise))


def replicate(
    n: int,
    seed: int,
    preset: str = "letter-D2",
    campaign: Campaign = Campaign(),
    options: BudgetOptions = BudgetOptions(posterior="laplace"),
    fixed_beat: bool = False,
    progress: bool = False,
) -> Replicas:
    """Run ``n`` replicas of simulate + budget; seeds derive from ``seed`` (reproducible)."""
    root = np.random.SeedSequence(seed)
    children = root.spawn(n + 1)
    area, u_stat, u_noise = [], [], []
    truth_area = None
    it = range(n)
    if progress:
        from tqdm import tqdm

        it = tqdm(it, desc=f"replicas {preset}")
    for i in it:
        rng = np.random.default_rng(children[i])
        streams = None
        if fixed_beat:
            # the same beat-note draws in every replica: spawn a fresh copy of the fixed stream
            streams = {
                "beat": np.random.default_rng(
                    np.random.SeedSequence(children[-1].entropy, spawn_key=children[-1].spawn_key)
                )
            }
        bundle, truth = simulate_campaign([preset], rng, campaign, streams=streams)
        cfg = next(iter(bundle.configs.values()))
        res = run_budget(bundle, cfg, options, np.random.default_rng([seed, i]))
        s = res.summary
        area.append(s["line_area"]["value_si"] if s["line_area"] else np.nan)
        u_stat.append(float(line_area_from_cm2(s["line_area"]["u_statistical"])))
        # everything ring-down noise drives: the line fit given H and the refinement of H, with
        # the correlation the budget gives them (GUM Eq. 16 on that subset of rows)
        bud = res.budget_a
        sub = tuple(
            c
            for c in bud.components
            if c.name.startswith("ring-down noise") or c.name.endswith("(refined on ring-downs)")
        )
        names = {c.name for c in sub}
        corr = {k: v for k, v in bud.correlations.items() if k[0] in names and k[1] in names}
        u_noise.append(
            Budget(
                quantity="ring-down noise",
                value=bud.value,
                unit=bud.unit,
                components=sub,
                correlations=corr,
            ).combined_u
        )
        truth_area = truth["line"]["line_area_hz_per_m"]
    return Replicas(
        area=np.array(area),
        u_stat=np.array(u_stat),
        u_noise=np.array(u_noise),
        area_true=truth_area,
    )
