"""Scale-out: a study on a local Dask cluster gives the same numbers as the serial run."""

import json

import pytest

from bayes_tfcrds.studies.registry import run_study

STUDY = """
[study]
name = "dask_check"
kind = "tcut"
seed = 12
[campaign]
presets = ["letter-D2", "letter-D4"]
points = 15
samples = 4096
averages = 4
[analysis]
t_cuts_us = [4, 8]
"""


def test_study_on_a_local_dask_cluster_equals_the_serial_run(tmp_path):
    distributed = pytest.importorskip("distributed")
    study = tmp_path / "s.toml"
    study.write_text(STUDY)
    run_study(study, tmp_path / "serial")
    with (
        distributed.LocalCluster(
            n_workers=2,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
            silence_logs=40,
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        # a raw Client is not a pool (emcee and the runner call pool.map and expect results);
        # its executor is
        run_study(study, tmp_path / "dask", pool=client.get_executor())
    serial = json.loads((tmp_path / "serial" / "numbers.json").read_text())
    dask = json.loads((tmp_path / "dask" / "numbers.json").read_text())
    assert serial == dask
    assert len(serial["rows"]) == 2 * 2 * 2
