"""Interruption (issue #9, part 3): a budget run that is stopped (Ctrl-C or SIGKILL) and run again
gives the samples of the uninterrupted run bit for bit, and no output file is left half-written.

The end-to-end tests run the installed ``bayes-tfcrds budget`` command in a subprocess, as a user
would, and stop it when its own progress output says it is sampling (never after a fixed sleep).
The store-level tests reproduce the moments a kill can land inside a commit of the chain file.
Every comparison is exact (``array_equal``, equal JSON, equal bytes): the sampler is deterministic
given the seed, so a tolerance would only hide a broken resume.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from bayes_tfcrds.cli import main

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from test_sampling import assert_same, reference_run, short_run  # noqa: E402

STEPS = 200  # per ensemble: a commit every 20 steps (a tenth of the run), the last at 200
SEED = 5
OUTPUTS = ("budget.json", "budget.md", "budget.csv", "tau_posterior.csv")
RUNS = ("h", "line", "cmds")


# ----------------------------------------------------------------------------- chain store
def _iterations(path):
    with h5py.File(path, "r") as f:
        return [
            int(f[f"ensemble{i}"].attrs["iteration"]) if f"ensemble{i}" in f else 0
            for i in range(4)
        ]


def _run_interrupted_at_commit(path, monkeypatch, at):
    """A 200-step run to ``path`` stopped by Ctrl-C inside its ``at``-th group commit, after the
    rows and generator state are written and before the ``iteration`` counter moves on (commits go
    ensemble 0, 1, 2, 3 at step 100, then at step 200)."""
    setitem = h5py.AttributeManager.__setitem__
    commits = []

    def interrupting(self, name, value):
        if name == "iteration" and int(value) > 0:
            commits.append(int(value))
            if len(commits) == at:
                raise KeyboardInterrupt
        return setitem(self, name, value)

    monkeypatch.setattr(h5py.AttributeManager, "__setitem__", interrupting)
    with pytest.raises(KeyboardInterrupt):
        short_run(n=200, backend_path=path)
    monkeypatch.undo()


@pytest.mark.parametrize(
    "at, left",
    [
        (2, [100, 0, 0, 0]),  # ensemble 1's first commit: resume rolls ensemble 0 back to 0
        (6, [200, 100, 100, 100]),  # its second: ensemble 0 goes back to step 100's slot
    ],
)
def test_interrupt_between_rows_and_commit_point_resumes_exactly(tmp_path, monkeypatch, at, left):
    """Ctrl-C after a chunk's rows and generator state are written but before ``iteration`` moves
    on: the file then holds the state of an uncommitted chunk. A resume that took that state
    with the last committed position would continue a different chain. The ensembles are
    committed one after another, so the ones already written are a chunk ahead and must come
    back to where all of them are."""
    path = tmp_path / "chains.h5"
    _run_interrupted_at_commit(path, monkeypatch, at)
    assert _iterations(path) == left
    assert_same(short_run(n=200, backend_path=path), reference_run(200))
    assert _iterations(path) == [200] * 4


def test_rollback_leaves_a_consistent_emcee_group(tmp_path, monkeypatch):
    """A group rolled back to the common step reads, through emcee's own HDFBackend, as a run that
    stopped there: its acceptance counts and generator state are those of that step."""
    import emcee

    from bayes_tfcrds.inference.stores import _HDFStore

    path = tmp_path / "chains.h5"
    _run_interrupted_at_commit(path, monkeypatch, 6)  # ensemble 1's commit at step 200
    with h5py.File(path, "r") as f:
        fp = f["ensemble0"].attrs["bayes_tfcrds_seed"]
        walkers, ndim = int(f["ensemble0"].attrs["nwalkers"]), int(f["ensemble0"].attrs["ndim"])
    store = _HDFStore(path, "ensemble0", walkers, ndim, fp)
    assert store.iteration == 200
    store.rollback(100)
    ahead = emcee.backends.HDFBackend(str(path), name="ensemble0", read_only=True)
    assert ahead.iteration == 100
    with h5py.File(path, "r") as f:
        kept = f["ensemble0/accepted_step"][:100].sum(axis=0)
        g = f["ensemble1"]  # the group behind: its slot for step 100 holds the sampler's state
        slot = next(s for s in (0, 1) if g.attrs[f"bayes_tfcrds_state{s}_iteration"] == 100)
        behind = [g.attrs[f"bayes_tfcrds_state{slot}_{i}"] for i in range(5)]
    assert np.array_equal(ahead.accepted, kept)
    a = ahead.random_state
    assert a[0] == behind[0] and np.array_equal(a[1], behind[1]) and list(a[2:]) == behind[2:]


def test_a_damaged_later_group_restarts_every_ensemble(tmp_path):
    """Ensemble 2 with no intact commit: the file is set aside once and all four restart from
    their seeds (the others' groups went with the file), to the uninterrupted samples."""
    path = tmp_path / "chains.h5"
    short_run(n=200, backend_path=path)
    with h5py.File(path, "a") as f:
        for s in (0, 1):
            f["ensemble2"].attrs[f"bayes_tfcrds_state{s}_iteration"] = -1
    with pytest.warns(RuntimeWarning, match="ensemble2 has no intact commit.*moved to"):
        resumed = short_run(n=200, backend_path=path)
    assert_same(resumed, reference_run(200))
    assert _iterations(path) == [200] * 4


def test_incomplete_last_commit_is_rolled_back(tmp_path):
    """A kill inside HDF5's flush can leave the counter advanced but the chunk's rows (or its
    generator state) not on disk. Both are detected and the store rolls back one chunk."""
    path = tmp_path / "chains.h5"
    short_run(n=200, backend_path=path)
    with h5py.File(path, "a") as f:
        f["ensemble1/chain"][150:200] = 0.0  # rows of the last chunk lost
        g = f["ensemble2"]
        slot = next(s for s in (0, 1) if g.attrs[f"bayes_tfcrds_state{s}_iteration"] == 200)
        g.attrs[f"bayes_tfcrds_state{slot}_iteration"] = -1  # its state half-written
    assert_same(short_run(n=200, backend_path=path), reference_run(200))
    assert _iterations(path) == [200] * 4


def test_unreadable_chain_file_is_moved_aside_and_resampled(tmp_path):
    path = tmp_path / "chains.h5"
    short_run(n=200, backend_path=path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 3])  # truncated by a crash
    with pytest.warns(RuntimeWarning, match="cannot be read.*moved to .*damaged"):
        resumed = short_run(n=200, backend_path=path)
    assert_same(resumed, reference_run(200))
    assert sorted(p.name.split("-")[0] for p in tmp_path.iterdir()) == [
        "chains.h5",
        "chains.h5.damaged",
    ]


def test_chain_file_in_use_by_another_run_is_left_alone(tmp_path):
    """Two runs writing to one output: HDF5's lock refuses the second, which must not mistake the
    file for a damaged one and move it aside under the first."""
    path = tmp_path / "chains.h5"
    short_run(n=100, backend_path=path)
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            f"import h5py, sys, time\nf = h5py.File({str(path)!r}, 'a'); print('open', "
            "flush=True); time.sleep(60)",
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "open"
        with pytest.raises(RuntimeError, match="open in another process"):
            short_run(n=200, backend_path=path)
    finally:
        holder.kill()
        holder.wait()
    assert sorted(os.listdir(tmp_path)) == ["chains.h5"] and _iterations(path) == [100] * 4


def test_ctrl_c_in_the_diagnostics_after_the_last_step_stops_the_run(tmp_path, monkeypatch):
    """Ctrl-C that lands after the last step, while the gates are evaluated, was dropped: the
    command carried on to its end (CI saw exit 3 where 130 was due). It must stop the run, with
    every step committed, so that the same command resumes without sampling again."""
    from bayes_tfcrds.inference import runner

    evaluate = runner._evaluate

    def evaluate_then_ctrl_c(*args, **kwargs):
        result = evaluate(*args, **kwargs)
        os.kill(os.getpid(), signal.SIGINT)  # handled by the sampler's stop request
        return result

    path = tmp_path / "chains.h5"
    monkeypatch.setattr(runner, "_evaluate", evaluate_then_ctrl_c)
    # Python's own Ctrl-C handler, as in a terminal (the sampler installs its stop request only
    # over that one; a test worker may have inherited SIGINT ignored)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            short_run(n=200, backend_path=path)
    finally:
        signal.signal(signal.SIGINT, previous)
    monkeypatch.undo()
    assert _iterations(path) == [200] * 4
    assert_same(short_run(n=200, backend_path=path), reference_run(200))


# ----------------------------------------------------------------------------- the command
def _command(bundle, out):
    exe = Path(sys.executable).with_name("bayes-tfcrds")
    head = [str(exe)] if exe.exists() else [sys.executable, "-m", "bayes_tfcrds.cli"]
    return head + [
        "budget",
        str(bundle),
        "--config",
        "D2",
        "--seed",
        str(SEED),
        "--steps",
        str(STEPS),
        "--max-steps",
        str(STEPS),
        "-o",
        str(out),
    ]


def _ctrl_c_as_in_a_terminal():
    """In the child before exec: SIGINT back to its default action.

    A process started with SIGINT ignored keeps it ignored (Python then installs no Ctrl-C
    handler), and test workers can inherit it ignored: the command must see Ctrl-C as a user's
    shell gives it.
    """
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _env():
    # one BLAS thread: the test's time budget is for one core, and the other core is the suite's
    return dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")


def _run(bundle, out):
    proc = subprocess.run(
        _command(bundle, out), capture_output=True, text=True, env=_env(), timeout=400
    )
    # 3 = ran to the end but the (deliberately short) chains miss the convergence gates
    assert proc.returncode == 3, proc.stderr[-3000:]
    assert "FAILED: failed: convergence gates not met" in proc.stderr
    return proc


class _Watched:
    """A budget command whose stderr (progress lines) is read as it is written."""

    def __init__(self, bundle, out):
        self.proc = subprocess.Popen(
            _command(bundle, out),
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            env=_env(),
            preexec_fn=_ctrl_c_as_in_a_terminal,
        )
        self.text = ""
        self._lock = threading.Lock()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self):
        for chunk in iter(lambda: self.proc.stderr.read1(4096), b""):
            with self._lock:
                self.text += chunk.decode("utf-8", "replace")

    def wait_for(self, predicate, what, timeout=300.0):
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            with self._lock:
                text = self.text
            if predicate(text):
                return
            if self.proc.poll() is not None:
                break
            time.sleep(0.005)
        self.proc.kill()
        pytest.fail(f"never saw {what} (exit {self.proc.poll()}):\n{self.text[-3000:]}")

    def stop(self, sig):
        self.proc.send_signal(sig)
        rc = self.proc.wait(timeout=120)
        self._reader.join(timeout=10)
        return rc


def _sampling_line_past_first_commit(text):
    """True once the line posterior's ensembles (which step together) are at step 120: the
    commits up to step 100 (every 20 steps) are made, and the run has 80 steps to go."""
    # stderr is a pipe here: progress comes as plain lines ("...ensemble 0: 120/200 (60 %), ..."),
    # a line every 10 % of the steps (bayes_tfcrds.output.progress)
    steps = re.findall(r"line \| CRDS ensemble 0: (\d+)/", text)
    return any(int(s) >= 120 for s in steps)


def _chains(out):
    """Every committed row of every chain file.

    As {(run, ensemble): (chain, log_prob, accepted_step)}.
    """
    rows = {}
    for run in RUNS:
        with h5py.File(out / f"chains_{run}.h5", "r") as f:
            for e in range(4):
                g = f[f"ensemble{e}"]
                n = int(g.attrs["iteration"])
                rows[run, e] = tuple(g[k][:n] for k in ("chain", "log_prob", "accepted_step"))
    return rows


def _posteriors(out):
    import arviz as az

    values = {}
    for run in RUNS:
        idata = az.from_netcdf(out / f"posterior_{run}.nc")
        for group in ("posterior", "sample_stats"):
            ds = idata[group]
            values.update({(run, group, k): ds[k].values for k in ds.data_vars})
        values[run, "attrs"] = {
            k: v
            for k, v in idata.posterior.attrs.items()
            if k not in ("created_at", "arviz_version", "inference_library_version")
        }
    return values


def _assert_same_outputs(out, ref):
    """The interrupted-and-resumed run's outputs equal the uninterrupted run's, exactly."""
    assert json.loads((out / "budget.json").read_text()) == json.loads(
        (ref / "budget.json").read_text()
    )
    for name in OUTPUTS[1:]:
        assert (out / name).read_bytes() == (ref / name).read_bytes(), name
    a, b = _chains(out), _chains(ref)
    assert a.keys() == b.keys()
    for key in a:
        assert all(np.array_equal(x, y) for x, y in zip(a[key], b[key])), key
        assert a[key][0].shape[0] == STEPS, key
    pa, pb = _posteriors(out), _posteriors(ref)
    assert pa.keys() == pb.keys()
    for key in pa:
        if key[1] == "attrs":
            assert {k: str(v) for k, v in pa[key].items()} == {
                k: str(v) for k, v in pb[key].items()
            }, key
        else:
            assert np.array_equal(pa[key], pb[key]), key


def _assert_outputs_whole(out):
    """Every output file present in ``out`` is complete and readable (temporary names aside)."""
    import arviz as az

    for p in out.iterdir():
        if p.name.startswith("."):
            continue
        if p.suffix == ".json":
            json.loads(p.read_text())
        elif p.suffix in (".md", ".csv"):
            text = p.read_text()
            assert text.endswith("\n") and len(text) > 100, p
        elif p.suffix == ".nc":
            assert az.from_netcdf(p).posterior.sizes["draw"] > 0, p
        elif p.suffix == ".png":
            assert p.read_bytes()[-12:] == b"\x00\x00\x00\x00IEND\xaeB`\x82", (
                p
            )  # PNG's closing chunk
        elif p.suffix == ".h5":
            _iterations(p)
        else:
            raise AssertionError(f"unexpected output {p}")


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """A small simulated bundle and the outputs of one uninterrupted budget run on it."""
    root = tmp_path_factory.mktemp("interrupt")
    bundle = root / "campaign.h5"
    assert (
        main(
            [
                "simulate",
                "--preset",
                "letter-D2",
                "--points",
                "15",
                "--samples",
                "2048",
                "--seed",
                "1",
                "-o",
                str(bundle),
            ]
        )
        == 0
    )
    out = root / "reference"
    _run(bundle, out)
    return bundle, out


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGKILL], ids=["SIGINT", "SIGKILL"])
def test_budget_stopped_mid_sampling_resumes_to_the_same_samples(reference, tmp_path, sig):
    bundle, ref = reference
    out = tmp_path / "run"
    run = _Watched(bundle, out)
    run.wait_for(_sampling_line_past_first_commit, "the line posterior past its first commits")
    rc = run.stop(sig)
    if sig == signal.SIGINT:
        assert rc == 130 and "interrupted: the chains sampled so far are kept" in run.text, (
            run.text[-2000:]
        )
        assert "Traceback" not in run.text
    else:
        assert rc == -signal.SIGKILL
    # stopped mid-sampling: H complete, the line run partly committed, nothing written yet
    assert _iterations(out / "chains_h.h5") == [STEPS] * 4
    line = _iterations(out / "chains_line.h5")
    # SIGINT commits the steps taken by all ensembles alike. SIGKILL lands at or after the commit
    # that follows step 120's progress line (the ensembles are committed one after another, a few
    # ms each): they may be one commit (STEPS // 10 steps) apart, which resume rolls back to the
    # step all of them hold. On a loaded machine the signal can land after the last step, in the
    # diagnostics, and the line chains are then complete (the resume must still read them and not
    # sample again)
    assert STEPS // 2 <= min(line) and max(line) <= STEPS, line
    assert max(line) - min(line) <= (0 if sig == signal.SIGINT else STEPS // 10), line
    assert not (out / "budget.json").exists()
    h_stat = (out / "chains_h.h5").stat()
    kept = {e: _chains_rows(out / "chains_line.h5", e) for e in (0, 1)}

    _run(bundle, out)  # the same command again
    # resumed, not restarted: the finished H chains were read, never rewritten, and the committed
    # line rows are the beginning of the final chains
    assert (out / "chains_h.h5").stat().st_mtime_ns == h_stat.st_mtime_ns
    for e, rows in kept.items():
        final = _chains_rows(out / "chains_line.h5", e)
        assert np.array_equal(final[: rows.shape[0]], rows)
    _assert_same_outputs(out, ref)
    assert not [p.name for p in out.iterdir() if p.name.startswith(".")]


def _chains_rows(path, e):
    with h5py.File(path, "r") as f:
        g = f[f"ensemble{e}"]
        return g["chain"][: int(g.attrs["iteration"])]


def test_sigkill_while_writing_outputs_leaves_no_half_written_file(reference, tmp_path):
    """Killed as soon as the first output appears, i.e. while the others are being written (the
    corner plots and netCDF files take seconds). Whatever is there is whole; a rerun completes
    it."""
    bundle, ref = reference
    out = tmp_path / "run"
    shutil.copytree(
        ref, out, ignore=shutil.ignore_patterns("budget*", "tau_*", "posterior_*", "corner_*")
    )
    run = _Watched(bundle, out)  # every chain is committed: straight to the outputs
    run.wait_for(lambda _: (out / "budget.json").exists(), "budget.json being written")
    assert run.stop(signal.SIGKILL) == -signal.SIGKILL
    present = {p.name for p in out.iterdir() if not p.name.startswith(".")}
    assert "budget.json" in present and not {f"corner_{r}.png" for r in RUNS} <= present, present
    _assert_outputs_whole(out)
    _run(bundle, out)
    _assert_same_outputs(out, ref)
    assert not [
        p.name for p in out.iterdir() if p.name.startswith(".")
    ]  # stale temporaries removed
