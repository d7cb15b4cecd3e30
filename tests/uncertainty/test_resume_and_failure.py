"""A budget never resumes chains of another posterior, nor shows a failed result as a result.

Issue 20, items 1 and 4.
"""

from dataclasses import replace

import numpy as np
import pytest

from bayes_tfcrds.bundle.writer import save_bundle
from bayes_tfcrds.cli import main
from bayes_tfcrds.fit.h_calibration import AnalysisError
from bayes_tfcrds.simulate.campaign import Campaign, simulate_campaign
from bayes_tfcrds.uncertainty.line_budget import (
    BudgetOptions,
    claim_chains,
    run_budget,
    run_fingerprint,
)

TINY = replace(Campaign(), n_points=21, n_samples=4096, n_avg=25)
# a few sampler steps: the gates fail, but chain files are written, which is all that matters here
SHORT = BudgetOptions(t_cuts_s=(4e-6, 8e-6), n_steps=30, max_steps=30, n_h_draws=100)


@pytest.fixture(scope="module")
def bundles():
    b2, _ = simulate_campaign(["letter-D2"], np.random.default_rng(5), TINY)
    b2b, _ = simulate_campaign(["letter-D2"], np.random.default_rng(6), TINY)
    return b2, b2b


def test_fingerprint_sees_data_options_and_not_the_sampler_length(bundles):
    b, other = bundles
    cfg = b.configs["D2"]
    base = run_fingerprint(b, cfg, SHORT)
    assert run_fingerprint(b, cfg, SHORT.with_steps(60, 600)) == base  # resume may extend
    assert run_fingerprint(b, cfg, replace(SHORT, method="crds")) != base
    assert run_fingerprint(b, cfg, replace(SHORT, t_cut_s=8e-6)) != base
    assert run_fingerprint(b, cfg, replace(SHORT, profile="sdvp")) != base
    changed = run_fingerprint(other, other.configs["D2"], SHORT)
    assert changed["data_sha256"] != base["data_sha256"]  # same layout, other noise draws


def test_chains_of_another_budget_are_refused_by_name(bundles, tmp_path):
    b, other = bundles
    cfg = b.configs["D2"]
    run_budget(b, cfg, SHORT, np.random.default_rng(1), outdir=tmp_path)
    assert list(tmp_path.glob("chains*.h5"))
    with pytest.raises(AnalysisError, match="option method"):
        run_budget(b, cfg, replace(SHORT, method="crds"), np.random.default_rng(1), tmp_path)
    with pytest.raises(AnalysisError, match="option t_cut_s"):
        run_budget(b, cfg, replace(SHORT, t_cut_s=8e-6), np.random.default_rng(1), tmp_path)
    with pytest.raises(AnalysisError, match="data_sha256"):
        run_budget(other, other.configs["D2"], SHORT, np.random.default_rng(1), tmp_path)
    # the same posterior, sampled longer: resumes (no error)
    res = run_budget(b, cfg, SHORT.with_steps(30, 60), np.random.default_rng(1), tmp_path)
    assert res.status.startswith("failed") or res.passed  # a result, not a refusal


def test_chains_without_a_record_are_refused(tmp_path):
    (tmp_path / "chains_h.h5").write_bytes(b"")
    with pytest.raises(AnalysisError, match="no chains.json"):
        claim_chains(tmp_path, {"code_version": "x", "options": {}})
    # an empty folder is claimed and recorded
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    claim_chains(fresh, {"code_version": "x", "options": {}})
    assert (fresh / "chains.json").exists()


def test_a_failed_budget_is_marked_failed_where_a_reader_looks_first(bundles, tmp_path, capsys):
    b, _ = bundles
    path = tmp_path / "d2.h5"
    save_bundle(b, path)
    out = tmp_path / "out"
    args = ["budget", str(path), "--config", "D2", "--seed", "1", "--quiet", "-o", str(out)]
    code = main([*args, "--steps", "30", "--max-steps", "30"])
    assert code == 3  # 30 steps cannot pass the gates
    printed = capsys.readouterr()
    assert printed.out.startswith("FAILED: ")
    for name in ("budget.md", "budget.csv", "tau_posterior.csv"):
        first = (out / name).read_text().splitlines()[0]
        assert first.startswith("# FAILED: "), name
    # the same command into the same folder resumes; another method there is refused by name
    assert main([*args, "--method", "crds", "--steps", "30", "--max-steps", "30"]) == 1
    assert "option method" in capsys.readouterr().err


def test_a_second_budget_into_a_busy_folder_is_refused_in_one_line(bundles, tmp_path, capsys):
    # issue 20: two budgets into one folder interleaved their chain commits or stopped in HDF5's
    # BlockingIOError; the folder is now held by one run (a flock, released when it ends)
    import subprocess
    import sys

    b, _ = bundles
    path = tmp_path / "d2.h5"
    save_bundle(b, path)
    out = tmp_path / "out"
    out.mkdir()
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import fcntl, os, sys, time\n"
            "fd = os.open(sys.argv[1], os.O_RDONLY)\n"
            "fcntl.flock(fd, fcntl.LOCK_EX)\n"
            "print('held', flush=True)\n"
            "time.sleep(120)\n",
            str(out),
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline() == "held\n"
        args = ["budget", str(path), "--config", "D2", "--quiet", "-o", str(out)]
        assert main([*args, "--steps", "30", "--max-steps", "30"]) == 1
        err = capsys.readouterr().err
        assert err.startswith(f"error: {out} is in use by another run") and err.count("\n") == 1
        assert list(out.iterdir()) == []  # nothing claimed, nothing sampled
    finally:
        holder.kill()
        holder.wait()
    # the holder is gone: the folder is free again
    assert main([*args, "--steps", "30", "--max-steps", "30"]) == 3


def test_a_budget_of_one_step_fails_its_gates_instead_of_crashing(bundles, tmp_path, capsys):
    # found by the CLI property test (issue 20): an IndexError in the burn-in
    b, _ = bundles
    path = tmp_path / "d2.h5"
    save_bundle(b, path)
    out = tmp_path / "out"
    args = ["budget", str(path), "--config", "D2", "--quiet", "--profile", "voigt"]
    assert main([*args, "--steps", "1", "--max-steps", "1", "-o", str(out)]) == 3
    assert "FAILED: failed" in capsys.readouterr().err
