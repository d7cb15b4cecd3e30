"""Write a bundle (and its simulation truth) to HDF5 as FORMAT.md says, atomically."""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping

import h5py
import numpy as np

from bayes_tfcrds.bundle.reader import _join, validate_file
from bayes_tfcrds.bundle.records import (
    FORMAT_NAME,
    FORMAT_VERSION,
    Bundle,
    BundleError,
    CmdsData,
    RingdownData,
    TransferFunctionData,
)
from bayes_tfcrds.output.files import atomic_path

# --------------------------------------------------------------------------- writing


def _utf8_lcpl():
    lcpl = h5py.h5p.create(h5py.h5p.LINK_CREATE)
    lcpl.set_char_encoding(h5py.h5t.CSET_UTF8)
    return lcpl


def _group(parent, name: str, ordered: bool = False) -> h5py.Group:
    """A new group without timestamps (byte-identical output).

    ``ordered`` keeps creation order so readers see configurations in the writer's order.
    """
    gcpl = h5py.h5p.create(h5py.h5p.GROUP_CREATE)
    gcpl.set_obj_track_times(False)
    if ordered:
        gcpl.set_link_creation_order(h5py.h5p.CRT_ORDER_TRACKED | h5py.h5p.CRT_ORDER_INDEXED)
    return h5py.Group(
        h5py.h5g.create(parent.id, name.encode("utf-8"), lcpl=_utf8_lcpl(), gcpl=gcpl)
    )


def _dataset(group, name: str, data) -> None:
    group.create_dataset(name, data=data, track_times=False)


def _write_optional(group, name: str, data) -> None:
    if data is not None:
        _dataset(group, name, data)


def _dimension_scales(g, scales: tuple[str, ...]) -> None:
    """Make ``scales`` (1-D datasets of ``g``) HDF5 dimension scales and attach them by shape.

    Each other dataset of ``g`` gets, per axis, the scale whose length matches in order (axis 0
    the first, axis 1 the second), and the scale's name as the axis label, so netCDF-4/xarray
    tools see named dimensions (nu_hz, time_s, f_hz) instead of phony ones.
    """
    for name in scales:
        g[name].make_scale(name)
    for name, ds in g.items():
        if name in scales:
            continue
        for axis, scale in zip(range(ds.ndim), scales):
            if ds.shape[axis] == g[scale].shape[0]:
                ds.dims[axis].attach_scale(g[scale])
                ds.dims[axis].label = scale


def _write_ringdowns(cg, rd: RingdownData) -> None:
    g = _group(cg, "ringdowns")
    g.attrs["dt_s"] = float(rd.dt_s)
    g.attrs["t0_s"] = float(rd.t0_s)
    _dataset(g, "nu_hz", rd.nu_hz)
    _dataset(g, "time_s", rd.time_s)  # the time axis (dimension scale); dt_s, t0_s define it
    _dataset(g, "signal_v", rd.signal_v)
    _write_optional(g, "n_avg", rd.n_avg)
    _write_optional(g, "noise_v", rd.noise_v)
    _dimension_scales(g, ("nu_hz", "time_s"))


def _write_tf(cg, tf: TransferFunctionData) -> None:
    g = _group(cg, "transfer_function")
    _dataset(g, "f_hz", tf.f_hz)
    _dataset(g, "b12_v", tf.b12_v)
    _write_optional(g, "b12_u_v", tf.b12_u_v)
    _dataset(g, "i1_v", np.float64(tf.i1_v) if np.ndim(tf.i1_v) == 0 else tf.i1_v)
    _dataset(g, "i2_v", np.float64(tf.i2_v) if np.ndim(tf.i2_v) == 0 else tf.i2_v)
    _dimension_scales(g, ("f_hz",))


def _write_cmds(cg, cm: CmdsData) -> None:
    g = _group(cg, "cmds")
    for f in dataclasses.fields(cm):
        _write_optional(g, f.name, getattr(cm, f.name))
    _dimension_scales(g, ("nu_hz",))


def _write_truth(group, truth: Mapping, where: str) -> None:
    for key, value in truth.items():
        if not isinstance(key, str):
            raise TypeError(f"truth key {key!r} at {where} is not a str")
        here = _join(where, key)
        if isinstance(value, Mapping):
            _write_truth(_group(group, key), value, here)
        elif isinstance(value, (str, bool, int, float, np.generic)) or (
            isinstance(value, np.ndarray) and value.ndim == 0
        ):
            group.attrs[key] = value
        elif isinstance(value, (np.ndarray, list, tuple)):
            array = np.asarray(value)
            if array.dtype.kind == "U":
                group.create_dataset(
                    key, data=array.astype(object), dtype=h5py.string_dtype(), track_times=False
                )
            elif array.dtype.kind in "biuf":
                _dataset(group, key, array)
            else:
                raise TypeError(f"truth {here}: cannot store an array of dtype {array.dtype}")
        else:
            raise TypeError(f"truth {here}: cannot store {type(value).__name__}")


def _write_file(f: h5py.File, bundle: Bundle, truth: Mapping | None) -> None:
    f.attrs["format"] = FORMAT_NAME
    f.attrs["format_version"] = np.int64(FORMAT_VERSION)
    if bundle.description is not None:
        f.attrs["description"] = str(bundle.description)
    s = bundle.sample
    g = _group(f, "sample")
    g.attrs["molecule"] = s.molecule
    g.attrs["line"] = s.line
    for name in (
        "nu0_hz",
        "pressure_pa",
        "pressure_u_pa",
        "temperature_k",
        "temperature_u_k",
        "mole_fraction",
        "mass_u",
    ):
        if getattr(s, name) is not None:
            g.attrs[name] = float(getattr(s, name))
    g = _group(f, "cavity")
    g.attrs["fsr_hz"] = float(bundle.cavity.fsr_hz)
    if bundle.cavity.finesse is not None:
        g.attrs["finesse"] = float(bundle.cavity.finesse)
    configs = _group(f, "configs", ordered=True)
    for name, cfg in bundle.configs.items():
        cg = _group(configs, name)
        if cfg.description is not None:
            cg.attrs["description"] = str(cfg.description)
        if cfg.transfer_function is not None:
            _write_tf(cg, cfg.transfer_function)
        _write_ringdowns(cg, cfg.ringdowns)
        if cfg.cmds is not None:
            _write_cmds(cg, cfg.cmds)
    if truth is not None:
        _write_truth(_group(f, "truth"), truth, "/truth")


def save_bundle(bundle: Bundle, path, truth: Mapping | None = None) -> None:
    """Write ``bundle`` (SI units) to ``path`` exactly as FORMAT.md says.

    The optional ``truth`` (nested dict: scalars/str -> attributes, arrays -> datasets, dicts ->
    groups) goes under /truth.

    Atomic: written to a temporary file in the same directory, checked with the reader
    (so nothing is written that load_bundle would refuse: BundleError), then moved into
    place with os.replace; on any failure no file is left behind and an existing file at
    ``path`` is untouched. Deterministic: no HDF5 timestamps, so equal inputs give equal
    bytes.
    """
    target = os.fspath(path)
    with atomic_path(target) as tmp:
        fcpl = h5py.h5p.create(h5py.h5p.FILE_CREATE)
        fcpl.set_obj_track_times(False)
        with h5py.File(h5py.h5f.create(os.fsencode(tmp), h5py.h5f.ACC_TRUNC, fcpl=fcpl)) as f:
            _write_file(f, bundle, truth)
        _, errors, _ = validate_file(os.fspath(tmp))
        if errors:
            raise BundleError(target, errors)
