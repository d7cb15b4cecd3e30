"""Reduced campaigns shared by the discovery tests (each module simulates its own copy)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from bayes_tfcrds.simulate.campaign import Campaign, simulate_campaign

REDUCED = replace(Campaign(), n_points=21, n_samples=4096)  # 21 modes, 4096 samples: seconds


def letter_d2_with_chain(seed: int = 8):
    """A reduced letter-D2 campaign with its detection chain on and a Voigt line (the bundle)."""
    bundle, _ = simulate_campaign(
        ["letter-D2"],
        np.random.default_rng(seed),
        REDUCED,
        {"transfer_function": {}},
        line_effects_default=False,
    )
    return bundle
