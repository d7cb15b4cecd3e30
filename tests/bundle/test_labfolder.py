"""Lab folders (lab.toml + CSV/TSV/NPY/NPZ) -> bundles, and the bundle's dimension scales.

The done-when of issue 18: a lab folder written from a simulated bundle imports back to the
same numbers (to the two roundings of the unit conversion) and gives the same fit and line fit.
Unit conversions are checked against values fixed by definition (760 Torr = 1 atm, 0 degC =
273.15 K, 1 cm^-1 = 29.9792458 GHz), not against the module's own tables.
"""

from __future__ import annotations

import dataclasses
import shutil

import h5py
import numpy as np
import pytest

from bayes_tfcrds.bundle.labfolder import (
    LabFolderError,
    read_lab_folder,
    read_lab_spectrum,
    write_lab_folder,
)
from bayes_tfcrds.bundle.reader import load_bundle, validate_file
from bayes_tfcrds.bundle.records import Bundle
from bayes_tfcrds.bundle.writer import save_bundle
from bayes_tfcrds.core.constants import C
from bayes_tfcrds.fit.h_calibration import fit_config
from bayes_tfcrds.fit.line_analysis import SPECTRUM_LEVEL, analyse_line, analyse_spectrum
from bayes_tfcrds.simulate.campaign import Campaign, simulate_campaign

#: each imported value went through two roundings (SI -> lab unit on writing, back on reading),
#: each at most half an ulp (1.1e-16 relative): 4.5e-16 bounds both with margin
TWO_ROUNDINGS = 4.5e-16


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    """A small simulated campaign (12 modes x 4096 samples, D2), written as a lab folder."""
    campaign = Campaign(n_points=12, n_samples=4096)
    bundle, _ = simulate_campaign(["letter-D2"], np.random.default_rng(5), campaign)
    folder = tmp_path_factory.mktemp("lab")
    write_lab_folder(bundle, folder)
    return bundle, folder


def _assert_same_record(a, b):
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if x is None or isinstance(x, str):
            assert y == x, f.name
        else:
            np.testing.assert_allclose(y, x, rtol=TWO_ROUNDINGS, atol=0, err_msg=f.name)


def test_lab_folder_gives_back_the_bundle_it_came_from(source):
    bundle, folder = source
    back = read_lab_folder(folder)
    _assert_same_record(back.sample, bundle.sample)
    _assert_same_record(back.cavity, bundle.cavity)
    assert list(back.configs) == list(bundle.configs) and back.description == bundle.description
    for name, cfg in bundle.configs.items():
        got = back.configs[name]
        assert got.description == cfg.description
        for part in ("ringdowns", "transfer_function", "cmds"):
            _assert_same_record(getattr(got, part), getattr(cfg, part))


def test_lab_folder_gives_the_same_fit_and_line_fit(source):
    bundle, folder = source
    back = read_lab_folder(folder)
    (name,) = bundle.configs
    a = fit_config(bundle.configs[name], [4e-6], method="crds")
    b = fit_config(back.configs[name], [4e-6], method="crds")
    # inputs equal to 4.5e-16: a least-squares fit stopped at 1e-13 (xtol) moves far less
    # than 1e-9 of tau; a unit slip (1e-3, 1e-6) is far outside
    np.testing.assert_allclose(b.tau_s, a.tau_s, rtol=1e-9)
    la = analyse_line(bundle, bundle.configs[name], method="tf-crds", profile_name="voigt")
    lb = analyse_line(back, back.configs[name], method="tf-crds", profile_name="voigt")
    # A and A/A_ref equal to 1e-8 relative: the fits' stopping rules (xtol, ftol 1e-13, and the
    # beat-note and refinement fits before them) turn input changes of 4.5e-16 into ~1e-10
    # (measured 1.4e-10); a unit slip would move A by orders of magnitude
    assert lb.line_fit.line_area == pytest.approx(la.line_fit.line_area, rel=1e-8)
    assert lb.line_fit.line_area_u == pytest.approx(la.line_fit.line_area_u, rel=1e-6)
    assert lb.ratio.value == pytest.approx(la.ratio.value, rel=1e-8)


def test_units_convert_to_si_by_their_definitions(tmp_path, source):
    bundle, folder = source
    lab = tmp_path / "lab"
    shutil.copytree(folder, lab)
    text = (lab / "lab.toml").read_text()
    start, end = text.index("[sample]"), text.index("[configs.")
    new = (
        '[sample]\nmolecule = "CO"\nline = "R(23)"\nnu0 = "6400 cm^-1"\npressure = "760 Torr"\n'
        'pressure_u = "1 hPa"\ntemperature = "0 degC"\ntemperature_u = "0.5 degC"\n'
        'mole_fraction = "5 %"\nmass = "28 u"\n\n[cavity]\nlength = "60 cm"\n\n'
    )
    (lab / "lab.toml").write_text(text[:start] + new + text[end:])
    got = read_lab_folder(lab)
    s = got.sample
    assert s.nu0_hz == pytest.approx(6400 * 29.9792458e9, rel=1e-15)  # 1 cm^-1 = c x 100 /m
    assert s.pressure_pa == pytest.approx(101325.0, rel=1e-15)  # 760 Torr = 1 atm exactly
    assert s.pressure_u_pa == pytest.approx(100.0, rel=1e-15)
    assert s.temperature_k == pytest.approx(273.15, rel=1e-15)
    assert s.temperature_u_k == pytest.approx(0.5, rel=1e-15)  # a difference: no offset
    assert s.mole_fraction == pytest.approx(0.05, rel=1e-15)
    assert got.cavity.fsr_hz == pytest.approx(C / 1.2, rel=1e-15)  # c / (2 L)


def _edit(folder, tmp_path, file, old, new):
    lab = tmp_path / "lab"
    shutil.copytree(folder, lab)
    text = (lab / file).read_text()
    assert old in text
    (lab / file).write_text(text.replace(old, new, 1))
    return lab


def test_a_bad_cell_is_named_by_file_line_and_column(tmp_path, source):
    _, folder = source
    lines = (folder / "D2_cmds.csv").read_text().splitlines()
    fields = lines[3].split(",")
    bad = ",".join([*fields[:2], "12.5kHz", *fields[3:]])
    lab = _edit(folder, tmp_path, "D2_cmds.csv", lines[3], bad)
    with pytest.raises(LabFolderError) as exc:
        read_lab_folder(lab)
    msg = str(exc.value)
    assert "D2_cmds.csv:4:3:" in msg and "'shift_u_kHz'" in msg and "lab.toml" in msg


def test_a_missing_column_says_how_to_map_it(tmp_path, source):
    _, folder = source
    lab = _edit(folder, tmp_path, "D2_beat.csv", "b12_mV", "amplitude_mV")
    with pytest.raises(
        LabFolderError,
        match=r"D2_beat.csv:1: no column 'b12_mV' for b12.*"
        r"columns = \{ b12 = ",
    ):
        read_lab_folder(lab)


def test_a_misspelt_key_is_named_with_the_likely_one(tmp_path, source):
    _, folder = source
    lab = _edit(folder, tmp_path, "lab.toml", "pressure_u =", "presure_u =")
    with pytest.raises(
        LabFolderError, match=r"unknown key 'presure_u' \(did you mean 'pressure_u'"
    ):
        read_lab_folder(lab)


def test_an_unknown_unit_lists_the_known_ones(tmp_path, source):
    _, folder = source
    lab = _edit(folder, tmp_path, "lab.toml", 'shift = "kHz"', 'shift = "kHzz"')
    with pytest.raises(LabFolderError, match=r"units.shift: unknown frequency unit 'kHzz'.*MHz"):
        read_lab_folder(lab)


def test_modes_and_records_must_have_equal_counts(tmp_path, source):
    _, folder = source
    lines = (folder / "D2_modes.csv").read_text().splitlines()
    lab = _edit(folder, tmp_path, "D2_modes.csv", lines[-1] + "\n", "")
    with pytest.raises(LabFolderError, match=r"D2_ringdowns.csv: 12 rows .* lists 11 cavity modes"):
        read_lab_folder(lab)


def test_one_file_per_mode_with_a_time_column(tmp_path, source):
    bundle, folder = source
    rd = bundle.configs["D2"].ringdowns
    lab = tmp_path / "lab"
    shutil.copytree(folder, lab)
    (lab / "D2_ringdowns.csv").unlink()
    (lab / "rec").mkdir()
    for i, row in enumerate(rd.signal_v):  # mode_1 ... mode_12: natural order, not 1, 10, 11, 2
        body = "\n".join(f"{t!r}\t{v!r}" for t, v in zip((rd.time_s * 1e6).tolist(), row.tolist()))
        (lab / "rec" / f"mode_{i + 1}.tsv").write_text("# one ring-down\nt_us\tV\n" + body + "\n")
    text = (lab / "lab.toml").read_text()
    text = text.replace('signal = "D2_ringdowns.csv"', 'records = "rec/mode_*.tsv"')
    text = text.replace('dt = "20.0 ns"\n', "").replace('t0 = "-2.0 us"\n', "")
    text = text.replace('signal = "signal_mV" }', 'signal = "V", time = "t_us" }')
    text = text.replace('signal = "mV" }', 'signal = "V", time = "us" }')
    (lab / "lab.toml").write_text(text)
    got = read_lab_folder(lab).configs["D2"].ringdowns
    np.testing.assert_array_equal(got.signal_v, rd.signal_v)  # volts written as volts: exact
    # dt from (t_last - t_first)/(k - 1) of times in us: a few roundings of 1e-16
    assert got.dt_s == pytest.approx(rd.dt_s, rel=1e-12)
    assert got.t0_s == pytest.approx(rd.t0_s, rel=1e-15)


def test_one_npy_per_mode_with_dt_and_t0_in_lab_toml(tmp_path, source):
    bundle, folder = source
    rd = bundle.configs["D2"].ringdowns
    lab = tmp_path / "lab"
    shutil.copytree(folder, lab)
    (lab / "D2_ringdowns.csv").unlink()
    for i, row in enumerate(rd.signal_v):
        np.save(lab / f"r{i:02d}.npy", row)  # volts, float64
    text = (lab / "lab.toml").read_text()
    text = text.replace('signal = "D2_ringdowns.csv"', 'records = "r*.npy"')
    (lab / "lab.toml").write_text(text.replace('signal = "mV" }', 'signal = "V" }'))
    got = read_lab_folder(lab).configs["D2"].ringdowns
    np.testing.assert_array_equal(got.signal_v, rd.signal_v)  # .npy holds the float64 itself
    assert (got.dt_s, got.t0_s) == (rd.dt_s, rd.t0_s)
    (lab / "lab.toml").write_text(text)  # the same records said to be in mV
    np.testing.assert_allclose(
        read_lab_folder(lab).configs["D2"].ringdowns.signal_v, 1e-3 * rd.signal_v, rtol=1e-15
    )
    (lab / "r11.npy").unlink()
    with pytest.raises(LabFolderError, match=r"11 files match, but .*D2_modes.csv lists 12"):
        read_lab_folder(lab)


def test_npy_signal_and_npz_tables(tmp_path, source):
    bundle, folder = source
    cfg = bundle.configs["D2"]
    lab = tmp_path / "lab"
    shutil.copytree(folder, lab)
    np.save(lab / "sig.npy", cfg.ringdowns.signal_v.T)  # records as columns: transpose = true
    cm = cfg.cmds
    np.savez(lab / "cmds.npz", nu=cm.nu_hz, shift=cm.shift_hz, shift_u=cm.shift_u_hz)
    text = (lab / "lab.toml").read_text()
    text = text.replace('signal = "D2_ringdowns.csv"', 'signal = "sig.npy"\ntranspose = true')
    text = text.replace('signal = "mV" }', 'signal = "V" }')
    start = text.index("[configs.D2.cmds]")
    (lab / "lab.toml").write_text(text[:start] + '[configs.D2.cmds]\nfile = "cmds.npz"\n')
    got = read_lab_folder(lab).configs["D2"]
    np.testing.assert_array_equal(got.ringdowns.signal_v, cfg.ringdowns.signal_v)
    np.testing.assert_array_equal(got.cmds.shift_hz, cm.shift_hz)  # SI without a unit: exact
    assert got.cmds.width_hz is None


def test_from_arrays_builds_the_same_bundle_and_names_a_misspelt_field(source):
    bundle, _ = source
    cfg = bundle.configs["D2"]
    fields = {f.name: getattr(bundle.sample, f.name) for f in dataclasses.fields(bundle.sample)}
    rd = {n: getattr(cfg.ringdowns, n) for n in ("nu_hz", "signal_v", "dt_s", "t0_s", "n_avg")}
    built = Bundle.from_arrays(fields, {"fsr_hz": bundle.cavity.fsr_hz}, {"D2": {"ringdowns": rd}})
    np.testing.assert_array_equal(built.configs["D2"].ringdowns.signal_v, cfg.ringdowns.signal_v)
    assert built.sample == bundle.sample
    bad = dict(rd, nu=rd.pop("nu_hz"))
    with pytest.raises(ValueError, match=r"unknown field 'nu' \(did you mean 'nu_hz'\?\)"):
        Bundle.from_arrays(fields, {"fsr_hz": 2e8}, {"D2": {"ringdowns": bad}})


def _spectrum_folder(tmp_path, source_folder, name, header, rows):
    lab = tmp_path / name
    lab.mkdir()
    toml = (source_folder / "lab.toml").read_text()
    sample = toml[toml.index("[sample]") : toml.index("[cavity]")]
    cols, units = header
    (lab / "lab.toml").write_text(
        sample + f'[spectrum]\nfile = "s.csv"\ncolumns = {{ {cols} }}\nunits = {{ {units} }}\n'
    )
    (lab / "s.csv").write_text(
        "nu,y,u\n" + "\n".join(",".join(repr(float(x)) for x in r) for r in rows)
    )
    return lab


def test_spectrum_level_input_gives_the_line_fit_of_the_same_spectrum(tmp_path, source):
    bundle, folder = source
    ref = analyse_line(bundle, bundle.configs["D2"], method="crds", profile_name="voigt")
    sp = ref.spectrum  # alpha = 1/(c tau) (1/m) and its u
    tau = 1.0 / (C * sp.y)
    tau_u = sp.u / (C * sp.y**2)
    labs = {
        "tau": _spectrum_folder(
            tmp_path,
            folder,
            "tau",
            ('nu = "nu", tau = "y", tau_u = "u"', 'nu = "GHz", tau = "us", tau_u = "us"'),
            zip(sp.nu_hz / 1e9, tau * 1e6, tau_u * 1e6),
        ),
        "alpha": _spectrum_folder(
            tmp_path,
            folder,
            "alpha",
            (
                'nu = "nu", alpha = "y", alpha_u = "u"',
                'nu = "GHz", alpha = "1/cm", alpha_u = "1/cm"',
            ),
            zip(sp.nu_hz / 1e9, sp.y / 100, sp.u / 100),
        ),
    }
    for quantity, lab in labs.items():
        spec = read_lab_spectrum(lab)
        assert spec.quantity == quantity
        got = analyse_spectrum(spec, "voigt")
        assert got.input_note == SPECTRUM_LEVEL and got.to_dict()["input"] == SPECTRUM_LEVEL
        assert "transfer_function" not in got.to_dict() and got.t_cut_s is None
        # the same points to a few roundings: the same A to 1e-8 relative (the fit's stopping
        # rule turns 1e-16 input changes into ~1e-10, measured 6.7e-11)
        assert got.line_fit.line_area == pytest.approx(ref.line_fit.line_area, rel=1e-8)
        assert got.line_fit.line_area_u == pytest.approx(ref.line_fit.line_area_u, rel=1e-6)


# --------------------------------------------------------------------------- dimension scales


def test_written_bundles_carry_named_dimensions(source, tmp_path):
    bundle, _ = source
    out = tmp_path / "b.h5"
    save_bundle(bundle, out)
    with h5py.File(out, "r") as f:
        rd = f["configs/D2/ringdowns"]
        sig = rd["signal_v"]
        assert [d.label for d in sig.dims] == ["nu_hz", "time_s"]
        assert sig.dims[0][0].name.endswith("/ringdowns/nu_hz")
        assert sig.dims[1][0].name.endswith("/ringdowns/time_s")
        assert rd["n_avg"].dims[0].label == "nu_hz" and rd["noise_v"].dims[0].label == "nu_hz"
        assert h5py.h5ds.is_scale(rd["nu_hz"].id) and h5py.h5ds.is_scale(rd["time_s"].id)
        np.testing.assert_array_equal(rd["time_s"][()], bundle.configs["D2"].ringdowns.time_s)
        tf = f["configs/D2/transfer_function"]
        assert tf["b12_v"].dims[0][0].name.endswith("/f_hz")
        cm = f["configs/D2/cmds"]
        assert all(cm[n].dims[0].label == "nu_hz" for n in ("shift_hz", "shift_u_hz", "width_hz"))
    assert load_bundle(out) == bundle


def test_netcdf_reader_sees_the_named_dimensions(source, tmp_path):
    """h5netcdf (the netCDF-4 reader behind xarray's h5netcdf engine) names every axis."""
    h5netcdf = pytest.importorskip("h5netcdf")
    bundle, _ = source
    out = tmp_path / "b.h5"
    save_bundle(bundle, out)
    with h5netcdf.File(out, "r") as f:
        rd = f["configs/D2/ringdowns"]
        assert rd.variables["signal_v"].dimensions == ("nu_hz", "time_s")
        assert rd.variables["n_avg"].dimensions == ("nu_hz",)
        assert f["configs/D2/transfer_function"].variables["b12_v"].dimensions == ("f_hz",)
        assert f["configs/D2/cmds"].variables["shift_hz"].dimensions == ("nu_hz",)


def test_bundles_without_scales_still_read(good_bundle_path):
    # the conftest bundle is written with raw h5py as version 1 was: no scales, no time_s
    with h5py.File(good_bundle_path, "r") as f:
        assert "time_s" not in f["configs/D1/ringdowns"]
        assert f["configs/D1/ringdowns/signal_v"].dims[0].label == ""
    bundle, errors, _ = validate_file(good_bundle_path)
    assert errors == [] and bundle is not None


def test_a_time_axis_that_disagrees_with_t0_is_warned_about(source, tmp_path):
    bundle, _ = source
    out = tmp_path / "b.h5"
    save_bundle(bundle, out)
    with h5py.File(out, "a") as f:
        f["configs/D2/ringdowns"].attrs["t0_s"] = -1e-6
    got, errors, warnings = validate_file(out)
    assert errors == [] and got.configs["D2"].ringdowns.t0_s == -1e-6
    assert any(w.path.endswith("ringdowns/time_s") and "disagrees" in w.message for w in warnings)


@pytest.mark.parametrize(
    ("value", "unit", "kind", "si"),
    [
        (2.5, "us", "time", 2.5e-6),
        (20.0, "ns", "time", 2.0e-8),
        (3.0, "ms", "time", 3.0e-3),
        (7.0, "mV", "voltage", 7.0e-3),
        (1.5, "GHz", "frequency", 1.5e9),
        (250.0, "MHz", "frequency", 2.5e8),
        (12.0, "kHz", "frequency", 1.2e4),
        (1013.25, "hPa", "pressure", 101325.0),
        (2.0, "1/cm", "absorption", 200.0),
    ],
)
def test_lab_units_by_definition(value, unit, kind, si):
    from bayes_tfcrds.bundle.units import from_si, to_si

    assert to_si(value, unit, kind) == pytest.approx(si, rel=1e-15)
    assert from_si(si, unit, kind) == pytest.approx(value, rel=1e-15)
