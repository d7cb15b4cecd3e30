"""Read and check a TF-CRDS measurement bundle (one HDF5 file per campaign).

The contract is /work/shared/FORMAT.md (format ``tfcrds-bundle``, version 1). A file that
follows it loads; a file that breaks it is refused with every problem listed, each naming
the place inside the file:

* groups and datasets by their HDF5 path: ``/configs/D2/ringdowns/signal_v``;
* attributes by the owning object's path, ``@`` and the attribute name:
  ``/sample@pressure_pa``, ``/configs/D1/ringdowns@dt_s``, and ``/@format`` for the root;
* problems with the file as a whole (missing, empty, not HDF5, truncated) by ``/``.

Files are opened with h5py only and nothing is ever unpickled or evaluated: object,
reference, compound and non-text variable-length datatypes are refused without being
read, and text attributes (which may hold anything, ``<script>`` included) come back as
plain ``str``. Unknown extra items and attributes are allowed and only warned about.

Everything is SI, as in the file: Hz, s, V, Pa, K.
"""

from __future__ import annotations

import difflib
import os
from collections.abc import Iterable
from typing import Any

import h5py
import numpy as np

from bayes_tfcrds.bundle.records import (
    _HDF5_SIGNATURE,
    CLIP_RUN,
    FORMAT_NAME,
    FORMAT_VERSION,
    Bundle,
    BundleError,
    Cavity,
    CmdsData,
    Config,
    RingdownData,
    Sample,
    TransferFunctionData,
    Violation,
)

# --------------------------------------------------------------------------- reading

_POSITIVE = ("> 0", lambda a: a > 0)
_NONNEG = (">= 0", lambda a: a >= 0)
_AT_LEAST_1 = (">= 1", lambda a: a >= 1)
_FRACTION = ("in (0, 1]", lambda a: (a > 0) & (a <= 1))


def _within(lo: float, hi: float, what: str):
    """A plausibility rule: values in [lo, hi], beyond which no laboratory measures ``what``.

    Values far outside every CRDS experiment are a unit or export error, not data: they are
    refused by path before any analysis (issue 20: T = 1e-300 K or dt_s = 1e300 s validated).
    """
    return (f"in [{lo:g}, {hi:g}] ({what})", lambda a: (a >= lo) & (a <= hi))


# positive first (its message says so), then plausible
_TEMPERATURE = [_POSITIVE, _within(1.0, 5000.0, "K, a gas sample")]
_PRESSURE = [_POSITIVE, _within(1e-6, 1e8, "Pa")]
_MASS = [_POSITIVE, _within(1.0, 1000.0, "u, a molecule's mass")]
_OPTICAL = [_POSITIVE, _within(1e11, 1e16, "Hz, far infrared to ultraviolet")]
_SAMPLING = [_POSITIVE, _within(1e-12, 1e-2, "s, a digitiser's sample interval")]
_VOLTS = [_POSITIVE, _within(1e-15, 1e3, "V")]
_SHIFT_U = [_POSITIVE, _within(1e-6, 1e12, "Hz")]


def _rules(rule) -> list:
    """A rule (text, test) or a list of them, checked in order."""
    if rule is None:
        return []
    return [rule] if isinstance(rule[0], str) else list(rule)


_ROOT_ITEMS = ("sample", "cavity", "configs", "truth")
_ROOT_ATTRS = ("format", "format_version", "description")
_SAMPLE_ATTRS = (
    "molecule",
    "line",
    "nu0_hz",
    "pressure_pa",
    "pressure_u_pa",
    "temperature_k",
    "temperature_u_k",
    "mole_fraction",
    "mass_u",
)
_CONFIG_ITEMS = ("transfer_function", "ringdowns", "cmds")
_TF_ITEMS = ("f_hz", "b12_v", "b12_u_v", "i1_v", "i2_v")
_RD_ITEMS = ("nu_hz", "signal_v", "n_avg", "noise_v", "time_s")
_CMDS_ITEMS = ("nu_hz", "shift_hz", "shift_u_hz", "width_hz", "width_u_hz")


def _join(gpath: str, name: str) -> str:
    return f"/{name}" if gpath == "/" else f"{gpath}/{name}"


def _why(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}"


def _kind(obj) -> str:
    if isinstance(obj, h5py.Group):
        return "group"
    if isinstance(obj, h5py.Dataset):
        return "dataset"
    return "named datatype"


def _refused_dtype(dtype: np.dtype) -> str | None:
    """Why a datatype is refused without reading it (object, reference, vlen, compound)."""
    if h5py.check_string_dtype(dtype) is not None:
        return None
    if h5py.check_ref_dtype(dtype) is not None:
        return "holds HDF5 object references; refused (not read)"
    if h5py.check_vlen_dtype(dtype) is not None:
        return "has a variable-length non-text datatype; refused (not read)"
    if dtype.kind == "O":
        return "has an object datatype; refused (not read)"
    if dtype.kind == "V":
        return "has a compound/opaque datatype; refused (not read)"
    return None


def _describe(dtype: np.dtype) -> str:
    if h5py.check_string_dtype(dtype) is not None:
        return "text"
    return {"b": "a boolean", "c": "a complex number", "U": "text"}.get(dtype.kind, str(dtype))


def _index(flat: int, shape) -> Any:
    idx = np.unravel_index(flat, shape)
    return int(idx[0]) if len(idx) == 1 else tuple(int(i) for i in idx)


def _num(x) -> str:
    """A number as Python shows it (numpy 2 scalars would print as np.float64(...))."""
    return repr(np.asarray(x).item())


def _short(text: str, n: int = 40) -> str:
    return repr(text if len(text) <= n else text[:n] + "...")


class _Reader:
    """Walks an open file and collects every violation and warning with its path."""

    def __init__(self):
        self.errors: list[Violation] = []
        self.warnings: list[Violation] = []

    def error(self, path: str, message: str) -> None:
        self.errors.append(Violation(path, message))

    def warn(self, path: str, message: str) -> None:
        self.warnings.append(Violation(path, message))

    # -- structure

    def child(self, group, gpath: str, name: str, kind: str, required: bool = True):
        """The group or dataset ``name`` of ``group``, or None (recording why)."""
        path = _join(gpath, name)
        try:
            link = group.get(name, getlink=True)
            if link is None:
                if required:
                    self.error(path, f"required {kind} is missing")
                return None
            if isinstance(link, h5py.ExternalLink):
                self.error(
                    path, "is an external link to another file; a bundle must be self-contained"
                )
                return None
            obj = group.get(name)
        except Exception as exc:  # corrupt file: h5py raises many types
            self.error(path, f"cannot be read (corrupt or truncated file?): {_why(exc)}")
            return None
        if obj is None:
            self.error(path, "is a dangling link (points at nothing)")
            return None
        want = h5py.Group if kind == "group" else h5py.Dataset
        if not isinstance(obj, want):
            self.error(path, f"is a {_kind(obj)}, expected a {kind}")
            return None
        return obj

    def extras(self, group, gpath: str, items: Iterable[str] = (), attrs: Iterable[str] = ()):
        """Warn about unknown items and attributes (allowed; a typo may hide an optional one)."""
        items, attrs = tuple(items), tuple(attrs)
        try:
            names = list(group.keys())
            attr_names = list(group.attrs.keys())
        except Exception as exc:
            self.error(gpath, f"cannot list contents (corrupt or truncated file?): {_why(exc)}")
            return
        for name in names:
            if name not in items:
                self.warn(_join(gpath, name), "unknown item, ignored" + _hint(name, items))
        for name in attr_names:
            if name not in attrs:
                self.warn(f"{gpath}@{name}", "unknown attribute, ignored" + _hint(name, attrs))

    # -- attributes

    def attr(self, obj, gpath: str, name: str, kind: str, required: bool = True, rule=None):
        """Attribute ``name`` as str / float / int (``kind``), or None (recording why)."""
        path = f"{gpath}@{name}"
        try:
            if name not in obj.attrs:
                if required:
                    self.error(path, "required attribute is missing")
                return None
            aid = obj.attrs.get_id(name)
            dtype, shape = aid.dtype, aid.shape
        except Exception as exc:
            self.error(path, f"cannot be read (corrupt or truncated file?): {_why(exc)}")
            return None
        refused = _refused_dtype(dtype)
        if refused:
            self.error(path, refused)
            return None
        if shape is None:
            self.error(path, "is an empty (null) attribute; expected a value")
            return None
        if shape != ():
            if int(np.prod(shape)) != 1:
                self.error(path, f"must be a single value, found an array of shape {shape}")
                return None
            self.warn(path, f"stored as a 1-element array of shape {shape}; read as a scalar")
        try:
            raw = obj.attrs[name]
        except Exception as exc:
            self.error(path, f"cannot be read: {_why(exc)}")
            return None
        value = np.asarray(raw).reshape(-1)[0] if isinstance(raw, np.ndarray) else raw
        is_text = h5py.check_string_dtype(dtype) is not None
        if kind == "str":
            if not is_text:
                self.error(path, f"expected text, found {_describe(dtype)} ({_num(value)})")
                return None
            if isinstance(value, (bytes, np.bytes_)):
                try:
                    value = bytes(value).decode("utf-8")
                except UnicodeDecodeError:
                    self.error(path, "is not valid UTF-8 text")
                    return None
            return str(value)
        if is_text:
            text = value.decode("utf-8", "replace") if isinstance(value, bytes) else str(value)
            self.error(path, f"expected a number, found text {_short(text)}")
            return None
        if dtype.kind not in "iuf":
            self.error(path, f"expected a real number, found {_describe(dtype)} ({_num(value)})")
            return None
        number = float(value) if dtype.kind == "f" else int(value)
        if not np.isfinite(number):
            self.error(path, f"must be finite, found {number!r} (non-finite)")
            return None
        if kind == "int":
            if dtype.kind == "f":
                if number != int(number):
                    self.error(path, f"expected an integer, found {number!r}")
                    return None
                self.warn(
                    path, f"stored as a float ({number!r}); read as the integer {int(number)}"
                )
            number = int(number)
        else:
            number = float(number)
        for text, ok in _rules(rule):
            if not ok(number):
                self.error(path, f"must be {text}, found {number!r}")
                return None
        return number

    # -- datasets

    def array(
        self,
        group,
        gpath: str,
        name: str,
        ndims=(1,),
        required: bool = True,
        rule=None,
        integer: bool = False,
        precise: bool = False,
    ):
        """Dataset ``name`` as a read-only float64 (int64 if ``integer``) array, or None.

        Checks: numeric datatype, number of dimensions in ``ndims``, non-empty, finite,
        ``rule``; ``precise`` refuses floats narrower than float64 (absolute frequencies).
        """
        ds = self.child(group, gpath, name, "dataset", required)
        if ds is None:
            return None
        path = _join(gpath, name)
        dtype, shape = ds.dtype, ds.shape
        refused = _refused_dtype(dtype)
        if refused:
            self.error(path, refused)
            return None
        if dtype.kind not in "iuf":
            self.error(path, f"expected real numbers, found {_describe(dtype)} data")
            return None
        if shape is None:
            self.error(path, "is an empty (null) dataset")
            return None
        if len(shape) not in ndims:
            want = " or ".join({0: "a scalar ()", 1: "1-D", 2: "2-D"}[d] for d in ndims)
            self.error(path, f"must be {want}, found shape {shape}")
            return None
        if len(shape) and int(np.prod(shape)) == 0:
            self.error(path, f"is empty (shape {shape})")
            return None
        if dtype.kind == "f" and dtype.itemsize < 8:
            if precise:
                self.error(
                    path,
                    f"is stored as {dtype}: too few digits for an absolute optical frequency; "
                    "must be float64",
                )
                return None
            self.warn(path, f"stored as {dtype}, the contract says float64; read as float64")
        if ds.is_virtual or ds.external:
            self.error(
                path,
                "keeps its data in another file (virtual/external storage); a bundle must be "
                "self-contained",
            )
            return None
        try:
            raw = np.asarray(ds[()])
        except Exception as exc:
            self.error(path, f"cannot be read (corrupt or truncated file?): {_why(exc)}")
            return None
        if dtype.kind == "f":
            bad = ~np.isfinite(raw)
            if bad.any():
                first = int(np.argmax(bad.reshape(-1)))
                self.error(
                    path,
                    f"contains {int(bad.sum())} non-finite value(s) (NaN or inf); first at index "
                    f"{_index(first, raw.shape)}: {_num(raw.reshape(-1)[first])}",
                )
                return None
        if integer:
            if dtype.kind == "f":
                if not np.all(raw == np.round(raw)):
                    self.error(path, "must hold whole numbers (integers)")
                    return None
                self.warn(path, f"stored as {dtype}, the contract says integers; read as int64")
            values = raw.astype(np.int64)
        else:
            values = raw.astype(np.float64)
        for text, ok in _rules(rule):
            bad = ~ok(values)
            if np.any(bad):
                first = int(np.argmax(np.reshape(bad, -1)))
                self.error(
                    path,
                    f"must be {text}: {int(np.sum(bad))} of {values.size} value(s) are not, "
                    f"first at index {_index(first, values.shape)}: "
                    f"{_num(values.reshape(-1)[first])}",
                )
                return None
        values.setflags(write=False)
        return values

    def same_length(self, gpath: str, name: str, values, n: int | None, ref: str) -> None:
        """Check a 1-D array has length ``n``, which ``ref`` (a phrase) explains."""
        if values is not None and n is not None and values.shape != (n,):
            self.error(
                _join(gpath, name),
                f"has {values.shape[0]} value(s) but {ref}; expected shape ({n},)",
            )


def _hint(name: str, known: tuple[str, ...]) -> str:
    close = difflib.get_close_matches(name, known, n=1, cutoff=0.75)
    return f" (did you mean {close[0]!r}?)" if close else ""


def _read_bundle(f: h5py.File, r: _Reader) -> Bundle | None:
    fmt = r.attr(f, "/", "format", "str")
    if fmt is not None and fmt != FORMAT_NAME:
        r.error("/@format", f"is {_short(fmt)}, expected {FORMAT_NAME!r}")
    version = r.attr(f, "/", "format_version", "int")
    if version is not None and version != FORMAT_VERSION:
        r.error(
            "/@format_version",
            f"format version {version} found; this reader supports version {FORMAT_VERSION} only "
            "(file not checked further)",
        )
        return None
    description = r.attr(f, "/", "description", "str", required=False)
    r.extras(f, "/", _ROOT_ITEMS, _ROOT_ATTRS)
    sample = _read_sample(f, r)
    cavity = _read_cavity(f, r)
    configs = _read_configs(f, r)
    if r.errors:
        return None
    return Bundle(sample, cavity, configs, description)


def _read_sample(f, r: _Reader) -> Sample | None:
    g = r.child(f, "/", "sample", "group")
    if g is None:
        return None
    p, n0 = "/sample", len(r.errors)
    v = dict(
        molecule=r.attr(g, p, "molecule", "str"),
        line=r.attr(g, p, "line", "str"),
        nu0_hz=r.attr(g, p, "nu0_hz", "float", rule=_OPTICAL),
        pressure_pa=r.attr(g, p, "pressure_pa", "float", rule=_PRESSURE),
        pressure_u_pa=r.attr(g, p, "pressure_u_pa", "float", rule=_NONNEG),
        temperature_k=r.attr(g, p, "temperature_k", "float", rule=_TEMPERATURE),
        temperature_u_k=r.attr(g, p, "temperature_u_k", "float", rule=_NONNEG),
        mole_fraction=r.attr(g, p, "mole_fraction", "float", required=False, rule=_FRACTION),
        mass_u=r.attr(g, p, "mass_u", "float", required=False, rule=_MASS),
    )
    r.extras(g, p, (), _SAMPLE_ATTRS)
    if len(r.errors) > n0:
        return None
    if v["mole_fraction"] is None:
        v["mole_fraction"] = 1.0
    return Sample(**v)


def _read_cavity(f, r: _Reader) -> Cavity | None:
    g = r.child(f, "/", "cavity", "group")
    if g is None:
        return None
    p, n0 = "/cavity", len(r.errors)
    fsr = r.attr(g, p, "fsr_hz", "float", rule=_POSITIVE)
    finesse = r.attr(g, p, "finesse", "float", required=False, rule=_POSITIVE)
    r.extras(g, p, (), ("fsr_hz", "finesse"))
    return None if len(r.errors) > n0 else Cavity(fsr, finesse)


def _read_configs(f, r: _Reader) -> dict[str, Config]:
    g = r.child(f, "/", "configs", "group")
    if g is None:
        return {}
    try:
        names = list(g.keys())  # creation order if tracked, else by name
    except Exception as exc:
        r.error("/configs", f"cannot list contents (corrupt or truncated file?): {_why(exc)}")
        return {}
    configs, n_groups = {}, 0
    for name in names:
        path = _join("/configs", name)
        try:
            external = isinstance(g.get(name, getlink=True), h5py.ExternalLink)
            obj = None if external else g.get(name)
        except Exception as exc:
            r.error(path, f"cannot be read (corrupt or truncated file?): {_why(exc)}")
            continue
        if not external and not isinstance(obj, h5py.Group):
            r.warn(path, "is not a group, so not a configuration; ignored")
            continue
        n_groups += 1
        if external:  # never followed: it would open another file
            r.error(path, "is an external link to another file; a bundle must be self-contained")
            continue
        cfg = _read_config(obj, path, name, r)
        if cfg is not None:
            configs[name] = cfg
    if n_groups == 0:
        r.error(
            "/configs", "holds no configuration; at least one group /configs/<name> is required"
        )
    return configs


def _read_config(g, p: str, name: str, r: _Reader) -> Config | None:
    n0 = len(r.errors)
    description = r.attr(g, p, "description", "str", required=False)
    r.extras(g, p, _CONFIG_ITEMS, ("description",))
    ringdowns = _read_ringdowns(g, p, r)
    tf = _read_tf(g, p, r)
    cmds = _read_cmds(g, p, r)
    if len(r.errors) > n0:
        return None
    return Config(name, ringdowns, tf, cmds, description)


def _read_ringdowns(parent, cp: str, r: _Reader) -> RingdownData | None:
    g = r.child(parent, cp, "ringdowns", "group")
    if g is None:
        return None
    p, n0 = _join(cp, "ringdowns"), len(r.errors)
    r.extras(g, p, _RD_ITEMS, ("dt_s", "t0_s"))
    signal = r.array(g, p, "signal_v", ndims=(2,))
    nu = r.array(g, p, "nu_hz", rule=_OPTICAL, precise=True)
    dt = r.attr(g, p, "dt_s", "float", rule=_SAMPLING)
    t0 = r.attr(g, p, "t0_s", "float")
    n_avg = r.array(g, p, "n_avg", required=False, rule=_AT_LEAST_1, integer=True)
    noise = r.array(g, p, "noise_v", ndims=(1, 2), required=False, rule=_VOLTS)
    if signal is None:  # its own error says why; nothing to check lengths against
        return None
    m, k = signal.shape
    rows = f"signal_v has {m} rows (one per spectral point)"
    r.same_length(p, "nu_hz", nu, m, rows)
    r.same_length(p, "n_avg", n_avg, m, rows)
    if noise is not None and noise.shape not in ((m,), (m, k)):
        r.error(
            _join(p, "noise_v"),
            f"has shape {noise.shape}; expected ({m},) or ({m}, {k}) to match signal_v of shape "
            f"({m}, {k})",
        )
    if dt is not None and t0 is not None and t0 + dt * (k - 1) < 0:
        r.error(
            f"{p}@t0_s",
            "the record has no sample at t >= 0 (after laser extinction): its last sample is at t "
            f"= {t0 + dt * (k - 1):.6g} s (t0_s = {t0!r}, dt_s = {dt!r}, k = {k})",
        )
    _check_time_axis(g, p, dt, t0, k, r)
    if len(r.errors) > n0:
        return None
    data = RingdownData(nu, signal, dt, t0, n_avg, noise)
    sat = data.saturation
    for i in np.flatnonzero(data.saturated):
        r.warn(
            _join(p, "signal_v"),
            f"transient {i} (nu_hz = {data.nu_hz[i]:.12g}) looks saturated: its top is flat "
            f"(scatter {sat.scatter_v[i]:.2g} V where the record's noise is {sat.noise_v[i]:.2g} "
            f"V) until t = {sat.end_s[i]:.3g} s after extinction, below the digitizer rails "
            "(detector or amplifier saturation?); not fitted",
        )
    for i in np.flatnonzero(data.clipped & ~data.saturated):
        r.warn(
            _join(p, "signal_v"),
            f"transient {i} (nu_hz = {data.nu_hz[i]:.12g}) looks clipped: a flat run of >= "
            f"{CLIP_RUN} identical samples at its maximum or minimum reaching t > 0 (digitizer "
            "rail?)",
        )
    return data


def _check_time_axis(g, p: str, dt, t0, k: int, r: _Reader) -> None:
    """The optional ``time_s`` (the writer's dimension scale) should be t0_s + dt_s arange(k).

    dt_s and t0_s define the time axis and every analysis uses them; a time_s that says
    otherwise (t0_s edited after writing, say) is warned about, naming both, and not used.
    """
    if "time_s" not in g:
        return
    time = r.array(g, p, "time_s")
    if time is None or dt is None or t0 is None:
        return
    if time.shape != (k,):
        r.warn(
            _join(p, "time_s"), f"has shape {time.shape}, not ({k},) like signal_v's rows; ignored"
        )
        return
    off = np.abs(time - (t0 + dt * np.arange(k)))
    if np.max(off) > 1e-6 * dt:  # far above the rounding of t0 + dt i (1e-16 relative)
        i = int(np.argmax(off))
        r.warn(
            _join(p, "time_s"),
            f"disagrees with t0_s + dt_s * index: time_s[{i}] = {_num(time[i])} s, expected "
            f"{_num(t0 + dt * i)} s; t0_s and dt_s are used (correct or remove time_s)",
        )


def _check_beat_reference(p: str, b12, n: int | None, r: _Reader) -> None:
    """The beat note must have signal at its lowest frequencies.

    There the chain passes it at full gain, and |H| is normalised to them (fit.beat_note): an
    amplitude of 0 V there is no measurement (a dead channel), and the H fit of such a file ran
    without end instead of stopping.
    """
    if b12 is None or n is None or b12.shape != (n,):
        return
    k = max(3, n // 10)
    zero = np.flatnonzero(b12[:k] == 0)
    if zero.size:
        r.error(
            _join(p, "b12_v"),
            f"is 0 V at {zero.size} of the {min(k, n)} lowest frequencies (first at index "
            f"{int(zero[0])}), where the chain passes the beat note at full gain: no beat note "
            "was recorded there",
        )


def _read_tf(parent, cp: str, r: _Reader) -> TransferFunctionData | None:
    g = r.child(parent, cp, "transfer_function", "group", required=False)
    if g is None:
        return None
    p, n0 = _join(cp, "transfer_function"), len(r.errors)
    r.extras(g, p, _TF_ITEMS)
    f_hz = r.array(g, p, "f_hz", rule=_POSITIVE)
    b12 = r.array(g, p, "b12_v", rule=[_NONNEG, _within(0.0, 1e3, "V")])
    # a weight: 0 is infinite, and 1e-300 V as good (the fit then fails from every start)
    b12_u = r.array(g, p, "b12_u_v", required=False, rule=_VOLTS)
    i1 = r.array(g, p, "i1_v", ndims=(0, 1), rule=_POSITIVE)
    i2 = r.array(g, p, "i2_v", ndims=(0, 1), rule=_POSITIVE)
    n = None
    if f_hz is not None:
        n = f_hz.shape[0]
        step = np.diff(f_hz)
        if np.any(step <= 0):
            i = int(np.argmax(step <= 0))
            r.error(
                _join(p, "f_hz"),
                f"must be strictly increasing: f_hz[{i + 1}] = {_num(f_hz[i + 1])} <= f_hz[{i}] = "
                f"{_num(f_hz[i])}",
            )
    r.same_length(p, "b12_v", b12, n, f"f_hz has {n}")
    _check_beat_reference(p, b12, n, r)
    r.same_length(p, "b12_u_v", b12_u, n, f"f_hz has {n}")
    for name, level in (("i1_v", i1), ("i2_v", i2)):
        if level is not None and n is not None and level.shape not in ((), (n,)):
            r.error(
                _join(p, name),
                f"must be a scalar () or have shape ({n},) like f_hz; found shape {level.shape}",
            )
    if len(r.errors) > n0:
        return None
    return TransferFunctionData(f_hz, b12, i1, i2, b12_u)


def _read_cmds(parent, cp: str, r: _Reader) -> CmdsData | None:
    g = r.child(parent, cp, "cmds", "group", required=False)
    if g is None:
        return None
    p, n0 = _join(cp, "cmds"), len(r.errors)
    r.extras(g, p, _CMDS_ITEMS)
    nu = r.array(g, p, "nu_hz", rule=_OPTICAL, precise=True)
    shift = r.array(g, p, "shift_hz")
    shift_u = r.array(g, p, "shift_u_hz", rule=_SHIFT_U)
    width = r.array(g, p, "width_hz", required=False, rule=_POSITIVE)
    width_u = r.array(g, p, "width_u_hz", required=False, rule=_POSITIVE)  # a weight, like shift_u
    n = None if nu is None else nu.shape[0]
    for name, values in (
        ("shift_hz", shift),
        ("shift_u_hz", shift_u),
        ("width_hz", width),
        ("width_u_hz", width_u),
    ):
        r.same_length(p, name, values, n, f"nu_hz has {n} (all cmds arrays share length p)")
    if width_u is not None and width is None and len(r.errors) == n0:
        r.warn(_join(p, "width_u_hz"), "ignored: width_hz is missing")
        width_u = None
    if len(r.errors) > n0:
        return None
    return CmdsData(nu, shift, shift_u, width, width_u)


def _has_hdf5_signature(path: str, size: int) -> bool:
    """HDF5 files start with a signature at byte 0, 512, 1024, 2048, ... (user block)."""
    with open(path, "rb") as fh:
        offset = 0
        while offset + 8 <= size:
            fh.seek(offset)
            if fh.read(8) == _HDF5_SIGNATURE:
                return True
            offset = 512 if offset == 0 else 2 * offset
    return False


def _open_problem(path: str) -> str | None:
    """Why ``path`` cannot be a bundle before h5py is involved, or None."""
    if not os.path.exists(path):
        return f"file not found: {path!r}"
    if os.path.isdir(path):
        return f"is a directory, not a file: {path!r}"
    if os.path.getsize(path) == 0:
        return "file is empty (0 bytes), not an HDF5 file"
    if not os.access(path, os.R_OK):
        return "file cannot be read (permission denied)"
    return None


def validate_file(path) -> tuple[Bundle | None, list[Violation], list[Violation]]:
    """Check a file against FORMAT.md: (bundle or None, errors, warnings).

    Never raises for bad content; the bundle is returned only when there are no errors. Units: SI.
    """
    name = os.fspath(path)
    r = _Reader()
    problem = _open_problem(name)
    if problem:
        r.error("/", problem)
        return None, r.errors, r.warnings
    try:
        f = h5py.File(name, "r")
    except Exception as exc:
        try:
            signed = _has_hdf5_signature(name, os.path.getsize(name))
        except OSError as io_exc:
            r.error("/", f"file cannot be read: {_why(io_exc)}")
            return None, r.errors, r.warnings
        if not signed:
            r.error("/", "not an HDF5 file (no HDF5 signature found)")
        else:
            r.error("/", f"truncated or corrupt HDF5 file, cannot be opened: {exc}")
        return None, r.errors, r.warnings
    bundle = None
    try:
        with f:
            bundle = _read_bundle(f, r)
    except Exception as exc:  # last resort for damage the item-level checks did not catch
        r.error("/", f"file could not be read (corrupt or truncated?): {_why(exc)}")
        bundle = None
    return (bundle if not r.errors else None), r.errors, r.warnings


def load_bundle(path) -> Bundle:
    """Load a bundle (SI units, arrays read-only).

    Parameters
    ----------
    path : str or pathlib.Path
        The HDF5 measurement bundle (``bayes_tfcrds/data/FORMAT.md``).

    Returns
    -------
    Bundle
        The sample, and one configuration per ``/configs/NAME`` (``bundle.configs["D2"]``).

    Raises
    ------
    BundleError
        Listing every violation of the format, each with its path in the file. Warnings (e.g.
        clipped transients) are available from :func:`validate_file`.
    """
    bundle, errors, _ = validate_file(path)
    if errors:
        raise BundleError(path, errors)
    return bundle


def _read_truth(g: h5py.Group, where: str, file: str, ancestors: tuple = ()) -> dict:
    # a group hard-linked into its own subtree would recurse for ever: refused by path
    if any(g.id == a for a in ancestors):
        raise BundleError(
            file, [Violation(where, "is a hard link back to a group above it (a cycle)")]
        )
    ancestors = (*ancestors, g.id)
    out: dict[str, Any] = {}
    for key in g.attrs:
        refused = _refused_dtype(g.attrs.get_id(key).dtype)
        if refused:
            raise BundleError(file, [Violation(f"{where}@{key}", refused)])
        value = g.attrs[key]
        if isinstance(value, (bytes, np.bytes_)):
            value = bytes(value).decode("utf-8")
        elif isinstance(value, np.generic):
            value = value.item()
        elif isinstance(value, np.ndarray):
            value.setflags(write=False)
        out[key] = value
    for key in g:
        here = _join(where, key)
        obj = g.get(key)
        if isinstance(obj, h5py.Group):
            out[key] = _read_truth(obj, here, file, ancestors)
        elif isinstance(obj, h5py.Dataset):
            if h5py.check_string_dtype(obj.dtype) is not None:
                value = np.asarray(obj.asstr()[()])
            else:
                refused = _refused_dtype(obj.dtype)
                if refused:
                    raise BundleError(file, [Violation(here, refused)])
                value = np.asarray(obj[()])
            value.setflags(write=False)
            out[key] = value
    return out


def load_truth(path) -> dict | None:
    """The simulator's /truth as a nested dict (None if absent).

    For tests and studies only: analyses must never read it. Raises BundleError if the file cannot
    be opened.
    """
    name = os.fspath(path)
    problem = _open_problem(name)
    if problem:
        raise BundleError(name, [Violation("/", problem)])
    try:
        f = h5py.File(name, "r")
    except Exception as exc:
        raise BundleError(name, [Violation("/", f"cannot be opened as HDF5: {exc}")]) from None
    with f:
        g = f.get("truth")
        return _read_truth(g, "/truth", name) if isinstance(g, h5py.Group) else None
