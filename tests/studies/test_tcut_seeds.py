"""The tcut study over seeds: numbers.json structure, intervals, resume, interval arithmetic."""

import json

import numpy as np
import pytest
from scipy import stats

from bayes_tfcrds.studies import tcut_seeds
from bayes_tfcrds.studies.registry import run_study
from bayes_tfcrds.studies.spec import StudyError, load_study

STUDY = """
[study]
name = "seeds_check"
kind = "tcut"
seed = 5
seeds = 2
[campaign]
presets = ["letter-D2"]
points = 15
samples = 4096
averages = 4
[analysis]
t_cuts_us = [4, 8]
"""


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("seeds")
    study = folder / "s.toml"
    study.write_text(STUDY)
    out = folder / "rep"
    run_study(study, out)
    return study, out


def _intervals(node):
    """Every {mean, lo, hi} entry below ``node``."""
    if isinstance(node, dict):
        if {"mean", "lo", "hi"} <= set(node):
            yield node
        for v in node.values():
            yield from _intervals(v)


def test_numbers_hold_both_references_with_intervals_that_contain_the_mean(run):
    _, out = run
    num = json.loads((out / "numbers.json").read_text())
    assert num["n_seeds"] == 2 and len(num["per_seed"]) == 2
    d2 = num["configs"]["D2"]
    for m in ("crds", "tf-crds"):
        assert set(d2[m]) == {"bias_against_truth", "bias_against_cmds"}
    assert set(d2["reduction_factor"]) == {"against_truth", "against_cmds"}
    assert d2["letter"]["reduction_factor_against_cmds"] == 87
    found = list(_intervals(num["configs"]))
    assert len(found) == 2 * 2 * 2 + 2  # method x reference x (signed, abs), + two factors
    for iv in found:
        assert iv["lo"] <= iv["mean"] <= iv["hi"], iv
    # the mean over seeds is recomputed here from the stored rows (A/A_true - 1 over t_cut)
    per_seed = [
        np.mean(
            [
                abs(r["area_si"] / s["a_true_si"] - 1)
                for r in s["rows"]
                if r["method"] == "tf-crds" and r["config"] == "D2"
            ]
        )
        for s in num["per_seed"]
    ]
    got = d2["tf-crds"]["bias_against_truth"]["abs_mean_over_t_cut"]["mean"]
    assert got == pytest.approx(np.mean(per_seed), rel=1e-12)
    html = (out / "seeds_check.html").read_text()
    assert "ours, against truth" in html and "letter, against CMDS" in html
    assert "What each factor is a ratio of" in html
    assert (out / "campaign.h5").exists() and not (out / "seeds" / "s0001.h5").exists()


def test_rerun_skips_the_seeds_already_done(run, monkeypatch):
    study, out = run
    before = (out / "numbers.json").read_text()
    calls = []
    real = tcut_seeds.run_seed
    monkeypatch.setattr(tcut_seeds, "run_seed", lambda s, i, f: calls.append(i) or real(s, i, f))
    run_study(study, out)
    assert calls == []
    (out / "seeds" / "s0001.json").unlink()
    run_study(study, out)
    assert calls == [1]
    after = json.loads((out / "numbers.json").read_text())
    # seed 1 recomputed from its own SeedSequence: the same numbers as the first run
    assert after["configs"] == json.loads(before)["configs"]


def test_t_interval_is_students():
    x = np.array([0.3, -0.1, 0.7, 0.2, 0.05])
    iv = tcut_seeds.t_interval(x)
    lo, hi = stats.t.interval(0.95, x.size - 1, loc=x.mean(), scale=stats.sem(x))
    assert (iv.lo, iv.hi) == pytest.approx((lo, hi), rel=1e-12)


def test_bootstrap_ratio_is_a_ratio_of_means():
    rng = np.random.default_rng(0)
    num = np.array([4.0, 6.0, 5.0, 5.0])
    den = np.array([1.0, 1.0, 1.0, 1.0])
    iv = tcut_seeds.bootstrap_ratio(num, den, rng)
    assert iv.mean == 5.0
    # resampling 4 values from {4, 5, 5, 6}: the mean never leaves [4, 6], and is symmetric
    assert 4.0 <= iv.lo < 5.0 < iv.hi <= 6.0 and iv.lo + iv.hi == pytest.approx(10.0, abs=0.3)
    same = tcut_seeds.bootstrap_ratio(2 * den, den, rng)
    assert (same.lo, same.mean, same.hi) == (2.0, 2.0, 2.0)


def test_seeds_need_a_simulated_tcut_study(tmp_path):
    bad = tmp_path / "b.toml"
    bad.write_text('[study]\nname = "b"\nkind = "budgets"\nseeds = 3\n')
    with pytest.raises(StudyError, match="study.seeds"):
        load_study(bad)
    bad.write_text('[study]\nname = "b"\nkind = "tcut"\nseeds = 0\n')
    with pytest.raises(StudyError, match=r"study.seeds must be in \[1, 10000\]"):
        load_study(bad)
