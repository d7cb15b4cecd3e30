"""The public API: ``import bayes_tfcrds as bt`` gives the main job in a few lines, lazily."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

import bayes_tfcrds as bt

README = Path(__file__).resolve().parents[1] / "README.md"


def test_every_public_name_resolves_to_its_defining_module():
    for name in bt.__all__:
        obj = getattr(bt, name)
        if name != "__version__":
            assert obj.__module__ == bt._API[name], name
    assert set(bt.__all__) == {"__version__", *bt._API}
    with pytest.raises(AttributeError):
        bt.no_such_name  # noqa: B018


def test_no_public_name_is_shadowed_by_a_subpackage():
    """Importing a subpackage sets it as an attribute of the package: a public name equal to a
    subpackage's would then resolve to the module instead of the function."""
    subpackages = {p.parent.name for p in Path(bt.__file__).parent.glob("*/__init__.py")}
    assert not subpackages & set(bt.__all__)


def test_import_is_lazy():
    """Importing the package (as the CLI does at start) loads no numerical stack."""
    code = (
        "import sys, bayes_tfcrds; print(sorted(m for m in ('numpy', 'scipy', 'h5py', 'emcee') if "
        "m in sys.modules))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout
    assert out.strip() == "[]"


def test_readme_python_section_runs_as_written(tmp_path, monkeypatch):
    """Every ```python block of the README's "Python" section, as written, in a fresh folder.

    TF-CRDS A/A_ref within 4 of its own u of 1 (the simulated CMDS reference measures the same
    line; 4 sigma keeps a false alarm below 1e-4); the budget passes its gates and agrees with
    the line fit's A within the budget's u_c (the fit's u is part of it); the figures are drawn.
    """
    text = README.read_text(encoding="utf-8")
    section = text.split("\n## Python\n", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```python\n(.*?)```", section, re.S)
    assert blocks, "the README's Python section has no python block"
    monkeypatch.chdir(tmp_path)
    namespace = {}
    for block in blocks:
        exec(compile(block, "README.md", "exec"), namespace)  # noqa: S102 - our own documentation
    line, budget = namespace["line"], namespace["budget"]
    assert isinstance(line, bt.LineAnalysis) and line.line_area.unit == "cm^-2"
    assert abs(line.ratio.value - 1) < 4 * line.ratio.u
    assert line.to_dict()["ratio"] == {"value": line.ratio.value, "u": line.ratio.u}
    assert budget.passed, budget.status
    assert abs(budget.line_area.value - line.line_area.value) < budget.line_area.u
    assert namespace["record"]["line_area"]["unit"] == "cm^-2"
    assert (tmp_path / "line.png").stat().st_size > 10_000
