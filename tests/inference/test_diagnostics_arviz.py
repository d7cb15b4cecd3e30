"""The runner's R-hat and ESS are arviz's, to the bit, though computed on shared ranks.

``chain_diagnostics`` ranks each quantity's draws once for tau_int, the bulk R-hat and the bulk
ESS (and once more, folded, for the tail R-hat), where arviz's public functions rank them three
times besides tau_int's; these tests hold the two to exact equality
(``==``, not a tolerance: the gates compare to thresholds, and the files promise that
``az.rhat``/``az.ess`` give the gated numbers) on draws shaped like an emcee run: random walks,
repeated values from rejected moves, coarse rounding (many ties), odd draw counts and 2 to 11
ensembles (arviz's sums change order at 8 split chains).
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.stats import rankdata

from bayes_tfcrds.inference.diagnostics import (
    _average_ranks,
    _import_arviz,
    chain_diagnostics,
    ess,
    rhat_rank,
    to_draws,
)


def _run_like(rng) -> np.ndarray:
    """(ensembles, steps, walkers) draws with an emcee run's features, drawn at random."""
    shape = (int(rng.integers(2, 12)), int(rng.integers(2, 300)), int(rng.integers(1, 40)))
    x = rng.normal(size=shape)
    if rng.random() < 0.5:  # strongly autocorrelated: Geyer's sums run long
        x = np.cumsum(x, axis=1) * rng.uniform(0.01, 1.0)
    if rng.random() < 0.5:  # rejected moves repeat a walker's value: ties in the ranks
        stay = rng.random(shape) < 0.6
        for t in range(1, shape[1]):
            x[:, t][stay[:, t]] = x[:, t - 1][stay[:, t]]
    if rng.random() < 0.2:  # coarse values: large tie groups
        x = np.round(x, 1)
    return x


def test_average_ranks_are_scipys():
    rng = np.random.default_rng(3)
    for _ in range(50):
        x = np.round(rng.normal(size=int(rng.integers(1, 5000))), int(rng.integers(0, 3)))
        np.testing.assert_array_equal(_average_ranks(x), rankdata(x))


def _same(a, b) -> bool:
    return a == b or (np.isnan(a) and np.isnan(b))


def _assert_arviz_numbers(x):
    d = chain_diagnostics(x)
    draws = to_draws(x)
    assert _same(d["rhat"], rhat_rank(draws)), x.shape
    assert _same(d["ess_bulk"], ess(draws, "bulk")), x.shape
    assert _same(d["ess_tail"], ess(draws, "tail")), x.shape


@pytest.fixture
def numba_off():
    """arviz's numpy arithmetic, as in the pinned environment (numba is no dependency)."""
    numba = _import_arviz().utils.Numba
    flag = numba.numba_flag
    numba.numba_flag = False
    yield
    numba.numba_flag = flag


def test_rhat_and_ess_equal_arviz_to_the_bit_on_random_runs(numba_off):
    rng = np.random.default_rng(20261129)
    checked = 0
    for _ in range(150):
        x = _run_like(rng)
        if x.shape[1] * x.shape[2] < 4:
            continue
        _assert_arviz_numbers(x)
        checked += 1
    assert checked > 100


def test_constant_and_one_step_runs_equal_arviz(numba_off):
    """A quantity that never moves (ESS = number of draws) and runs of a single kept step."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # arviz warns on a constant chain's zero variance
        _assert_arviz_numbers(np.full((4, 30, 8), 2.5))
        _assert_arviz_numbers(np.random.default_rng(4).normal(size=(4, 1, 7)))


def test_arviz_computing_otherwise_is_called_itself():
    """With arviz's numba variances switched on (its default when numba is installed) the
    last bits differ from numpy's: the diagnostics are then arviz's own call, still equal."""
    numba = _import_arviz().utils.Numba
    flag = numba.numba_flag
    numba.numba_flag = True  # the arithmetic numba would compile runs as Python without it
    try:
        rng = np.random.default_rng(2)
        for _ in range(10):
            _assert_arviz_numbers(np.cumsum(rng.normal(size=(4, 14, 3)), axis=1) * 37.0)
    finally:
        numba.numba_flag = flag


def test_too_few_draws_are_arviz_answers_and_one_chain_is_refused():
    """Outside the shared path (fewer than 4 draws per chain) arviz answers: NaN."""
    x = np.random.default_rng(1).normal(size=(4, 1, 3))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        d = chain_diagnostics(x)
    assert np.isnan(d["rhat"]) and np.isnan(d["ess_bulk"]) and np.isnan(d["ess_tail"])
    with pytest.raises(ValueError, match="n_chains >= 2"):  # R-hat needs chains that can disagree
        chain_diagnostics(np.zeros((1, 50, 8)) + np.arange(50)[:, None])
