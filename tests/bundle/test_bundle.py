"""The measurement bundle contract (FORMAT.md): round trip, determinism, refusals, clipping,
atomic writes."""

from __future__ import annotations

import dataclasses
import os
import time

import h5py
import numpy as np
import pytest

from bayes_tfcrds.bundle import reader as R
from bayes_tfcrds.bundle import writer as W
from bayes_tfcrds.bundle.reader import load_bundle, load_truth, validate_file
from bayes_tfcrds.bundle.records import (
    Bundle,
    BundleError,
    Cavity,
    CmdsData,
    Config,
    RingdownData,
    Sample,
    TransferFunctionData,
    Violation,
)
from bayes_tfcrds.bundle.summary import main_validate, summarize
from bayes_tfcrds.bundle.writer import save_bundle
from tests.conftest import GOOD

TRUTH = {
    "area_si": 1.25e-3,
    "model": "voigt",
    "seed": 7,
    "noisy": True,
    "tau_s": np.array([1e-5, 2e-5]),
    "tf": {"f_c_hz": 2e6, "labels": ["D1", "D2"], "deep": {"n_r": 2}},
}


# ----------------------------------------------------------------------------- good files


def test_good_file_loads_with_contents(good_bundle_path):
    b, errors, warnings = validate_file(good_bundle_path)
    assert errors == [] and warnings == []
    assert list(b.configs) == ["D1", "D2"]
    s = b.sample
    assert (s.molecule, s.line, s.pressure_pa, s.mole_fraction, s.mass_u) == (
        "CO",
        "(3-0) R(23)",
        1333.22,
        0.01,
        27.995,
    )
    d1, d2 = b.configs["D1"], b.configs["D2"]
    rd = d1.ringdowns
    assert rd.signal_v.shape == (GOOD["m"], GOOD["k"]) and rd.n_points == GOOD["m"]
    assert rd.n_samples == GOOD["k"]
    np.testing.assert_allclose(rd.time_s[[0, 20]], [GOOD["t0_s"], 0.0], atol=1e-18)
    assert rd.n_avg.dtype == np.int64 and rd.noise_v.shape == rd.signal_v.shape
    assert not rd.clipped.any()
    # |H| = b12 / (2 sqrt(i1 i2)) recovers the single-pole magnitude the file was made from
    tf = d1.transfer_function
    np.testing.assert_allclose(tf.h_mag, 1 / np.abs(1 + 1j * tf.f_hz / GOOD["f_c_hz"]), rtol=1e-12)
    np.testing.assert_allclose(tf.h_mag_u, 1e-4 / (2 * np.sqrt(GOOD["i1_v"] * GOOD["i2_v"])))
    assert isinstance(tf.i2_v, float) and tf.i1_v.shape == (GOOD["n_tf"],)
    assert d1.cmds.width_hz is not None and d1.description.startswith("InGaAs")
    assert d2.transfer_function is None and d2.cmds is None and d2.ringdowns.n_avg is None
    assert b.description == "synthetic test bundle <b>not</b> real data"


def test_arrays_are_read_only(good_bundle_path):
    rd = load_bundle(good_bundle_path).configs["D1"].ringdowns
    for a in (rd.signal_v, rd.nu_hz, rd.n_avg, rd.noise_v, rd.clipped):
        with pytest.raises(ValueError):
            a[0] = 0
    with pytest.raises(dataclasses.FrozenInstanceError):
        rd.dt_s = 1.0


def test_round_trip_and_truth(good_bundle_path, tmp_path):
    b = load_bundle(good_bundle_path)
    out = tmp_path / "copy.h5"
    save_bundle(b, out, truth=TRUTH)
    again = load_bundle(out)
    assert again == b
    assert again.configs["D1"].transfer_function is not None and again.configs["D2"].cmds is None
    # changing one number breaks equality (equality really compares arrays)
    rd = b.configs["D2"].ringdowns
    other = dataclasses.replace(rd, signal_v=rd.signal_v + 1e-9)
    assert other != rd
    truth = load_truth(out)
    assert truth["area_si"] == 1.25e-3 and truth["model"] == "voigt" and truth["seed"] == 7
    assert truth["noisy"] is True
    np.testing.assert_array_equal(truth["tau_s"], TRUTH["tau_s"])
    assert truth["tf"]["f_c_hz"] == 2e6 and list(truth["tf"]["labels"]) == ["D1", "D2"]
    assert truth["tf"]["deep"] == {"n_r": 2}
    assert load_truth(good_bundle_path) is None


def test_writer_follows_contract_layout(good_bundle_path, tmp_path):
    """Checked with raw h5py, not with the reader, so writer and reader cannot share a slip."""
    out = tmp_path / "w.h5"
    save_bundle(load_bundle(good_bundle_path), out)
    with h5py.File(out, "r") as f:
        assert f.attrs["format"] == "tfcrds-bundle" and f.attrs["format_version"] == 1
        assert set(f["sample"].attrs) == {
            "molecule",
            "line",
            "nu0_hz",
            "pressure_pa",
            "pressure_u_pa",
            "temperature_k",
            "temperature_u_k",
            "mole_fraction",
            "mass_u",
        }
        assert set(f["configs/D1"]) == {"transfer_function", "ringdowns", "cmds"}
        # time_s: the time axis as a dimension scale (FORMAT.md, optional)
        assert set(f["configs/D1/ringdowns"]) == {"nu_hz", "time_s", "signal_v", "n_avg", "noise_v"}
        assert set(f["configs/D1/ringdowns"].attrs) == {"dt_s", "t0_s"}
        assert set(f["configs/D1/transfer_function"]) == set(R._TF_ITEMS)
        assert f["configs/D1/transfer_function/i2_v"].shape == ()
        assert set(f["configs/D1/cmds"]) == set(R._CMDS_ITEMS)
        assert set(f["configs/D2"]) == {"ringdowns"}
        assert f["configs/D1/ringdowns/signal_v"].dtype == np.float64
        assert f["configs/D1/ringdowns/n_avg"].dtype.kind == "i"


def test_config_order_is_writer_order(good_bundle_path, tmp_path):
    b = load_bundle(good_bundle_path)
    rd = b.configs["D2"].ringdowns
    configs = [Config(n, rd) for n in ("D2", "D10", "D1")]
    save_bundle(Bundle(b.sample, b.cavity, configs), tmp_path / "o.h5")
    assert list(load_bundle(tmp_path / "o.h5").configs) == ["D2", "D10", "D1"]


def test_identical_input_gives_identical_bytes(good_bundle_path, tmp_path):
    b = load_bundle(good_bundle_path)
    save_bundle(b, tmp_path / "a.h5", truth=TRUTH)
    time.sleep(1.1)  # HDF5 timestamps have one-second resolution
    save_bundle(b, tmp_path / "b.h5", truth=TRUTH)
    assert (tmp_path / "a.h5").read_bytes() == (tmp_path / "b.h5").read_bytes()


def test_main_validate_good(good_bundle_path, capsys):
    assert main_validate(good_bundle_path) == 0
    out = capsys.readouterr().out
    for text in (
        "format version 1",
        "CO (3-0) R(23)",
        "1333.22",
        "Pa",
        "296",
        " K",
        "5 points x 400 samples",
        "t0 = -2e-06 s",
        "dt = 1e-07 s",
        "record length 4e-05 s",
        "12 beat frequencies",
        "f = 1000 .. 10000000 Hz",
        "widths present",
        "n_avg: 100 .. 100",
        "noise_v: per sample",
        "transfer_function: absent",
        "cmds: absent",
        "OK",
    ):
        assert text in out, text
    assert "CLIPPED" not in out and "warning" not in out


def test_text_attributes_are_plain_strings(good_bundle_path, tmp_path):
    evil = "<script>alert('x')</script> {__import__('os')} \x1b[31m"
    with h5py.File(good_bundle_path, "a") as f:
        f.attrs["description"] = evil
        f["sample"].attrs["line"] = np.bytes_(b"(3-0) R(23)")  # fixed-length ASCII is text too
    b = load_bundle(good_bundle_path)
    assert b.description == evil and b.sample.line == "(3-0) R(23)"
    assert "\x1b" not in summarize(b)  # escaped when shown, never acted on
    save_bundle(b, tmp_path / "e.h5")
    assert load_bundle(tmp_path / "e.h5").description == evil


def test_unknown_items_are_only_warnings(good_bundle_path):
    with h5py.File(good_bundle_path, "a") as f:
        f.attrs["operator"] = "A. N. Other"
        f["sample"].attrs["mole_fracion"] = 0.5  # a typo of an optional attribute
        f["configs/D1/ringdowns/extra"] = np.arange(3.0)
        f.create_group("lab_notes")
    b, errors, warnings = validate_file(good_bundle_path)
    assert errors == [] and b is not None
    text = "\n".join(map(str, warnings))
    assert "/@operator: unknown attribute" in text
    assert (
        "/sample@mole_fracion: unknown attribute, ignored (did you mean 'mole_fraction'?)" in text
    )
    assert "/configs/D1/ringdowns/extra: unknown item" in text
    assert "/lab_notes: unknown item" in text


def test_lenient_where_the_contract_allows(good_bundle_path):
    """Integer-valued floats for ints and float32 signals load (with a warning)."""
    with h5py.File(good_bundle_path, "a") as f:
        f.attrs["format_version"] = 1.0
        rd = f["configs/D1/ringdowns"]
        sig = rd["signal_v"][()]
        del rd["signal_v"], rd["n_avg"]
        rd["signal_v"] = sig.astype(np.float32)
        rd["n_avg"] = np.full(GOOD["m"], 100.0)
    b, errors, warnings = validate_file(good_bundle_path)
    assert errors == []
    assert b.configs["D1"].ringdowns.n_avg.dtype == np.int64
    assert {w.path for w in warnings} == {
        "/@format_version",
        "/configs/D1/ringdowns/signal_v",
        "/configs/D1/ringdowns/n_avg",
    }


# ----------------------------------------------------------------------------- broken files


def _replace(f, path, data, **kw):
    del f[path]
    f.create_dataset(path, data=data, **kw)


def _scale_row(f, path, value):
    a = f[path][()]
    a.reshape(-1)[1] = value
    _replace(f, path, a)


RD = "/configs/D1/ringdowns"
TF = "/configs/D1/transfer_function"
CM = "/configs/D1/cmds"

# name, mutation of an open h5py file, exact path expected, phrase expected
BROKEN = [
    ("missing sample", lambda f: f.__delitem__("sample"), "/sample", "required group is missing"),
    (
        "missing configs",
        lambda f: f.__delitem__("configs"),
        "/configs",
        "required group is missing",
    ),
    (
        "no configuration",
        lambda f: [f["configs"].__delitem__(n) for n in ("D1", "D2")],
        "/configs",
        "holds no configuration",
    ),
    (
        "missing ringdowns",
        lambda f: f.__delitem__("configs/D2/ringdowns"),
        "/configs/D2/ringdowns",
        "required group is missing",
    ),
    (
        "missing attribute",
        lambda f: f["sample"].attrs.__delitem__("pressure_pa"),
        "/sample@pressure_pa",
        "required attribute is missing",
    ),
    (
        "missing dataset",
        lambda f: f.__delitem__(CM + "/shift_u_hz"),
        CM + "/shift_u_hz",
        "required dataset is missing",
    ),
    (
        "cavity is a dataset",
        lambda f: (f.__delitem__("cavity"), f.create_dataset("cavity", data=1.0)),
        "/cavity",
        "is a dataset, expected a group",
    ),
    (
        "format_version 2",
        lambda f: f.attrs.__setitem__("format_version", 2),
        "/@format_version",
        "format version 2 found; this reader supports version 1",
    ),
    (
        "format_version text",
        lambda f: f.attrs.__setitem__("format_version", "1"),
        "/@format_version",
        "expected a number, found text '1'",
    ),
    (
        "wrong format",
        lambda f: f.attrs.__setitem__("format", "hitran-par"),
        "/@format",
        "expected 'tfcrds-bundle'",
    ),
    (
        "NaN in signal_v",
        lambda f: _scale_row(f, RD + "/signal_v", np.nan),
        RD + "/signal_v",
        "non-finite value(s) (NaN or inf); first at index (0, 1): nan",
    ),
    (
        "inf in b12_v",
        lambda f: _scale_row(f, TF + "/b12_v", np.inf),
        TF + "/b12_v",
        "non-finite value(s) (NaN or inf); first at index 1: inf",
    ),
    (
        "inf in cmds nu_hz",
        lambda f: _scale_row(f, CM + "/nu_hz", -np.inf),
        CM + "/nu_hz",
        "non-finite",
    ),
    (
        "NaN attribute",
        lambda f: f["cavity"].attrs.__setitem__("finesse", np.nan),
        "/cavity@finesse",
        "must be finite",
    ),
    (
        "non-increasing f_hz",
        lambda f: _scale_row(f, TF + "/f_hz", 1e3),
        TF + "/f_hz",
        "must be strictly increasing: f_hz[1] = 1000.0 <= f_hz[0] = 1000.0",
    ),
    (
        "f_hz <= 0",
        lambda f: _replace(f, TF + "/f_hz", np.linspace(-1e3, 1e7, GOOD["n_tf"])),
        TF + "/f_hz",
        "must be > 0",
    ),
    (
        "dt_s = 0",
        lambda f: f[RD].attrs.__setitem__("dt_s", 0.0),
        RD + "@dt_s",
        "must be > 0, found 0.0",
    ),
    (
        "negative pressure",
        lambda f: f["sample"].attrs.__setitem__("pressure_pa", -5.0),
        "/sample@pressure_pa",
        "must be > 0, found -5.0",
    ),
    (
        "zero temperature",
        lambda f: f["sample"].attrs.__setitem__("temperature_k", 0),
        "/sample@temperature_k",
        "must be > 0",
    ),
    (
        "negative uncertainty",
        lambda f: f["sample"].attrs.__setitem__("temperature_u_k", -0.1),
        "/sample@temperature_u_k",
        "must be >= 0",
    ),
    (
        "zero fsr",
        lambda f: f["cavity"].attrs.__setitem__("fsr_hz", 0.0),
        "/cavity@fsr_hz",
        "must be > 0",
    ),
    (
        "mole_fraction > 1",
        lambda f: f["sample"].attrs.__setitem__("mole_fraction", 1.5),
        "/sample@mole_fraction",
        "must be in (0, 1], found 1.5",
    ),
    (
        "string for float",
        lambda f: f["cavity"].attrs.__setitem__("fsr_hz", "250 MHz"),
        "/cavity@fsr_hz",
        "expected a number, found text '250 MHz'",
    ),
    (
        "number for string",
        lambda f: f["sample"].attrs.__setitem__("molecule", 28),
        "/sample@molecule",
        "expected text",
    ),
    (
        "text dataset",
        lambda f: _replace(f, RD + "/nu_hz", ["a"] * GOOD["m"], dtype=h5py.string_dtype()),
        RD + "/nu_hz",
        "expected real numbers, found text data",
    ),
    (
        "vlen dataset",
        lambda f: _replace(
            f, RD + "/noise_v", None, shape=(GOOD["m"],), dtype=h5py.vlen_dtype(np.float64)
        ),
        RD + "/noise_v",
        "variable-length non-text datatype; refused (not read)",
    ),
    (
        "float32 nu_hz",
        lambda f: _replace(f, RD + "/nu_hz", f[RD + "/nu_hz"][()].astype(np.float32)),
        RD + "/nu_hz",
        "must be float64",
    ),
    (
        "signal_v 1-D",
        lambda f: _replace(f, RD + "/signal_v", np.ones(GOOD["k"])),
        RD + "/signal_v",
        "must be 2-D, found shape (400,)",
    ),
    (
        "nu_hz length",
        lambda f: _replace(f, RD + "/nu_hz", f[RD + "/nu_hz"][1:]),
        RD + "/nu_hz",
        "has 4 value(s) but signal_v has 5 rows",
    ),
    ("noise_v <= 0", lambda f: _scale_row(f, RD + "/noise_v", 0.0), RD + "/noise_v", "must be > 0"),
    (
        "noise_v shape",
        lambda f: _replace(f, RD + "/noise_v", np.ones((GOOD["m"], 3))),
        RD + "/noise_v",
        "expected (5,) or (5, 400)",
    ),
    ("n_avg < 1", lambda f: _scale_row(f, RD + "/n_avg", 0), RD + "/n_avg", "must be >= 1"),
    (
        "n_avg shape",
        lambda f: _replace(f, RD + "/n_avg", np.ones((GOOD["m"], 2), dtype=int)),
        RD + "/n_avg",
        "must be 1-D",
    ),
    (
        "n_avg fractional",
        lambda f: _replace(f, RD + "/n_avg", np.full(GOOD["m"], 2.5)),
        RD + "/n_avg",
        "whole numbers",
    ),
    (
        "no sample at t >= 0",
        lambda f: f[RD].attrs.__setitem__("t0_s", -1.0),
        RD + "@t0_s",
        "no sample at t >= 0",
    ),
    (
        "tf lengths",
        lambda f: _replace(f, TF + "/b12_v", f[TF + "/b12_v"][:-2]),
        TF + "/b12_v",
        "has 10 value(s) but f_hz has 12",
    ),
    (
        "i1_v shape",
        lambda f: _replace(f, TF + "/i1_v", np.ones(3)),
        TF + "/i1_v",
        "must be a scalar () or have shape (12,)",
    ),
    ("i2_v <= 0", lambda f: _replace(f, TF + "/i2_v", 0.0), TF + "/i2_v", "must be > 0"),
    (
        "cmds lengths",
        lambda f: _replace(f, CM + "/shift_hz", np.zeros(4)),
        CM + "/shift_hz",
        "has 4 value(s) but nu_hz has 5",
    ),
    (
        "shift_u_hz <= 0",
        lambda f: _scale_row(f, CM + "/shift_u_hz", 0.0),
        CM + "/shift_u_hz",
        "must be > 0",
    ),
    ("empty array", lambda f: _replace(f, CM + "/nu_hz", np.zeros(0)), CM + "/nu_hz", "is empty"),
    (
        "external link",
        lambda f: (
            f.__delitem__("cavity"),
            f.__setitem__("cavity", h5py.ExternalLink("other.h5", "/cavity")),
        ),
        "/cavity",
        "external link",
    ),
    (
        "external config",
        lambda f: f["configs"].__setitem__("D3", h5py.ExternalLink("x.h5", "/D3")),
        "/configs/D3",
        "external link",
    ),
    (
        "boolean for float",
        lambda f: f["cavity"].attrs.__setitem__("finesse", True),
        "/cavity@finesse",
        "expected a real number, found a boolean (True)",
    ),
]


@pytest.mark.parametrize("name, mutate, path, phrase", BROKEN, ids=[c[0] for c in BROKEN])
def test_broken_bundle_is_refused(good_bundle_path, capsys, name, mutate, path, phrase):
    with h5py.File(good_bundle_path, "a") as f:
        mutate(f)
    assert main_validate(good_bundle_path) == 1
    out = capsys.readouterr().out
    assert "REFUSED" in out and f"error: {path}: " in out and phrase in out, out
    with pytest.raises(BundleError) as info:
        load_bundle(good_bundle_path)
    assert any(v.path == path and phrase in v.message for v in info.value.violations)


def _text_file(p):
    p.write_text("nu_hz,signal_v\n1,2\n")


def _truncated(p):
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])


def _empty(p):
    p.write_bytes(b"")


def _missing(p):
    p.unlink()


def _directory(p):
    p.unlink()
    p.mkdir()


FILE_LEVEL = [
    ("text renamed .h5", _text_file, "not an HDF5 file"),
    ("truncated", _truncated, "truncated or corrupt"),
    ("empty", _empty, "file is empty (0 bytes)"),
    ("missing", _missing, "file not found"),
    ("directory", _directory, "is a directory"),
]


@pytest.mark.parametrize("name, damage, phrase", FILE_LEVEL, ids=[c[0] for c in FILE_LEVEL])
def test_unreadable_file_is_refused(good_bundle_path, capsys, name, damage, phrase):
    damage(good_bundle_path)
    assert main_validate(good_bundle_path) == 1
    out = capsys.readouterr().out
    assert f"error: /: {phrase}" in out and "Traceback" not in out, out
    with pytest.raises(BundleError, match="/: " + phrase.split(" (")[0]):
        load_bundle(good_bundle_path)


def test_all_violations_are_collected(good_bundle_path):
    with h5py.File(good_bundle_path, "a") as f:
        f["sample"].attrs["pressure_pa"] = -1.0
        del f["cavity"].attrs["fsr_hz"]
        _scale_row(f, RD + "/signal_v", np.nan)
        _replace(f, "/configs/D2/ringdowns/nu_hz", np.ones(2))
    with pytest.raises(BundleError) as info:
        load_bundle(good_bundle_path)
    err = info.value
    assert isinstance(err, ValueError)
    assert {v.path for v in err.violations} == {
        "/sample@pressure_pa",
        "/cavity@fsr_hz",
        RD + "/signal_v",
        "/configs/D2/ringdowns/nu_hz",
    }
    lines = str(err).splitlines()
    assert len(lines) == 1 + 4
    assert all(line.startswith(f"{good_bundle_path}: ") for line in lines)
    _, errors, _ = validate_file(good_bundle_path)  # never raises
    assert errors == err.violations and isinstance(errors[0], Violation)


# ----------------------------------------------------------------------------- clipping


def test_clipped_transient_is_a_warning(good_bundle_path, capsys):
    with h5py.File(good_bundle_path, "a") as f:
        sig = f[RD + "/signal_v"][()]
        sig[3] = np.minimum(sig[3], 0.8)  # rail at 0.8 V: early decay saturates
        _replace(f, RD + "/signal_v", sig)
    b, errors, warnings = validate_file(good_bundle_path)
    assert errors == []
    np.testing.assert_array_equal(b.configs["D1"].ringdowns.clipped, [0, 0, 0, 1, 0])
    assert not b.configs["D2"].ringdowns.clipped.any()
    assert [w.path for w in warnings] == [RD + "/signal_v"]
    assert "transient 3" in warnings[0].message and "clipped" in warnings[0].message
    assert main_validate(good_bundle_path) == 0
    out = capsys.readouterr().out
    assert "CLIPPED transients (1): #3" in out and "looks clipped" in out


def _rd(signal, t0_s=-2e-6, dt_s=1e-7):
    signal = np.atleast_2d(signal)
    return RingdownData(np.full(signal.shape[0], 1.9e14), signal, dt_s, t0_s)


def test_clipping_rule():
    rng = np.random.default_rng(3)
    t = -2e-6 + 1e-7 * np.arange(400)
    exact = np.where(t < 0, 1.0, np.exp(-t / 1e-5))
    # noiseless model: exactly flat before extinction, equal at t = 0, then decays: not clipped
    assert not _rd(exact).clipped.any()
    # averaged noisy transients (100 acquisitions of a 12-bit digitizer) are never flagged
    lsb = 2.0 / 4096
    acq = exact + rng.normal(0, 5e-3, (200, 100, 400))
    noisy = (np.round(acq / lsb) * lsb).mean(axis=1)
    assert not _rd(noisy).clipped.any()
    # every acquisition on the top rail: flat run at the max reaching t > 0
    clipped = (np.clip(np.round(acq / lsb) * lsb, None, 0.9)).mean(axis=1)
    assert _rd(clipped).clipped.all()
    # a bottom rail is flagged too
    assert _rd(np.maximum(noisy - 0.9, -0.05)).clipped.all()
    # a run of only two samples is not enough; three is
    two = noisy[0].copy()
    two[30:32] = two.max() + 0.1
    assert not _rd(two).clipped.any()
    two[32] = two[30]
    assert _rd(two).clipped.all()
    # a flat top confined to t < 0 never enters a fit: not flagged
    pre = noisy[0].copy()
    pre[5:15] = pre.max() + 0.1
    assert not _rd(pre).clipped.any()


# ----------------------------------------------------------------------------- writing


def test_failure_mid_write_leaves_nothing(good_bundle_path, tmp_path, monkeypatch):
    b = load_bundle(good_bundle_path)
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    target = out_dir / "bundle.h5"

    def boom(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(W, "_write_cmds", boom)  # dies after /sample, /cavity, D1 ringdowns
    with pytest.raises(RuntimeError, match="disk full"):
        save_bundle(b, target)
    assert os.listdir(out_dir) == []
    # an existing file is left exactly as it was
    target.write_bytes(b"old contents")
    with pytest.raises(RuntimeError):
        save_bundle(b, target)
    assert os.listdir(out_dir) == ["bundle.h5"] and target.read_bytes() == b"old contents"


def test_writer_refuses_invalid_bundle(good_bundle_path, tmp_path):
    b = load_bundle(good_bundle_path)
    bad_sample = dataclasses.replace(b.sample, pressure_pa=float("nan"))
    with pytest.raises(BundleError, match="/sample@pressure_pa: must be finite"):
        save_bundle(dataclasses.replace(b, sample=bad_sample), tmp_path / "bad.h5")
    assert os.listdir(tmp_path) == ["good.h5"]


def test_constructed_bundle_saves_and_loads(tmp_path):
    """A simulator-style bundle built in memory, scalar i1/i2 and (m,) noise."""
    k = 64
    t = 1e-7 * np.arange(k)
    rd = RingdownData(
        [1.9e14, 1.9e14 + 2.5e8],
        np.exp(-t / 1e-6) * [[1.0], [0.9]],
        1e-7,
        0.0,
        n_avg=[10, 10],
        noise_v=[1e-3, 1e-3],
    )
    tf = TransferFunctionData([1e3, 1e4], [0.9, 0.8], 0.5, 0.5)
    cmds = CmdsData([1.9e14], [10.0], [1.0])
    b = Bundle(
        Sample("CO", "R(0)", 1.9e14, 100.0, 0.1, 296.0, 0.1),
        Cavity(2.5e8),
        {"A": Config("A", rd, tf, cmds, description="sim")},
    )
    save_bundle(b, tmp_path / "sim.h5")
    assert load_bundle(tmp_path / "sim.h5") == b
    np.testing.assert_allclose(b.configs["A"].transfer_function.h_mag, [0.9, 0.8])
    with pytest.raises(ValueError, match="differs"):
        Bundle(b.sample, b.cavity, {"B": b.configs["A"]})
