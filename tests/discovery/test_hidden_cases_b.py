"""The physics of family B's hidden effects (tests/discovery/hidden_cases_b.py), against
independent references: hitran-api's profiles, closed forms and limits; and discovery on a few of
them (the full confusion study is benchmarks/discovery_confusion.py).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy import integrate, signal

from bayes_tfcrds.bundle.reader import validate_file
from bayes_tfcrds.bundle.writer import save_bundle
from bayes_tfcrds.discovery.workflow import discover
from bayes_tfcrds.simulate.campaign import Campaign
from tests.discovery import hidden_cases_b as hb

hapi = pytest.importorskip("hapi")

C_CM = 2.99792458e10  # cm/s: Hz -> cm^-1 for hapi
DOP, G0, D0 = 2.3e8, 1.0e7, -1.6e6  # Hz: the reduced campaign's line at 5 Torr, roughly
DET = np.linspace(-3e9, 3e9, 41)
SMALL = replace(Campaign(), n_points=8, n_samples=1024, n_avg=10)


def _hapi_qsd(det, gamma0, delta0, gamma2, delta2):
    """hitran-api's quadratic speed-dependent profile (complex, 1/Hz) at detunings ``det`` (Hz).

    One detuning per call: hapi 1.3's vectorised branches mis-index mixed arrays when Gamma2 is
    large.
    """
    out = []
    for d in np.atleast_1d(det):
        re, im = hapi.pcqsdhc(
            0.0,
            DOP / C_CM,
            gamma0 / C_CM,
            gamma2 / C_CM,
            delta0 / C_CM,
            delta2 / C_CM,
            0.0,
            0.0,
            np.array([d / C_CM]),
        )
        out.append((float(np.ravel(re)[0]) + 1j * float(np.ravel(im)[0])) / C_CM)
    return np.array(out)


def test_voigt_matches_hitran_api():
    # both evaluate the Faddeeva function (scipy's wofz and hapi's CPF): 5e-11 apart measured
    g = hb.voigt_complex(DET - D0, G0, DOP)
    ref = _hapi_qsd(DET, G0, D0, 0.0, 0.0)
    assert np.max(np.abs(g - ref)) < 1e-8 * np.max(np.abs(ref))


def test_power_law_speed_dependence_has_the_quadratic_and_voigt_limits():
    # m = 0: no speed dependence, the Voigt profile (Simpson over speeds, error ~1e-12)
    v = hb.voigt_complex(DET - D0, G0, DOP)
    s0 = hb.speed_dependent_complex(DET, G0, D0, DOP, 0.0)
    assert np.max(np.abs(s0 - v)) < 1e-8 * np.max(np.abs(v))
    # m = 2: Gamma(v) = Gamma0 x^2 / <x^2> = Gamma0 + (2/3) Gamma0 (x^2 - 3/2), hapi's qSDV with
    # Gamma2 = 2 Gamma0 / 3 (and likewise the shift): an independent evaluation of the same profile
    s2 = hb.speed_dependent_complex(DET, G0, D0, DOP, 2.0)
    ref = _hapi_qsd(DET, G0, D0, 2 * G0 / 3, 2 * D0 / 3)
    # 2.6e-9 measured, hapi's own level (its CPF approximations, ~1e-8)
    assert np.max(np.abs(s2 - ref)) < 1e-7 * np.max(np.abs(ref)), np.max(np.abs(s2 - ref))
    # speed dependence narrows the line: the peak rises above the Voigt's
    s = hb.speed_dependent_complex(np.array([D0]), G0, D0, DOP, 0.35)
    assert s.real[0] > hb.voigt_complex(np.array([0.0]), G0, DOP).real[0]


def test_galatry_has_the_voigt_and_dicke_limits():
    v = hb.voigt_complex(DET - D0, G0, DOP)
    g0 = hb.galatry_complex(DET, G0, D0, DOP, 0.0)
    assert np.max(np.abs(g0 - v)) < 1e-5 * np.max(np.abs(v))  # quadrature: 2e-7 measured
    # strong collisions (beta >> k v_p): the Doppler part becomes a Lorentzian of HWHM
    # (k v_p)^2 / (2 beta) rad/s (Dicke narrowing); corrections are O(k v_p / beta) = 1 %
    kvp = 2 * np.pi * DOP / np.sqrt(np.log(2.0))
    beta = 100 * kvp
    hw = G0 + kvp**2 / (2 * beta) / (2 * np.pi)
    gd = hb.galatry_complex(np.array([D0]), G0, D0, DOP, beta)
    assert abs(gd.real[0] * np.pi * hw - 1.0) < 0.02
    # unit area (the Lorentz wings beyond +/- 5 GHz hold 2 Gamma0 / (pi 5 GHz) = 0.13 %)
    d = np.linspace(-5e9, 5e9, 1001)
    area = integrate.trapezoid(hb.galatry_complex(d, G0, D0, DOP, 2 * np.pi * 4.6e6).real, d)
    assert abs(area - (1 - 2 * G0 / (np.pi * 5e9))) < 2e-4


def test_chain_is_the_letters_eq2_and_its_time_response_is_the_forced_one():
    f = np.geomspace(1e3, 4e7, 50)
    c = hb.CHAIN
    eq2 = (
        1 / (1 + 1j * f / c["f_c_hz"])
        + c["a_r"] / (1 - (f / c["f_r_hz"]) ** 2 + 1j * f / (c["q"] * c["f_r_hz"]))
    ) / (1 + c["a_r"])
    _, h = signal.freqs(*hb.chain_tf(), worN=2 * np.pi * f)
    assert np.max(np.abs(h - eq2)) < 1e-12
    # late in a ring-down the output is H(s = -1/tau) exp(-t/tau): the chain's own poles (the
    # slowest, 150 kHz at Q 0.7, decays in 1.5 us) have died away after 60 us
    t = -2e-6 + 20e-9 * np.arange(4096)
    tau = np.array([8e-6, 30e-6])
    y = hb.chain_response(t, tau)
    late = t > 60e-6
    h_tau = np.polyval(hb.chain_tf()[0], -1 / tau) / np.polyval(hb.chain_tf()[1], -1 / tau)
    ratio = y[:, late] / np.exp(-t[late][None, :] / tau[:, None])
    assert np.allclose(ratio, h_tau[:, None], rtol=1e-6), (ratio[:, -1], h_tau)
    assert np.allclose(y[:, t < 0], 1.0)


def test_cavity_build_up_matches_the_closed_form_for_an_exponential_leak():
    # g = eps exp(-t/t_x): P = exp(-t/tau) + eps t_x/(t_x - tau) (exp(-t/t_x) - exp(-t/tau))
    t = -2e-6 + 20e-9 * np.arange(4096)
    tau, tx, eps = np.array([20e-6]), 10e-6, 2e-3
    g = eps * np.exp(-np.clip(t, 0, None) / tx) * (t >= 0)
    p = hb.cavity_fed_by(t, tau, g)[0]
    tp = np.clip(t, 0, None)
    exact = np.exp(-tp / tau[0]) + eps * tx / (tx - tau[0]) * (
        np.exp(-tp / tx) - np.exp(-tp / tau[0])
    )
    # trapezoid rule at 20 ns steps on a 10 us exponential: (dt/t_x)^2/12 of the leak, 3e-10
    assert np.max(np.abs(p - exact)) < 1e-8


@pytest.mark.parametrize("name", list(hb.HIDDEN_CASES_B))
def test_each_builder_changes_what_its_effect_changes(name, tmp_path):
    builder, _ = hb.HIDDEN_CASES_B[name]
    bundle, _ = builder(np.random.default_rng(3), SMALL)
    base, _ = hb.nothing(np.random.default_rng(3), SMALL)
    save_bundle(bundle, tmp_path / "b.h5")
    _, errors, _ = validate_file(tmp_path / "b.h5")
    assert errors == [], (name, errors)
    cfg, ref = bundle.configs[hb.CONFIG], base.configs[hb.CONFIG]
    t = cfg.ringdowns.time_s
    d_sig = cfg.ringdowns.signal_v - ref.ringdowns.signal_v
    assert bundle.sample.temperature_k == hb.TEMPERATURE_K
    if name in ("transfer_function", "window_history", "static_nonlinearity"):
        # the detector acts on the beat note too
        assert not np.allclose(cfg.transfer_function.h_mag, ref.transfer_function.h_mag)
    else:
        assert np.array_equal(cfg.transfer_function.b12_v, ref.transfer_function.b12_v)
    spectral = ("speed_dependence", "hard_collisions", "etalon", "neighbour_line")
    moves_cmds = ("speed_dependence", "hard_collisions", "neighbour_line")
    assert np.array_equal(cfg.cmds.shift_hz, ref.cmds.shift_hz) == (name not in moves_cmds)
    # every effect acts after extinction; before it only the saturating detector does
    assert np.any(np.abs(d_sig[:, t > 2e-6]) > 1e-6), name
    if name not in ("static_nonlinearity",):
        assert np.allclose(d_sig[:, t < 0], 0.0, atol=1e-12), name
    if name in spectral:
        # a change of loss only: each record stays one exponential at its new tau
        assert np.all(np.abs(d_sig[:, t < 0]) < 1e-12)


@pytest.mark.slow
@pytest.mark.parametrize(
    ("name", "seed", "right"),
    [
        ("static_nonlinearity", 21, ["static_nonlinearity"]),
        ("etalon", 21, ["etalon"]),
        ("second_mode", 11, ["second_mode"]),
        ("transfer_function", [2, 11], ["transfer_function", "window_history"]),
    ],
)
def test_discovery_names_an_effect_written_in_another_form(name, seed, right):
    # second_mode on seed 11: the mode sees the line 61 MHz away, which the family's detuned
    # member describes (an AC-coupled amplifier, the nearest other candidate, leaves decay times
    # that no longer make a line; the misfit left in all the data settles it); the chain: an Eq. 2
    # chain of the other regime needs H and the extinction window, and nothing else (a veto on
    # worsening the CMDS gap had rejected H, which moves A away from CMDS until the window
    # follows)
    builder, start = hb.HIDDEN_CASES_B[name]
    camp = replace(Campaign(), n_points=21, n_samples=4096)
    bundle, _ = builder(np.random.default_rng(seed), camp)
    res = discover(bundle, hb.CONFIG, start, rng=np.random.default_rng(seed))
    assert res.effects_added == right, res.effects_added  # named, nothing spurious
    if name == "second_mode":
        # named by the family's detuned member, at the mode's offset (61 MHz above TEM00)
        p = res.steps[0]["params"]
        assert "detuning_hz" in p, res.steps[0]["form"]
        assert abs(p["detuning_hz"]["value"] - 61e6) < 4 * p["detuning_hz"]["u"], p


@pytest.mark.slow
@pytest.mark.parametrize("name", ["speed_dependence", "hard_collisions"])
def test_line_shape_written_in_another_form_is_named(name):
    # the power law (width and shift ~ v^m) is named by the family's power-law member, with m and
    # the shift's speed dependence recovered; the soft collisions are named too, but in the
    # Doppler regime a quadratic speed dependence gives the same profile to < 1e-6 of its peak,
    # so the step names both (Delta BIC < 2) and nothing else is added
    builder, start = hb.HIDDEN_CASES_B[name]
    camp = replace(Campaign(), n_points=21, n_samples=4096)
    bundle, truth = builder(np.random.default_rng([2, 11]), camp)
    res = discover(bundle, hb.CONFIG, start, rng=np.random.default_rng(11))
    assert len(res.steps) == 1, res.effects_added
    step = res.steps[0]
    named = {step["effect"], *(a["effect"] for a in step["alternatives"])}
    if name == "speed_dependence":
        assert step["effect"] == name and step["form"] == "power law v^m", step["form"]
        assert not step["alternatives"]
        p = step["params"]
        assert abs(p["sd_exponent"]["value"] - 0.2) < 4 * p["sd_exponent"]["u"], p
        d0 = truth["line"]["delta0_hz"]
        assert abs(p["delta_sd_hz"]["value"] - d0) < 4 * p["delta_sd_hz"]["u"], (p, d0)
    else:
        assert named == {"hard_collisions", "speed_dependence"}, step
    assert not res.unexplained, res.stop_reason
