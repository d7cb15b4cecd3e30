"""``bayes-tfcrds import``: the worked example folder, its import, refusals, and
``linefit --spectrum`` (spectrum-level input) recovering a known line area."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bayes_tfcrds.bundle.reader import load_bundle, load_truth
from bayes_tfcrds.cli import main
from bayes_tfcrds.core.constants import line_area_to_cm2
from bayes_tfcrds.physics.lineshape import doppler_hwhm_hz, voigt


def test_example_folder_imports_to_the_bundle_it_came_from(tmp_path, capsys):
    lab, src, imp = tmp_path / "lab", tmp_path / "src.h5", tmp_path / "imp.h5"
    assert main(["import", "--example", str(lab), "-o", str(src), "--seed", "3"]) == 0
    assert "import it: bayes-tfcrds import" in capsys.readouterr().err
    assert main(["import", str(lab), "-o", str(imp)]) == 0
    a, b = load_bundle(src), load_bundle(imp)
    assert load_truth(src) is not None and load_truth(imp) is None  # truth is not lab data
    for name, cfg in a.configs.items():
        # written in mV, GHz, MHz, kHz: two roundings of 1.1e-16 relative each
        for x, y in (
            (cfg.ringdowns.signal_v, b.configs[name].ringdowns.signal_v),
            (cfg.transfer_function.b12_v, b.configs[name].transfer_function.b12_v),
            (cfg.cmds.shift_hz, b.configs[name].cmds.shift_hz),
        ):
            np.testing.assert_allclose(y, x, rtol=4.5e-16, atol=0)
    # the lab file holds millivolts: an independent look at the unit written
    first = (lab / "D2_ringdowns.csv").read_text().splitlines()[1].split(",")[0]
    assert float(first) == pytest.approx(1e3 * a.configs["D2"].ringdowns.signal_v[0, 0], rel=1e-15)


def test_import_refusals_name_what_to_do(tmp_path, capsys):
    lab = tmp_path / "lab"
    assert main(["import", "--example", str(lab), "--quiet"]) == 0
    assert main(["import", "--example", str(lab)]) == 2
    assert "already holds a lab.toml" in capsys.readouterr().err
    assert main(["import", str(lab)]) == 2
    assert "-o BUNDLE.h5 is required" in capsys.readouterr().err
    text = (lab / "D2_modes.csv").read_text().splitlines()
    text[2] = text[2].replace(",", ",x", 1)
    (lab / "D2_modes.csv").write_text("\n".join(text) + "\n")
    assert main(["import", str(lab), "-o", str(tmp_path / "b.h5")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "D2_modes.csv:3:2:" in err and "is not a number" in err
    assert not (tmp_path / "b.h5").exists()


def test_linefit_spectrum_recovers_a_known_area(tmp_path, capsys):
    """alpha(nu) = A g_R(nu) + loss with known noise: A comes back within 4 of its u."""
    nu0, t_k, mass = 1.9219e14, 296.0, 27.995
    gd = float(doppler_hwhm_hz(nu0, t_k, mass))
    nu = nu0 + np.linspace(-5, 5, 61) * gd
    area, loss, sd = 400.0, 2e-5, 2e-7  # Hz/m, 1/m, 1/m (peak alpha ~ 8e-4 1/m)
    alpha = area * voigt(nu, nu0, gd, 0.05 * gd).real + loss
    alpha += np.random.default_rng(11).normal(0.0, sd, nu.size)
    (tmp_path / "lab.toml").write_text(
        '[sample]\nmolecule = "CO"\nline = "R(23)"\n'
        f'nu0 = "{nu0 / 1e12!r} THz"\npressure = "5 Torr"\npressure_u = "0.0025 Torr"\n'
        f'temperature = "{t_k!r} K"\ntemperature_u = "0.03 K"\nmass = "{mass!r} u"\n'
        '[spectrum]\nfile = "alpha.tsv"\nunits = { nu = "THz", alpha = "1/cm", alpha_u = "1/cm" }\n'
    )
    rows = [f"{n / 1e12!r}\t{a / 100!r}\t{sd / 100!r}" for n, a in zip(nu.tolist(), alpha.tolist())]
    (tmp_path / "alpha.tsv").write_text("nu\talpha\talpha_u\n" + "\n".join(rows) + "\n")
    out = tmp_path / "fit.json"
    args = ["linefit", "--spectrum", str(tmp_path), "--profile", "voigt", "-o", str(out)]
    assert main(args) == 0
    assert "spectrum-level input: no transfer-function rows" in capsys.readouterr().err
    res = json.loads(out.read_text())
    assert res["input"] == "spectrum-level input: no transfer-function rows"
    assert res["method"] == "spectrum" and res["t_cut_s"] is None
    got = res["line_area"]
    # Gaussian noise of known sd: |A - A_true| < 4 u fails by chance once in 16 000
    assert abs(got["value"] - line_area_to_cm2(area)) < 4 * got["u"]
    budget = res["budget"]
    assert budget["input"] == res["input"]
    names = [c["name"] for c in budget["line_area"]["components"]]
    assert names == [
        "line fit (spectrum-level input)",
        "line-shape model (voigt vs sdvp)",
        "temperature T (Doppler width of the line fit)",
    ]
    # the budget's A is linefit.json's, in the same unit (cm^-2; SI only in the *_si twins)
    assert budget["line_area"]["unit"] == got["unit"] == "cm^-2"
    assert budget["line_area"]["value"] == pytest.approx(got["value"], rel=1e-14)
    # its u_c holds the fit's u and more rows (line shape, T): not below it, nor 1e3 times it
    assert 0.999 * got["u"] <= budget["line_area"]["combined_u"] < 1e3 * got["u"]
    # S(296 K) two ways: the budget (reference_intensity_from_area) and the line fit's entry
    # (A/N times intensity_ratio); equal up to rounding when both are right
    assert budget["intensity"]["value"] == pytest.approx(res["intensity"]["value"], rel=1e-12)
    assert main(["linefit", str(out), "--spectrum", str(tmp_path), "-o", str(out)]) == 2
    assert "one of them" in capsys.readouterr().err


def test_readme_lab_toml_imports_the_example_folder(tmp_path):
    """The README's lab.toml, as written, reads the example folder's files."""
    import re
    from pathlib import Path

    from bayes_tfcrds.bundle.labfolder import read_lab_folder

    readme = (Path(__file__).resolve().parents[2] / "README.md").read_text(encoding="utf-8")
    block = re.search(r"```toml\n(.*?)```", readme, re.S).group(1)
    lab = tmp_path / "lab"
    assert main(["import", "--example", str(lab), "--quiet"]) == 0
    (lab / "lab.toml").write_text(block)
    bundle = read_lab_folder(lab)
    assert bundle.sample.temperature_k == pytest.approx(296.0, rel=1e-12)  # 22.85 degC
    assert bundle.cavity.fsr_hz == 203e6 and list(bundle.configs) == ["D2"]
