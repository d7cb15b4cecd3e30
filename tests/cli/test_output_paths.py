"""Results are written over regular files only (issue 20, item 7) with one-line errors."""

import os

import pytest

from bayes_tfcrds.cli import main
from bayes_tfcrds.output.files import OutputPathError, atomic_write_text


def test_fifo_symlink_and_directory_are_refused_and_left_alone(tmp_path):
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    with pytest.raises(OutputPathError, match="not a regular file"):
        atomic_write_text(fifo, "x")
    assert fifo.exists() and not fifo.is_file()  # still a FIFO
    real = tmp_path / "real.txt"
    real.write_text("keep")
    link = tmp_path / "link.txt"
    link.symlink_to(real)
    with pytest.raises(OutputPathError, match="symbolic link"):
        atomic_write_text(link, "x")
    assert link.is_symlink() and real.read_text() == "keep"
    with pytest.raises(OutputPathError, match="directory"):
        atomic_write_text(tmp_path, "x")
    atomic_write_text(real, "new")  # a regular file is replaced
    assert real.read_text() == "new"


def test_simulate_into_a_fifo_or_under_a_file_is_a_one_line_error(tmp_path, capsys):
    args = ["simulate", "--points", "9", "--samples", "512", "-o"]
    (tmp_path / "afile").write_text("x")
    assert main([*args, str(tmp_path / "afile" / "x.h5")]) == 2
    assert "is not a folder" in capsys.readouterr().err
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    assert main([*args, str(fifo)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1
    assert not list(tmp_path.glob(".*tmp*"))  # no temporary file left behind


@pytest.mark.parametrize("command", ["budget", "discover", "study", "demo"])
def test_folder_commands_refuse_an_existing_file_before_any_work(tmp_path, capsys, command):
    target = tmp_path / "taken"
    target.write_text("someone's file")
    args = {
        "budget": ["budget", "missing.h5"],
        "discover": ["discover", "missing.h5"],
        "study": ["study", "missing.toml"],
        "demo": ["demo"],
    }[command]
    assert main([*args, "-o", str(target)]) == 2
    assert "is not a folder" in capsys.readouterr().err
    assert target.read_text() == "someone's file"


def test_a_killed_writers_temporary_is_cleaned_on_the_next_write(tmp_path):
    # issue 20 item 8: SIGKILL during a save left a hidden temporary forever
    import subprocess
    import sys

    target = tmp_path / "bundle.h5"
    code = (
        "import os, sys, pathlib\n"
        "from bayes_tfcrds.output.files import atomic_path\n"
        "with atomic_path(pathlib.Path(sys.argv[1])) as tmp:\n"
        "    tmp.write_bytes(b'x' * 1000)\n"
        "    os.kill(os.getpid(), 9)\n"
    )
    subprocess.run([sys.executable, "-c", code, str(target)], check=False)
    left = list(tmp_path.glob(".bundle.h5.*.tmp*"))
    assert len(left) == 1 and not target.exists()  # what a SIGKILL leaves
    other = tmp_path / f".other.h5.{os.getpid()}-0123456789ab.tmp"
    other.write_text("a live writer's file of another target")
    atomic_write_text(target, "done")
    assert target.read_text() == "done"
    assert not list(tmp_path.glob(".bundle.h5.*.tmp*"))  # the dead writer's file is gone
    assert other.exists()  # not ours to remove


def test_missing_folders_of_a_file_output_are_created(tmp_path):
    # issue 20: simulate -o missing_dir/x.h5 raised a traceback; every file output now behaves as
    # fit and linefit always did
    out = tmp_path / "new" / "deeper" / "x.h5"
    assert main(["simulate", "--points", "9", "--samples", "512", "-o", str(out)]) == 0
    assert out.is_file()


@pytest.mark.parametrize(
    "options, phrase",
    [
        (["--samples", "0"], "n_samples = 0"),
        (["--samples", "-1"], "n_samples = -1"),
        (["--samples", "100000000"], "n_samples = 100000000"),
        (["--points", "0"], "n_points = 0"),
        (["--points", "1"], "n_points = 1"),
        (["--points", "2"], "n_points = 2"),
        (["--effect", "extinction_tail:tau_s=0"], "tau_s = 0.0 is outside"),
        (["--effect", "extinction_tail:tau_s=nan"], "tau_s = nan is outside"),
        (["--effect", "second_mode:fraction=-1"], "fraction = -1.0 is outside"),
        (["--effect", "speed_dependence:gamma2_ratio=-10"], "gamma2_ratio = -10.0"),
        (["--effect", "etalon:period_hz=inf"], "period_hz = inf"),
        (["--preset", "letter-D1", "--preset", "letter-D1"], "letter-D1 given more than once"),
        (["--effect", "etalon", "--effect", "etalon:phase_rad=1"], "--effect etalon given more"),
    ],
)
def test_simulate_refuses_impossible_settings_in_one_line(tmp_path, capsys, options, phrase):
    # issue 20: these gave MemoryError, ZeroDivisionError, "Singular matrix" or silent merges
    out = tmp_path / "x.h5"
    assert main(["simulate", *options, "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and phrase in err and err.count("\n") == 1, err
    assert not out.exists()


@pytest.mark.parametrize(
    "options, phrase",
    [(["--threshold", "nan"], "--threshold must be"), (["--tcut=0"], "t_cut must be > 0")],
)
def test_discover_refuses_options_that_give_nonsense(tmp_path, capsys, options, phrase):
    # issue 20: --threshold nan added every candidate; --tcut=0 wrote NaN into discovery.json
    bundle = tmp_path / "c.h5"
    assert main(["simulate", "--points", "9", "--samples", "1024", "-o", str(bundle)]) == 0
    capsys.readouterr()
    out = tmp_path / "disc"
    assert main(["discover", str(bundle), "--config", "D2", *options, "-o", str(out)]) == 2
    assert phrase in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("command", ["fit", "linefit", "simulate"])
def test_file_commands_into_a_directory_are_refused_before_any_work(tmp_path, capsys, command):
    # issue 20: -o <directory> raised IsADirectoryError after the work and left a .tmp behind
    bundle = tmp_path / "c.h5"
    assert main(["simulate", "--points", "9", "--samples", "1024", "-o", str(bundle)]) == 0
    capsys.readouterr()
    folder = tmp_path / "results"
    folder.mkdir()
    args = ["simulate"] if command == "simulate" else [command, str(bundle), "--config", "D2"]
    assert main([*args, "-o", str(folder)]) == 2
    err = capsys.readouterr().err
    assert err == f"error: {folder} is a directory; give a file name inside it\n"
    assert not list(folder.iterdir()) and not list(tmp_path.glob(".*tmp*"))


def test_a_live_writers_temporaries_survive_a_budget_folder_clean_up(tmp_path):
    # a budget's outputs clean what killed runs left; a concurrent writer's file is not theirs
    from bayes_tfcrds.output.files import clean_dead_writers, folder_lock

    live = tmp_path / f".budget.json.{os.getpid()}-0123456789ab.tmp"
    live.write_text("being written")
    dead = tmp_path / ".budget.json.999999999-0123456789ab.tmp"
    dead.write_text("left by a SIGKILL")
    assert clean_dead_writers(tmp_path) == [dead]
    assert live.exists() and not dead.exists()
    with folder_lock(tmp_path / "new"), folder_lock(tmp_path / "new"):  # nested use in one run
        assert (tmp_path / "new").is_dir()


@pytest.mark.parametrize("command", ["simulate", "fit", "budget", "study", "discover", "demo"])
@pytest.mark.parametrize("seed", ["-1", str(2**63), "1.5"])
def test_a_seed_outside_the_seed_range_is_refused_as_an_option(tmp_path, capsys, command, seed):
    # issue 20 (study seed -1): the option had no rule; demo --seed -1 ended in numpy's
    # traceback, simulate and budget in its "expected non-negative integer", the others took it
    args = {
        "simulate": ["simulate"],
        "fit": ["fit", "c.h5"],
        "budget": ["budget", "c.h5"],
        "study": ["study", "s.toml"],
        "discover": ["discover", "c.h5"],
        "demo": ["demo"],
    }[command]
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as info:
        main([*args, "--seed", seed, "-o", str(out)])
    assert info.value.code == 2
    assert f"argument --seed: expected an integer in [0, 2**63), got '{seed}'" in (
        capsys.readouterr().err
    )
    assert not out.exists()
