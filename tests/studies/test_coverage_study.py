"""Simulation-based calibration (issue #9): the budget's intervals cover the truth as often as they
claim.

The reduced study: 40 campaigns at small size, truths drawn per campaign, Laplace posterior,
run through the ``coverage`` study kind exactly as ``bayes-tfcrds study`` runs it.
"""

import json
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace

import numpy as np
import pytest

from bayes_tfcrds.inference.posteriors import H_PRIOR
from bayes_tfcrds.simulate.campaign import PRESETS, Campaign, simulate_campaign
from bayes_tfcrds.studies import coverage as cs
from bayes_tfcrds.studies.registry import run_study
from bayes_tfcrds.studies.spec import load_study

N = 40
STUDY = f"""
[study]
name = "coverage_test"
kind = "coverage"
seed = 11

[campaign]
presets = ["letter-D1", "letter-D2", "letter-D3", "letter-D4"]
campaigns = {N}
points = 21
samples = 4096
averages = 25

[analysis]
t_cut_us = 4
t_cuts_us = [4, 8]
posterior = "laplace"
"""


@pytest.fixture(scope="module")
def study_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("coverage")
    path = d / "coverage_test.toml"
    path.write_text(STUDY)
    html, pdf = run_study(path, d / "out")
    numbers = json.loads((d / "out" / "numbers.json").read_text())
    return load_study(path), d / "out", numbers, html, pdf


def test_drawn_simulator_is_the_campaign_simulator():
    # with the preset's own truth, the drawn-campaign simulator must give simulate_campaign's bytes:
    # same physics, same noise streams
    camp = replace(Campaign(), n_points=15, n_samples=1024, n_avg=2)
    for preset in ("letter-D2", "letter-D3"):
        b1, t1 = simulate_campaign([preset], np.random.default_rng(4), camp)
        b2, t2 = cs.simulate_draw(cs.preset_draw(preset, camp), np.random.default_rng(4), camp)
        c1, c2 = next(iter(b1.configs.values())), next(iter(b2.configs.values()))
        assert np.array_equal(c1.ringdowns.signal_v, c2.ringdowns.signal_v)
        assert np.array_equal(c1.transfer_function.b12_v, c2.transfer_function.b12_v)
        assert np.array_equal(c1.cmds.shift_hz, c2.cmds.shift_hz)
        assert t1["line"] == t2["line"]


def test_truths_lie_inside_the_analysis_priors():
    # flat priors: SBC then needs every truth inside their support (inference/posteriors.py bounds)
    rng = np.random.default_rng(0)
    d = cs.TruthDistribution()
    for _ in range(500):
        t = cs.draw_truth(rng, tuple(PRESETS), d)
        assert (
            0 <= t.gamma2_ratio <= 2 / 3 and t.nu_vc_ratio >= 0 and t.intensity_cm_per_molecule > 0
        )
        for name in ("f_c_hz", "a_r", "f_r_hz", "gamma_r"):
            lo, hi = H_PRIOR[name]
            assert lo < getattr(t.tf, name) < hi
        assert d.pressure_pa[0] <= t.pressure_pa <= d.pressure_pa[1]


def test_coverage_and_ranks_within_binomial_limits(study_run):
    _, _, numbers, _, _ = study_run
    recs = numbers["records"]
    assert numbers["n_ok"] == N and not numbers["failed"]
    # each coverage within 3 binomial sd of nominal: for n = 40, sd = 3.4 % (95 %) and 7.4 % (68 %);
    # 8 such checks at ~0.3 % false alarm each (normal approx.) keep the suite's false-fail rate ~2
    # %.
    # Ranks: chi-square over 5 bins (8 expected per bin) at alpha = 1 %.
    # every recorded quantity states the unit of its truth, estimate and u; A's is SI (the truth
    # in the bundle's /truth is Hz/m), S's cm/molecule like the drawn intensity
    assert set(numbers["units"]) == {q for r in recs for q in r["quantities"]} - {"S (U, MC)"}
    assert numbers["units"]["A"] == "Hz/m" and numbers["units"]["S (u_c)"] == "cm/molecule"
    for r in recs:  # the letter's lines: A ~ 4e5 Hz/m (1.3e-7 cm^-2: 3e12 times smaller)
        assert 1e3 < r["quantities"]["A"]["truth"] < 1e8
        s_true = r["quantities"]["S (u_c)"]["truth"]
        assert s_true == pytest.approx(r["draw"]["intensity_cm_per_molecule"], rel=1e-12)
    for q in cs.QUANTITIES:
        s = cs.summarise(recs, q, bins=5)
        assert s["n"] == N
        assert all(cs.check(s, k_sigma=3.0, alpha=0.01).values()), (q, s)
        # unbiased: the mean pull is within 3 standard errors (1/sqrt(n)) of zero
        assert abs(s["mean_pull"]) < 3 / np.sqrt(N), (q, s["mean_pull"])


def test_a_misstated_uncertainty_fails_the_check(study_run):
    _, _, numbers, _, _ = study_run
    recs = numbers["records"]
    for q in cs.QUANTITIES:
        # u x 0.5: the 95 % interval becomes +/-0.98 sigma and covers ~67 %, far below 95 - 3 x 3.4
        # %
        s = cs.summarise(recs, q, u_scale=0.5, bins=5)
        assert not cs.check(s)["coverage_95"], (q, s["coverage_95"])
        # u x 2: over-stated; the 68 % interval becomes +/-1.99 sigma (covers ~95 %, above 68 + 3 x
        # 7.4 %)
        # and the ranks pile up in the middle bins: at least one of the checks must fail
        assert not all(cs.check(cs.summarise(recs, q, u_scale=2.0, bins=5)).values()), q


def test_report_and_numbers(study_run):
    _, out, numbers, html, pdf = study_run
    text = html.read_text()
    for needle in ("Truth distribution", "Coverage", "Rank histograms", "Provenance", "binomial"):
        assert needle in text, needle
    assert pdf.stat().st_size > 5000
    assert len(list((out / "campaigns").glob("c*_laplace.json"))) == N
    a = numbers["summaries"]["A"]
    assert a["n"] == N and len(a["rank_counts"]) == 5 and sum(a["rank_counts"]) == N


def test_finished_campaigns_are_reused_and_workers_do_not_change_results(
    study_run, tmp_path, monkeypatch
):
    study, out, numbers, _, _ = study_run
    settings = cs.settings_of(study)
    by_index = {r["index"]: r for r in numbers["records"]}
    # two workers, fresh folder: the same records as the serial run
    with ProcessPoolExecutor(max_workers=2) as pool:
        recs = cs.run_campaigns(settings, [0, 1], tmp_path, pool=pool)
    for r in recs:
        assert {k: r[k] for k in ("draw", "quantities")} == {
            k: by_index[r["index"]][k] for k in ("draw", "quantities")
        }

    def boom(*a, **k):
        raise AssertionError("a finished campaign was run again")

    monkeypatch.setattr(cs, "run_campaign", boom)
    again = cs.campaign_task((settings, 3, str(out / "campaigns")))
    assert again["quantities"] == by_index[3]["quantities"]
    # other settings (a different seed): the stored record does not match and the campaign runs
    # again
    with pytest.raises(AssertionError, match="run again"):
        cs.campaign_task((replace(settings, seed=12), 3, str(out / "campaigns")))


def test_study_file_is_valid():
    from pathlib import Path

    root = Path(__file__).resolve().parents[2] / "studies"
    shipped = load_study(root / "coverage.toml")
    laplace = load_study(root / "coverage_laplace.toml")
    # the committed coverage report calibrates what budget ships (emcee, its default first
    # length); the Laplace study analyses the very same campaigns
    from bayes_tfcrds.uncertainty.line_budget import BudgetOptions

    assert shipped.kind == "coverage" and shipped.n_campaigns >= 200
    assert shipped.posterior == "mcmc" and shipped.mcmc_steps == BudgetOptions().n_steps
    assert laplace.posterior == "laplace" and laplace.mcmc_campaigns == 0
    same = ("seed", "n_campaigns", "presets", "chain_kinds", "noise_kinds", "points", "samples")
    assert all(getattr(shipped, k) == getattr(laplace, k) for k in same)


def test_calibration_draws_temperature_and_the_gauges_reading_errors():
    """T over 280-310 K; the pressure reading error is N(0, u(p)^2) and the temperature's is
    rectangular with sd u(T) (its half-width sqrt(3) u(T) never exceeded). 4000 draws: the sd
    of the sample sd is about 1.1 % (normal) and 0.7 % (rectangular), so 5 % bounds cannot fail
    by chance and fail if either error is dropped or mis-scaled by sqrt(3)."""
    rng = np.random.default_rng(1)
    camp = Campaign()
    draws = [cs.draw_truth(rng, tuple(PRESETS), cs.TruthDistribution(), camp) for _ in range(4000)]
    t = np.array([d.temperature_k for d in draws])
    dp = np.array([d.pressure_error_pa for d in draws])
    dt = np.array([d.temperature_error_k for d in draws])
    assert 280.0 <= t.min() and t.max() <= 310.0 and np.ptp(t) > 25.0
    assert np.std(dp) == pytest.approx(camp.pressure_u_pa, rel=0.05)
    assert np.std(dt) == pytest.approx(camp.temperature_u_k, rel=0.05)
    assert np.max(np.abs(dt)) <= np.sqrt(3.0) * camp.temperature_u_k


def test_the_bundle_reports_the_gauges_readings_and_the_truth_the_gas():
    """A campaign with reading errors: /sample holds p + dp and T + dT, the truth the gas's own
    p and T, and the simulated line (its area) follows the gas, not the readings."""
    camp = replace(Campaign(), n_points=11, pressure_error_pa=0.5, temperature_error_k=0.04)
    hot = replace(camp, temperature_k=305.0)
    b, truth = simulate_campaign(["letter-D1"], np.random.default_rng(2), hot)
    assert b.sample.pressure_pa == pytest.approx(hot.pressure_pa + 0.5, rel=1e-15)
    assert b.sample.temperature_k == pytest.approx(305.04, rel=1e-15)
    assert truth["sample"] == {"pressure_pa": hot.pressure_pa, "temperature_k": 305.0}
    _, exact = simulate_campaign(
        ["letter-D1"],
        np.random.default_rng(2),
        replace(hot, pressure_error_pa=0.0, temperature_error_k=0.0),
    )
    assert truth["line"]["line_area_hz_per_m"] == exact["line"]["line_area_hz_per_m"]


def test_the_study_file_has_the_chain_and_noise_strata():
    from pathlib import Path

    s = load_study(Path(__file__).resolve().parents[2] / "studies" / "coverage.toml")
    assert s.chain_kinds == ("preset", "zoo") and s.noise_kinds == ("white", "coloured")
    settings = cs.settings_of(s)
    assert settings.strata == [
        ("preset", "white"),
        ("preset", "coloured"),
        ("zoo", "white"),
        ("zoo", "coloured"),
    ]


def test_strata_draw_zoo_chains_and_coloured_noise_and_leave_the_rest_as_drawn():
    settings = cs.CoverageSettings(
        seed=3,
        campaign=Campaign(),
        options=None,
        presets=tuple(PRESETS),
        chains=("preset", "zoo"),
        noises=("white", "coloured"),
    )
    kinds = {"preset": 0, "zoo": 0}
    for i in range(40):
        draw, _, _ = settings.draw(i)
        chain, noise = settings.strata[i % 4]
        assert draw.chain.startswith(chain)
        assert draw.noise.is_white == (noise == "white")
        assert draw.stratum["chain"] == ("zoo" if chain == "zoo" else cs.PRESET_REGIME[draw.preset])
        kinds[chain] += 1
        # the stratum's own draws come last: the line, p, T, noise level are those of the plain draw
        ss = np.random.SeedSequence(3, spawn_key=(i,))
        plain = cs.draw_truth(np.random.default_rng(ss.spawn(3)[0]), tuple(PRESETS))
        assert (draw.pressure_pa, draw.temperature_k, draw.noise_v) == (
            plain.pressure_pa,
            plain.temperature_k,
            plain.noise_v,
        )
        if chain == "preset":
            assert draw.tf == plain.tf
        else:
            assert draw.tf != plain.tf
    assert kinds == {"preset": 20, "zoo": 20}
    with pytest.raises(ValueError, match="chain kind"):
        cs.draw_truth(np.random.default_rng(0), tuple(PRESETS), chain_kind="other")


def test_a_stratum_out_of_its_binomial_band_is_flagged():
    def rec(pull, stratum):
        q = {k: {"pull": pull} for k in cs.STRATUM_QUANTITIES}
        return {"status": "ok", "stratum": stratum, "quantities": q}

    good = {"chain": "zoo", "noise": "white"}
    bad = {"chain": "zoo", "noise": "coloured"}
    rng = np.random.default_rng(2)
    # 400 campaigns each: N(0, 1) pulls are in band; pulls of sd 2 cover ~62 % at 95 %, far out
    recs = [rec(float(p), good) for p in rng.standard_normal(400)]
    recs += [rec(float(p), bad) for p in 2.0 * rng.standard_normal(400)]
    rows = {r["stratum"]: r for r in cs.strata_table(recs)}
    assert rows["zoo, white noise"]["quantities"]["A"]["in_band_95"]
    assert not rows["zoo, coloured noise"]["quantities"]["A"]["in_band_95"]
    assert rows["zoo, coloured noise"]["campaigns"] == 400


@pytest.mark.parametrize("p, n", [(0.95, 33), (0.68, 33), (0.95, 200), (0.68, 50)])
def test_the_chance_of_a_band_exit_is_the_simulated_one(p, n):
    # independent check: calibrated coverages simulated as Binomial(n, p) counts; 200 000 draws
    # give the exit rate to +/- 0.001 (1 sd), so 0.004 is a 4-sigma tolerance
    hits = np.random.default_rng(5).binomial(n, p, 200_000)
    simulated = np.mean(~np.array([cs.in_band(h / n, p, n) for h in range(n + 1)])[hits])
    assert abs(cs.chance_exit(p, n) - simulated) < 0.004
    assert 0.0 < cs.chance_exit(p, n) < 0.1  # a two-sigma band: a few per cent exit by chance


def test_band_exits_are_counted_against_chance():
    rng = np.random.default_rng(3)

    def table(sd):
        recs = [
            {
                "status": "ok",
                "stratum": {"chain": c, "noise": nz},
                "quantities": {
                    k: {"pull": float(sd * rng.standard_normal())} for k in cs.STRATUM_QUANTITIES
                },
            }
            for c in ("preset", "zoo")
            for nz in ("white", "coloured")
            for _ in range(50)
        ]
        return cs.band_exits(cs.strata_table(recs))

    calibrated, wide = table(1.0), table(2.0)
    assert calibrated["tests"] == 4 * len(cs.STRATUM_QUANTITIES) * 2
    # 40 tests at ~3-6 % each: about 2 exits expected, and a calibrated table is not surprising
    assert 1.0 < calibrated["expected"] < 3.0 and calibrated["p_value"] > 0.01
    # pulls twice too wide leave nearly every band, which chance cannot explain
    assert wide["observed"] > 30 and wide["p_value"] < 1e-10


def test_strata_keys_are_refused_outside_a_coverage_study(tmp_path):
    from bayes_tfcrds.studies.spec import StudyError

    bad = tmp_path / "bad.toml"
    bad.write_text('[study]\nname = "x"\nkind = "tcut"\n[campaign]\nchains = ["zoo"]\n')
    with pytest.raises(StudyError, match="coverage"):
        load_study(bad)
    bad.write_text('[study]\nname = "x"\nkind = "coverage"\n[campaign]\nnoise = ["pink"]\n')
    with pytest.raises(StudyError, match="noise"):
        load_study(bad)


def test_an_f_c_the_budget_calls_not_identified_is_left_out_of_its_coverage_only():
    # 60 campaigns with calibrated pulls, and 6 where the budget reported f_c as not identified
    # and the reported description sits 800 u from the truth's (a label switch)
    rng = np.random.default_rng(4)

    def rec(i, identified):
        q = {k: {"pull": float(rng.standard_normal()), "cdf": 0.5} for k in cs.QUANTITIES}
        if not identified:
            q["f_c"].update(
                pull=800.0,
                cdf=1.0,
                identified=False,
                truth_in_a_description=True,
                truth=2.87e6,
                estimate=8.6e4,
                descriptions_f_c_hz=[2.87e6],
            )
        return {
            "index": i,
            "status": "ok",
            "stratum": {"chain": "zoo", "noise": "white"},
            "quantities": q,
        }

    recs = [rec(i, i % 10 != 3) for i in range(60)]
    assert cs.summarise(recs, "f_c")["n"] == 54 and cs.summarise(recs, "A")["n"] == 60
    assert cs.summarise(recs, "f_c")["sd_pull"] < 2  # the 800 u pulls are not in it
    row = cs.strata_table(recs)[0]["quantities"]
    assert row["f_c"]["n"] == 54 and row["A"]["n"] == 60
    assert not cs.counted(recs[3], "f_c") and cs.counted(recs[3], "A")
    assert cs.counted(recs[4], "f_c")  # a record without the flag (identified) counts

    class Rep:  # the report's calls, recorded
        def __init__(self):
            self.calls = []

        def add_summary(self, *a):
            self.calls.append(a)

        def add_table(self, *a, **k):
            self.calls.append(a)

    rep = Rep()
    got = cs._not_identified_report(recs, rep)
    assert got["campaigns"] == [3, 13, 23, 33, 43, 53] and got["truth_in_a_description"] == 6
    # the unconditional coverage is given too: the six 800 u pulls are misses in it
    every = got["f_c_all_campaigns"]
    assert every["n"] == 60 and every["coverage_95"] <= 54 / 60
    assert "6 of 60 campaigns" in rep.calls[0][1]


def test_the_truth_of_an_unidentified_f_c_is_looked_for_in_every_description():
    from bayes_tfcrds.fit.h_identification import HDescription, HIdentification
    from bayes_tfcrds.physics.transfer_function import TFParams

    names = ("f_c_hz", "a_r", "f_r_hz", "gamma_r")
    twin = HDescription(TFParams(2.87e6, 0.026, 5e5, 0.17), 0.1, (0.05, 0.01, 2.0, 2.0), names)
    ident = HIdentification(names, TFParams(8.6e4, 37.0, 4e8, 0.007), 4.0, (twin,), names[:2])
    entry = {"pull": 846.0}  # the reported f_c, 86 kHz, against a truth of 2.87 MHz
    got = cs._f_c_identification(ident, 2.866e6, entry)
    assert got == {
        "identified": False,
        "descriptions_f_c_hz": [2.87e6],
        "truth_in_a_description": True,
    }
    # a truth 20 % from the twin is 4 of its u (5 % in log f_c) away: in no description
    assert not cs._f_c_identification(ident, 2.87e6 * 1.2, entry)["truth_in_a_description"]
    assert cs._f_c_identification(None, 2.866e6, entry) == {"identified": True}
