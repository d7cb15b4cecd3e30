"""Tests of the shipped line data and its conversion to SI."""

from __future__ import annotations

import dataclasses
import tomllib
from importlib import resources

import numpy as np
import pytest

from bayes_tfcrds.core.constants import ATM, TORR
from bayes_tfcrds.physics import linedata
from bayes_tfcrds.physics.linedata import LineData, available_lines, load_line
from bayes_tfcrds.physics.lineshape import SHAPE_PARAMETERS, profile

FILE = "co_3-0_R23.toml"


def _raw():
    text = resources.files("bayes_tfcrds").joinpath("data", FILE).read_text(encoding="utf-8")
    return tomllib.loads(text)


def test_file_parses_and_every_number_is_cited():
    raw = _raw()
    assert raw["name"] == "CO (3-0) R(23)"
    numeric = [
        k
        for k, v in raw.items()
        if isinstance(v, (int, float)) and not isinstance(v, bool) and k != "schema"
    ]
    assert len(numeric) >= 15
    for key in numeric:
        entry = raw["sources"][key]
        assert isinstance(entry["estimate"], bool)
        assert len(entry["reference"]) > 40, key  # a real citation, not a stub
    # the measured core of the line is not an estimate; the guessed parts say so
    for key in ("nu0_cm", "intensity_cm_per_molecule", "gamma0_self_cm_per_atm", "mass_u"):
        assert raw["sources"][key]["estimate"] is False
    for key in ("gamma2_ratio", "nu_vc_self_cm_per_atm", "delta0_self_cm_per_atm"):
        assert raw["sources"][key]["estimate"] is True
    # position near 6410.88 cm^-1 and the HITRAN and letter intensities agree to < 0.5 %
    assert raw["nu0_cm"] == pytest.approx(6410.88, abs=0.01)
    assert raw["intensity_cm_per_molecule"] == pytest.approx(
        raw["hitran_intensity_cm_per_molecule"], rel=5e-3
    )


def test_intensity_is_the_letters_value():
    # Cygan et al., Sci. Adv. 11, eadp8556 (2025): S = 8.0603(70)e-25 cm/molecule at 296 K
    line = load_line()
    assert line.intensity_cm_per_molecule == 8.0603e-25
    assert line.intensity_u_cm_per_molecule == pytest.approx(7.0e-28, rel=1e-12)
    assert line.temperature_k == 296.0
    assert line.mass_u == pytest.approx(27.9949, abs=1e-4)


def test_unit_conversions_by_hand():
    line = load_line("CO (3-0) R(23)")
    # 6410.879558 cm^-1 * 29 979 245 800 cm/s = 1.921933340635e14 Hz
    assert line.nu0_hz == pytest.approx(1.921933340635e14, rel=1e-12)
    # 0.051 cm^-1/atm = 0.051 * 2.99792458e10 Hz / 101325 Pa = 15 089.48 Hz/Pa
    assert line.gamma0_hz_per_pa == pytest.approx(15089.48, rel=1e-6)
    # -0.0080 cm^-1/atm = -2366.98 Hz/Pa; 0.0483 cm^-1/atm = 14 290.62 Hz/Pa
    assert line.delta0_hz_per_pa == pytest.approx(-2366.98, rel=1e-5)
    assert line.gamma0_air_hz_per_pa == pytest.approx(14290.62, rel=1e-6)
    # 1e-4 cm^-1 = 2.998 MHz
    assert line.nu0_u_hz == pytest.approx(2.99792458e6, rel=1e-12)
    # and the generic rule: value_Hz_per_Pa = value_cm_per_atm * 100 c / 101325
    raw = _raw()
    assert line.nu_vc_hz_per_pa == pytest.approx(
        raw["nu_vc_self_cm_per_atm"] * 2.99792458e10 / 101325.0, rel=1e-14
    )


def test_shape_at_pure_and_mixed():
    line = load_line()
    p = 10.0 * TORR
    shape = line.shape_at(p, 296.0)
    assert tuple(shape) == SHAPE_PARAMETERS
    # pure CO at 10 Torr: Gamma0 = 0.051 cm^-1/atm * (10/760) atm = 6.71e-4 cm^-1 = 20.12 MHz
    assert shape["gamma0_hz"] == pytest.approx(0.051 * 10.0 / 760.0 * 2.99792458e10, rel=1e-12)
    assert shape["gamma0_hz"] == pytest.approx(20.12e6, rel=1e-3)
    assert shape["gamma2_hz"] == pytest.approx(line.gamma2_ratio * shape["gamma0_hz"])
    assert shape["delta2_hz"] == pytest.approx(line.delta2_ratio * shape["delta0_hz"])
    assert shape["nu_vc_hz"] == pytest.approx(line.nu_vc_hz_per_pa * p)
    # half CO in air at 1 atm and 296 K: the average of the self and air coefficients
    mixed = line.shape_at(ATM, 296.0, 0.5)
    assert mixed["gamma0_hz"] == pytest.approx(
        0.5 * ATM * (line.gamma0_hz_per_pa + line.gamma0_air_hz_per_pa), rel=1e-14
    )
    # only the air width has a temperature exponent: (296/T)^0.67
    hot = line.shape_at(ATM, 350.0, 0.0)
    assert hot["gamma0_hz"] == pytest.approx(
        ATM * line.gamma0_air_hz_per_pa * (296.0 / 350.0) ** 0.67, rel=1e-14
    )
    assert line.shape_at(ATM, 350.0, 1.0)["gamma0_hz"] == pytest.approx(
        ATM * line.gamma0_hz_per_pa, rel=1e-14
    )
    # broadcasting over pressure
    arr = line.shape_at(np.array([1.0, 2.0]) * TORR, 296.0)
    assert arr["gamma0_hz"].shape == (2,)
    for bad in ((-1.0, 296.0, 1.0), (TORR, 0.0, 1.0), (TORR, 296.0, 1.5)):
        with pytest.raises(ValueError):
            line.shape_at(*bad)


def test_shape_feeds_the_profile():
    # The parameters drive the qSDHC profile directly. With Delta2 = 0 the profile is
    # symmetric about nu0 + Delta0, so its maximum sits there (to the 2.2 kHz grid step).
    line = load_line()
    gd = line.doppler_hwhm_hz(296.0)
    assert gd == pytest.approx(223.8e6, rel=1e-3)
    shape = line.shape_at(5.0 * TORR, 296.0)
    centre = line.nu0_hz + shape["delta0_hz"]
    fine = centre + np.linspace(-0.01, 0.01, 2001) * gd
    g = profile("qsdhcp", fine, line.nu0_hz, gd, **shape)
    assert abs(fine[np.argmax(g.real)] - centre) <= 2.3e3
    # Normalised: Riemann sum over +-50 GammaD (step 5e-4 GammaD, far below every width)
    # plus the analytic Lorentzian wings beyond, 2 Gamma0/(pi L) ~ 6e-4; what is left is
    # the O(GammaD^2/L^2) correction to those wings, ~2e-7 of the area.
    half = 50.0 * gd
    nu = line.nu0_hz + np.linspace(-half, half, 200001)
    g = profile("qsdhcp", nu, line.nu0_hz, gd, **shape)
    assert np.all(np.isfinite(g)) and np.all(g.real > 0)
    wings = 2.0 * shape["gamma0_hz"] / (np.pi * half)
    assert np.sum(g.real) * (nu[1] - nu[0]) + wings == pytest.approx(1.0, abs=1e-5)


def test_line_data_is_frozen_and_lookup_is_strict():
    line = load_line()
    assert isinstance(line, LineData)
    assert "CO (3-0) R(23)" in available_lines()
    with pytest.raises(dataclasses.FrozenInstanceError):
        line.nu0_hz = 0.0
    with pytest.raises(TypeError):
        line.sources["nu0_cm"] = None
    assert set(line.estimates) == {k for k, v in _raw()["sources"].items() if v["estimate"]}
    with pytest.raises(ValueError, match="available"):
        load_line("CO (2-0) R(0)")


def test_parser_rejects_uncited_numbers():
    text = resources.files("bayes_tfcrds").joinpath("data", FILE).read_text(encoding="utf-8")
    bad = text.replace("gamma2_ratio = 0.10", "gamma2_ratio = 0.10\nmystery_number = 1.0")
    with pytest.raises(ValueError, match="mystery_number"):
        linedata._parse(bad, "test")
    with pytest.raises(ValueError, match="missing"):
        linedata._parse(text.replace("nu0_cm = 6410.879558", ""), "test")
