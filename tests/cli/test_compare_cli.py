"""``bayes-tfcrds compare``: budget.json files and a CSV in, comparison files out.

The two budget.json files are the D1 and D2 budgets recorded in reports/budget_D1_D4/numbers.json
(the committed output of ``bayes-tfcrds budget``, same structure), so the reader is checked on
real budget output rather than on a shape written by hand.
"""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from bayes_tfcrds.cli import main

ROOT = Path(__file__).resolve().parents[2]
RECORDED = json.loads((ROOT / "reports/budget_D1_D4/numbers.json").read_text())["configs"]


@pytest.fixture
def inputs(tmp_path):
    for name in ("D1", "D2"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "budget.json").write_text(json.dumps(RECORDED[name]))
    # one lab in m/molecule with U and k, one in cm/molecule: both end up in cm/molecule
    (tmp_path / "others.csv").write_text(
        "# results from elsewhere\n"
        "lab,value,U,k,unit,dof\n"
        "HITRAN,8.0603e-25,1.4e-27,2,cm/molecule,\n"
        "LabX,8.07e-27,2.4e-29,2,m/molecule,12\n"
    )
    (tmp_path / "corr.csv").write_text("lab_a,lab_b,r\nD1,second,0.8\n")
    return tmp_path


def run(inputs, *extra):
    d = inputs
    args = ["compare", str(d / "D1"), f"second={d / 'D2' / 'budget.json'}", str(d / "others.csv")]
    return main([*args, "-o", str(d / "out"), "--quiet", *extra])


def test_compare_writes_every_file_and_uses_one_unit(inputs, capsys):
    assert run(inputs, "--correlations", str(inputs / "corr.csv")) == 0
    out = inputs / "out"
    for name in ("comparison.json", "comparison.md", "comparison.csv", "doe.png", "doe.svg"):
        assert (out / name).stat().st_size > 0, name
    data = json.loads((out / "comparison.json").read_text())
    assert data["labs"] == ["D1", "second", "HITRAN", "LabX"]
    assert data["unit"] == "cm/molecule" and data["reference_si"]["unit"] == "m/molecule"
    s1, s2 = (RECORDED[k]["intensity"] for k in ("D1", "D2"))
    # every value in cm/molecule: the m/molecule row is x100, U/k gives the standard u
    assert data["values"] == pytest.approx([s1["value"], s2["value"], 8.0603e-25, 8.07e-25])
    assert data["u"] == pytest.approx([s1["u"], s2["u"], 7e-28, 1.2e-27])
    assert data["correlation"][0][1] == 0.8 and data["dof"]["LabX"] == 12
    # the reference is the GLS mean of the four with the declared correlation
    u = np.array(data["u"])
    r = np.eye(4)
    r[0, 1] = r[1, 0] = 0.8
    vinv_1 = np.linalg.solve(r * np.outer(u, u), np.ones(4))
    assert data["reference"]["value"] == pytest.approx(vinv_1 @ data["values"] / vinv_1.sum())
    # the csv holds the same degrees of equivalence as the json
    rows = (out / "comparison.csv").read_text().splitlines()
    assert rows[0].startswith("lab,value,u,d,u_d,U_d,en,zeta,unit")
    d_csv = [float(row.split(",")[3]) for row in rows[1:]]
    assert d_csv == pytest.approx([e["d"] for e in data["equivalence"]], rel=1e-6)  # %.6e
    assert "x_ref =" in capsys.readouterr().out


def test_the_png_is_at_least_200_dpi(inputs):
    from PIL import Image

    assert run(inputs) == 0
    dpi = Image.open(inputs / "out" / "doe.png").info["dpi"]
    assert min(dpi) >= 199.9  # PNG stores pixels per metre: 200 dpi reads back as 199.999


def test_a_laboratory_or_a_stated_value_as_reference(inputs):
    assert run(inputs, "--reference", "HITRAN") == 0
    data = json.loads((inputs / "out" / "comparison.json").read_text())
    assert data["reference"]["value"] == 8.0603e-25
    assert data["equivalence"][2]["en"] is None  # the reference against itself
    assert run(inputs, "--reference", "8.0603e-25,7e-28") == 0
    data = json.loads((inputs / "out" / "comparison.json").read_text())
    assert data["reference"]["method"] == "stated value"
    assert data["equivalence"][2]["u"] == pytest.approx(math.sqrt(2) * 7e-28)


def test_the_ratio_of_a_budget(inputs):
    d = inputs
    args = ["compare", str(d / "D1"), str(d / "D2"), "--quantity", "ratio", "-o", str(d / "q")]
    assert main(args) == 0
    data = json.loads((d / "q" / "comparison.json").read_text())
    assert data["unit"] == "1" and "reference_si" not in data
    assert data["values"][0] == RECORDED["D1"]["ratio"]["value"]


def test_a_line_area_in_hz_per_m_is_converted_to_cm2(inputs):
    # the budget's own pair of fields (value in cm^-2, value_si in Hz/m) is the oracle
    a = RECORDED["D1"]["line_area"]
    (inputs / "a.csv").write_text(f"lab,value,u,unit\nSI,{a['value_si']!r},{a['u_si']!r},Hz/m\n")
    args = ["compare", str(inputs / "D1"), str(inputs / "a.csv"), "--quantity", "line_area"]
    assert main([*args, "-o", str(inputs / "a")]) == 0
    data = json.loads((inputs / "a" / "comparison.json").read_text())
    assert data["unit"] == "cm^-2" and data["reference_si"]["unit"] == "Hz/m"
    assert data["values"][1] == pytest.approx(a["value"], rel=1e-14)  # one product, rounding
    assert data["u"][1] == pytest.approx(a["u"], rel=1e-14)
    assert data["reference_si"]["value"] == pytest.approx(a["value_si"], rel=1e-12)


@pytest.mark.parametrize(
    "csv_text, message",
    [
        ("lab,value,u\nA,1e-25,1e-28\n", "line 1: missing column(s) unit"),
        ("lab,value,u,unit\nA,1e-25,oops,cm/molecule\n", "line 2, column u: expected a finite"),
        ("lab,value,u,unit\n\nA,1e-25,1e-28,cm^-1\n", "line 3, column unit: unit 'cm^-1'"),
        ("lab,value,u,unit\nA,1e-25,1e-28\n", "line 2: 3 columns where the header has 4"),
    ],
)
def test_a_bad_csv_names_file_line_and_column(inputs, capsys, csv_text, message):
    bad = inputs / "bad.csv"
    bad.write_text(csv_text)
    assert main(["compare", str(inputs / "D1"), str(bad), "-o", str(inputs / "x")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1
    assert str(bad) in err and message in err
    assert not (inputs / "x" / "comparison.json").exists()


def test_bad_correlations_and_failed_budgets_are_refused(inputs, capsys):
    (inputs / "c.csv").write_text("lab_a,lab_b,r\nD1,NOPE,0.5\n")
    assert run(inputs, "--correlations", str(inputs / "c.csv")) == 1
    assert "line 2, column lab_b: 'NOPE'" in capsys.readouterr().err
    failed = dict(RECORDED["D1"], status="failed: convergence gates not met", intensity=None)
    (inputs / "D1" / "budget.json").write_text(json.dumps(failed))
    assert run(inputs) == 1
    assert "budget failed its gates" in capsys.readouterr().err


def test_compare_reproduces_the_iupac_guide_example_4f(tmp_path, capsys):
    """CCQM-K145 Ni in bovine liver as a CSV of another measurand (mg/kg), REML + Knapp-Hartung.

    Published (Possolo et al., IUPAC Technical Report 2024, Example 4F; digits as printed):
    Q = 40.1205 on 16 dof, p = 0.0007, tau = 0.0463, consensus 2.0428, se 0.0159,
    95 % interval [2.0091, 2.0765] mg/kg. See tests/uncertainty/test_random_effects.py.
    """
    rows = (
        "JSI 1.930 0.110|INMC 1.940 0.064|GLHK 1.942 0.092|LNE 1.958 0.075|NIST 1.984 0.020|"
        "KRISS 1.993 0.033|INACAL 2.010 0.060|NMIA 2.020 0.050|NIM 2.022 0.023|NMIJ 2.050 0.020|"
        "RISE 2.055 0.052|NRC 2.070 0.050|PTB 2.077 0.035|LATU 2.080 0.059|LGC 2.131 0.042|"
        "UME 2.150 0.030|HSA 2.180 0.080"
    )
    lines = ["lab,value,u,unit"] + [",".join(r.split()) + ",mg/kg" for r in rows.split("|")]
    (tmp_path / "ni.csv").write_text("\n".join(lines) + "\n")
    args = ["compare", str(tmp_path / "ni.csv"), "--quantity", "other", "--random-effects"]
    out = tmp_path / "out"
    assert main([*args, "REML", "--knapp-hartung", "-o", str(out), "--quiet"]) == 0
    data = json.loads((out / "comparison.json").read_text())
    ref, cons = data["reference"], data["consistency"]
    assert data["unit"] == "mg/kg" and "reference_si" not in data
    assert (round(cons["chi2"], 4), cons["dof"], round(cons["p_value"], 4)) == (40.1205, 16, 0.0007)
    assert (round(ref["tau"], 4), round(ref["value"], 4), round(ref["u"], 4)) == (
        0.0463,
        2.0428,
        0.0159,
    )
    assert [round(v, 4) for v in ref["interval"]] == [2.0091, 2.0765]
    md = (out / "comparison.md").read_text()
    assert "Dark uncertainty tau" in md and "Student's t, 16 dof" in md


def test_compare_refuses_other_results_in_two_units_and_a_stray_knapp_hartung(tmp_path):
    (tmp_path / "mixed.csv").write_text("lab,value,u,unit\nA,1.0,0.1,mg/kg\nB,1.1,0.1,g/kg\n")
    base = ["compare", str(tmp_path / "mixed.csv"), "-o", str(tmp_path / "o"), "--quiet"]
    assert main([*base, "--quantity", "other"]) != 0
    (tmp_path / "one.csv").write_text("lab,value,u,unit\nA,1.0,0.1,mg/kg\nB,1.1,0.1,mg/kg\n")
    one = ["compare", str(tmp_path / "one.csv"), "-o", str(tmp_path / "p"), "--quiet"]
    assert main([*one, "--quantity", "other", "--knapp-hartung"]) != 0
    assert main([*one, "--quantity", "other", "--reference", "A", "--random-effects", "DL"]) != 0
    assert main([*one, "--quantity", "other"]) == 0


def test_compare_points_a_failed_chi2_test_and_a_foreign_unit_to_what_to_do(tmp_path, capsys):
    (tmp_path / "far.csv").write_text(
        "lab,value,u,unit\nA,1.0,0.01,mg/kg\nB,1.5,0.01,mg/kg\nC,2.0,0.01,mg/kg\n"
    )
    base = ["compare", str(tmp_path / "far.csv"), "-o", str(tmp_path / "o")]
    assert main([*base, "--quantity", "other"]) == 0
    assert "--random-effects" in capsys.readouterr().err
    assert "--random-effects" in (tmp_path / "o" / "comparison.md").read_text()
    assert main(base) != 0  # mg/kg is not a unit of S: the message names --quantity other
    assert "--quantity other" in capsys.readouterr().err
