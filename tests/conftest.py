"""Shared fixtures.

``good_bundle_path`` is a small valid measurement bundle written with raw h5py straight
from /work/shared/FORMAT.md (not with bayes_tfcrds.bundle.writer.save_bundle), so the reader is
checked against the contract rather than against its own writer. Contents:

* ``D1``: every optional item: transfer_function (with b12_u_v, i1_v as (n,), i2_v as a
  scalar), ringdowns (with n_avg and per-sample noise_v, pre-extinction samples), cmds
  (with width_hz and width_u_hz) and a description;
* ``D2``: ringdowns only.

The ring-downs are exponentials with Gaussian noise (seeded), well inside any digitizer
range, so nothing is clipped. ``GOOD`` holds the numbers used, for tests that need them.
"""

from __future__ import annotations

import os

if os.environ.get("PYTEST_XDIST_WORKER"):
    # ``pytest -n 2`` runs two processes on two cores: one BLAS thread each (set before numpy
    # loads OpenBLAS), or their threads oversubscribe the cores. Results are the same to the bit;
    # two budget processes side by side took 18.8 and 17.9 s with OpenBLAS's threads, 16.5 and
    # 15.7 s with one each.
    for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_var, "1")

import h5py
import numpy as np
import pytest

C = 299_792_458.0

GOOD = dict(
    nu0_hz=6.383e3 * C * 100.0,  # ~6383 cm^-1, CO (3-0) band
    fsr_hz=250.0e6,
    m=5,
    k=400,
    dt_s=1.0e-7,
    t0_s=-2.0e-6,
    tau_s=10.0e-6,
    amp_v=1.0,
    noise_v=2.0e-3,
    n_tf=12,
    f_c_hz=2.0e6,
    i1_v=0.5,
    i2_v=0.4,
    n_avg=100,
)


def _transients(rng, nu_hz, g):
    t = g["t0_s"] + g["dt_s"] * np.arange(g["k"])
    tau = g["tau_s"] * (1.0 - 0.1 * np.exp(-(((nu_hz - g["nu0_hz"]) / 1e9) ** 2)))
    clean = np.where(t[None, :] < 0, g["amp_v"], g["amp_v"] * np.exp(-t[None, :] / tau[:, None]))
    return clean + rng.normal(0.0, g["noise_v"], clean.shape)


def write_good_bundle(path, seed: int = 1) -> None:
    """Write the valid two-configuration bundle described in the module docstring."""
    g = GOOD
    rng = np.random.default_rng(seed)
    nu = g["nu0_hz"] + g["fsr_hz"] * np.arange(-(g["m"] // 2), g["m"] - g["m"] // 2)
    with h5py.File(path, "w") as f:
        f.attrs["format"] = "tfcrds-bundle"
        f.attrs["format_version"] = 1
        f.attrs["description"] = "synthetic test bundle <b>not</b> real data"
        s = f.create_group("sample")
        s.attrs["molecule"] = "CO"
        s.attrs["line"] = "(3-0) R(23)"
        s.attrs["nu0_hz"] = g["nu0_hz"]
        s.attrs["pressure_pa"] = 1333.22
        s.attrs["pressure_u_pa"] = 1.3
        s.attrs["temperature_k"] = 296.0
        s.attrs["temperature_u_k"] = 0.05
        s.attrs["mole_fraction"] = 0.01
        s.attrs["mass_u"] = 27.995
        cav = f.create_group("cavity")
        cav.attrs["fsr_hz"] = g["fsr_hz"]
        cav.attrs["finesse"] = 20000.0

        d1 = f.create_group("configs/D1")
        d1.attrs["description"] = "InGaAs PD, 10 kV/A, 14-bit digitizer"
        tf = d1.create_group("transfer_function")
        f_hz = np.geomspace(1e3, 1e7, g["n_tf"])
        h = np.abs(1.0 / (1.0 + 1j * f_hz / g["f_c_hz"]))
        i1 = np.full(g["n_tf"], g["i1_v"])
        tf["f_hz"] = f_hz
        tf["b12_v"] = 2.0 * np.sqrt(i1 * g["i2_v"]) * h
        tf["b12_u_v"] = np.full(g["n_tf"], 1e-4)
        tf["i1_v"] = i1
        tf["i2_v"] = g["i2_v"]
        rd = d1.create_group("ringdowns")
        rd.attrs["dt_s"] = g["dt_s"]
        rd.attrs["t0_s"] = g["t0_s"]
        rd["nu_hz"] = nu
        rd["signal_v"] = _transients(rng, nu, g)
        rd["n_avg"] = np.full(g["m"], g["n_avg"], dtype=np.int64)
        rd["noise_v"] = np.full((g["m"], g["k"]), g["noise_v"])
        cm = d1.create_group("cmds")
        cm["nu_hz"] = nu
        cm["shift_hz"] = 1e3 * (nu - g["nu0_hz"]) / g["fsr_hz"]
        cm["shift_u_hz"] = np.full(g["m"], 50.0)
        cm["width_hz"] = np.full(g["m"], 3.0e3)
        cm["width_u_hz"] = np.full(g["m"], 40.0)

        rd = f.create_group("configs/D2/ringdowns")
        rd.attrs["dt_s"] = g["dt_s"]
        rd.attrs["t0_s"] = 0.0
        rd["nu_hz"] = nu[::-1]  # non-monotonic order is allowed
        rd["signal_v"] = _transients(rng, nu[::-1], dict(g, t0_s=0.0))


@pytest.fixture
def good_bundle_path(tmp_path):
    """Path (in tmp_path) of a fresh valid bundle; tests may corrupt their own copy."""
    path = tmp_path / "good.h5"
    write_good_bundle(path)
    return path


def _module_fixtures(item) -> bool:
    """Does the test use a module-scoped fixture (built once per module and process)?"""
    info = getattr(item, "_fixtureinfo", None)
    if info is None:
        return False
    return any(d.scope == "module" for defs in info.name2fixturedefs.values() for d in defs)


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    """Schedule for ``pytest -n 2 --dist loadgroup`` (pyproject's addopts).

    The tests of a module that share a module-scoped fixture go to one worker as a group: the
    tour's fixture (2 min) was otherwise built on both workers. Tests marked ``slow`` come first,
    so that the last tests to start are short and the two workers end together.
    """
    for item in items:
        if _module_fixtures(item):
            item.add_marker(pytest.mark.xdist_group(item.module.__name__))
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)
