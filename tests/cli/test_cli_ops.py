"""Logging, progress without a terminal, the Laplace budget, executors and the batch form.

The Dask path is exercised with an in-process stand-in for ``distributed`` (a Client whose
executor runs each task here), so these tests need neither dask nor a scheduler; the real
cluster is tested in tests/studies/test_scaleout.py when dask is installed.
"""

import json
import sys
import types
from concurrent.futures import Future
from pathlib import Path

import numpy as np
import pytest

from bayes_tfcrds.cli import main

ROOT = Path(__file__).resolve().parents[2]


def _simulate(path, seed):
    argv = ["simulate", "--preset", "letter-D2", "--seed", str(seed), "--points", "15"]
    assert main([*argv, "--samples", "4096", "--quiet", "-o", str(path)]) == 0
    return path


@pytest.fixture(scope="module")
def bundles(tmp_path_factory):
    folder = tmp_path_factory.mktemp("ops")
    return (_simulate(folder / "first.h5", 4),)


@pytest.fixture(scope="module")
def laplace(bundles, tmp_path_factory):
    """One Laplace budget through the command line, stdout and stderr captured (not a tty)."""
    out = tmp_path_factory.mktemp("laplace") / "b"
    capture = pytest.MonkeyPatch()
    stdout, stderr = _Capture(), _Capture()
    capture.setattr(sys, "stdout", stdout)
    capture.setattr(sys, "stderr", stderr)
    try:
        code = main(
            ["budget", str(bundles[0]), "--posterior", "laplace", "--seed", "3", "-o", str(out)]
        )
    finally:
        capture.undo()
    return code, out, stdout.getvalue(), stderr.getvalue()


class _Capture:
    """A text stream that is not a terminal (like a log file)."""

    def __init__(self):
        self.parts = []

    def write(self, text):
        self.parts.append(text)

    def flush(self):
        pass

    def isatty(self):
        return False

    def getvalue(self):
        return "".join(self.parts)


def _coverage_file():
    return json.loads((ROOT / "reports" / "coverage_laplace" / "numbers.json").read_text())


def test_laplace_budget_is_labelled_an_approximation_with_its_measured_coverage(laplace):
    code, out, stdout, _ = laplace
    assert code == 0
    numbers = _coverage_file()
    assert numbers["posterior"] == "laplace"  # the figures quoted are those of the Laplace study
    a = numbers["summaries"]["A"]
    quoted = f"A {100 * a['coverage_68']:.1f} % / {100 * a['coverage_95']:.1f} %"
    summary = json.loads((out / "budget.json").read_text())
    post = summary["posterior"]
    assert post["method"] == "laplace" and post["approximation"] is True
    cov = post["measured_coverage"]
    assert cov["n_campaigns"] == numbers["n_campaigns"]
    assert cov["coverage"]["A"] == {"68": a["coverage_68"], "95": a["coverage_95"]}
    ratio = numbers["summaries"]["A/A_ref"]
    assert cov["coverage"]["A/A_ref"] == {"68": ratio["coverage_68"], "95": ratio["coverage_95"]}
    first = stdout.splitlines()[0]
    assert first.startswith("posterior: APPROXIMATION, Laplace approximation") and quoted in first
    md = (out / "budget.md").read_text()
    assert md.startswith("## Posterior: Laplace approximation")
    assert f"| A | {100 * a['coverage_68']:.1f} % | {100 * a['coverage_95']:.1f} % |" in md
    # no sampler ran: no chains, no netCDF posteriors
    assert not list(out.glob("chains_*.h5")) and not list(out.glob("posterior_*.nc"))
    # the result on stdout, in the same units as budget.json
    a_line = next(x for x in stdout.splitlines() if x.startswith("A = "))
    assert f"{summary['line_area']['value']:.6e}" in a_line


def test_laplace_budget_agrees_with_its_line_fit(laplace, bundles, tmp_path):
    # the Laplace A is the least-squares A at the same t_cut: linefit gives it independently
    _, out, _, _ = laplace
    assert main(["linefit", str(bundles[0]), "--quiet", "-o", str(tmp_path / "l.json")]) == 0
    lf = json.loads((tmp_path / "l.json").read_text())
    b = json.loads((out / "budget.json").read_text())
    # the budget's A is the mean of the H-shifted posterior draws about that fit (and H* is the
    # posterior centre, not the refined point): within a fraction of u_c, not to the digit
    assert abs(b["line_area"]["value"] - lf["line_area"]["value"]) < 0.5 * b["line_area"]["u"]


def test_budget_progress_without_a_terminal_is_plain_lines_with_time_left(laplace):
    _, _, _, stderr = laplace
    assert "\r" not in stderr
    stages = [x for x in stderr.splitlines() if ": stage " in x]
    assert [x.split("stage ")[1].split(" ")[0] for x in stages] == [f"{k}/9" for k in range(1, 10)]
    assert all(x.startswith("# budget D2 (laplace): ") for x in stages)
    assert "left" in stages[0] and "left" not in stages[-1]


def test_sampler_progress_without_a_terminal_is_periodic_lines(capsys):
    from bayes_tfcrds.cli import configure_logging
    from bayes_tfcrds.inference.runner import run_ensembles

    configure_logging(0)
    run_ensembles(
        lambda x: -0.5 * float(x @ x),
        lambda rng, n: rng.normal(size=(n, 2)),
        ["a", "b"],
        np.random.default_rng(1),
        n_steps=200,
        max_steps=200,
        progress=True,
        label="toy",
    )
    err = capsys.readouterr().err
    assert "\r" not in err
    lines = [x for x in err.splitlines() if x.startswith("# toy ensemble 0: ")]
    # every 10 % of 200 steps, each a whole line with the count
    assert len(lines) == 10 and lines[-1].startswith("# toy ensemble 0: 200/200 (100 %)")


def test_quiet_leaves_only_warnings_and_verbose_adds_debug_lines(bundles, tmp_path, capsys):
    argv = ["fit", str(bundles[0]), "--tcut", "4e-6"]
    assert main([*argv, "-o", str(tmp_path / "a.csv")]) == 0
    normal = capsys.readouterr().err
    assert "# H: f_c=" in normal and "wrote " in normal and "# debug" not in normal
    assert main([*argv, "--quiet", "-o", str(tmp_path / "b.csv")]) == 0
    assert capsys.readouterr().err == ""
    assert main([*argv, "--verbose", "-o", str(tmp_path / "c.csv")]) == 0
    verbose = capsys.readouterr().err
    assert "# debug bayes_tfcrds.cli: bayes-tfcrds " in verbose and "'tcut': [4e-06]" in verbose
    assert "# H: f_c=" in verbose
    # the same numbers whatever is said about them
    assert (tmp_path / "a.csv").read_text() == (tmp_path / "c.csv").read_text()


def test_quiet_and_verbose_together_are_refused(bundles, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["validate", str(bundles[0]), "--quiet", "--verbose"])
    assert exc.value.code == 2 and "not allowed with" in capsys.readouterr().err


class _InProcessExecutor:
    """What ``Client.get_executor()`` gives, run here: ``submit`` and ``map``, with a log."""

    def __init__(self):
        self.tasks = []

    def submit(self, fn, *args):
        self.tasks.append((fn.__name__, args))
        fut = Future()
        fut.set_result(fn(*args))
        return fut

    def map(self, fn, items):
        return (self.submit(fn, i).result() for i in items)


@pytest.fixture
def fake_dask(monkeypatch):
    """A ``distributed`` module whose Client records its address and runs tasks in process."""
    seen = {}

    class Client:
        def __init__(self, address, timeout=None):
            seen["address"] = address
            seen["executor"] = _InProcessExecutor()

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            seen["closed"] = True

        def get_executor(self):
            return seen["executor"]

    monkeypatch.setitem(sys.modules, "distributed", types.SimpleNamespace(Client=Client))
    return seen


def test_batch_on_a_dask_scheduler_gives_each_bundle_its_own_budget(
    bundles, laplace, fake_dask, tmp_path, capsys
):
    bad = tmp_path / "broken.h5"
    bad.write_text("not HDF5")
    out = tmp_path / "batch"
    argv = ["budget", str(bundles[0]), str(bad), "--posterior", "laplace", "--seed", "3"]
    argv += ["--executor", "dask", "--scheduler", "tcp://10.0.0.5:8786", "-o", str(out)]
    assert main(argv) == 1  # one bundle refused: said in the exit status, the others still run
    assert fake_dask["address"] == "tcp://10.0.0.5:8786" and fake_dask["closed"]
    assert [name for name, _ in fake_dask["executor"].tasks] == ["budget_task"] * 2
    index = json.loads((out / "batch.json").read_text())
    status = {Path(r["bundle"]).name: r["status"] for r in index["budgets"]}
    assert status["first.h5"] == "ok"
    assert status["broken.h5"].startswith("error: ") and "broken.h5" in status["broken.h5"]
    # a bundle in a batch gets exactly the numbers of its own budget command (same seed)
    single = json.loads((laplace[1] / "budget.json").read_text())
    first = json.loads((out / "first" / "budget.json").read_text())
    assert first["line_area"] == single["line_area"] and first["ratio"] == single["ratio"]
    captured = capsys.readouterr()
    assert "\r" not in captured.err and "# bundles: 2/2 (100 %)" in captured.err
    assert captured.out.count(": A = ") == 1 and "error: " in captured.err
    assert not (out / "broken").exists() or not list((out / "broken").glob("budget.*"))


def test_without_dask_the_dask_executor_is_refused_before_any_work(
    bundles, tmp_path, capsys, monkeypatch
):
    monkeypatch.setitem(sys.modules, "distributed", None)  # import distributed -> ImportError
    out = tmp_path / "never"
    argv = ["budget", str(bundles[0]), "--executor", "dask", "--scheduler", "tcp://x:8786"]
    assert main([*argv, "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --executor dask needs dask.distributed")
    assert "pip install 'bayes-tfcrds[dask]'" in err and not out.exists()


@pytest.mark.parametrize(
    ("options", "phrase"),
    [
        (["--executor", "dask"], "--executor dask needs --scheduler ADDRESS"),
        (["--scheduler", "tcp://x:8786"], "give --executor dask too"),
        (["--workers", "0"], "--workers must be >= 1"),
    ],
)
def test_executor_options_that_cannot_work_are_refused(bundles, tmp_path, capsys, options, phrase):
    assert main(["budget", str(bundles[0]), *options, "-o", str(tmp_path / "o")]) == 2
    assert phrase in capsys.readouterr().err


def test_two_bundles_with_one_stem_are_refused(bundles, tmp_path, capsys):
    other = tmp_path / "x" / bundles[0].name
    other.parent.mkdir()
    other.write_bytes(bundles[0].read_bytes())
    assert main(["budget", str(bundles[0]), str(other), "-o", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "would both write into" in err and not (tmp_path / "o").exists()


STUDY = """
[study]
name = "exec_check"
kind = "tcut"
seed = 12
[campaign]
presets = ["letter-D2", "letter-D4"]
points = 11
samples = 4096
averages = 4
[analysis]
t_cuts_us = [4]
"""


def test_study_on_a_dask_scheduler_sends_one_task_per_configuration(fake_dask, tmp_path, capsys):
    study = tmp_path / "s.toml"
    study.write_text(STUDY)
    argv = ["study", str(study), "--executor", "dask", "--scheduler", "tcp://h:8786"]
    assert main([*argv, "-o", str(tmp_path / "rep")]) == 0
    assert [n for n, _ in fake_dask["executor"].tasks] == ["_tcut_config"] * 2
    numbers = json.loads((tmp_path / "rep" / "numbers.json").read_text())
    assert {r["config"] for r in numbers["rows"]} == {"D2", "D4"}
    err = capsys.readouterr().err
    assert "# configurations: 2/2 (100 %)" in err and "\r" not in err


def test_coverage_is_quoted_only_from_a_laplace_coverage_study(tmp_path):
    from bayes_tfcrds.uncertainty.outputs import laplace_coverage, posterior_record

    numbers = _coverage_file()
    path = tmp_path / "numbers.json"
    path.write_text(json.dumps(numbers))
    assert laplace_coverage(path)["coverage"]["A"]["68"] == numbers["summaries"]["A"]["coverage_68"]
    path.write_text(json.dumps(dict(numbers, posterior="mcmc")))  # another study's figures
    assert laplace_coverage(path) is None
    assert laplace_coverage(tmp_path / "absent.json") is None
    record = posterior_record("laplace", tmp_path / "absent.json")
    assert record["approximation"] and "coverage" not in record["measured_coverage"]
    assert "reports/coverage_laplace/numbers.json" in record["measured_coverage"]["source"]


def test_packaged_laplace_coverage_equals_the_committed_coverage_report():
    """An installed package has no reports/: budget quotes the copy in data/. It must be the
    committed report's figures. After regenerating reports/coverage_laplace, refresh it with
    ``json.dumps(laplace_coverage("reports/coverage_laplace/numbers.json"), indent=1)`` into
    bayes_tfcrds/data/laplace_coverage.json."""
    from pathlib import Path

    from bayes_tfcrds.uncertainty.outputs import laplace_coverage

    report = Path(__file__).resolve().parents[2] / "reports" / "coverage_laplace" / "numbers.json"
    assert laplace_coverage() == laplace_coverage(report)


def test_a_budget_that_fails_with_two_workers_leaves_no_corner_plot(bundles, tmp_path, monkeypatch):
    """--workers 2 draws each corner plot in the pool as soon as its run is sampled. A run that
    then fails (here: the line fit, after H and with the CMDS reference under way) exits 1 with
    no plot in the folder, neither named nor pending: nothing beside an earlier run's budget."""
    from bayes_tfcrds.fit.line_analysis import LineFitError
    from bayes_tfcrds.uncertainty import line_budget

    def fail(*args, **kwargs):
        raise LineFitError("the line fit failed (a test)")

    monkeypatch.setattr(line_budget, "_line_posterior", fail)
    out = tmp_path / "failed"
    argv = ["budget", str(bundles[0]), "--steps", "60", "--max-steps", "60", "--seed", "2"]
    assert main([*argv, "--workers", "2", "--quiet", "-o", str(out)]) == 1
    assert not list(out.glob("corner_*")) and not (out / "budget.json").exists()
