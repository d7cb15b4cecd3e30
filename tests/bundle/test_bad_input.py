"""Bad input (issue #9, part 2): every kind of broken measurement gives an error or a warning that
names the problem, never a silent number; nothing the toolkit reads is unpickled or evaluated.

Bundle-level refusals are checked through both doors a user has, ``bayes-tfcrds validate`` and
``load_bundle``, with the exact path inside the file; analysis-level problems through the commands
(``fit``, ``linefit``, ``budget``, ``study``) a user would run. The broken files are made from the
contract-written fixture (conftest) or a small simulated campaign, one defect at a time.
"""

from __future__ import annotations

import csv
import html
import json
import pickle
import re
import shutil
import time
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest

from bayes_tfcrds.bundle.reader import load_bundle, load_truth, validate_file
from bayes_tfcrds.bundle.records import BundleError, RingdownData
from bayes_tfcrds.bundle.summary import main_validate, summarize
from bayes_tfcrds.bundle.writer import save_bundle
from bayes_tfcrds.cli import main
from bayes_tfcrds.fit.line_analysis import analyse_line
from bayes_tfcrds.fit.ringdown import fit_ringdowns
from tests.bundle.test_bundle import CM, RD, TF, _replace, _scale_row
from tests.conftest import GOOD

ROOT = Path(__file__).resolve().parents[2]


def _refused(path, capsys, where, phrase):
    """The file is refused by validate (exit 1, the path and phrase printed) and by load_bundle."""
    assert main_validate(path) == 1
    out = capsys.readouterr().out
    assert "REFUSED" in out and f"error: {where}: " in out and phrase in out, out
    with pytest.raises(BundleError) as info:
        load_bundle(path)
    assert any(v.path == where and phrase in v.message for v in info.value.violations), info.value


# ----------------------------------------------------------------------------- bundle contents
M, K = GOOD["m"], GOOD["k"]
BROKEN = [
    # non-finite numbers, wherever they are
    (
        "+inf in signal_v",
        lambda f: _scale_row(f, RD + "/signal_v", np.inf),
        RD + "/signal_v",
        "1 non-finite value(s) (NaN or inf); first at index (0, 1): inf",
    ),
    (
        "-inf in signal_v",
        lambda f: _scale_row(f, RD + "/signal_v", -np.inf),
        RD + "/signal_v",
        "non-finite",
    ),
    (
        "NaN in noise_v",
        lambda f: _scale_row(f, RD + "/noise_v", np.nan),
        RD + "/noise_v",
        "non-finite",
    ),
    (
        "NaN in ring-down nu_hz",
        lambda f: _scale_row(f, RD + "/nu_hz", np.nan),
        RD + "/nu_hz",
        "non-finite",
    ),
    (
        "NaN in shift_hz",
        lambda f: _scale_row(f, CM + "/shift_hz", np.nan),
        CM + "/shift_hz",
        "non-finite",
    ),
    ("inf dt_s", lambda f: f[RD].attrs.__setitem__("dt_s", np.inf), RD + "@dt_s", "must be finite"),
    ("NaN t0_s", lambda f: f[RD].attrs.__setitem__("t0_s", np.nan), RD + "@t0_s", "must be finite"),
    (
        "NaN pressure",
        lambda f: f["sample"].attrs.__setitem__("pressure_pa", np.nan),
        "/sample@pressure_pa",
        "must be finite",
    ),
    # zero or negative noise: a standard uncertainty is a weight, 0 would be an infinite one
    (
        "negative noise_v",
        lambda f: _scale_row(f, RD + "/noise_v", -2e-3),
        RD + "/noise_v",
        "must be > 0: 1 of 2000 value(s) are not, first at index (0, 1): -0.002",
    ),
    (
        "zero noise_v per transient",
        lambda f: _replace(f, RD + "/noise_v", np.zeros(M)),
        RD + "/noise_v",
        "must be > 0: 5 of 5",
    ),
    ("zero b12_u_v", lambda f: _scale_row(f, TF + "/b12_u_v", 0.0), TF + "/b12_u_v", "must be > 0"),
    # found by the CLI property test (issue 20): validated, and linefit's overlap error printed
    # the frequency with 30 digits
    (
        "CMDS nu_hz 1e30 times an optical frequency",
        lambda f: _replace(f, CM + "/nu_hz", f[CM + "/nu_hz"][()] * 1e30),
        CM + "/nu_hz",
        "must be in [1e+11, 1e+16] (Hz, far infrared to ultraviolet)",
    ),
    (
        "ring-down nu_hz 1e-30 times an optical frequency",
        lambda f: _replace(f, RD + "/nu_hz", f[RD + "/nu_hz"][()] * 1e-30),
        RD + "/nu_hz",
        "must be in [1e+11, 1e+16] (Hz, far infrared to ultraviolet)",
    ),
    # found by the CLI property test (issue 20): validated, then the H fit failed from every
    # start with a RuntimeError traceback
    (
        "b12_u_v 1e-300 V",
        lambda f: _scale_row(f, TF + "/b12_u_v", 1e-300),
        TF + "/b12_u_v",
        "must be in [1e-15, 1000] (V)",
    ),
    (
        "b12_v 1e300 V",
        lambda f: _scale_row(f, TF + "/b12_v", 1e300),
        TF + "/b12_v",
        "must be in [0, 1000] (V)",
    ),
    # found by the CLI property test (issue 20): validated, then the H fit never ended
    (
        "b12_v of 0 V at a low frequency",
        lambda f: _scale_row(f, TF + "/b12_v", 0.0),
        TF + "/b12_v",
        "is 0 V at 1 of the 3 lowest frequencies (first at index 1), where the chain passes",
    ),
    (
        "negative shift_u_hz",
        lambda f: _scale_row(f, CM + "/shift_u_hz", -50.0),
        CM + "/shift_u_hz",
        "must be > 0",
    ),
    (
        "zero width_u_hz",
        lambda f: _scale_row(f, CM + "/width_u_hz", 0.0),
        CM + "/width_u_hz",
        "must be > 0",
    ),
    (
        "negative pressure_u_pa",
        lambda f: f["sample"].attrs.__setitem__("pressure_u_pa", -1.0),
        "/sample@pressure_u_pa",
        "must be >= 0",
    ),
    # wrong shapes
    (
        "signal_v 3-D",
        lambda f: _replace(f, RD + "/signal_v", np.ones((M, K, 2))),
        RD + "/signal_v",
        "must be 2-D, found shape (5, 400, 2)",
    ),
    (
        "nu_hz 2-D",
        lambda f: _replace(f, RD + "/nu_hz", np.ones((M, 1)) * 1.9e14),
        RD + "/nu_hz",
        "must be 1-D, found shape (5, 1)",
    ),
    (
        "noise_v one per sample of one transient",
        lambda f: _replace(f, RD + "/noise_v", np.full(K, 2e-3)),
        RD + "/noise_v",
        "has shape (400,); expected (5,) or (5, 400)",
    ),
    (
        "noise_v transposed",
        lambda f: _replace(f, RD + "/noise_v", np.full((K, M), 2e-3)),
        RD + "/noise_v",
        "has shape (400, 5); expected (5,) or (5, 400)",
    ),
    (
        "width_hz length",
        lambda f: _replace(f, CM + "/width_hz", np.ones(M + 1)),
        CM + "/width_hz",
        "has 6 value(s) but nu_hz has 5",
    ),
    (
        "f_hz 2-D",
        lambda f: _replace(f, TF + "/f_hz", np.ones((GOOD["n_tf"], 2))),
        TF + "/f_hz",
        "must be 1-D",
    ),
    (
        "scalar signal_v",
        lambda f: _replace(f, RD + "/signal_v", 1.0),
        RD + "/signal_v",
        "must be 2-D, found shape ()",
    ),
    # frequencies: the beat-note axis must increase (the spectra's point order is free, see below)
    (
        "f_hz decreasing",
        lambda f: _replace(f, TF + "/f_hz", f[TF + "/f_hz"][()][::-1]),
        TF + "/f_hz",
        "must be strictly increasing: f_hz[1] = ",
    ),
    (
        "f_hz with one step back",
        lambda f: _replace(f, TF + "/f_hz", np.r_[f[TF + "/f_hz"][:5], 1.5e3, f[TF + "/f_hz"][6:]]),
        TF + "/f_hz",
        "must be strictly increasing: f_hz[5] = 1500.0 <= f_hz[4]",
    ),
    (
        "negative optical frequency",
        lambda f: _scale_row(f, RD + "/nu_hz", -1.9e14),
        RD + "/nu_hz",
        "must be > 0",
    ),
    # sample conditions
    (
        "negative pressure",
        lambda f: f["sample"].attrs.__setitem__("pressure_pa", -666.6),
        "/sample@pressure_pa",
        "must be > 0, found -666.6",
    ),
    (
        "zero pressure",
        lambda f: f["sample"].attrs.__setitem__("pressure_pa", 0.0),
        "/sample@pressure_pa",
        "must be > 0, found 0.0",
    ),
    (
        "negative temperature",
        lambda f: f["sample"].attrs.__setitem__("temperature_k", -296.0),
        "/sample@temperature_k",
        "must be > 0",
    ),
    # positive but beyond any laboratory (issue 20 item 5: these validated and were analysed)
    (
        "temperature 1e-300 K",
        lambda f: f["sample"].attrs.__setitem__("temperature_k", 1e-300),
        "/sample@temperature_k",
        "must be in [1, 5000] (K, a gas sample), found 1e-300",
    ),
    (
        "mass 1e-30 u",
        lambda f: f["sample"].attrs.__setitem__("mass_u", 1e-30),
        "/sample@mass_u",
        "must be in [1, 1000]",
    ),
    (
        "dt_s 1e300 s",
        lambda f: f[RD].attrs.__setitem__("dt_s", 1e300),
        RD + "@dt_s",
        "must be in [1e-12, 0.01] (s, a digitiser's sample interval)",
    ),
    (
        "dt_s 20 s",
        lambda f: f[RD].attrs.__setitem__("dt_s", 20.0),
        RD + "@dt_s",
        "must be in [1e-12, 0.01]",
    ),
    (
        "noise_v 1e300 V",
        lambda f: _scale_row(f, RD + "/noise_v", 1e300),
        RD + "/noise_v",
        "must be in [1e-15, 1000] (V)",
    ),
    (
        "shift_u_hz 1e-300 Hz",
        lambda f: _scale_row(f, CM + "/shift_u_hz", 1e-300),
        CM + "/shift_u_hz",
        "must be in [1e-06, 1e+12] (Hz)",
    ),
]


@pytest.mark.parametrize("name, mutate, where, phrase", BROKEN, ids=[c[0] for c in BROKEN])
def test_broken_contents_are_refused_with_the_path(
    good_bundle_path, capsys, name, mutate, where, phrase
):
    with h5py.File(good_bundle_path, "a") as f:
        mutate(f)
    _refused(good_bundle_path, capsys, where, phrase)


def _truncate_to(fraction):
    def damage(p):
        data = p.read_bytes()
        p.write_bytes(data[: int(len(data) * fraction)])

    return damage


@pytest.mark.parametrize("cut", [0.02, 0.3, 0.7, 0.999], ids=lambda c: f"{100 * c:g}%")
def test_truncated_files_are_refused(good_bundle_path, capsys, cut):
    """Cut anywhere, from inside the superblock's neighbourhood to the last bytes: HDF5 records the
    end of the file, so every truncation is caught at open, never read as fewer numbers."""
    _truncate_to(cut)(good_bundle_path)
    _refused(good_bundle_path, capsys, "/", "truncated or corrupt HDF5 file")
    assert "Traceback" not in capsys.readouterr().out


def test_truncated_file_is_refused_by_every_command(good_bundle_path, tmp_path, capsys):
    _truncate_to(0.5)(good_bundle_path)
    out = tmp_path / "out"
    for argv in (
        ["fit", str(good_bundle_path), "-o", str(out / "x.csv")],
        ["linefit", str(good_bundle_path), "-o", str(out / "x.json")],
        ["budget", str(good_bundle_path), "-o", str(out / "b")],
    ):
        assert main(argv) == 1
        err = capsys.readouterr().err
        assert err.startswith("error: ") and err.count("\n") == 1, err
        assert "not a valid bundle: /: truncated or corrupt HDF5 file" in err
    assert not out.exists()


# ----------------------------------------------------------------------------- clipped vs saturated
def _acquisitions(rng, n_avg=50, level=None, post_noise=0.0):
    """Averaged transients of the fixture's shape from ``n_avg`` single acquisitions.

    Detector noise (sd 14 mV per acquisition, 2 mV averaged as in the fixture) is added before
    the optional saturation at ``level`` (V), which pins the output there and so removes that
    noise; ``post_noise`` (V) is the amplifier/digitizer noise added after it.
    """
    t = GOOD["t0_s"] + GOOD["dt_s"] * np.arange(K)
    tau = np.array([10e-6, 9e-6, 8e-6, 9e-6, 10e-6])
    clean = np.where(t < 0, 1.0, np.exp(-np.clip(t, 0, None) / tau[:, None]))
    total = np.zeros_like(clean)
    for _ in range(n_avg):
        v = clean + 2e-3 * np.sqrt(n_avg) * rng.standard_normal(clean.shape)
        if level is not None:
            v = np.minimum(v, level)
        total += v + post_noise * rng.standard_normal(clean.shape)
    return t, total / n_avg


def _rows(t, signal):
    return RingdownData(
        np.linspace(1.9e14, 1.9e14 + 1e9, signal.shape[0]), signal, GOOD["dt_s"], t[0]
    )


def test_saturation_below_the_rails_is_told_apart_from_clipping():
    rng = np.random.default_rng(11)
    t, fine = _acquisitions(rng)
    t, sat = _acquisitions(rng, level=0.8, post_noise=1.4e-3)  # amplifier pinned at 0.8 V
    signal = fine.copy()
    signal[2] = sat[2]
    rd = _rows(t, signal)
    np.testing.assert_array_equal(rd.saturated, [0, 0, 1, 0, 0])
    np.testing.assert_array_equal(rd.clipped, rd.saturated)  # left out of the fits, like clipping
    top = signal[2][(t > 0) & (t < 1.5e-6)]
    assert np.unique(top).size == top.size  # no value repeats: the rail rule alone would miss it
    # the plateau's end: exp(-t/8 us) = 0.8 at 1.79 us; the window ends within a few samples of it
    assert 1.5e-6 < rd.saturation.end_s[2] < 1.9e-6, rd.saturation.end_s[2]
    # flatter than the noise allows: 1.4 mV / sqrt(50) after saturation against 2 mV before it
    ratio = rd.saturation.scatter_v[2] / rd.saturation.noise_v[2]
    assert ratio < 0.2, ratio
    # an inverting chain saturates at the bottom: the same rule applies there
    np.testing.assert_array_equal(_rows(t, -signal).saturated, [0, 0, 1, 0, 0])
    fits = fit_ringdowns(rd, [2e-6], "crds")
    assert [fits.status(i, 0) for i in range(5)] == ["ok", "ok", "saturated", "ok", "ok"]
    assert np.isnan(fits.tau_s[2, 0]) and np.all(np.isfinite(fits.tau_s[[0, 1, 3, 4], 0]))


def test_no_saturation_in_plain_noisy_or_noiseless_records():
    """False alarms: 200 noisy averaged records (40 x 5), a record whose top merely carries less
    noise than usual (0.6 sigma, within what a low-noise top can be), and noiseless models."""
    rng = np.random.default_rng(12)
    for _ in range(40):
        t, fine = _acquisitions(rng, n_avg=20)
        assert not _rows(t, fine).clipped.any()
    t, fine = _acquisitions(rng)
    quiet = fine.copy()
    top = t < 0.3e-6
    quiet[:, top] = 1.0 + 0.6 * (fine[:, top] - 1.0)
    assert not _rows(t, quiet).saturated.any()
    exact = np.where(t < 0, 1.0, np.exp(-np.clip(t, 0, None) / 1e-5))
    assert not _rows(t, np.tile(exact, (2, 1))).saturated.any()  # sigma: the decay's curvature only
    settled = np.round(
        np.where(t < 0, 1.0, np.exp(-np.clip(t, 0, None) / 1e-6)), 6
    )  # tail on 0: sigma = 0
    rd = _rows(t, np.tile(settled, (2, 1)))
    assert np.all(rd.saturation.noise_v == 0) and not rd.saturated.any()


def test_saturated_bundle_warns_in_validate_and_fit(campaign, tmp_path, capsys):
    b = load_bundle(campaign)
    cfg = b.configs["D2"]
    rd = cfg.ringdowns
    i = int(np.argmax(rd.signal_v.max(axis=1)))  # a baseline point: long tau
    level = 0.9 * rd.signal_v[i].max()
    sig = rd.signal_v.copy()
    noise = float(np.median(rd.noise_v)) if rd.noise_v is not None else 1e-4
    pinned = sig[i] > level
    sig[i, pinned] = level + 0.1 * noise * np.random.default_rng(1).standard_normal(
        int(pinned.sum())
    )
    path = tmp_path / "saturated.h5"
    save_bundle(replace(b, configs={"D2": replace(cfg, ringdowns=replace(rd, signal_v=sig))}), path)
    assert main(["validate", str(path)]) == 0  # a warning, the file is valid
    out = capsys.readouterr().out
    assert f"transient {i} (nu_hz = " in out and "looks saturated: its top is flat" in out
    assert "SATURATED transients (1)" in out
    csv_out = tmp_path / "fits.csv"
    assert (
        main(
            [
                "fit",
                str(path),
                "--config",
                "D2",
                "--method",
                "crds",
                "--tcut",
                "2e-6",
                "-o",
                str(csv_out),
            ]
        )
        == 0
    )
    err = capsys.readouterr().err
    assert (
        "1 clipped transients not fitted" in err
        and "1 of them saturated below the digitizer rails" in err
    )
    rows = list(csv.DictReader(csv_out.open()))
    bad = [r for r in rows if r["status"] == "saturated"]
    assert len(bad) == 1 and float(bad[0]["nu_hz"]) == pytest.approx(rd.nu_hz[i], abs=1e-3)
    assert bad[0]["tau_s"] == "nan"


def test_clipped_transient_is_not_fitted_by_the_commands(campaign, tmp_path, capsys):
    b = load_bundle(campaign)
    cfg = b.configs["D2"]
    rd = cfg.ringdowns
    sig = rd.signal_v.copy()
    sig[3] = np.minimum(sig[3], 0.7 * sig[3].max())  # every acquisition on one rail
    path = tmp_path / "clipped.h5"
    save_bundle(replace(b, configs={"D2": replace(cfg, ringdowns=replace(rd, signal_v=sig))}), path)
    out = tmp_path / "l.json"
    assert main(["linefit", str(path), "--config", "D2", "--method", "crds", "-o", str(out)]) == 0
    assert "1 clipped or saturated transients were left out" in capsys.readouterr().err
    result = json.loads(out.read_text())
    assert result["clipped_points"] == 1 and result["n_points"] == rd.n_points - 1


# ----------------------------------------------------------------------------- analysis-level
# problems
@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    path = tmp_path_factory.mktemp("bad") / "c.h5"
    assert (
        main(
            [
                "simulate",
                "--preset",
                "letter-D2",
                "--seed",
                "4",
                "--points",
                "21",
                "--samples",
                "4096",
                "-o",
                str(path),
            ]
        )
        == 0
    )
    return path


@pytest.mark.parametrize("command", ["fit", "linefit", "budget"])
@pytest.mark.parametrize(
    "tcut, phrase",
    [("1e-3", "beyond the record"), ("-1e-6", "must be >= 0")],
    ids=["beyond", "negative"],
)
def test_t_cut_outside_the_record_is_refused_before_any_work(
    campaign, tmp_path, capsys, command, tcut, phrase
):
    """The record is 4096 x 20 ns (80 us); the budget must refuse before minutes of sampling."""
    out = tmp_path / "out"
    start = time.perf_counter()
    assert (
        main(
            [
                command,
                str(campaign),
                "--config",
                "D2",
                "--method",
                "crds",
                f"--tcut={tcut}",
                "-o",
                str(out),
            ]
        )
        == 1
    )
    assert time.perf_counter() - start < 20  # a refusal, not a run (a run takes minutes)
    err = capsys.readouterr().err
    assert "error: t_cut" in err and phrase in err, err
    assert not out.exists()


def test_t_cut_that_is_not_a_number_is_refused(campaign, tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["fit", str(campaign), "--tcut", "4us", "-o", str(tmp_path / "x.csv")])
    assert "expected comma-separated numbers in seconds, got '4us'" in capsys.readouterr().err


@pytest.mark.parametrize(
    "command, tcut, phrase",
    [
        ("fit", ",", "expected at least one number in seconds, got ','"),
        ("discover", ",", "expected at least one number in seconds, got ','"),
        ("fit", "nan", "expected finite numbers in seconds, got 'nan'"),
        ("fit", "4e-6,inf", "expected finite numbers in seconds, got '4e-6,inf'"),
        ("linefit", "nan", "expected finite numbers in seconds, got 'nan'"),
        ("fit", "4e-6,4e-6", "a value is given more than once in '4e-6,4e-6'"),
    ],
)
def test_t_cut_lists_without_a_usable_value_are_refused_as_options(
    campaign, tmp_path, capsys, command, tcut, phrase
):
    # issue 20: --tcut=, gave numpy's "zero-size array to reduction operation" after the H fit
    # (discover took it as "no --tcut" and ran with its defaults); nan reached the analysis
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as info:
        main([command, str(campaign), "--config", "D2", f"--tcut={tcut}", "-o", str(out)])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert f"argument --tcut: {phrase}" in err and "Traceback" not in err, err
    assert not out.exists()


def test_control_characters_in_a_configuration_name_are_escaped_in_error_lines(
    campaign, tmp_path, capsys
):
    # issue 20: a newline or ANSI escape in a name rewrote the terminal in error lines
    evil = tmp_path / "evil.h5"
    shutil.copy(campaign, evil)
    name = "D\x1b[31mX\nY"
    with h5py.File(evil, "a") as f:
        f.move("configs/D2", f"configs/{name}")
    for command in ("fit", "linefit", "budget", "discover"):
        out = tmp_path / command
        argv = [command, str(evil), "--config", name, "--tcut", "1", "-o", str(out)]
        assert main(argv) in (1, 2)
        err = capsys.readouterr().err
        assert err.startswith("error: t_cut = 1 s is beyond the record of /configs/D") and (
            "D\\x1b[31mX\\nY" in err
        ), err
        assert err.count("\n") == 1 and "\x1b" not in err, err
        assert not out.exists()


def _far_cmds(campaign, tmp_path):
    b = load_bundle(campaign)
    cfg = b.configs["D2"]
    far = replace(cfg.cmds, nu_hz=cfg.cmds.nu_hz + 1e12)  # 1 THz from the ring-downs
    path = tmp_path / "far.h5"
    save_bundle(replace(b, configs={"D2": replace(cfg, cmds=far)}), path)
    return path


@pytest.mark.parametrize("command", ["linefit", "budget"])
def test_cmds_that_does_not_overlap_the_ring_downs_is_refused(campaign, tmp_path, capsys, command):
    path = _far_cmds(campaign, tmp_path)
    out = tmp_path / "out"
    assert main([command, str(path), "--config", "D2", "--method", "crds", "-o", str(out)]) == 1
    err = capsys.readouterr().err
    assert re.search(
        r"error: /configs/D2/cmds/nu_hz spans .* THz and does not overlap the ring-down range "
        r"/configs/D2/ringdowns/nu_hz .* \(0 CMDS points inside it; at least 8 needed\)",
        err,
    ), err
    assert not out.exists()


def test_records_too_short_for_the_longest_decay_are_warned_about(tmp_path, capsys):
    path = tmp_path / "short.h5"
    # 1024 samples at 20 ns: 20 us of record, less than twice the 32 us empty-cavity decay
    assert (
        main(
            [
                "simulate",
                "--preset",
                "letter-D2",
                "--points",
                "15",
                "--samples",
                "1024",
                "--seed",
                "1",
                "-o",
                str(path),
            ]
        )
        == 0
    )
    capsys.readouterr()
    assert (
        main(
            ["fit", str(path), "--method", "crds", "--tcut", "2e-6", "-o", str(tmp_path / "f.csv")]
        )
        == 0
    )
    err = capsys.readouterr().err
    assert re.search(
        r"warning: \d+ fits have less than two decay times of record after t_cut", err
    ), err
    out = tmp_path / "l.json"
    assert main(["linefit", str(path), "--method", "crds", "--tcut", "2e-6", "-o", str(out)]) == 0
    err = capsys.readouterr().err
    n = json.loads(out.read_text())["record_short_points"]
    assert (
        n > 0 and f"warning: {n} decay times come from less than two decay times of record" in err
    )


def test_point_order_of_the_spectra_does_not_matter(campaign, tmp_path):
    """Non-monotonic ring-down and CMDS frequencies are allowed (FORMAT.md fixes no order): a
    shuffled bundle gives the same line fit, to 1 % of u(A). The least-squares optimiser sums in
    another order and stops at its own tolerance (measured: 2.3e-7 of A, 2e-4 of u(A))."""
    b = load_bundle(campaign)
    cfg = b.configs["D2"]
    rd, cm = cfg.ringdowns, cfg.cmds
    p, q = (
        np.random.default_rng(3).permutation(rd.n_points),
        np.random.default_rng(4).permutation(cm.nu_hz.size),
    )
    assert np.any(np.diff(rd.nu_hz[p]) < 0) and np.any(np.diff(cm.nu_hz[q]) < 0)
    shuffled = replace(
        cfg,
        ringdowns=replace(
            rd,
            nu_hz=rd.nu_hz[p],
            signal_v=rd.signal_v[p],
            noise_v=None if rd.noise_v is None else rd.noise_v[p],
            n_avg=None if rd.n_avg is None else rd.n_avg[p],
        ),
        cmds=replace(
            cm,
            **{k: getattr(cm, k)[q] for k in ("nu_hz", "shift_hz", "shift_u_hz")},
            width_hz=None if cm.width_hz is None else cm.width_hz[q],
            width_u_hz=None if cm.width_u_hz is None else cm.width_u_hz[q],
        ),
    )
    path = tmp_path / "shuffled.h5"
    save_bundle(replace(b, configs={"D2": shuffled}), path)
    b2 = load_bundle(path)
    a = analyse_line(b, cfg, method="crds", t_cut_s=4e-6).to_dict()
    s = analyse_line(b2, b2.configs["D2"], method="crds", t_cut_s=4e-6).to_dict()
    for key in ("line_area", "reference_area"):
        assert abs(s[key]["value_si"] - a[key]["value_si"]) < 0.01 * a[key]["u_si"], key
        assert s[key]["u_si"] == pytest.approx(a[key]["u_si"], rel=1e-3), key


# ----------------------------------------------------------------------------- text, markup,
# pickles
EVIL_SCRIPT = "<script>alert('description')</script>"
EVIL_NAME = "D2<img src=x onerror=alert(1)>"  # an HDF5 name cannot hold '/', so no </script>


def test_markup_in_text_attributes_is_shown_escaped_in_the_report(campaign, tmp_path):
    bundle = tmp_path / "evil.h5"
    bundle.write_bytes(Path(campaign).read_bytes())
    with h5py.File(bundle, "a") as f:
        f.attrs["description"] = EVIL_SCRIPT
        f["sample"].attrs["line"] = "<b onmouseover=alert(2)>R(23)</b>"
        f.move("configs/D2", f"configs/{EVIL_NAME}")
        f[f"configs/{EVIL_NAME}"].attrs["description"] = "<script>alert('config')</script>"
    study = tmp_path / "s.toml"
    study.write_text(
        '[study]\nname = "evil"\nkind = "tcut"\n[campaign]\nbundle = '
        f'"{bundle}"\n[analysis]\nmethods = ["crds"]\nt_cuts_us = [4, 8]\n'
    )
    assert (
        main(["study", str(study), "-o", str(tmp_path / "rep"), "--quiet", "--workers", "1"]) == 0
    )
    page = (tmp_path / "rep" / "evil.html").read_text()
    for raw in (EVIL_SCRIPT, EVIL_NAME):
        assert raw not in page
    assert html.escape(EVIL_SCRIPT) in page  # the description, in the provenance
    assert html.escape(EVIL_NAME) in page  # the configuration, in the tables
    assert page.count("<script>") == 1  # the report's own image check only
    assert "<img src=x" not in page and "onerror=alert" not in page.replace(
        html.escape(EVIL_NAME), ""
    )
    assert "<b onmouseover" not in page


class _Trap:
    """Unpickling this creates the marker file: proof that something was unpickled."""

    marker = None

    def __reduce__(self):
        return (open, (self.marker, "w"))


def test_nothing_is_unpickled_or_evaluated(good_bundle_path, tmp_path, capsys):
    marker = tmp_path / "unpickled-or-evaluated"
    _Trap.marker = str(marker)
    blob = pickle.dumps(_Trap())
    code = f"__import__('pathlib').Path({str(marker)!r}).touch()"
    with h5py.File(good_bundle_path, "a") as f:
        f.attrs["description"] = pickle.dumps(_Trap(), protocol=0).decode("ascii")  # a text pickle
        f["sample"].attrs["molecule"] = code  # Python code
        f["configs/D1"].attrs["description"] = "{" + code + "}"  # an f-string
    b, errors, _ = validate_file(good_bundle_path)
    assert errors == []
    assert b.sample.molecule == code and b.configs["D1"].description == "{" + code + "}"
    assert b.description == pickle.dumps(_Trap(), protocol=0).decode("ascii")
    summarize(b)
    assert main_validate(good_bundle_path) == 0
    # binary pickles in an opaque dataset, in an opaque attribute, and an object reference: refused
    # unread
    with h5py.File(good_bundle_path, "a") as f:
        _replace(f, RD + "/noise_v", np.void(blob))
        f["cavity"].attrs["finesse"] = np.void(blob)
        f["sample"].attrs["line"] = f["cavity"].ref
        f.create_group("truth").create_dataset("model", data=np.void(blob))
    _, errors, _ = validate_file(good_bundle_path)
    found = {v.path: v.message for v in errors}
    assert "compound/opaque datatype; refused (not read)" in found[RD + "/noise_v"]
    assert "compound/opaque datatype; refused (not read)" in found["/cavity@finesse"]
    assert "holds HDF5 object references; refused (not read)" in found["/sample@line"]
    with pytest.raises(BundleError, match="/truth/model: has a compound/opaque datatype; refused"):
        load_truth(good_bundle_path)
    assert main_validate(good_bundle_path) == 1
    capsys.readouterr()
    assert not marker.exists()


def test_the_package_has_no_unpickling_or_eval():
    """What the toolkit reads goes through h5py, json, csv and tomllib only; a code path that could
    unpickle (pickle, numpy allow_pickle, marshal, shelve, yaml.load) or evaluate text would show
    here."""
    pattern = re.compile(
        r"\b(pickle|marshal|shelve|yaml|eval|exec|allow_pickle\s*=\s*True|__import__)\b"
    )
    hits = [
        f"{p.name}:{i}: {line.strip()}"
        for p in sorted((ROOT / "bayes_tfcrds").glob("*.py"))
        for i, line in enumerate(p.read_text().splitlines(), 1)
        if pattern.search(line.split("#")[0])
    ]
    assert hits == [], hits


def test_t_cut_before_the_first_sample_is_refused(campaign, tmp_path, capsys):
    # issue 20 item 5: a record that starts after t_cut gave identical rows for every t_cut
    late = tmp_path / "late.h5"
    shutil.copy(campaign, late)
    with h5py.File(late, "a") as f:
        f["configs/D2/ringdowns"].attrs["t0_s"] = 10e-6
    out = tmp_path / "x.csv"
    assert (
        main(["fit", str(late), "--config", "D2", "--tcut", "2e-6,4e-6,12e-6", "-o", str(out)]) == 1
    )
    assert "t_cut = 2e-06 s is before the first sample" in capsys.readouterr().err
    assert not out.exists()


def test_truth_with_a_hard_link_cycle_is_refused_by_path(tmp_path):
    # issue 20: load_truth recursed for ever (RecursionError) on /truth/a/loop -> /truth/a
    path = tmp_path / "cycle.h5"
    with h5py.File(path, "w") as f:
        a = f.create_group("truth/a")
        a.attrs["x"] = 1.0
        a["loop"] = a  # a hard link to its own parent
    with pytest.raises(BundleError) as info:
        load_truth(path)
    assert any(v.path == "/truth/a/loop" and "cycle" in v.message for v in info.value.violations), (
        info.value
    )


def test_validate_escapes_control_characters_in_the_paths_it_refuses(campaign, tmp_path, capsys):
    # found by the property test (issue 20): the REFUSED list printed a configuration name with
    # an ANSI escape raw (the summary of a good file already escaped it)
    evil = tmp_path / "evil.h5"
    shutil.copy(campaign, evil)
    with h5py.File(evil, "a") as f:
        del f["configs/D2/cmds/nu_hz"]
        f.move("configs/D2", "configs/\x1b[31mD2\n")
    assert main_validate(evil) == 1
    out = capsys.readouterr().out
    assert "error: /configs/\\x1b[31mD2\\n/cmds/nu_hz: required dataset is missing" in out, out
    assert all(line.isprintable() for line in out.splitlines()), out


def test_a_beat_note_without_signal_stops_the_h_fit_at_once():
    # a record built in code (not read from a file) reaches the fit: refused, never a search
    # from a NaN start that does not end (issue 20, found by the CLI property test)
    from types import SimpleNamespace

    from bayes_tfcrds.fit.beat_note import fit_beat_note

    dead = SimpleNamespace(f_hz=np.geomspace(1e3, 4e7, 60), h_mag=np.zeros(60), h_mag_u=None)
    start = time.perf_counter()
    with pytest.raises(ValueError, match="no signal at its lowest frequencies"):
        fit_beat_note(dead)
    assert time.perf_counter() - start < 5
