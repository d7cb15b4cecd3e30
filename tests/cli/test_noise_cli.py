"""Coloured detector noise from the command line: simulate it, and see fit, linefit and budget
flag it and widen u(tau) by what the noise's correlation costs."""

import csv
import json

import numpy as np

from bayes_tfcrds.cli import main


def _simulate(path, noise):
    args = ["simulate", "--preset", "letter-D2", "--seed", "5", "--points", "41"]
    args += ["--samples", "8192", "--noise", noise, "-o", str(path)]
    assert main(args) == 0


def _fit(path, out, capsys):
    assert main(["fit", str(path), "--config", "D2", "--tcut", "4e-6", "-o", str(out)]) == 0
    err = capsys.readouterr().err
    with open(out) as fh:
        rows = list(csv.DictReader(fh))
    col = lambda name: np.array([float(r[name]) for r in rows])  # noqa: E731
    return err, col("tau_u_noise_s"), col("chi2_red"), col("noise_kappa")


def test_fit_flags_coloured_noise_and_widens_u_tau(tmp_path, capsys):
    white, coloured = tmp_path / "w.h5", tmp_path / "c.h5"
    _simulate(white, "white")
    _simulate(coloured, "lowpass:f_hz=5e6,order=2")
    err_w, u_w, chi2_w, kappa_w = _fit(white, tmp_path / "w.csv", capsys)
    err_c, u_c, chi2_c, kappa_c = _fit(coloured, tmp_path / "c.csv", capsys)
    assert "white: u(tau) from the stated noise" in err_w
    assert "COLOURED" in err_c
    # same seed, same per-sample noise: u(tau) grows by sqrt(kappa) = sqrt(4.5) = 2.1 (kappa of
    # a 5 MHz 2nd-order low-pass sampled at 50 MHz; estimated within a few %)
    assert 1.9 < np.median(u_c / u_w) < 2.35
    # the CSV says why: kappa per record (1 where white), and chi2_red at the stated per-sample
    # noise, which the colour leaves as it is (~1; at the fits' weights it would read 1/4.5).
    # Its sd over 41 records of ~6000 correlated samples is < 0.01: 0.1 is a wide, safe band
    assert np.all(kappa_w == 1) and np.all((kappa_c > 3.5) & (kappa_c < 5.5))
    assert abs(np.median(chi2_w) - 1) < 0.1 and abs(np.median(chi2_c) - 1) < 0.1


def test_linefit_records_the_noise_diagnosis(tmp_path, capsys):
    path, out = tmp_path / "c.h5", tmp_path / "l.json"
    _simulate(path, "chain")
    args = ["linefit", str(path), "--config", "D2", "--tcut", "4e-6", "-o", str(out)]
    assert main(args) == 0
    assert "warning: noise:" in capsys.readouterr().err
    noise = json.loads(out.read_text())["noise"]
    assert noise["white"] is False and noise["kappa_median"] > 3
    assert noise["box_pierce"]["p_value"] < 1e-3


def test_simulate_refuses_an_unknown_noise(tmp_path, capsys):
    args = ["simulate", "--noise", "violet", "--points", "9", "--samples", "1024"]
    assert main(args + ["-o", str(tmp_path / "x.h5")]) == 2
    assert "--noise 'violet'" in capsys.readouterr().err
    assert not (tmp_path / "x.h5").exists()
