"""The CI schedule (tests/conftest.py, pyproject's addopts): tests that share a module fixture run
on one worker, so that an expensive fixture (the tour, the coverage study) is built once.

pytest 9.2 renamed the node attribute that pytest-xdist 3.8 writes for ``--dist loadgroup``; the
groups were then ignored without a word and both workers built both fixtures. This runs a small
suite through the real conftest and addopts and counts the builds.
"""

import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

SUITE = """
import os

import pytest


@pytest.fixture(scope="module")
def built():
    with open(os.environ["BUILD_LOG"], "a") as f:
        f.write(os.environ.get("PYTEST_XDIST_WORKER", "main") + "\\n")


@pytest.mark.parametrize("i", range(8))
def test_shares_the_fixture(built, i):
    pass


@pytest.mark.parametrize("i", range(8))
def test_alone(i):
    pass
"""


def _builds(tmp_path, *extra) -> list:
    suite = tmp_path / "suite"
    suite.mkdir(exist_ok=True)
    shutil.copy(ROOT / "tests" / "conftest.py", suite / "conftest.py")
    (suite / "test_shared.py").write_text(textwrap.dedent(SUITE))
    log = tmp_path / f"builds{len(extra)}.txt"
    env = {"BUILD_LOG": str(log), "PATH": "/usr/bin:/bin"}
    cmd = [sys.executable, "-m", "pytest", "-q", "-n", "2", "-p", "no:cacheprovider"]
    cmd += ["-c", str(ROOT / "pyproject.toml"), "--rootdir", str(suite), *extra, str(suite)]
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=tmp_path)
    assert out.returncode == 0, out.stdout + out.stderr
    return log.read_text().split()


def test_tests_sharing_a_module_fixture_run_on_one_worker(tmp_path):
    pytest.importorskip("xdist")
    assert _builds(tmp_path) in (["gw0"], ["gw1"])
    # the control: xdist's plain load schedule deals the same tests to both workers, and the
    # fixture is built twice (what the groups prevent)
    assert sorted(_builds(tmp_path, "--dist", "load")) == ["gw0", "gw1"]
