"""The code stamp of a report: a commit, marked dirty by code changes but not by reports."""

import subprocess

import pytest

from bayes_tfcrds.output.report import git_commit


def _git(repo, *args):
    subprocess.run(["git", *args], cwd=repo, check=True, capture_output=True)


@pytest.fixture
def repo(tmp_path):
    (tmp_path / "pkg").mkdir()
    (tmp_path / "reports").mkdir()
    (tmp_path / "pkg" / "code.py").write_text("x = 1\n")
    (tmp_path / "reports" / "numbers.json").write_text("{}\n")
    _git(tmp_path, "init", "-q")
    _git(tmp_path, "add", ".")
    _git(tmp_path, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "start")
    return tmp_path


def test_a_regenerated_report_does_not_make_the_stamp_dirty(repo):
    """Asked from inside the package (as the report module asks), a changed report is clean."""
    (repo / "reports" / "numbers.json").write_text('{"a": 1}\n')
    stamp = git_commit(repo / "pkg")
    assert len(stamp) == 40 and not stamp.endswith("+dirty")


def test_a_code_change_anywhere_makes_the_stamp_dirty(repo):
    """A code change outside the asking folder still counts (the status is of the whole tree)."""
    (repo / "other.py").write_text("y = 2\n")
    _git(repo, "add", "other.py")
    assert git_commit(repo / "pkg").endswith("+dirty")
    (repo / "pkg" / "code.py").write_text("x = 2\n")
    assert git_commit(repo / "reports").endswith("+dirty")
