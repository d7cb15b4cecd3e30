"""``run_budget(workers=2)`` samples the CMDS reference in a second process: the same result.

The reference draws from its own random stream, so running it beside the H and line posteriors
(issue 16, item 2: a budget fast enough on 2 cores) must change nothing but the wall time.
"""

import json
from dataclasses import replace

import numpy as np
import pytest

from bayes_tfcrds.simulate.campaign import Campaign, simulate_campaign
from bayes_tfcrds.uncertainty.line_budget import BudgetOptions, run_budget, side_pool
from bayes_tfcrds.uncertainty.outputs import corner_job, write_outputs

TINY = replace(Campaign(), n_points=21, n_samples=4096, n_avg=25)
# short chains: the gates fail, which does not matter for an identity of two runs
SHORT = BudgetOptions(t_cuts_s=(4e-6, 8e-6), n_steps=60, max_steps=60, n_h_draws=100)


@pytest.fixture(scope="module")
def bundle():
    b, _ = simulate_campaign(["letter-D2"], np.random.default_rng(5), TINY)
    return b


def _budget_json(bundle, workers, out, shared=False):
    # with an output folder: the chains go to chains_*.h5 (the CMDS one written by the child)
    if shared:  # the CLI's way: one pool for the side steps and the corner plots
        with side_pool(workers) as pool:
            on_run, started = corner_job(pool, out, None, "D2")
            res = run_budget(
                bundle, bundle.configs["D2"], SHORT, np.random.default_rng(1), outdir=out,
                pool=pool, on_run=on_run,
            )  # fmt: skip
            write_outputs(res, out, seed=1, workers=workers, started=started)
            assert set(started) == {"h", "line", "cmds"}  # every plot was started in the pool
    else:
        res = run_budget(
            bundle, bundle.configs["D2"], SHORT, np.random.default_rng(1), outdir=out,
            workers=workers,
        )  # fmt: skip
        write_outputs(res, out, seed=1, workers=workers)
    data = json.loads((out / "budget.json").read_text())
    data.pop("provenance", None)
    return res, data


@pytest.mark.slow
def test_two_workers_give_the_same_budget_bit_for_bit(bundle, tmp_path):
    one, d1 = _budget_json(bundle, 1, tmp_path / "one")
    two, d2 = _budget_json(bundle, 2, tmp_path / "two")
    assert d1 == d2
    assert np.array_equal(one.samples["a_ref"], two.samples["a_ref"])
    assert np.array_equal(one.runs["cmds"].samples, two.runs["cmds"].samples)
    assert set(two.runs) == {"h", "line", "cmds"}
    assert one.tau_table == two.tau_table
    assert (tmp_path / "two" / "chains_cmds.h5").stat().st_size > 0
    # the corner plots drawn in worker processes are the very files drawn in this one, and so
    # are those started in the shared pool while the budget ran (some taken back and drawn here)
    _, d3 = _budget_json(bundle, 2, tmp_path / "three", shared=True)
    assert d3 == d1
    for key in ("h", "line", "cmds"):
        png = f"corner_{key}.png"
        assert (tmp_path / "one" / png).read_bytes() == (tmp_path / "two" / png).read_bytes()
        assert (tmp_path / "one" / png).read_bytes() == (tmp_path / "three" / png).read_bytes()


def test_the_corner_plot_thins_whole_steps():
    from bayes_tfcrds.uncertainty.outputs import thin_steps

    shape = (4, 500, 16)  # ensembles, steps, walkers
    flat = np.arange(np.prod(shape) * 2, dtype=float).reshape(-1, 2)
    shown = thin_steps(flat, shape, 20_000)
    assert shown.shape[0] <= 20_000
    # every walker of every ensemble is still there (row index mod 16 is the walker)
    walkers = (shown[:, 0] // 2).astype(int) % 16
    assert set(walkers) == set(range(16))


def test_workers_below_one_are_refused(bundle):
    with pytest.raises(ValueError, match="workers"):
        run_budget(bundle, bundle.configs["D2"], SHORT, workers=0)
