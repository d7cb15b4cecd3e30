"""The command line end to end, study files, and the reports as a browser renders them."""

import csv
import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from bayes_tfcrds.cli import main
from bayes_tfcrds.fit.ringdown import CSV_COLUMNS
from bayes_tfcrds.studies.spec import StudyError, load_study

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    path = tmp_path_factory.mktemp("cli") / "c.h5"
    assert (
        main(
            [
                "simulate",
                "--preset",
                "letter-D2",
                "--preset",
                "letter-D4",
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


def test_simulate_then_validate(campaign, capsys):
    assert main(["validate", str(campaign)]) == 0
    out = capsys.readouterr().out
    assert "D2" in out and "D4" in out


def test_fit_reports_how_the_ring_downs_moved_each_refined_parameter(campaign, tmp_path, capsys):
    out = tmp_path / "fits.csv"
    args = ["fit", str(campaign), "--config", "D2", "--tcut", "4e-6", "-o", str(out)]
    assert main(args + ["--refine", "f_c_hz,a_r"]) == 0
    err = capsys.readouterr().err
    for name in ("f_c_hz", "a_r"):
        line = next(x for x in err.splitlines() if x.startswith(f"# {name}: beat note"))
        assert "tension z = " in line and "-> refined" in line
    with pytest.raises(SystemExit):
        main(args + ["--refine", "f_c,bogus"])
    assert "expected a comma-separated list" in capsys.readouterr().err


def test_fit_writes_one_row_per_point_and_t_cut(campaign, tmp_path):
    out = tmp_path / "fits.csv"
    assert (
        main(
            [
                "fit",
                str(campaign),
                "--config",
                "D4",
                "--method",
                "tf-crds",
                "--tcut",
                "2e-6,4e-6,8e-6",
                "-o",
                str(out),
            ]
        )
        == 0
    )
    rows = list(csv.DictReader(out.open()))
    from bayes_tfcrds.bundle.reader import load_bundle

    m = load_bundle(campaign).configs["D4"].ringdowns.n_points  # ~21 unique cavity modes
    assert len(rows) == m * 3 and m >= 15
    assert list(rows[0]) == list(CSV_COLUMNS)
    tau = np.array([float(r["tau_s"]) for r in rows])
    u = {
        k: np.array([float(r[k]) for r in rows]) for k in ("tau_u_s", "tau_u_noise_s", "tau_u_h_s")
    }
    # the total is the noise and H parts in quadrature (to the CSV's 5 digits), and H has a part
    assert np.allclose(u["tau_u_s"], np.hypot(u["tau_u_noise_s"], u["tau_u_h_s"]), rtol=1e-3)
    assert np.all(u["tau_u_h_s"] > 0)
    assert np.all((tau > 3e-6) & (tau < 40e-6))
    assert np.median([float(r["chi2_red"]) for r in rows]) < 1.2


def test_linefit_json_and_crds_bias(campaign, tmp_path, capsys):
    out_tf, out_c = tmp_path / "tf.json", tmp_path / "crds.json"
    assert (
        main(
            [
                "linefit",
                str(campaign),
                "--config",
                "D4",
                "--method",
                "tf-crds",
                "--tcut",
                "4e-6",
                "--profile",
                "qsdhcp",
                "-o",
                str(out_tf),
            ]
        )
        == 0
    )
    assert (
        main(
            [
                "linefit",
                str(campaign),
                "--config",
                "D4",
                "--method",
                "crds",
                "--tcut",
                "4e-6",
                "-o",
                str(out_c),
            ]
        )
        == 0
    )
    tf, cr = json.loads(out_tf.read_text()), json.loads(out_c.read_text())
    for key in ("line_area", "reference_area"):
        assert set(tf[key]) >= {"value", "u", "unit"} and tf[key]["unit"] == "cm^-2"
    # one unit for A in every output of the command: the fit's parameter and the notes on stderr
    par = tf["parameters"]["line_area"]
    assert (par["value"], par["unit"], par["unit_si"]) == (
        tf["line_area"]["value"],
        "cm^-2",
        "Hz/m",
    )
    assert par["u"] <= tf["line_area"]["u"]  # the line fit's u, without H's
    assert tf["parameters"]["gamma0_hz"]["unit"] == "Hz"
    assert "Hz/m" not in capsys.readouterr().err + out_tf.read_text().replace(
        '"unit_si": "Hz/m"', ""
    )
    assert set(tf["ratio"]) >= {"value", "u"}
    assert abs(tf["ratio"]["value"] - 1) < 4 * tf["ratio"]["u"]
    assert cr["ratio"]["value"] < 0.95  # D4: the letter's -8 %


def test_bad_invocations_give_clear_errors(campaign, tmp_path, capsys):
    assert main(["fit", str(campaign), "--config", "D9", "-o", str(tmp_path / "x.csv")]) == 1
    assert capsys.readouterr().err.startswith("error: no configuration 'D9'")
    assert (
        main(["fit", str(campaign), "--config", "D2", "--tcut", "1", "-o", str(tmp_path / "x.csv")])
        == 1
    )
    assert "beyond the record" in capsys.readouterr().err
    assert main(["simulate", "--effect", "nonsense", "-o", str(tmp_path / "y.h5")]) == 2
    assert not (tmp_path / "x.csv").exists()


def test_study_files_are_validated_with_the_key_named(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('[study]\nname = "x"\nkind = "tcut"\n[analysis]\nt_cut_usx = 4\n')
    with pytest.raises(StudyError, match=r"analysis\.t_cut_usx.*did you mean analysis\.t_cut_us"):
        load_study(bad)
    bad.write_text('[study]\nname = "x"\nkind = "tcut"\n[campaign]\npoints = "many"\n')
    with pytest.raises(StudyError, match=r"campaign\.points: expected int"):
        load_study(bad)
    bad.write_text('[study]\nname = "x"\nkind = "tcut"\n[analysis]\nshape_bounds = "loose"\n')
    with pytest.raises(StudyError, match=r"analysis\.shape_bounds must be 'free' or 'physical'"):
        load_study(bad)
    bad.write_text('[study]\nname = "x"\nkind = "nope"\n')
    with pytest.raises(StudyError, match="study.kind"):
        load_study(bad)
    for shipped in (ROOT / "studies").glob("*.toml"):
        load_study(shipped)  # every shipped study is valid


def _chromium():
    return shutil.which("chromium") or shutil.which("chromium-browser")


def _rendered_dom(exe, html_path, profile_dir) -> str:
    """The page's DOM after headless Chromium has loaded it (no network, a fresh profile)."""
    return subprocess.run(
        [
            exe,
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            f"--user-data-dir={profile_dir}",
            "--virtual-time-budget=5000",
            "--dump-dom",
            Path(html_path).as_uri(),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    ).stdout


def test_small_study_report_renders_in_a_browser(tmp_path):
    study = tmp_path / "s.toml"
    study.write_text(
        '[study]\nname = "s"\nkind = "tcut"\nseed = 2\ntitle = "<script>alert(1)</script> t"\n'
        '[campaign]\npresets = ["letter-D4"]\npoints = 21\nsamples = 4096\naverages = 10\n'
        "[analysis]\nt_cuts_us = [4, 8]\n"
    )
    assert (
        main(["study", str(study), "-o", str(tmp_path / "rep"), "--quiet", "--workers", "1"]) == 0
    )
    html = (tmp_path / "rep" / "s.html").read_text()
    assert (
        "<script>alert(1)</script>" not in html and "&lt;script&gt;alert(1)&lt;/script&gt;" in html
    )
    assert (tmp_path / "rep" / "s.pdf").stat().st_size > 1000
    assert "sha256 campaign.h5" in html and "git_commit" in html
    exe = _chromium()
    if exe is None:
        pytest.skip("chromium is not installed (.ci/run installs it)")
    dom = _rendered_dom(exe, tmp_path / "rep" / "s.html", tmp_path / "chromium")
    assert 'data-images-ok="true"' in dom
    assert 'data-image-count="1"' in dom


def test_committed_reports_render_in_a_browser(tmp_path):
    exe = _chromium()
    if exe is None:
        pytest.skip("chromium is not installed (.ci/run installs it)")
    for html in (ROOT / "reports").glob("*/*.html"):
        dom = _rendered_dom(exe, html, tmp_path / html.stem)
        assert 'data-images-ok="true"' in dom, html


def test_cmds_that_does_not_overlap_the_ring_downs_is_refused(campaign):
    from dataclasses import replace

    from bayes_tfcrds.bundle.reader import load_bundle
    from bayes_tfcrds.fit.line_analysis import LineFitError, analyse_line

    b = load_bundle(campaign)
    cfg = b.configs["D2"]
    far = replace(cfg.cmds, nu_hz=cfg.cmds.nu_hz + 1e12)  # 1 THz away from the line
    with pytest.raises(LineFitError, match=r"/configs/D2/cmds/nu_hz .* does not overlap"):
        analyse_line(b, replace(cfg, cmds=far), method="crds")


def test_records_too_short_for_the_decay_are_flagged(tmp_path):
    out = tmp_path / "short.h5"
    # 1024 samples at 20 ns: 20 us of record, shorter than twice the 32 us empty-cavity decay
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
                str(out),
            ]
        )
        == 0
    )
    csv_out = tmp_path / "f.csv"
    assert (
        main(
            [
                "fit",
                str(out),
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
    rows = list(csv.DictReader(csv_out.open()))
    status = {r["status"] for r in rows}
    assert "record-short" in status  # the baseline decays
    long_tau = max(rows, key=lambda r: float(r["tau_s"]))
    assert long_tau["status"] == "record-short"


@pytest.mark.parametrize(
    "name", ["../../../x", "a/b", "", ".hidden", "$\\frac{1}$", "x" * 65, "new\nline"]
)
def test_study_name_is_a_file_stem_never_a_path(tmp_path, name):
    # issue 20 item 6: the name becomes the report's file name inside -o
    bad = tmp_path / "bad.toml"
    bad.write_text(f'[study]\nname = {name!r}\nkind = "tcut"\n'.replace("'", '"'))
    with pytest.raises(StudyError, match=r"study\.name"):
        load_study(bad)


def test_study_seed_must_be_non_negative(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('[study]\nname = "ok_name-1.2"\nkind = "tcut"\nseed = -1\n')
    with pytest.raises(StudyError, match=r"study\.seed"):
        load_study(bad)


@pytest.mark.parametrize(
    "body, phrase",
    [
        ("[analysis]\nt_cuts_us = [4000]\n", r"analysis\.t_cuts_us must be"),
        ("[analysis]\nt_cuts_us = [nan]\n", r"analysis\.t_cuts_us must be"),
        ("[analysis]\nt_cuts_us = [inf]\n", r"analysis\.t_cuts_us must be"),
        ("[analysis]\nt_cuts_us = []\n", r"analysis\.t_cuts_us must be"),
        ("[analysis]\nmethods = []\n", r"analysis\.methods is empty"),
        ("[campaign]\npresets = []\n", r"campaign\.presets is empty"),
        ("[analysis]\nmcmc_steps = -5\n", r"analysis\.mcmc_steps must be"),
    ],
)
def test_study_values_that_cannot_run_are_refused(tmp_path, body, phrase):
    # issue 20: each of these ran (or crashed) instead of being refused with the key named
    bad = tmp_path / "bad.toml"
    bad.write_text('[study]\nname = "x"\nkind = "tcut"\n' + body)
    with pytest.raises(StudyError, match=phrase):
        load_study(bad)


def test_study_file_that_is_not_text_or_is_a_folder_is_refused(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_bytes(b'[study]\nname = "\xff\xfe"\n')
    with pytest.raises(StudyError, match="not UTF-8"):
        load_study(bad)
    with pytest.raises(StudyError, match="is a folder"):
        load_study(tmp_path)


@pytest.fixture(scope="module")
def small_bundle(tmp_path_factory):
    path = tmp_path_factory.mktemp("study_bundle") / "d2.h5"
    argv = ["simulate", "--points", "9", "--samples", "2048", "--seed", "1", "-o", str(path)]
    assert main(argv) == 0
    return path


def _study_on(tmp_path, bundle, kind="tcut"):
    study = tmp_path / "s.toml"
    study.write_text(
        f'[study]\nname = "s"\nkind = "{kind}"\n[campaign]\nbundle = "{bundle}"\n'
        "[analysis]\nt_cuts_us = [2, 4]\nmcmc_steps = 50\n"
    )
    return study


def _no_cmds(src, dst):
    import h5py

    shutil.copy(src, dst)
    with h5py.File(dst, "a") as f:
        del f["configs/D2/cmds"]


@pytest.mark.parametrize(
    "damage, kind, phrase",
    [
        ("missing", "tcut", "campaign.bundle: {b}: not a valid bundle: /: file not found"),
        ("truncated", "tcut", "not a valid bundle: /: truncated or corrupt HDF5 file"),
        ("no cmds", "tcut", "a tcut study compares each configuration with its CMDS reference"),
        ("no cmds", "window_history", "has no /cmds in ['D2']"),
        ("no cmds", "budgets", "has no /cmds in ['D2']"),
    ],
)
def test_a_study_bundle_it_cannot_use_is_refused_before_any_work(
    small_bundle, tmp_path, capsys, damage, kind, phrase
):
    # issue 20: a missing or truncated bundle gave a traceback (and left an empty report folder);
    # without /cmds the tcut and window_history studies crashed on None after their fits, and a
    # budgets study after its whole MCMC run
    bundle = tmp_path / "b.h5"
    if damage == "truncated":
        bundle.write_bytes(small_bundle.read_bytes()[:50000])
    elif damage == "no cmds":
        _no_cmds(small_bundle, bundle)
    out = tmp_path / "report"
    assert main(["study", str(_study_on(tmp_path, bundle, kind)), "--quiet", "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1, err
    assert phrase.format(b=bundle) in err, err
    assert not out.exists()


@pytest.mark.parametrize("kind", ["tcut", "figures", "window_history"])
def test_a_configuration_name_with_dollars_is_drawn_as_text(small_bundle, tmp_path, kind):
    # issue 20: matplotlib read a configuration named $\frac{1}$ as mathtext and the study ended
    # in a parse error after all its work, with an empty report folder
    import h5py

    bundle = tmp_path / "frac.h5"
    shutil.copy(small_bundle, bundle)
    with h5py.File(bundle, "a") as f:
        f.move("configs/D2", "configs/$\\frac{1}$")
    out = tmp_path / "report"
    argv = ["study", str(_study_on(tmp_path, bundle, kind)), "--quiet", "--workers", "1"]
    assert main([*argv, "-o", str(out)]) == 0
    assert (out / "s.html").is_file() and (out / "s.pdf").is_file()
    assert "frac{1}" in (out / "numbers.json").read_text()  # the configuration was analysed


def test_linefit_json_stays_json_when_a_shape_parameter_is_held_at_its_bound(
    small_bundle, tmp_path, capsys
):
    # found by the property test (issue 20): the correlation row of a parameter held at 0 by
    # --shape-bounds physical was NaN, written as the non-JSON token NaN
    out = tmp_path / "line.json"
    argv = ["linefit", str(small_bundle), "--shape-bounds", "physical", "-o", str(out)]
    assert main(argv) == 0

    def refuse(token):
        raise ValueError(f"{token} in {out}")

    result = json.loads(out.read_text(), parse_constant=refuse)
    held = result["shape_at_bound"]
    assert held, "this bundle's Gamma2 ends at 0 under physical bounds (the case under test)"
    names, matrix = result["correlation"]["names"], result["correlation"]["matrix"]
    for i, name in enumerate(names):
        if name in held:  # undefined for u = 0: null, in its row and its column
            assert matrix[i] == [None] * len(names)
            assert all(row[i] is None for row in matrix)
        else:
            assert matrix[i][i] == 1.0
