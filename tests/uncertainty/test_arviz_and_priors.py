"""A budget's posterior files give arviz the gated diagnostics, and every output states the priors.

Issue 16, items 4 and 5: ``az.rhat``/``az.ess`` on ``posterior_*.nc`` are the numbers the gates
judged (one chain per ensemble, not per walker), H is stored in natural units with units, and the
priors in budget.json, budget.md, the netCDF attributes and the studies' report are read from the
posterior definitions.
"""

import json
import warnings
from dataclasses import replace

import numpy as np
import pytest

from bayes_tfcrds.fit.h_calibration import BEAT_FREE
from bayes_tfcrds.inference.posteriors import H_PRIORS, LINE_PRIORS, Prior
from bayes_tfcrds.output.report import Report
from bayes_tfcrds.simulate.campaign import Campaign, simulate_campaign
from bayes_tfcrds.studies.budgets import _priors_table
from bayes_tfcrds.uncertainty.line_budget import BudgetOptions, run_budget
from bayes_tfcrds.uncertainty.outputs import priors_markdown, write_outputs

TINY = replace(Campaign(), n_points=21, n_samples=4096, n_avg=25)
# short chains: the gates fail, but the diagnostics and the files are complete, which is all that
# matters here (agreement with arviz does not depend on convergence)
SHORT = BudgetOptions(t_cuts_s=(4e-6, 8e-6), n_steps=60, max_steps=60, n_h_draws=100)


def _arviz():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        import arviz

    return arviz


@pytest.fixture(scope="module")
def bundle():
    b, _ = simulate_campaign(["letter-D2"], np.random.default_rng(5), TINY)
    return b


@pytest.fixture(scope="module")
def budget(bundle, tmp_path_factory):
    out = tmp_path_factory.mktemp("budget")
    res = run_budget(bundle, bundle.configs["D2"], SHORT, np.random.default_rng(1))
    write_outputs(res, out, seed=1)
    return res, out, json.loads((out / "budget.json").read_text())


def test_arviz_on_the_saved_files_gives_the_gated_diagnostics(budget):
    az = _arviz()
    res, out, s = budget
    assert set(res.runs) == {"h", "line", "cmds"}
    for key, run in res.runs.items():
        idata = az.from_netcdf(out / f"posterior_{key}.nc")
        post = idata.posterior
        assert post.sizes["chain"] == run.n_ensembles  # a chain is an ensemble, not a walker
        rhat, bulk, tail = az.rhat(idata), az.ess(idata), az.ess(idata, method="tail")
        assert set(post.data_vars) == set(run.diagnostics)
        for name, d in run.diagnostics.items():
            # the package calls the same arviz functions on the same float64 draws: equal to
            # rounding (a walker-as-chain layout differs in the second decimal of R-hat)
            assert float(rhat[name]) == pytest.approx(d["rhat"], rel=1e-12, abs=0), (key, name)
            assert float(bulk[name]) == pytest.approx(d["ess_bulk"], rel=1e-12), (key, name)
            assert float(tail[name]) == pytest.approx(d["ess_tail"], rel=1e-12), (key, name)
            for k in (
                "rhat",
                "ess_bulk",
                "ess_tail",
                "tau_int",
                "n_tau",
            ):  # structured, per variable
                assert float(post[name].attrs[k]) == pytest.approx(d[k], rel=1e-12), (key, name, k)
        # and what budget.json reports for the run is the extreme over the gated variables
        gated = [n for n in post.data_vars if post[n].attrs["gated"]]
        reported = s["diagnostics"]["runs"][key]
        assert max(float(rhat[n]) for n in gated) == pytest.approx(reported["rhat_max"], rel=1e-12)
        ess_min = min(min(float(bulk[n]), float(tail[n])) for n in gated)
        assert ess_min == pytest.approx(reported["ess_min"], rel=1e-12)


def test_h_is_saved_in_natural_units_with_unit_attributes(budget):
    az = _arviz()
    res, out, s = budget
    post = az.from_netcdf(out / "posterior_h.nc").posterior
    assert not [n for n in post.data_vars if n.startswith("log_")]
    assert all(post[n].attrs["units"] for n in post.data_vars)
    assert post["f_c_hz"].attrs["units"] == "Hz" and post["gamma_r"].attrs["units"] == "1"
    # every draw is the sampled log f_c, exponentiated, at the step and walker it names
    run = res.runs["h"]
    step, walker = post["step"].values - run.burn, post["walker"].values
    i = run.names.index("log_f_c_hz")
    assert np.allclose(post["f_c_hz"].values, np.exp(run.samples[:, step, walker, i]), rtol=1e-15)
    # in Hz: within 5 of the beat-note fit's standard errors of its least-squares f_c (an
    # independent estimate; the beat-note posterior is close to Gaussian there)
    ref = s["transfer_function"]["refinement"]["parameters"]["f_c_hz"]
    assert abs(float(post["f_c_hz"].median()) - ref["beat_note"]) < 5 * ref["beat_note_u"]


def test_every_output_records_the_priors_of_the_posterior_definitions(budget):
    az = _arviz()
    res, out, s = budget
    h = {p["parameter"]: p for p in s["priors"]["h"]["parameters"]}
    assert set(h) == {*BEAT_FREE, "scale"}
    for name, p in h.items():
        ref = H_PRIORS[name]
        assert (p["family"], p["unit"]) == (ref.family, ref.unit), name
        if name == "a_r":  # the branch the ring-downs chose: one side of the domain, cut at 0
            assert ref.lower <= p["lower"] < p["upper"] <= ref.upper and 0.0 in (
                p["lower"],
                p["upper"],
            )
        else:
            assert (p["lower"], p["upper"]) == (ref.lower, ref.upper), name
    # the frequencies and the quality factor are log-uniform, sampled as logarithms
    assert [h[n]["family"] for n in ("f_c_hz", "f_r_hz", "gamma_r")] == ["log-uniform"] * 3
    assert h["f_c_hz"]["sampled_as"] == "log_f_c_hz"
    for key in ("line", "cmds"):
        line = {p["parameter"]: p for p in s["priors"][key]["parameters"]}
        assert tuple(line) == res.runs[key].names
        assert line["line_area"]["family"] == LINE_PRIORS["line_area"].family
        assert (line["line_area"]["lower"], line["line_area"]["upper"]) == (0.0, None)
        assert line["gamma2_hz"]["condition"] == "gamma2_hz < (2/3) gamma0_hz"
    assert {
        p["unit"] for p in s["priors"]["cmds"]["parameters"] if p["parameter"] == "baseline0"
    } == {
        "Hz"  # the CMDS spectrum is a dispersion in Hz
    }
    md = (out / "budget.md").read_text()
    assert "## Priors" in md and "| f_c_hz | log-uniform | 1 | 1e+10 | Hz |" in md
    post = az.from_netcdf(out / "posterior_line.nc").posterior
    assert post["gamma0_hz"].attrs["prior_family"] == "uniform"
    assert (
        post["gamma0_hz"].attrs["prior_lower"] == 0.0 and post["gamma0_hz"].attrs["units"] == "Hz"
    )
    # the studies' report of budgets shows them too
    rep = Report("budgets")
    _priors_table(rep, [("D2", s, None, None)])
    header, rows, _ = next(payload for kind, payload in rep.blocks if kind == "table")
    assert header[:3] == ["configs", "posterior", "parameter"]
    # SHORT fails the H gates, so the label names the re-runs with fitted jumps (posterior_steps)
    h_label = s["priors"]["h"]["posterior"]
    assert h_label.startswith("H | beat note")
    assert ["D2", h_label, "f_c_hz", "log-uniform", "1", "1e+10", "Hz", ""] in rows


def _keys_and_units(obj, path=""):
    """Every (key path, value) of a JSON object whose key or value names a unit of A."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _keys_and_units(v, f"{path}.{k}")
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _keys_and_units(v, f"{path}[{i}]")
    else:
        yield path, obj


def test_the_line_area_has_one_unit_in_every_file_of_the_run(budget):
    """cm^-2 for A and A_ref in budget.json, budget.md, budget.csv, the priors and the netCDF
    posteriors; SI (Hz/m) only as the labelled twin (``unit_si``, ``units_sampled``)."""
    from bayes_tfcrds.core.constants import line_area_to_cm2

    az = _arviz()
    res, out, s = budget
    pairs = list(_keys_and_units(s))
    # no key names the SI unit, and "Hz/m" is only ever the value of an SI twin's unit
    assert not [p for p, _ in pairs if "hz_per_m" in p]
    assert {p.rsplit(".", 1)[1] for p, v in pairs if v == "Hz/m"} == {"unit_si"}
    assert "Hz/m" not in (out / "budget.md").read_text()
    for key in ("line", "cmds"):
        prior = next(p for p in s["priors"][key]["parameters"] if p["parameter"] == "line_area")
        assert (prior["unit"], prior["unit_si"]) == ("cm^-2", "Hz/m")
        post = az.from_netcdf(out / f"posterior_{key}.nc").posterior["line_area"]
        assert (post.attrs["units"], post.attrs["units_sampled"]) == ("cm^-2", "Hz/m")
        assert post.attrs["prior_lower"] == 0.0 and post.attrs["prior_upper"] == np.inf
        # the draws are the sampler's, converted (R-hat and ESS do not change with the scale)
        run = res.runs[key]
        sampled = run.samples[..., run.names.index("line_area")]
        assert float(post.mean()) == pytest.approx(float(line_area_to_cm2(sampled.mean())), 1e-12)
        assert float(post.attrs["rhat"]) == pytest.approx(run.diagnostics["line_area"]["rhat"])
    # the posterior's A sits where budget.json's A is (the model average moves it by less than
    # its u; 3 u is a loose bound that a factor 1e4 c between the files would miss by far)
    # (SHORT fails its gates, so budget.json keeps A under unconverged_estimates)
    a = s["line_area"] or s["unconverged_estimates"]["line_area"]
    post = az.from_netcdf(out / "posterior_line.nc").posterior["line_area"]
    assert a["unit"] == "cm^-2" and abs(float(post.mean()) - a["value"]) < 3 * a["u"]
    inst = s["instrument"]
    assert inst and all("delta_a_cm2" in d for d in inst.values())
    assert "da_dt_cm2_per_k" in s["doppler_width"] and s["sensitivities_cm2"]


def test_flipping_a_prior_family_changes_the_sampler_and_the_outputs(bundle, monkeypatch):
    monkeypatch.setitem(H_PRIORS, "f_c_hz", replace(H_PRIORS["f_c_hz"], family="uniform"))
    res = run_budget(
        bundle, bundle.configs["D2"], SHORT.with_steps(20, 20), np.random.default_rng(1)
    )
    assert res.runs["h"].names[0] == "f_c_hz"  # the sampler now moves in f_c itself
    # budget.json's entry, the budget.md table made from it, and the netCDF attributes
    p = next(p for p in res.summary["priors"]["h"]["parameters"] if p["parameter"] == "f_c_hz")
    assert (p["family"], p["sampled_as"]) == ("uniform", "f_c_hz")
    assert "| f_c_hz | uniform |" in priors_markdown(res.summary["priors"])
    post = res.runs["h"].to_inference_data().posterior
    assert post["f_c_hz"].attrs["prior_family"] == "uniform"


def test_a_prior_that_cannot_be_sampled_is_refused():
    with pytest.raises(ValueError, match="not in"):
        Prior("f_hz", "normal", 1.0, 2.0, "Hz")  # no such family here
    with pytest.raises(ValueError, match="log-uniform needs"):
        Prior("f_hz", "log-uniform", 0.0, 1e6, "Hz")  # log 0
    with pytest.raises(ValueError, match="log-uniform needs"):
        Prior("f_hz", "log-uniform", 1.0, np.inf, "Hz")  # improper in log
    with pytest.raises(ValueError, match="lower < upper"):
        Prior("a", "uniform", 1.0, 1.0, "1")
