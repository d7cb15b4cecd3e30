"""The simulated CMDS reference scatters as the letter's references do (< 0.06 % spread)."""

from dataclasses import replace

import numpy as np
import pytest

from bayes_tfcrds.fit.line_analysis import fit_reference
from bayes_tfcrds.simulate.campaign import Campaign, simulate_campaign

LETTER = ["letter-D1", "letter-D2", "letter-D3", "letter-D4"]
# the CMDS shift noise depends on the mode grid (the letter's 101 points) and not on the
# ring-downs: their length and averaging are cut to the minimum to keep the test fast
GRID = replace(Campaign(), n_samples=256, n_avg=1)


@pytest.fixture(scope="module")
def references():
    """A_ref/A_true - 1 and the reference fit's stated u(A_ref)/A_ref, (seed, configuration)."""
    dev, rel_u = [], []
    for seed in range(3):
        bundle, truth = simulate_campaign(LETTER, np.random.default_rng(seed), GRID)
        a_true = truth["line"]["line_area_hz_per_m"]
        fits = [fit_reference(bundle, cfg) for cfg in bundle.configs.values()]
        k = fits[0].names.index("line_area")
        dev.append([f.values[k] / a_true - 1 for f in fits])
        rel_u.append([np.sqrt(f.cov[k, k]) / a_true for f in fits])
    return np.array(dev), np.array(rel_u)


def test_reference_fit_states_the_campaign_cmds_u(references):
    # cmds_noise sets the shift noise from the Jacobian of the reference fit's own parameters;
    # the fit's covariance is evaluated at its estimate, not the truth: 2 % covers that (a
    # Jacobian of A, position and Gamma0 alone gives 1.57x the target)
    _, rel_u = references
    target = Campaign().cmds_area_rel_u
    assert np.all(np.abs(rel_u / target - 1) < 0.02), rel_u / target


def test_cmds_scatter_is_below_the_letter_spread(references):
    dev, _ = references
    spread = np.ptp(dev, axis=1)  # max - min over D1-D4 of A_ref (relative), per seed
    # the letter: "the individual CMDS-based A_ref references exhibit a spread below 0.06 %";
    # with u = 0.015 % a seed exceeds it with probability 2.4 % (range of 4 normals > 4 sd)
    assert np.all(spread < 6e-4), spread
    per_config_sd = np.std(dev, axis=0, ddof=1)
    assert np.all(per_config_sd < 6e-4), per_config_sd
    # and the realised scatter is the stated one: 12 draws about a zero mean (the reference fit
    # is unbiased), rms/u within the chi2(12) 0.5-99.5 % band [0.51, 1.54]
    rms = np.sqrt(np.mean(dev**2)) / Campaign().cmds_area_rel_u
    assert 0.51 < rms < 1.54, rms
