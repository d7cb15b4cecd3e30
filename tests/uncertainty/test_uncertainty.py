"""The line-area budget: outputs, convergence gates, bias, and honesty of the stated u(A)."""

import json
from dataclasses import replace

import numpy as np
import pytest

from bayes_tfcrds.bundle.writer import save_bundle
from bayes_tfcrds.cli import main
from bayes_tfcrds.simulate.campaign import Campaign, simulate_campaign
from bayes_tfcrds.uncertainty.line_budget import run_budget
from tests.uncertainty.replicas import FAST, sd_ratio_band

SMALL = replace(Campaign(), n_points=31, n_samples=8192, n_avg=10)
# The stated u(A) against the scatter of A over simulated campaigns, and the ring-down-noise rows
# against the scatter with the beat note held fixed, are benchmarks/budget_replicas.py (60 replicas
# each, about 7 s per replica on one core). In CI the coverage study's test checks the whole u
# (tests/studies/test_coverage_study.py: 40 campaigns, where a u off by a factor 2 moves the 68 %
# coverage to 38 or 95 %, outside its binomial band); the replicas' sd band is checked below.


@pytest.fixture(scope="module")
def small_bundle(tmp_path_factory):
    path = tmp_path_factory.mktemp("budget") / "d2d4.h5"
    b, t = simulate_campaign(["letter-D2", "letter-D4"], np.random.default_rng(21), SMALL)
    save_bundle(b, path, truth=t)
    return path, t


def test_budget_command_writes_every_output_and_passes_the_gates(small_bundle, tmp_path):
    path, truth = small_bundle
    out = tmp_path / "D2"
    assert (
        main(["budget", str(path), "--config", "D2", "--seed", "3", "--quiet", "-o", str(out)]) == 0
    )
    s = json.loads((out / "budget.json").read_text())
    for key in ("line_area", "reference_area", "ratio", "en", "components", "diagnostics"):
        assert key in s
    assert s["line_area"]["unit"] == "cm^-2" and s["reference_area"]["unit"] == "cm^-2"
    d = s["diagnostics"]
    assert d["passed"] and d["rhat_max"] < 1.01 and d["ess_min"] > 400
    shares = [c["share"] for c in s["components"]]
    assert abs(sum(shares) - 1) < 1e-9
    names = [c["name"] for c in s["components"]]
    for needed in (
        "ring-down noise",
        "H: f_c_hz",
        "H: posterior of",
        "H model form",
        "t_cut choice",
        "line-shape model",
    ):
        assert any(n.startswith(needed) for n in names), needed
    # how the ring-downs updated the beat note, in budget.json and budget.md
    ref = s["transfer_function"]["refinement"]["parameters"]["f_c_hz"]
    assert ref["refined_u"] < ref["beat_note_u"] and np.isfinite(ref["z"])
    assert "H: beat note updated by the ring-downs" in (out / "budget.md").read_text()
    # a preset chain (underdamped resonance): one description of H, every parameter identified
    ident = s["transfer_function"]["identification"]
    assert ident["not_identified"] == [] and ident["descriptions"] == []
    assert "H: parameters the data identify" in (out / "budget.md").read_text()
    form = s["transfer_function"]["model_form"]
    assert 0 <= form["weight_n_r_free"] < 0.5 and not form["asks_for_free_order"]  # n_r = 2 truth
    for f in (
        "budget.md",
        "budget.csv",
        "posterior_h.nc",
        "posterior_line.nc",
        "posterior_cmds.nc",
        "corner_h.png",
        "corner_line.png",
        "tau_posterior.csv",
    ):
        assert (out / f).stat().st_size > 0, f
    import csv

    taus = list(csv.DictReader((out / "tau_posterior.csv").open()))
    assert len({r["t_cut_s"] for r in taus}) == 6
    # H moves short decays most: its share of u(tau) is larger at the line centre than at baseline
    at4 = [r for r in taus if abs(float(r["t_cut_s"]) - 4e-6) < 1e-9]
    short = min(at4, key=lambda r: float(r["tau_s"]))
    long_ = max(at4, key=lambda r: float(r["tau_s"]))
    assert float(short["u_h_s"]) / float(short["tau_s"]) > float(long_["u_h_s"]) / float(
        long_["tau_s"]
    )
    # unbiased against the truth within the statistical uncertainty (3 sigma)
    a_true = truth["line"]["line_area_hz_per_m"]
    assert abs(s["line_area"]["value_si"] - a_true) < 3 * s["line_area"]["u_si"]
    assert abs(s["ratio"]["value"] - 1) < 3 * s["ratio"]["u"]
    import arviz as az

    idata = az.from_netcdf(out / "posterior_line.nc")
    assert "line_area" in idata.posterior


def test_crds_budget_shows_the_letter_bias(small_bundle):
    from bayes_tfcrds.bundle.reader import load_bundle

    path, _ = small_bundle
    b = load_bundle(path)
    crds = run_budget(
        b, b.configs["D4"], replace(FAST, method="crds"), np.random.default_rng(1)
    ).summary
    tf = run_budget(b, b.configs["D4"], FAST, np.random.default_rng(1)).summary
    assert crds["ratio"]["value"] < 0.95 and crds["en"] < -5  # the letter: -8 % for D4
    assert abs(tf["ratio"]["value"] - 1) < 3 * tf["ratio"]["u"]


def test_the_sd_band_holds_the_sample_sd_of_normal_samples_as_often_as_it_says():
    # 200 000 samples of 20 N(0, 1) values: 0.135 % below the 3-sigma band and 0.135 % above,
    # 270 +/- 16 each; 4.5 s.e. allow 196-344. The normal approximation of the sd's spread
    # (1 +/- 3 x 0.162) puts 139 below and 388 above (the chi distribution is skewed) and fails
    lo, hi = sd_ratio_band(20)
    sd = np.std(np.random.default_rng(0).standard_normal((200_000, 20)), axis=1, ddof=1)
    below, above = int(np.sum(sd <= lo)), int(np.sum(sd >= hi))
    assert 196 <= below <= 344 and 196 <= above <= 344, (lo, hi, below, above)


def test_unconverged_decay_times_never_reach_a_line_fit():
    # An unconverged fit (tau run to 1e-14 s) made `budget` crash in its line fit, or, at another
    # t_cut, enter the t_cut row with A wrong by 100 %. The budget leaves such fits out (NaN,
    # which every spectrum and the tau table skip) and counts them.
    import numpy as np

    from bayes_tfcrds.fit.ringdown import RingdownFits
    from bayes_tfcrds.fit.spectrum import crds_spectrum
    from bayes_tfcrds.uncertainty.line_budget import _converged_only

    tau = np.array([[3e-6, 3e-6], [4e-6, 3e-14], [5e-6, 5e-6]])
    conv = np.array([[True, True], [True, False], [True, True]])
    fits = RingdownFits(
        nu_hz=1.9e14 + 2e8 * np.arange(3.0),  # three cavity modes, one FSR apart
        t_cut_s=np.array([2e-6, 8e-6]),
        tau_s=tau,
        tau_u_s=np.full_like(tau, 1e-9),
        amplitude_v=np.ones_like(tau),
        offset_v=np.zeros_like(tau),
        chi2_red=np.ones_like(tau),
        converged=conv,
        clipped=np.zeros(3, bool),
        method="tf-crds",
        window="extinction",
        noise_estimated=False,
    )
    kept = _converged_only(fits)
    assert np.isnan(kept.tau_s[1, 1]) and np.isnan(kept.tau_u_s[1, 1])
    np.testing.assert_array_equal(kept.unconverged, ~conv)
    assert kept.tau_s[1, 0] == 4e-6  # the same record's converged fit stays
    spec = crds_spectrum(kept.nu_hz, kept.tau_s[:, 1], kept.tau_u_s[:, 1])
    np.testing.assert_array_equal(spec.nu_hz, kept.nu_hz[[0, 2]])
