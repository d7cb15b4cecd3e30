"""Tests of the MCMC runner: correctness, honest gates, determinism, resume, netCDF.

Targets are cheap closed-form densities so that every number has a known answer; each
test is built to fail if the property it names breaks (see the comments on the asserts).
"""

from __future__ import annotations

import functools
import json
import logging
import os
import signal
import subprocess
import sys

import emcee
import h5py
import numpy as np
import pytest

from bayes_tfcrds.inference.diagnostics import (
    Gates,
    _gate_failures,
    burn_in,
    chain_diagnostics,
    ess,
    integrated_time,
)
from bayes_tfcrds.inference.result import SamplingResult
from bayes_tfcrds.inference.runner import _evaluate, extended_length, run_ensembles

MU = np.array([1.0, -2.0, 0.5])
COV = np.array([[1.0, 0.8, 0.2], [0.8, 2.0, 0.5], [0.2, 0.5, 0.5]])
PREC = np.linalg.inv(COV)
NAMES = ("a", "b", "c")
W = 12  # walkers per ensemble in the tests


def gauss_logp(x):
    """Vectorised log density of N(MU, COV): thetas (n, 3) -> (n,)."""
    d = np.atleast_2d(x) - MU
    return -0.5 * np.einsum("ij,jk,ik->i", d, PREC, d)


def gauss_logp_scalar(x):
    return float(gauss_logp(x)[0])


def gauss_p0(rng, n):
    return MU + 0.5 * rng.normal(size=(n, 3))


def short_run(seed=3, n=300, **kw):
    """A run too short to pass (max_steps = n), used where only equality matters."""
    kw.setdefault("vectorize", True)
    kw.setdefault("n_walkers", W)
    return run_ensembles(
        kw.pop("log_prob", gauss_logp),
        kw.pop("p0_fn", gauss_p0),
        NAMES,
        np.random.default_rng(seed),
        n_steps=n,
        max_steps=n,
        **kw,
    )


@functools.cache
def reference_run(n):
    """Uninterrupted in-memory run (results are immutable, so tests may share them)."""
    return short_run(n=n)


def assert_same(r1: SamplingResult, r2: SamplingResult):
    """Bit-for-bit equality of everything a run reports."""
    assert r1.samples.shape == r2.samples.shape
    assert np.array_equal(r1.samples, r2.samples)
    assert np.array_equal(r1.log_prob, r2.log_prob)
    assert np.array_equal(r1.acceptance, r2.acceptance)
    assert (r1.n_steps, r1.burn, r1.status) == (r2.n_steps, r2.burn, r2.status)
    assert json.dumps(r1.diagnostics) == json.dumps(r2.diagnostics)


# ----------------------------------------------------------------------------- estimators
def _ar1(rng, phi, shape):
    """AR(1) series (ensembles, steps, walkers), unit stationary variance; tau = (1+phi)/(1-phi)."""
    e, n, w = shape
    x = np.empty(shape)
    x[:, 0] = rng.normal(size=(e, w))
    eps = rng.normal(size=shape) * np.sqrt(1.0 - phi**2)
    for t in range(1, n):
        x[:, t] = phi * x[:, t - 1] + eps[:, t]
    return x


@pytest.mark.parametrize("phi", [0.0, 0.95])
def test_ess_and_tau_match_ar1_truth(phi):
    rng = np.random.default_rng(11)
    x = _ar1(rng, phi, (4, 1000, 32))
    d = chain_diagnostics(x)
    tau_true = (1 + phi) / (1 - phi)
    n_total = x.size
    # bulk ESS of a Gaussian AR(1) is N / tau exactly; emcee's per-walker-centred
    # estimator is ~25 % high here (tau biased low), so 10 % separates the two
    assert d["ess_bulk"] == pytest.approx(n_total / tau_true, rel=0.10)
    if phi > 0.0:  # the files' layout matters: arviz on the step-major order is tau times high
        assert ess(x.reshape(4, -1), "bulk") > 0.5 * n_total
    assert d["tau_int"] >= tau_true * 0.9 and max(d["tau_int_ensembles"]) == d["tau_int"]
    assert d["n_tau"] == pytest.approx(1000 / d["tau_int"])
    assert d["rhat"] < 1.01
    if phi == 0.0:  # iid: the tail indicator is iid too, tail ESS ~ N
        assert d["ess_tail"] == pytest.approx(n_total, rel=0.10)
    if (
        phi > 0.0
    ):  # exact tail ESS from the bivariate normal: corr of 1[x_t <= q05], 1[x_t+k <= q05]
        from scipy.stats import multivariate_normal, norm

        q, p = norm.ppf(0.05), 0.05
        rho = phi ** np.arange(1, 400)
        joint = [multivariate_normal([0, 0], [[1, r], [r, 1]]).cdf([q, q]) for r in rho]
        tau_tail = 1 + 2 * np.sum((np.array(joint) - p * p) / (p * (1 - p)))
        assert d["ess_tail"] == pytest.approx(n_total / tau_tail, rel=0.12)


def test_integrated_time_survives_walkers_that_never_visit_the_tail():
    rng = np.random.default_rng(2)
    x = _ar1(rng, 0.9, (1, 200, 32))[0]
    ind = (x <= np.quantile(x, 0.05)).astype(float)
    assert np.any(ind.sum(axis=0) == 0)  # the case that makes emcee's estimator NaN
    tau = integrated_time(ind)
    assert np.isfinite(tau) and tau > 1
    assert integrated_time(np.ones((100, 4))) == np.inf  # constant: no information


def test_a_run_of_one_or_two_steps_is_diagnosed_not_crashed():
    # found by the CLI property test (issue 20): budget --steps 1 --max-steps 1 ended in an
    # IndexError, the burn-in's pilot of a one-step chain being empty
    rng = np.random.default_rng(3)
    assert integrated_time(np.empty((0, 8))) == np.inf
    assert integrated_time(rng.normal(size=(1, 8))) == np.inf
    for n in (1, 2):
        chains = rng.normal(size=(4, n, 8, 2))
        assert burn_in(chains) <= n // 2
        d = chain_diagnostics(chains[:, burn_in(chains) :, :, 0])
        # arviz counts the walkers of one step as draws and gives an ESS; the length gate,
        # which knows the walkers of a step are coupled, fails such a run whatever ESS says
        assert d["n_tau"] == 0 and any(
            f.startswith("n_tau(x)") for f in _gate_failures({"x": d}, Gates())
        )


def test_derived_quantities_are_gated():
    rng = np.random.default_rng(5)
    chains = rng.normal(size=(4, 3000, 16, 2))  # iid: the parameters pass every gate
    lp = -0.5 * (chains**2).sum(-1)
    acc = np.ones(chains.shape[:3], bool)

    def derived(s):
        return {"sum": s[:, 0] + s[:, 1], "broken": np.full(len(s), np.nan)}

    ok = _evaluate(("x", "y"), chains, lp, acc, None, Gates(), "")
    assert ok.passed and ok.status == "passed"
    bad = _evaluate(("x", "y"), chains, lp, acc, derived, Gates(), "")
    assert set(bad.diagnostics) == {"x", "y", "sum", "broken"}
    assert bad.derived["sum"].shape == bad.samples.shape[:3]
    assert not bad.passed and "rhat(broken)" in bad.status and "(sum)" not in bad.status


# ----------------------------------------------------------------------------- Gaussian
def test_correlated_gaussian_recovered_and_gates_pass():
    r = run_ensembles(
        gauss_logp,
        gauss_p0,
        NAMES,
        np.random.default_rng(2024),
        n_walkers=W,
        n_steps=3300,
        max_steps=5000,
        vectorize=True,
        derived_fn=lambda s: {"a_plus_b": s[:, 0] + s[:, 1]},
    )
    assert r.passed and r.status == "passed", r.status
    assert r.rhat_max < 1.01 and r.ess_min > 400
    e, s, w, _ = r.samples.shape
    assert (e, w) == (4, W) and s == r.n_steps - r.burn and r.burn >= 0.2 * r.n_steps
    # differential evolution at its Gaussian-optimal scale 2.38/sqrt(2d) accepts about a third
    # of its proposals in 3 dimensions (random-walk theory: 0.44 in 1-d, 0.234 as d grows)
    assert np.all((r.acceptance > 0.2) & (r.acceptance < 0.5))
    flat = r.flat()

    # mean within 4 Monte Carlo standard errors (MCSE = sd / sqrt(ESS_bulk))
    for i, n in enumerate(NAMES):
        mcse = np.sqrt(COV[i, i] / r.diagnostics[n]["ess_bulk"])
        assert abs(flat[:, i].mean() - MU[i]) < 4 * mcse, (n, flat[:, i].mean(), mcse)
    # covariance: whitened sample covariance ~ identity, sd of entries ~ sqrt(2/ESS)
    L = np.linalg.cholesky(COV)
    white = np.linalg.solve(L, np.linalg.solve(L, np.cov(flat.T)).T)
    tol = 4 * np.sqrt(2 / min(d["ess_bulk"] for d in r.diagnostics.values()))
    assert np.max(np.abs(white - np.eye(3))) < tol
    # derived quantity: diagnosed, gated and right
    d = r.derived["a_plus_b"].ravel()
    assert r.diagnostics["a_plus_b"]["ess_bulk"] > 400
    var_ab = COV[0, 0] + COV[1, 1] + 2 * COV[0, 1]
    assert abs(d.mean() - (MU[0] + MU[1])) < 4 * np.sqrt(
        var_ab / r.diagnostics["a_plus_b"]["ess_bulk"]
    )

    # ESS in a sensible range: far below the raw draw count (walkers are not independent)
    # and consistent with an independent batch-means estimate of Var(posterior mean)
    for i, n in enumerate(NAMES):
        diag = r.diagnostics[n]
        assert flat.shape[0] / (2 * diag["tau_int"]) < diag["ess_bulk"] < flat.shape[0] / 10
        step_means = r.samples[..., i].mean(axis=2)  # (E, S) walker averages
        nb = 8
        batches = step_means[:, : s // nb * nb].reshape(e, nb, -1).mean(axis=2).ravel()
        var_mean = batches.var(ddof=1) / batches.size
        ess_bm = flat[:, i].var() / var_mean
        assert 0.5 < diag["ess_bulk"] / ess_bm < 2.0, (n, diag["ess_bulk"], ess_bm)


def test_too_short_run_is_reported_as_failed_not_passed():
    r = run_ensembles(
        gauss_logp,
        gauss_p0,
        NAMES,
        np.random.default_rng(1),
        n_walkers=W,
        n_steps=200,
        max_steps=320,
        vectorize=True,
    )
    assert not r.passed
    assert r.n_steps == 320  # extended from 200 by what the tau gate misses, capped at max_steps
    assert r.status.startswith("failed after 320 steps") and "n_tau(" in r.status


def _diag(rhat=1.0, ess=5000.0, n_tau=100.0):
    return {"rhat": rhat, "ess_bulk": ess, "ess_tail": ess, "n_tau": n_tau, "tau_int": 30.0}


@pytest.mark.parametrize(
    "diagnostics, expected",
    [
        # kept length / tau_int = 40 of the 50 needed: 1.1 * 50/40 = 1.375 -> 2750 steps
        ({"a": _diag(n_tau=40.0), "b": _diag()}, 2750),
        # a hair short: the smallest extension, 1.2x
        ({"a": _diag(n_tau=49.9)}, 2400),
        # R-hat alone says nothing about how much longer: half again
        ({"a": _diag(rhat=1.02)}, 3000),
        # ESS 100 of 400: 4.4x wanted, one extension is at most 3x
        ({"a": _diag(ess=100.0)}, 6000),
        # the largest shortfall decides: ESS 250 of 400 (1.76x) over tau 45 of 50 (1.22x)
        ({"a": _diag(n_tau=45.0), "b": _diag(ess=250.0)}, 3520),
        # a NaN diagnostic grows the chain as much as one extension may
        ({"a": _diag(n_tau=float("nan"))}, 6000),
    ],
)
def test_a_failed_run_is_extended_by_what_its_gates_miss(diagnostics, expected):
    result = type("R", (), {"diagnostics": diagnostics})()
    assert extended_length(result, 2000, Gates(), 24000) == expected
    assert extended_length(result, 2000, Gates(), 2500) == min(expected, 2500)  # max_steps caps


def test_the_extension_follows_the_gated_quantities_only():
    diagnostics = {"p": _diag(ess=50.0), "h": _diag(n_tau=40.0)}  # p not gated (a mode swap)
    result = type("R", (), {"diagnostics": diagnostics})()
    assert extended_length(result, 2000, Gates(gated=("h",)), 24000) == 2750


def bimodal_logp(x):
    x = np.atleast_2d(x)
    m = np.logaddexp(-0.5 * ((x[:, 0] - 5) / 0.5) ** 2, -0.5 * ((x[:, 0] + 5) / 0.5) ** 2)
    return m - 0.5 * x[:, 1] ** 2


def bimodal_p0(rng, n):
    """Each ensemble starts (at random) in one of the two modes, which it cannot leave."""
    mode = rng.choice([-5.0, 5.0])
    return np.column_stack([mode + 0.3 * rng.normal(size=n), rng.normal(size=n)])


def test_bimodal_ensembles_stuck_in_different_modes_fail_rhat():
    r = run_ensembles(
        bimodal_logp,
        bimodal_p0,
        ("x", "y"),
        np.random.default_rng(1),
        n_walkers=8,
        n_steps=300,
        max_steps=450,
        vectorize=True,
    )
    means = r.samples[..., 0].mean(axis=(1, 2))
    assert np.any(means > 0) and np.any(means < 0)  # the seed does put them in both modes
    assert not r.passed and r.n_steps == 450
    assert "rhat(x)" in r.status and r.diagnostics["x"]["rhat"] > 1.5
    assert r.rhat_max == r.diagnostics["x"]["rhat"]


def test_gating_on_predictions_ignores_modes_that_predict_the_same():
    """Label switching: +x and -x predict the same x^2; gated on x^2 the run passes, on x it fails.

    The budget gates the H sampler on H(f) for this reason (Eq. 2's poles can trade roles).
    """
    kw = dict(n_walkers=8, n_steps=3500, max_steps=3500, vectorize=True)

    def square(s):
        return {"x2": s[:, 0] ** 2}

    on_x2 = run_ensembles(
        bimodal_logp,
        bimodal_p0,
        ("x", "y"),
        np.random.default_rng(1),
        derived_fn=square,
        gates=Gates(gated=("x2", "y")),
        **kw,
    )
    assert on_x2.passed, on_x2.status
    assert on_x2.diagnostics["x"]["rhat"] > 1.5  # still reported
    on_all = run_ensembles(
        bimodal_logp, bimodal_p0, ("x", "y"), np.random.default_rng(1), derived_fn=square, **kw
    )
    assert not on_all.passed and "rhat(x)" in on_all.status


# ----------------------------------------------------------------------------- determinism
def test_same_seed_same_chains_whatever_the_global_numpy_state():
    np.random.seed(1)
    r1 = short_run(seed=3, n=120)
    np.random.seed(2)  # emcee would take its RNG from here if we did not seed it
    r2 = short_run(seed=3, n=120)
    assert_same(r1, r2)
    r3 = short_run(seed=4, n=120)
    assert not np.array_equal(r1.samples, r3.samples)
    # ensembles are independent streams, not copies of one another
    assert not np.array_equal(r1.samples[0], r1.samples[1])


def test_chunking_scalar_log_prob_and_pool_do_not_change_the_chains():
    class CountingPool:
        calls = 0

        def map(self, f, it):
            CountingPool.calls += 1
            return list(map(f, it))

    ref = short_run(n=120, log_prob=gauss_logp_scalar, vectorize=False)
    assert_same(ref, short_run(n=120, log_prob=gauss_logp_scalar, vectorize=False, chunk_steps=37))
    pooled = short_run(n=120, log_prob=gauss_logp_scalar, vectorize=False, pool=CountingPool())
    assert CountingPool.calls > 0
    assert_same(ref, pooled)


def test_progress_bars_are_labelled_per_ensemble(capsys, caplog):
    # stderr is not a terminal under pytest: the bars are periodic log lines, captured here
    # whatever logging configuration an earlier test (or none) left behind
    with caplog.at_level(logging.INFO, logger="bayes_tfcrds.output.progress"):
        short_run(n=30, progress=True, label="H(f) fit")
    err = capsys.readouterr().err + caplog.text
    assert all(f"H(f) fit ensemble {i}" in err for i in range(4))


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="at least 4"):
        short_run(n=10, n_ensembles=3)
    with pytest.raises(ValueError, match="non-finite log_prob"):
        run_ensembles(
            lambda x: np.where(x[:, 0] > 100, -np.inf, gauss_logp(x)),
            lambda g, n: 1000 + g.normal(size=(n, 3)),
            NAMES,
            np.random.default_rng(0),
            n_walkers=W,
            n_steps=10,
            vectorize=True,
        )
    for bad_p0 in (lambda g, n: g.normal(size=n), lambda g, n: g.normal(size=(n, 2))):
        with pytest.raises(ValueError, match=r"p0_fn returned shape \(\d+(, 2)?,?\), need"):
            short_run(n=10, p0_fn=bad_p0)
    with pytest.raises(ValueError, match="would couple the independent ensembles"):
        short_run(n=10, moves=[(emcee.moves.StretchMove(), 1.0)])
    calls = []

    def one_degenerate_ensemble(g, n):  # pooled, the 4 x n walkers would look independent
        calls.append(n)
        x = g.normal(size=(n, 3))
        return np.repeat(x[:1], n, axis=0) if len(calls) == 2 else x

    with pytest.raises(ValueError, match="ensemble 1: p0_fn returned walkers that are not indep"):
        short_run(n=10, p0_fn=one_degenerate_ensemble)


def test_moves_are_taken_in_emcees_forms():
    # one move, a list of moves, or (move, weight) pairs: the same chains for the same move
    from bayes_tfcrds.inference.moves import DifferentialEvolutionMove

    ref = short_run(n=60, moves=[(DifferentialEvolutionMove(), 1.0)])
    assert_same(ref, short_run(n=60, moves=DifferentialEvolutionMove()))
    assert_same(ref, short_run(n=60, moves=[DifferentialEvolutionMove()]))


# ----------------------------------------------------------------------------- resume
class CountingLogp:
    """Vectorised Gaussian that counts evaluated rows and can interrupt itself."""

    def __init__(self, interrupt_after=None, kill_after=None):
        self.rows = 0
        self.interrupt_after, self.kill_after = interrupt_after, kill_after

    def __call__(self, x):
        self.rows += len(x)
        if self.interrupt_after is not None and self.rows > self.interrupt_after:
            raise KeyboardInterrupt
        if self.kill_after is not None and self.rows > self.kill_after:
            os.kill(os.getpid(), signal.SIGKILL)
        return gauss_logp(x)


def _iterations(path):
    with h5py.File(path, "r") as f:
        return [
            int(f[f"ensemble{i}"].attrs["iteration"]) if f"ensemble{i}" in f else 0
            for i in range(4)
        ]


def test_resume_from_backend_equals_uninterrupted_run(tmp_path):
    path = tmp_path / "chains.h5"
    short_run(n=200, backend_path=path)
    assert _iterations(path) == [200] * 4
    lp = CountingLogp()
    resumed = short_run(n=400, backend_path=path, log_prob=lp)
    # continued, not restarted: exactly the 200 missing steps x 4 ensembles were evaluated
    assert lp.rows == 200 * 4 * W
    assert_same(resumed, reference_run(400))
    # the file is a plain emcee HDFBackend
    be = emcee.backends.HDFBackend(str(path), name="ensemble2", read_only=True)
    assert be.iteration == 400
    assert np.array_equal(be.get_chain()[resumed.burn :], resumed.samples[2])
    # rerunning a finished run samples nothing and returns the same result
    again = CountingLogp()
    assert_same(short_run(n=400, backend_path=path, log_prob=again), reference_run(400))
    assert again.rows == 0


def test_backend_refuses_a_different_seed(tmp_path):
    path = tmp_path / "chains.h5"
    short_run(n=50, backend_path=path, seed=1)
    with pytest.raises(ValueError, match="another seed"):
        short_run(n=100, backend_path=path, seed=2)


ROWS_PER_STEP = 4 * W  # the four ensembles step together: every walker once per step


def test_keyboard_interrupt_then_rerun_equals_uninterrupted(tmp_path):
    path = tmp_path / "chains.h5"
    lp = CountingLogp(interrupt_after=ROWS_PER_STEP * (1 + 250))  # p0, then inside step 251
    with pytest.raises(KeyboardInterrupt):
        short_run(n=400, backend_path=path, log_prob=lp)
    assert _iterations(path) == [200] * 4  # the committed chunks (of 100 steps) survived
    assert_same(short_run(n=400, backend_path=path), reference_run(400))


def test_sigkill_then_rerun_equals_uninterrupted(tmp_path):
    path = tmp_path / "chains.h5"
    here = os.path.dirname(os.path.abspath(__file__))
    kill_after = ROWS_PER_STEP * (1 + 130)  # inside step 131, after one commit
    script = (
        f"import sys; sys.path.insert(0, {here!r}); import test_sampling as t\nt.short_run(n=400, "
        f"backend_path={str(path)!r}, log_prob=t.CountingLogp(kill_after={kill_after}))\n"
    )
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, timeout=120)
    assert proc.returncode == -signal.SIGKILL, proc.stderr.decode()[-2000:]
    assert _iterations(path) == [100] * 4
    assert_same(short_run(n=400, backend_path=path), reference_run(400))


# ----------------------------------------------------------------------------- arviz
def test_inference_data_round_trips_through_netcdf(tmp_path):
    import arviz as az

    r = short_run(n=199, derived_fn=lambda s: {"ab": s[:, 0] * s[:, 1]})
    path = tmp_path / "posterior.nc"
    path.write_bytes(b"old contents")  # replaced, not appended to
    r.save_netcdf(path)
    assert sorted(os.listdir(tmp_path)) == ["posterior.nc"]  # no temp file left behind
    idata = az.from_netcdf(path)
    post = idata.posterior
    e, s, w, _ = r.samples.shape
    assert s % 2 == 1  # an odd kept length: the layout's middle step is exercised
    assert post["a"].dims == ("chain", "draw") and post["a"].shape == (e, s * w)
    # chain = ensemble; every draw says which step and walker it is, and all are there once
    step = post["step"].values - r.burn
    walker = post["walker"].values
    assert len(set(zip(step, walker))) == s * w
    for ens in (0, 3):
        assert np.array_equal(post["b"].values[ens], r.samples[ens, step, walker, 1])
        assert np.array_equal(post["ab"].values[ens], r.derived["ab"][ens, step, walker])
        assert np.array_equal(idata.sample_stats["lp"].values[ens], r.log_prob[ens, step, walker])
    assert int(post.attrs["n_ensembles"]) == 4 and int(post.attrs["n_walkers"]) == W
    assert post.attrs["status"] == r.status and int(post.attrs["passed"]) == int(r.passed)
    # the diagnostics are structured attributes of each variable, and arviz agrees with them
    rhat, ess_bulk, ess_tail = az.rhat(idata), az.ess(idata), az.ess(idata, method="tail")
    for name in ("a", "b", "c", "ab"):
        d = r.diagnostics[name]
        for key in ("rhat", "ess_bulk", "ess_tail", "tau_int", "n_tau"):
            assert float(post[name].attrs[key]) == d[key]
        assert float(rhat[name]) == d["rhat"]
        assert float(ess_bulk[name]) == d["ess_bulk"] and float(ess_tail[name]) == d["ess_tail"]


def test_parameters_are_diagnosed_and_saved_in_the_natural_units_of_their_priors(tmp_path):
    """A log-uniform parameter is sampled as its log; diagnostics and the file use the value."""
    import arviz as az

    from bayes_tfcrds.inference.posteriors import Prior

    priors = (Prior("f_hz", "log-uniform", 1.0, 1e6, "Hz"), Prior("k", "uniform", -1e3, 1e3, "1"))

    def logp(x):  # log f ~ N(log 1e3, 0.5), k ~ N(0, 1)
        return -0.5 * (((x[:, 0] - np.log(1e3)) / 0.5) ** 2 + x[:, 1] ** 2)

    def p0(rng, n):
        return np.column_stack([np.log(1e3) + 0.5 * rng.normal(size=n), rng.normal(size=n)])

    r = run_ensembles(
        logp,
        p0,
        ("log_f_hz", "k"),
        np.random.default_rng(4),
        n_walkers=8,
        n_steps=300,
        max_steps=300,
        vectorize=True,
        priors=priors,
    )
    assert set(r.diagnostics) == {"f_hz", "k"} and r.units == {"f_hz": "Hz", "k": "1"}
    assert np.allclose(r.parameters()["f_hz"], np.exp(r.samples[..., 0]))
    r.save_netcdf(tmp_path / "p.nc")
    post = az.from_netcdf(tmp_path / "p.nc").posterior
    assert np.median(post["f_hz"].values) == pytest.approx(1e3, rel=0.2)  # Hz, not log Hz
    assert (
        post["f_hz"].attrs["units"] == "Hz" and post["f_hz"].attrs["prior_family"] == "log-uniform"
    )
    assert post["f_hz"].attrs["sampled_as"] == "log_f_hz" and post["k"].attrs["prior_lower"] == -1e3
    assert float(az.rhat(post)["f_hz"]) == r.diagnostics["f_hz"]["rhat"]
    with pytest.raises(ValueError, match="priors sample"):
        run_ensembles(
            logp,
            p0,
            ("f_hz", "k"),
            np.random.default_rng(4),
            n_walkers=8,
            n_steps=10,
            vectorize=True,
            priors=priors,
        )
