"""The command line under random options and random damage to its bundle (issue 20, "done when").

Hypothesis draws a command (validate, fit, linefit, simulate, and budget with at most six
sampler steps; ``BAYES_TFCRDS_CLI_BUDGET=0`` leaves budget out), option values (0, negative,
nan, inf, huge numbers, names with ``/``, ``..`` and control characters) and edits to a small
bundle (a dataset dropped, a value scaled by 1e+-300, a NaN, a shape changed, a frequency
repeated, a configuration renamed).
Whatever it draws, ``main`` must

* return an exit status (argparse's ``SystemExit(2)`` for a malformed option is fine) and raise
  nothing else;
* on a refusal, end stderr in one ``error:`` line with no control character, after nothing but
  progress and warning lines;
* on success, write finite results: every JSON parses without NaN or Infinity, every number of
  the fit CSV is finite where the fit says "ok";
* create nothing outside ``-o`` (the file, or the folder and what is inside it), and leave no
  temporary file behind;
* end within two minutes (on a bundle that takes seconds).

The examples are derandomised (CI sees the same ones every run). ``BAYES_TFCRDS_CLI_EXAMPLES``
raises their number for a longer local search.
"""

from __future__ import annotations

import contextlib
import csv
import functools
import io
import json
import math
import os
import shutil
import signal
import tempfile
from pathlib import Path

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from bayes_tfcrds.cli import main

EXAMPLES = int(os.environ.get("BAYES_TFCRDS_CLI_EXAMPLES", "100"))
WITH_BUDGET = os.environ.get("BAYES_TFCRDS_CLI_BUDGET", "1") == "1"

#: stderr lines a command may print before its error line (progress, warnings, notes)
PROGRESS = ("# ", "H refinement: ", "warning: ", "note: ", "finding: ")

NUMBERS = st.sampled_from(
    ["0", "-1", "1", "nan", "-nan", "inf", "-inf", "1e300", "-1e300", "1e-300", "4e-6", "2e-6"]
    + ["8e-6", "3.9e-5", "1e-3", "", ",", "4e-6,4e-6", "2e-6,nan", "1e5", "0x10", "1_0", " 4e-6"]
)
INTEGERS = st.one_of(
    st.sampled_from(["0", "1", "-1", "2", "8", "9", "10", "256", "1024", "100000000", "1e3", ""]),
    st.integers(-(2**70), 2**70).map(str),
)
NAMES = st.one_of(
    st.sampled_from(["D2", "D4", "d2", "", "/", "..", "../D2", "D2/x", "D2\n", "\x1b[31mD2", "$"]),
    st.text(st.characters(codec="utf-8", exclude_characters="\x00"), max_size=6),
)
OUT_NAMES = st.sampled_from(
    ["out", "a/b/out", "a/../out", "out.x", ".out", "o\nut", "o\x1b[2Jut", "o ut", "out/"]
)
EFFECTS = st.one_of(
    st.sampled_from(
        [
            "etalon",
            "extinction_tail:tau_s=0",
            "extinction_tail:tau_s=1e-5,fraction=0",
            "second_mode:fraction=-1",
            "second_mode:tau_ratio=nan",
            "speed_dependence:gamma2_ratio=-10",
            "static_nonlinearity:kind=power,gamma=0.01",
            "static_nonlinearity:kind=../x",
            "mode_beating:freq_hz=inf",
            "neighbour_line:offset_hz=0,intensity_ratio=10",
            "baseline_drift:slope_v_per_s=1e6",
            "transfer_function",
            "transfer_function:x=1",
            "nonsense",
            ":",
            "etalon:=",
            "etalon:period_hz",
        ]
    ),
    st.builds(
        lambda k, v: f"etalon:{k}={v}",
        st.sampled_from(["amplitude_per_m", "period_hz", "phase_rad"]),
        NUMBERS,
    ),
)


# ----------------------------------------------------------------------------- the bundle
@pytest.fixture(scope="module")
def base_bundle(tmp_path_factory):
    path = tmp_path_factory.mktemp("prop") / "base.h5"
    argv = ["simulate", "--points", "9", "--samples", "2048", "--seed", "1", "-o", str(path)]
    with contextlib.redirect_stderr(io.StringIO()):
        assert main(argv) == 0
    return path


@functools.cache
def _numeric_places(path):
    """Every numeric dataset and numeric attribute of the bundle (the places edits act on)."""
    datasets, attrs = [], []
    with h5py.File(path, "r") as f:

        def visit(name, obj):
            for key, value in obj.attrs.items():
                if np.issubdtype(np.asarray(value).dtype, np.number):
                    attrs.append((name, key))
            if isinstance(obj, h5py.Dataset) and np.issubdtype(obj.dtype, np.number):
                datasets.append(name)

        f.visititems(visit)
        for key, value in f.attrs.items():
            if np.issubdtype(np.asarray(value).dtype, np.number):
                attrs.append(("/", key))
    return sorted(datasets), sorted(attrs)


def _renamed(path: str, current: str) -> str:
    """``path`` inside the configuration under its current name (a drawn rename comes first)."""
    head = "configs/D2"
    return f"configs/{current}{path[len(head) :]}" if path.startswith(head) else path


def _edit(f, edit) -> None:
    """Apply one drawn edit to the open bundle ``f``."""
    kind, where, arg = edit
    (current,) = f["configs"]  # the one configuration, under its latest name
    if kind == "rename":  # a configuration name from the drawn text
        if "/" not in arg and arg not in ("", ".", "..") and arg not in f["configs"]:
            f["configs"].move(current, arg)
        return
    if kind == "attr":
        group, key = where
        group = _renamed(group, current)
        f[group].attrs[key] = np.asarray(f[group].attrs[key]) * arg
        return
    where = _renamed(where, current)
    if where not in f:  # an earlier edit removed or renamed it
        return
    data = f[where][()]
    if kind == "drop":
        del f[where]
        return
    if kind == "scale":
        data = data * arg
    elif kind == "nan" and data.size and np.issubdtype(data.dtype, np.floating):
        data = data.copy()
        data.flat[arg % data.size] = np.nan
    elif kind == "shape" and data.ndim:
        data = data[:-1] if arg else np.concatenate([data, data[-1:]])
    elif kind == "repeat" and data.ndim and data.shape[0] > 1:
        data = data.copy()
        data[1] = data[0]
    del f[where]
    f[where] = data


def _edits(datasets, attrs):
    factors = st.sampled_from([0.0, -1.0, 1e300, 1e-300, -1e-300, 1e30, 1e-30, np.nan, np.inf])
    one = st.one_of(
        st.tuples(st.just("drop"), st.sampled_from(datasets), st.none()),
        st.tuples(st.just("scale"), st.sampled_from(datasets), factors),
        st.tuples(st.just("nan"), st.sampled_from(datasets), st.integers(0, 10**6)),
        st.tuples(st.just("shape"), st.sampled_from(datasets), st.booleans()),
        st.tuples(
            st.just("repeat"),
            st.sampled_from([d for d in datasets if d.endswith("nu_hz")]),
            st.none(),
        ),
        st.tuples(st.just("attr"), st.sampled_from(attrs), factors),
        st.tuples(st.just("rename"), st.none(), NAMES),
    )
    return st.lists(one, max_size=3)


# ----------------------------------------------------------------------------- the commands
def _options(draw, command):
    """Option words for ``command``; each option appears with probability 1/2."""
    words = []

    def maybe(option, strategy):
        if draw(st.booleans()):
            words.append(f"{option}={draw(strategy)}")

    if command in ("fit", "linefit", "budget"):
        maybe("--config", NAMES)
        maybe("--method", st.sampled_from(["crds", "tf-crds", "CRDS", ""]))
        maybe("--window", st.sampled_from(["extinction", "letter", "x"]))
        maybe("--tcut", NUMBERS)
        maybe("--seed", INTEGERS)
    if command == "fit":
        maybe("--transfer-function", st.sampled_from(["refined", "beat"]))
        maybe("--refine", st.sampled_from(["f_c_hz", "f_c_hz,a_r", "n_r", "", ",", "x"]))
    if command == "linefit":
        maybe("--profile", st.sampled_from(["voigt", "sdvp", "rautian", "qsdhcp", "x"]))
        maybe("--shape-bounds", st.sampled_from(["free", "physical", ""]))
    if command == "budget":
        words += ["--quiet", "--profile=voigt"]
        words += [f"--steps={draw(st.integers(-1, 3))}", f"--max-steps={draw(st.integers(0, 6))}"]
    if command == "simulate":
        words += ["--points=9"] if draw(st.booleans()) else [f"--points={draw(INTEGERS)}"]
        words += ["--samples=1024"] if draw(st.booleans()) else [f"--samples={draw(INTEGERS)}"]
        for _ in range(draw(st.integers(0, 2))):
            words.append(f"--preset={draw(st.sampled_from(['letter-D2', 'letter-D4', 'x']))}")
        for _ in range(draw(st.integers(0, 2))):
            words.append(f"--effect={draw(EFFECTS)}")
        maybe("--seed", INTEGERS)
    return words


COMMANDS = ["validate", "fit", "linefit", "simulate"] + (["budget"] if WITH_BUDGET else [])


@st.composite
def invocations(draw, datasets, attrs):
    command = draw(st.sampled_from(COMMANDS))
    edits = [] if command == "simulate" else draw(_edits(datasets, attrs))
    out = None if command == "validate" else draw(OUT_NAMES)
    return command, edits, _options(draw, command), out


# ----------------------------------------------------------------------------- the checks
#: longest one command may take on the small bundle (a few seconds) before it counts as hung
HUNG_S = 120


def _hung(signum, frame):
    raise TimeoutError(f"the command ran longer than {HUNG_S} s")


def _run(argv):
    """(exit status, stdout, stderr, argparse?) of ``main(argv)``; any other exception raises."""
    out, err = io.StringIO(), io.StringIO()
    parse_error = False
    previous = signal.signal(signal.SIGALRM, _hung)
    signal.alarm(HUNG_S)  # a search that never ends is a defect too (a 0 V beat note was one)
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main(argv)
        except SystemExit as exc:  # argparse refuses a malformed option this way, and only it
            assert exc.code == 2, (exc.code, argv)
            code, parse_error = 2, True
        finally:
            signal.alarm(0)
            signal.signal(signal.SIGALRM, previous)
    assert isinstance(code, int), (code, argv)
    return code, out.getvalue(), err.getvalue(), parse_error


def _strict_json(text: str):
    def refuse(name):
        raise ValueError(f"{name} in JSON")

    return json.loads(text, parse_constant=refuse)


def _check_stderr(code, out, err, parse_error, argv) -> None:
    lines = err.splitlines()
    assert "Traceback" not in err + out, (argv, err)
    if argv[0] == "validate" and not parse_error:  # its report is the list of every problem
        assert code in (0, 1) and not err, (argv, err)
        assert ("REFUSED" in out) == (code == 1), (argv, out)
        assert all(line.isprintable() for line in out.splitlines()), (argv, out)
        return
    if parse_error:
        assert lines and ": error: " in lines[-1], (argv, err)
        return
    assert all(line.isprintable() for line in lines), (argv, err)
    if code in (1, 2):
        assert lines and lines[-1].startswith("error: "), (argv, err)
        assert all(line.startswith(PROGRESS) for line in lines[:-1]), (argv, err)
    elif code == 3:  # a run whose result failed its checks: said, not hidden
        assert any(line.startswith("FAILED") for line in lines), (argv, err)
    else:
        assert code == 0, (code, argv, err)
        assert not any(line.startswith("error") for line in lines), (argv, err)


def _check_files(before, sandbox, out_path, command, argv) -> None:
    """Nothing new outside -o, no temporaries left, JSON strict, CSV finite."""
    after = {p for p in sandbox.rglob("*") if p.is_file() or p.is_symlink()}
    created = after - before
    for p in created:
        assert out_path is not None, (argv, p)
        ap = Path(os.path.abspath(p))
        assert ap == out_path or out_path in ap.parents, (argv, p, out_path)
        assert ".tmp" not in p.name, (argv, p)
        if p.suffix == ".json":
            _strict_json(p.read_text(encoding="utf-8"))
    if command == "fit" and out_path in created and out_path.is_file():
        rows = list(csv.DictReader(out_path.read_text().splitlines()))
        assert rows, argv
        for row in rows:
            if row["status"] == "ok":
                assert all(math.isfinite(float(row[k])) for k in ("tau_s", "tau_u_s")), row


def _check_result(code, out_path, command, argv) -> None:
    if code != 0:
        return
    if command == "linefit":
        result = _strict_json(out_path.read_text(encoding="utf-8"))
        area = result["line_area"]
        assert math.isfinite(area["value"]) and area["u"] > 0, (argv, area)
    if command == "simulate":
        with contextlib.redirect_stdout(io.StringIO()):
            assert main(["validate", str(out_path)]) == 0, argv


# ----------------------------------------------------------------------------- the property
@pytest.mark.slow
@settings(
    max_examples=EXAMPLES,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(data=st.data())
def test_random_options_and_damaged_bundles_never_give_a_traceback(base_bundle, data):
    command, edits, options, out = data.draw(invocations(*_numeric_places(base_bundle)))
    with tempfile.TemporaryDirectory() as tmp:
        sandbox = Path(tmp)
        argv = [command]
        if command != "simulate":
            bundle = sandbox / "in.h5"
            shutil.copy(base_bundle, bundle)
            with h5py.File(bundle, "a") as f, np.errstate(over="ignore", invalid="ignore"):
                for edit in edits:
                    _edit(f, edit)
            argv.append(str(bundle))
        argv += options
        out_path = None
        if out is not None:
            argv += ["-o", str(sandbox / "run" / out)]
            out_path = Path(os.path.abspath(sandbox / "run" / out))
        before = {p for p in sandbox.rglob("*") if p.is_file()}
        cwd = os.getcwd()
        os.chdir(sandbox)  # a relative path written by mistake would land in the sandbox
        try:
            code, stdout, err, parse_error = _run(argv)
        finally:
            os.chdir(cwd)
        event(f"{command}: {'option refused' if parse_error else f'exit {code}'}")
        _check_stderr(code, stdout, err, parse_error, argv)
        _check_files(before, sandbox, out_path, command, argv)
        _check_result(code, out_path, command, argv)
