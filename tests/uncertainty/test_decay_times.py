"""``bayes-tfcrds fit``'s decay times: fitted at the centre of H's posterior, with the H part of
u(tau) beside the noise's, checked against the simulation's true decay times and against exact
refits at each H draw."""

import csv
from dataclasses import replace

import h5py
import numpy as np
import pytest

import bayes_tfcrds.uncertainty.decay_times as decay_times
from bayes_tfcrds.bundle.writer import save_bundle
from bayes_tfcrds.cli import main
from bayes_tfcrds.fit.h_calibration import AnalysisError, account_for_noise_colour, calibrate
from bayes_tfcrds.fit.ringdown import fit_ringdowns
from bayes_tfcrds.simulate.campaign import Campaign, simulate_campaign
from bayes_tfcrds.uncertainty.decay_times import (
    fit_decay_times,
    h_part_of_tau_u,
    laplace_h_draws,
)


def _config(preset="letter-D3", seed=0, points=21):
    bundle, truth = simulate_campaign(
        [preset], np.random.default_rng(seed), Campaign(n_points=points)
    )
    name = next(iter(bundle.configs))
    cfg, _, beat = account_for_noise_colour(bundle.configs[name])
    return cfg, calibrate(cfg, beat=beat), np.asarray(truth["configs"][name]["tau_s"])


def test_the_h_part_equals_the_spread_of_exact_refits_at_the_draws():
    # independent of the implicit-function kernels: refit every transient at each H draw and take
    # the sd of tau. First order holds to the curvature of tau(H) over ~1 posterior sd (a few %);
    # 10 % also covers 40 draws' sd of an sd of a difference (the same draws on both sides).
    cfg, cal, _ = _config(points=11)
    # 300 draws pass the importance gate (ESS >= 200); 40 of them are refitted
    h = laplace_h_draws(cfg, cal, np.random.default_rng(1), n_draws=300)
    h = replace(h, draws=h.draws[:40])
    fits = fit_ringdowns(cfg.ringdowns, [2e-6, 8e-6], "tf-crds", h.centre)
    u_h = h_part_of_tau_u(cfg, fits, h)
    refits = np.array(
        [
            fit_ringdowns(
                cfg.ringdowns, [2e-6, 8e-6], "tf-crds", h.centre.with_vector(d, h.names)
            ).tau_s
            for d in h.draws
        ]
    )
    exact = refits.std(axis=0)
    assert np.all(np.isfinite(u_h))
    np.testing.assert_allclose(u_h, exact, rtol=0.10)
    # and the comparison is not of two zeros: on the letter's D3 chain u_H is ~half the noise's
    assert np.median(u_h / fits.tau_u_s) > 0.2


def test_plain_crds_has_no_h_part_and_an_unfitted_point_none_at_all():
    cfg, cal, _ = _config(points=8)
    h = laplace_h_draws(cfg, cal, np.random.default_rng(1), n_draws=300)
    crds = fit_ringdowns(cfg.ringdowns, [4e-6], "crds")
    assert np.all(h_part_of_tau_u(cfg, crds, h) == 0.0)
    tf = fit_ringdowns(cfg.ringdowns, [4e-6], "tf-crds", h.centre)
    tau = tf.tau_s.copy()
    tau[2, 0] = np.nan
    u_h = h_part_of_tau_u(cfg, type(tf)(**{**tf.__dict__, "tau_s": tau}), h)
    assert np.isnan(u_h[2, 0]) and np.isfinite(np.delete(u_h[:, 0], 2)).all()


def _fit_table(tmp_path, preset, seed, points=41):
    path, out = tmp_path / f"{seed}.h5", tmp_path / f"{seed}.csv"
    args = ["simulate", "--preset", preset, "--seed", str(seed), "--points", str(points)]
    assert main([*args, "-o", str(path)]) == 0
    name = preset.split("-")[1]
    assert main(["fit", str(path), "--config", name, "--tcut", "2e-6", "-o", str(out)]) == 0
    with open(out) as fh:
        rows = list(csv.DictReader(fh))
    with h5py.File(path) as f:
        tau_true = f[f"truth/configs/{name}/tau_s"][()]
    col = {k: np.array([float(r[k]) for r in rows]) for k in rows[0] if k != "status"}
    return col, tau_true


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 2])
def test_fit_reports_tau_at_the_posterior_centre_with_its_total_u(tmp_path, seed):
    # letter D3 (3.7 us at line centre): the letter's H (f_c refined, the rest at the beat note)
    # puts the line-centre tau 12-16 noise u from the truth on these seeds; the centre of H's
    # posterior (the ring-downs inform a_r, f_r, Gamma_r too) within about one
    col, tau_true = _fit_table(tmp_path, "letter-D3", seed)
    assert np.allclose(np.hypot(col["tau_u_noise_s"], col["tau_u_h_s"]), col["tau_u_s"], rtol=1e-3)
    pull_total = (col["tau_s"] - tau_true) / col["tau_u_s"]
    pull_noise = (col["tau_s"] - tau_true) / col["tau_u_noise_s"]
    centre = np.argmin(tau_true)
    # |z| < 3 at the 3-sigma level of a calibrated total u
    assert abs(pull_total[centre]) < 3.0
    # 41 points: the noise part of the pulls has sd 1 (+/- 0.11 sampling); the H error common
    # to them adds at most its own (u_H ~ 2 u_noise at the centre, far less at long tau)
    assert np.std(pull_noise) < 1.5


def test_fit_decay_times_fits_at_the_posterior_centre_not_the_letter_h():
    cfg, cal, _ = _config(points=8)
    fits, h = fit_decay_times(cfg, [2e-6], cal, np.random.default_rng(3), n_draws=300)
    assert fits.tf == h.centre and h.centre != cal.params
    again = fit_ringdowns(cfg.ringdowns, [2e-6], "tf-crds", h.centre)
    np.testing.assert_array_equal(fits.tau_s, again.tau_s)
    assert np.all(fits.tau_u_h_s > 0)
    np.testing.assert_allclose(fits.tau_u_total_s, np.hypot(fits.tau_u_s, fits.tau_u_h_s))


def test_fit_says_so_and_writes_no_total_u_when_h_posterior_fails(tmp_path, monkeypatch, capsys):
    bundle, _ = simulate_campaign(
        ["letter-D2"], np.random.default_rng(4), Campaign(n_points=9, n_samples=8192, n_avg=20)
    )
    path, out = tmp_path / "b.h5", tmp_path / "f.csv"
    save_bundle(bundle, path)

    def refuse(*args, **kwargs):
        raise AnalysisError("the test refuses")

    monkeypatch.setattr(decay_times, "laplace_h_draws", refuse)
    assert main(["fit", str(path), "--config", "D2", "--tcut", "4e-6", "-o", str(out)]) == 0
    assert "no posterior of H to propagate (the test refuses)" in capsys.readouterr().err
    with open(out) as fh:
        rows = list(csv.DictReader(fh))
    assert all(r["tau_u_s"] == "nan" and r["tau_u_h_s"] == "nan" for r in rows)
    assert all(np.isfinite(float(r["tau_u_noise_s"])) for r in rows if r["status"] == "ok")
