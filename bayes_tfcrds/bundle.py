"""The TF-CRDS measurement bundle (one HDF5 file per campaign): load, check, summarise, save.

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

import dataclasses
import difflib
import os
import secrets
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import h5py
import numpy as np

from .constants import TORR, hz_to_wavenumber_cm

__all__ = [
    "FORMAT_NAME", "FORMAT_VERSION", "CLIP_RUN", "SAT_WINDOW", "SAT_FLATNESS",
    "Sample", "Cavity", "TransferFunctionData", "RingdownData", "CmdsData", "Config", "Bundle",
    "Violation", "BundleError",
    "load_bundle", "validate_file", "summarize", "save_bundle", "load_truth", "main_validate",
]

FORMAT_NAME = "tfcrds-bundle"
FORMAT_VERSION = 1
#: A transient is flagged as clipped when its maximum (or minimum) value is repeated
#: exactly in at least this many consecutive samples, the run reaching t > 0.
CLIP_RUN = 3
#: A transient is flagged as saturated when a window of SAT_WINDOW consecutive samples at its
#: top, ending after extinction, scatters less than SAT_FLATNESS times the record's noise.
SAT_WINDOW = 32
SAT_FLATNESS = 0.35

_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


# --------------------------------------------------------------------------- records


class _Record:
    """Value equality for frozen records that hold numpy arrays (same shapes, same values)."""

    __hash__ = None  # records hold arrays: not hashable

    def __eq__(self, other):
        if type(other) is not type(self):
            return NotImplemented
        return all(_same(getattr(self, f.name), getattr(other, f.name))
                   for f in dataclasses.fields(self))


def _same(a, b) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return (isinstance(a, np.ndarray) and isinstance(b, np.ndarray)
                and np.array_equal(a, b))
    return a == b


def _frozen(x, dtype=np.float64) -> np.ndarray | None:
    """``x`` as a read-only array of ``dtype``; copies unless it already is one."""
    if x is None:
        return None
    if isinstance(x, np.ndarray) and x.dtype == dtype and not x.flags.writeable:
        return x
    a = np.array(x, dtype=dtype)
    a.setflags(write=False)
    return a


def _set(obj, **values) -> None:
    for name, value in values.items():
        object.__setattr__(obj, name, value)


def _opt_float(x) -> float | None:
    return None if x is None else float(x)


@dataclass(frozen=True, eq=False)
class Sample(_Record):
    """Sample conditions: nu0_hz (Hz), pressure (Pa), temperature (K), each with its
    standard uncertainty; mole_fraction of the absorber (1); mass_u in u (Doppler width)."""

    molecule: str
    line: str
    nu0_hz: float
    pressure_pa: float
    pressure_u_pa: float
    temperature_k: float
    temperature_u_k: float
    mole_fraction: float = 1.0
    mass_u: float | None = None

    def __post_init__(self):
        _set(self, molecule=str(self.molecule), line=str(self.line),
             **{n: float(getattr(self, n)) for n in (
                 "nu0_hz", "pressure_pa", "pressure_u_pa", "temperature_k",
                 "temperature_u_k", "mole_fraction")},
             mass_u=_opt_float(self.mass_u))


@dataclass(frozen=True, eq=False)
class Cavity(_Record):
    """Cavity: free spectral range fsr_hz (Hz) and optional empty-cavity finesse (1)."""

    fsr_hz: float
    finesse: float | None = None

    def __post_init__(self):
        _set(self, fsr_hz=float(self.fsr_hz), finesse=_opt_float(self.finesse))


def _scalar_or_array(x):
    a = np.asarray(x, dtype=np.float64)
    return float(a) if a.ndim == 0 else _frozen(a)


@dataclass(frozen=True, eq=False)
class TransferFunctionData(_Record):
    """Beat-note measurement of the detection chain, one row per beat frequency.

    f_hz (n,) beat frequencies (Hz); b12_v (n,) beat amplitude (V, half peak-to-peak);
    i1_v, i2_v single-beam DC levels (V), scalars or (n,); b12_u_v (n,) optional standard
    uncertainty of b12_v (V).
    """

    f_hz: np.ndarray
    b12_v: np.ndarray
    i1_v: float | np.ndarray
    i2_v: float | np.ndarray
    b12_u_v: np.ndarray | None = None

    def __post_init__(self):
        _set(self, f_hz=_frozen(self.f_hz), b12_v=_frozen(self.b12_v),
             i1_v=_scalar_or_array(self.i1_v), i2_v=_scalar_or_array(self.i2_v),
             b12_u_v=_frozen(self.b12_u_v))

    @property
    def _norm_v(self):
        return 2.0 * np.sqrt(np.asarray(self.i1_v) * np.asarray(self.i2_v))

    @property
    def h_mag(self) -> np.ndarray:
        """Measured |H(f_B)| = b12_v / (2 sqrt(i1_v i2_v)), dimensionless, shape (n,)."""
        return self.b12_v / self._norm_v

    @property
    def h_mag_u(self) -> np.ndarray | None:
        """Standard uncertainty of h_mag from b12_u_v alone (dimensionless), or None."""
        return None if self.b12_u_v is None else self.b12_u_v / self._norm_v


@dataclass(frozen=True, eq=False)
class RingdownData(_Record):
    """Averaged ring-down transients of one configuration, one row per spectral point.

    nu_hz (m,) absolute optical frequency (Hz); signal_v (m, k) volts, uniformly sampled
    every dt_s (s), the first sample at t0_s (s) from laser extinction; n_avg (m,)
    acquisitions averaged (optional); noise_v (m,) or (m, k) standard deviation of each
    averaged sample (V, optional).
    """

    nu_hz: np.ndarray
    signal_v: np.ndarray
    dt_s: float
    t0_s: float
    n_avg: np.ndarray | None = None
    noise_v: np.ndarray | None = None

    def __post_init__(self):
        if self.n_avg is not None and np.any(np.mod(self.n_avg, 1) != 0):
            raise ValueError("n_avg must hold whole numbers")
        _set(self, nu_hz=_frozen(self.nu_hz), signal_v=_frozen(self.signal_v),
             dt_s=float(self.dt_s), t0_s=float(self.t0_s),
             n_avg=_frozen(self.n_avg, np.int64), noise_v=_frozen(self.noise_v))

    @property
    def n_points(self) -> int:
        """Number of spectral points m (transients)."""
        return self.signal_v.shape[0]

    @property
    def n_samples(self) -> int:
        """Number of samples k per transient."""
        return self.signal_v.shape[1]

    @property
    def time_s(self) -> np.ndarray:
        """Sample times (s), shape (k,), relative to laser extinction: t0_s + dt_s*arange(k)."""
        return self.t0_s + self.dt_s * np.arange(self.n_samples)

    @cached_property
    def clipped(self) -> np.ndarray:
        """Per-transient flag (m,) bool: the top of the transient is cut off, so it is not fitted.

        Either clipped at the digitizer's rails or saturated below them (``saturated``; the
        detector or amplifier limits). Rails: the bundle has no ADC range, so clipping is read
        from the data: a transient is
        flagged when its maximum (or its minimum) value is taken EXACTLY by at least
        ``CLIP_RUN`` = 3 consecutive samples and that run reaches t > 0. An average of
        acquisitions that all sat on the same rail is exactly the rail value, whereas
        averaged noisy data essentially never repeat a float at the extreme. Runs lying
        entirely at t <= 0 are not flagged: a noiseless model is exactly flat before
        extinction and equals that level at t = 0, and digitizer clipping there never
        enters a fit, which uses t >= t_cut >= 0 only. A noiseless record long enough
        for the exponential to round to its baseline (about 37 tau) would be flagged.
        """
        flags = self._rails | self.saturated
        flags.setflags(write=False)
        return flags

    @cached_property
    def _rails(self) -> np.ndarray:
        return _clip_flags(self.signal_v, self.time_s)

    @cached_property
    def saturation(self) -> "Saturation":
        """Flat tops below the rails, per transient (see :class:`Saturation`)."""
        return _saturation(self.signal_v, self.time_s)

    @property
    def saturated(self) -> np.ndarray:
        """Per-transient flag (m,) bool: a flat top flatter than the noise allows, reaching t > 0.

        A saturated detector or amplifier pins its output at a level inside the ADC range: its
        own noise is cut off with the signal, so the top is flatter than the rest of the record
        while the averaged values, unlike rail clipping, need not repeat exactly. Flagged when a
        window of ``SAT_WINDOW`` = 32 samples that holds extinction (starts at or before it,
        ends after it), lies at the transient's top (mean within 5 sigma of the maximum; or
        bottom, for an inverting chain) and has a standard deviation below ``SAT_FLATNESS`` =
        0.35 sigma, sigma being the noise of the record's second half (from second differences,
        so a smooth decay does not count). For white noise a window that flat has probability
        7e-10 (chi-square, 31 degrees of freedom) and at most 32 windows are tested per
        transient. ``saturation.end_s`` is where the run of flat windows ends. A record without
        noise (sigma = 0) cannot be judged and is never flagged. Transients
        clipped at the rails (exact repeats) are reported as clipped, not here.
        """
        return self.saturation.flags & ~self._rails


@dataclass(frozen=True, eq=False)
class Saturation:
    """Flat-top detection per transient: ``flags`` (m,) bool; ``end_s`` (m,) time (s) of the last
    flat sample after extinction (NaN if none); ``scatter_v`` (m,) standard deviation of the
    flattest window at the top (V); ``noise_v`` (m,) the record's noise scale (V)."""

    flags: np.ndarray
    end_s: np.ndarray
    scatter_v: np.ndarray
    noise_v: np.ndarray


def _noise_scale(signal: np.ndarray) -> np.ndarray:
    """Robust white-noise sigma (V) per row from second differences of the record's second half:
    a decay's curvature per sample is negligible there and a flat top early on is excluded."""
    tail = signal[:, signal.shape[1] // 2:]
    d2 = np.diff(tail, n=2, axis=1)
    mad = np.median(np.abs(d2 - np.median(d2, axis=1, keepdims=True)), axis=1)
    return 1.482602218505602 * mad / np.sqrt(6.0)   # var(second difference) = 6 sigma^2


def _saturation(signal: np.ndarray, t: np.ndarray) -> Saturation:
    m, k = signal.shape
    w = SAT_WINDOW
    nan = np.full(m, np.nan)
    if m == 0 or k < 2 * w:
        empty = np.zeros(m, dtype=bool)
        return Saturation(empty, nan, nan.copy(), nan.copy())
    sigma = _noise_scale(signal)
    y = signal - signal.mean(axis=1, keepdims=True)   # centred: the running sums stay accurate
    zero = np.zeros((m, 1))
    c1 = np.concatenate([zero, np.cumsum(y, axis=1)], axis=1)
    c2 = np.concatenate([zero, np.cumsum(y * y, axis=1)], axis=1)
    mean = (c1[:, w:] - c1[:, :-w]) / w
    sd = np.sqrt(np.maximum((c2[:, w:] - c2[:, :-w]) / w - mean**2, 0.0) * (w / (w - 1)))
    ends = t[w - 1:]                                   # time of each window's last sample
    # at the top, or at the bottom for a chain that inverts (the clipping rule checks both too)
    at_top = ((mean >= (y.max(axis=1) - 5.0 * sigma)[:, None])
              | (mean <= (y.min(axis=1) + 5.0 * sigma)[:, None]))
    flat = at_top & (sd < SAT_FLATNESS * sigma[:, None]) & (sigma > 0)[:, None]
    # a saturated output is pinned through extinction: the flat run must hold a window that
    # starts at or before it (or at the first sample) and ends after it. Only these few windows
    # are tested, so a long quiet baseline late in the record cannot raise a false alarm.
    i_ext = int(np.searchsorted(t, 0.0))               # first sample at t >= 0
    starts = np.arange(ends.size)
    candidates = at_top & ((starts <= i_ext) & (ends > 0))[None, :]
    seeds = flat & candidates
    flags = seeds.any(axis=1)
    first = np.argmax(seeds, axis=1)
    # the plateau goes on while the following windows stay flat: its end is the last of them
    after = (~flat) & (starts[None, :] > first[:, None])
    stop = np.where(after.any(axis=1), np.argmax(after, axis=1), ends.size) - 1
    end_s = np.where(flags, ends[np.clip(stop, 0, ends.size - 1)], np.nan)
    scatter = np.where(candidates.any(axis=1), np.min(np.where(candidates, sd, np.inf), axis=1), np.nan)
    for a in (flags, end_s, scatter, sigma):
        a.setflags(write=False)
    return Saturation(flags, end_s, scatter, sigma)


def _clip_flags(signal: np.ndarray, t: np.ndarray) -> np.ndarray:
    m, k = signal.shape
    flags = np.zeros(m, dtype=bool)
    if m == 0 or k < CLIP_RUN:
        return flags
    late = t > 0
    width = k - CLIP_RUN + 1
    for extreme in (signal.max(axis=1, keepdims=True), signal.min(axis=1, keepdims=True)):
        at = signal == extreme
        start = np.logical_and.reduce([at[:, j:j + width] for j in range(CLIP_RUN)])
        in_run = np.zeros_like(at)
        for j in range(CLIP_RUN):
            in_run[:, j:j + width] |= start
        flags |= (in_run & late).any(axis=1)
    return flags


@dataclass(frozen=True, eq=False)
class CmdsData(_Record):
    """Cavity mode dispersion spectroscopy, p points: nu_hz empty-cavity mode frequency,
    shift_hz mode shift and shift_u_hz its standard uncertainty; optional width_hz mode
    half width at half maximum and width_u_hz its uncertainty. All Hz, shape (p,)."""

    nu_hz: np.ndarray
    shift_hz: np.ndarray
    shift_u_hz: np.ndarray
    width_hz: np.ndarray | None = None
    width_u_hz: np.ndarray | None = None

    def __post_init__(self):
        _set(self, **{f.name: _frozen(getattr(self, f.name)) for f in dataclasses.fields(self)})


@dataclass(frozen=True, eq=False)
class Config(_Record):
    """One detection configuration: its ring-downs and optional TF and CMDS measurements."""

    name: str
    ringdowns: RingdownData
    transfer_function: TransferFunctionData | None = None
    cmds: CmdsData | None = None
    description: str | None = None


@dataclass(frozen=True, eq=False)
class Bundle(_Record):
    """One measurement campaign. ``configs`` maps name -> Config in file order (a sequence
    of Config is accepted and keyed by name)."""

    sample: Sample
    cavity: Cavity
    configs: dict[str, Config]
    description: str | None = None

    def __post_init__(self):
        items = (self.configs.items() if isinstance(self.configs, Mapping)
                 else ((c.name, c) for c in self.configs))
        configs = dict(items)
        for key, cfg in configs.items():
            if key != cfg.name:
                raise ValueError(f"configs key {key!r} differs from its Config.name {cfg.name!r}")
        _set(self, configs=configs)


# --------------------------------------------------------------------------- violations


@dataclass(frozen=True)
class Violation:
    """One problem: ``path`` inside the file (``/group/dataset`` or ``/group@attribute``)."""

    path: str
    message: str

    def __str__(self) -> str:
        return f"{self.path}: {self.message}"


class BundleError(ValueError):
    """A file that breaks the bundle contract; ``.violations`` lists every problem."""

    def __init__(self, file: str | os.PathLike, violations: list[Violation]):
        self.file = os.fspath(file)
        self.violations = list(violations)
        lines = [f"{self.file}: not a valid {FORMAT_NAME} v{FORMAT_VERSION} file "
                 f"({len(self.violations)} problem(s)):"]
        lines += [f"{self.file}: {v}" for v in self.violations]
        super().__init__("\n".join(lines))


# --------------------------------------------------------------------------- reading

_POSITIVE = ("> 0", lambda a: a > 0)
_NONNEG = (">= 0", lambda a: a >= 0)
_AT_LEAST_1 = (">= 1", lambda a: a >= 1)
_FRACTION = ("in (0, 1]", lambda a: (a > 0) & (a <= 1))

_ROOT_ITEMS = ("sample", "cavity", "configs", "truth")
_ROOT_ATTRS = ("format", "format_version", "description")
_SAMPLE_ATTRS = ("molecule", "line", "nu0_hz", "pressure_pa", "pressure_u_pa", "temperature_k",
                 "temperature_u_k", "mole_fraction", "mass_u")
_CONFIG_ITEMS = ("transfer_function", "ringdowns", "cmds")
_TF_ITEMS = ("f_hz", "b12_v", "b12_u_v", "i1_v", "i2_v")
_RD_ITEMS = ("nu_hz", "signal_v", "n_avg", "noise_v")
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
                self.error(path, "is an external link to another file; a bundle must be "
                                 "self-contained")
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
                self.warn(path, f"stored as a float ({number!r}); read as the integer {int(number)}")
            number = int(number)
        else:
            number = float(number)
        if rule is not None and not rule[1](number):
            self.error(path, f"must be {rule[0]}, found {number!r}")
            return None
        return number

    # -- datasets

    def array(self, group, gpath: str, name: str, ndims=(1,), required: bool = True,
              rule=None, integer: bool = False, precise: bool = False):
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
                self.error(path, f"is stored as {dtype}: too few digits for an absolute "
                                 "optical frequency; must be float64")
                return None
            self.warn(path, f"stored as {dtype}, the contract says float64; read as float64")
        if ds.is_virtual or ds.external:
            self.error(path, "keeps its data in another file (virtual/external storage); "
                             "a bundle must be self-contained")
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
                self.error(path, f"contains {int(bad.sum())} non-finite value(s) (NaN or inf); "
                                 f"first at index {_index(first, raw.shape)}: "
                                 f"{_num(raw.reshape(-1)[first])}")
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
        if rule is not None:
            bad = ~rule[1](values)
            if np.any(bad):
                first = int(np.argmax(np.reshape(bad, -1)))
                self.error(path, f"must be {rule[0]}: {int(np.sum(bad))} of {values.size} "
                                 f"value(s) are not, first at index {_index(first, values.shape)}: "
                                 f"{_num(values.reshape(-1)[first])}")
                return None
        values.setflags(write=False)
        return values

    def same_length(self, gpath: str, name: str, values, n: int | None, ref: str) -> None:
        """Check a 1-D array has length ``n``, which ``ref`` (a phrase) explains."""
        if values is not None and n is not None and values.shape != (n,):
            self.error(_join(gpath, name), f"has {values.shape[0]} value(s) but {ref}; "
                                           f"expected shape ({n},)")


def _hint(name: str, known: tuple[str, ...]) -> str:
    close = difflib.get_close_matches(name, known, n=1, cutoff=0.75)
    return f" (did you mean {close[0]!r}?)" if close else ""


def _read_bundle(f: h5py.File, r: _Reader) -> Bundle | None:
    fmt = r.attr(f, "/", "format", "str")
    if fmt is not None and fmt != FORMAT_NAME:
        r.error("/@format", f"is {_short(fmt)}, expected {FORMAT_NAME!r}")
    version = r.attr(f, "/", "format_version", "int")
    if version is not None and version != FORMAT_VERSION:
        r.error("/@format_version", f"format version {version} found; this reader supports "
                                    f"version {FORMAT_VERSION} only (file not checked further)")
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
        nu0_hz=r.attr(g, p, "nu0_hz", "float", rule=_POSITIVE),
        pressure_pa=r.attr(g, p, "pressure_pa", "float", rule=_POSITIVE),
        pressure_u_pa=r.attr(g, p, "pressure_u_pa", "float", rule=_NONNEG),
        temperature_k=r.attr(g, p, "temperature_k", "float", rule=_POSITIVE),
        temperature_u_k=r.attr(g, p, "temperature_u_k", "float", rule=_NONNEG),
        mole_fraction=r.attr(g, p, "mole_fraction", "float", required=False, rule=_FRACTION),
        mass_u=r.attr(g, p, "mass_u", "float", required=False, rule=_POSITIVE),
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
            r.error(path, "is an external link to another file; a bundle must be "
                          "self-contained")
            continue
        cfg = _read_config(obj, path, name, r)
        if cfg is not None:
            configs[name] = cfg
    if n_groups == 0:
        r.error("/configs", "holds no configuration; at least one group /configs/<name> "
                            "is required")
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
    nu = r.array(g, p, "nu_hz", rule=_POSITIVE, precise=True)
    dt = r.attr(g, p, "dt_s", "float", rule=_POSITIVE)
    t0 = r.attr(g, p, "t0_s", "float")
    n_avg = r.array(g, p, "n_avg", required=False, rule=_AT_LEAST_1, integer=True)
    noise = r.array(g, p, "noise_v", ndims=(1, 2), required=False, rule=_POSITIVE)
    if signal is None:  # its own error says why; nothing to check lengths against
        return None
    m, k = signal.shape
    rows = f"signal_v has {m} rows (one per spectral point)"
    r.same_length(p, "nu_hz", nu, m, rows)
    r.same_length(p, "n_avg", n_avg, m, rows)
    if noise is not None and noise.shape not in ((m,), (m, k)):
        r.error(_join(p, "noise_v"), f"has shape {noise.shape}; expected ({m},) or ({m}, {k}) "
                                     f"to match signal_v of shape ({m}, {k})")
    if dt is not None and t0 is not None and t0 + dt * (k - 1) < 0:
        r.error(f"{p}@t0_s", f"the record has no sample at t >= 0 (after laser extinction): "
                             f"its last sample is at t = {t0 + dt * (k - 1):.6g} s "
                             f"(t0_s = {t0!r}, dt_s = {dt!r}, k = {k})")
    if len(r.errors) > n0:
        return None
    data = RingdownData(nu, signal, dt, t0, n_avg, noise)
    sat = data.saturation
    for i in np.flatnonzero(data.saturated):
        r.warn(_join(p, "signal_v"),
               f"transient {i} (nu_hz = {data.nu_hz[i]:.12g}) looks saturated: its top is flat "
               f"(scatter {sat.scatter_v[i]:.2g} V where the record's noise is "
               f"{sat.noise_v[i]:.2g} V) until t = {sat.end_s[i]:.3g} s after extinction, below "
               "the digitizer rails (detector or amplifier saturation?); not fitted")
    for i in np.flatnonzero(data.clipped & ~data.saturated):
        r.warn(_join(p, "signal_v"),
               f"transient {i} (nu_hz = {data.nu_hz[i]:.12g}) looks clipped: a flat run of "
               f">= {CLIP_RUN} identical samples at its maximum or minimum reaching t > 0 "
               "(digitizer rail?)")
    return data


def _read_tf(parent, cp: str, r: _Reader) -> TransferFunctionData | None:
    g = r.child(parent, cp, "transfer_function", "group", required=False)
    if g is None:
        return None
    p, n0 = _join(cp, "transfer_function"), len(r.errors)
    r.extras(g, p, _TF_ITEMS)
    f_hz = r.array(g, p, "f_hz", rule=_POSITIVE)
    b12 = r.array(g, p, "b12_v", rule=_NONNEG)
    b12_u = r.array(g, p, "b12_u_v", required=False, rule=_POSITIVE)   # a weight: 0 is infinite
    i1 = r.array(g, p, "i1_v", ndims=(0, 1), rule=_POSITIVE)
    i2 = r.array(g, p, "i2_v", ndims=(0, 1), rule=_POSITIVE)
    n = None
    if f_hz is not None:
        n = f_hz.shape[0]
        step = np.diff(f_hz)
        if np.any(step <= 0):
            i = int(np.argmax(step <= 0))
            r.error(_join(p, "f_hz"), f"must be strictly increasing: f_hz[{i + 1}] = "
                                      f"{_num(f_hz[i + 1])} <= f_hz[{i}] = {_num(f_hz[i])}")
    r.same_length(p, "b12_v", b12, n, f"f_hz has {n}")
    r.same_length(p, "b12_u_v", b12_u, n, f"f_hz has {n}")
    for name, level in (("i1_v", i1), ("i2_v", i2)):
        if level is not None and n is not None and level.shape not in ((), (n,)):
            r.error(_join(p, name), f"must be a scalar () or have shape ({n},) like f_hz; "
                                    f"found shape {level.shape}")
    if len(r.errors) > n0:
        return None
    return TransferFunctionData(f_hz, b12, i1, i2, b12_u)


def _read_cmds(parent, cp: str, r: _Reader) -> CmdsData | None:
    g = r.child(parent, cp, "cmds", "group", required=False)
    if g is None:
        return None
    p, n0 = _join(cp, "cmds"), len(r.errors)
    r.extras(g, p, _CMDS_ITEMS)
    nu = r.array(g, p, "nu_hz", rule=_POSITIVE, precise=True)
    shift = r.array(g, p, "shift_hz")
    shift_u = r.array(g, p, "shift_u_hz", rule=_POSITIVE)
    width = r.array(g, p, "width_hz", required=False, rule=_POSITIVE)
    width_u = r.array(g, p, "width_u_hz", required=False, rule=_POSITIVE)  # a weight, like shift_u
    n = None if nu is None else nu.shape[0]
    for name, values in (("shift_hz", shift), ("shift_u_hz", shift_u), ("width_hz", width),
                         ("width_u_hz", width_u)):
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
    """Check a file against FORMAT.md: (bundle or None, errors, warnings). Never raises for
    bad content; the bundle is returned only when there are no errors. Units: SI."""
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
    """Load a bundle (SI units, arrays read-only). Raises BundleError listing every
    violation; warnings (e.g. clipped transients) are available from validate_file."""
    bundle, errors, _ = validate_file(path)
    if errors:
        raise BundleError(path, errors)
    return bundle


# --------------------------------------------------------------------------- summary


def _printable(text: str) -> str:
    """Text attributes may hold anything: show control characters escaped, never act on them."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def _range(a: np.ndarray, unit: str) -> str:
    return f"{a.min():.12g} .. {a.max():.12g} {unit}"


def summarize(bundle: Bundle) -> str:
    """A human-readable summary of a bundle (SI units; nu0 also in cm^-1, p also in Torr)."""
    s, c = bundle.sample, bundle.cavity
    out = [f"{FORMAT_NAME}, format version {FORMAT_VERSION}"]
    if bundle.description:
        out.append(f"  description: {_printable(bundle.description)}")
    extra = f", mole fraction {s.mole_fraction:g}"
    if s.mass_u is not None:
        extra += f", mass {s.mass_u:g} u"
    out += [
        f"sample: {_printable(s.molecule)} {_printable(s.line)}, nu0 = {s.nu0_hz:.12g} Hz "
        f"({float(hz_to_wavenumber_cm(s.nu0_hz)):.6f} cm^-1)",
        f"  p = {s.pressure_pa:.6g} +/- {s.pressure_u_pa:.2g} Pa "
        f"({s.pressure_pa / TORR:.6g} Torr), T = {s.temperature_k:.6g} +/- "
        f"{s.temperature_u_k:.2g} K{extra}",
        f"cavity: FSR = {c.fsr_hz:.10g} Hz"
        + ("" if c.finesse is None else f", finesse = {c.finesse:.6g}"),
        f"configurations: {len(bundle.configs)}",
    ]
    for name, cfg in bundle.configs.items():
        rd = cfg.ringdowns
        head = f"  {_printable(name)}"
        out.append(head + (f": {_printable(cfg.description)}" if cfg.description else ""))
        out.append(f"    ringdowns: {rd.n_points} points x {rd.n_samples} samples, "
                   f"t0 = {rd.t0_s:.6g} s, dt = {rd.dt_s:.6g} s, record length "
                   f"{rd.n_samples * rd.dt_s:.6g} s; nu {_range(rd.nu_hz, 'Hz')}")
        out.append("      n_avg: " + ("absent" if rd.n_avg is None else
                                      f"{rd.n_avg.min()} .. {rd.n_avg.max()}")
                   + "; noise_v: " + ("absent" if rd.noise_v is None else
                                      "per sample (m, k)" if rd.noise_v.ndim == 2
                                      else "per transient (m,)"))
        saturated = np.flatnonzero(rd.saturated)
        if saturated.size:
            listed = ", ".join(f"#{i} (nu = {rd.nu_hz[i]:.12g} Hz, flat until "
                               f"{rd.saturation.end_s[i]:.3g} s)" for i in saturated)
            out.append(f"      SATURATED transients ({saturated.size}): {listed}")
        clipped = np.flatnonzero(rd.clipped & ~rd.saturated)
        if clipped.size:
            listed = ", ".join(f"#{i} (nu = {rd.nu_hz[i]:.12g} Hz)" for i in clipped)
            out.append(f"      CLIPPED transients ({clipped.size}): {listed}")
        tf = cfg.transfer_function
        out.append("    transfer_function: absent" if tf is None else
                   f"    transfer_function: {tf.f_hz.size} beat frequencies, "
                   f"f = {_range(tf.f_hz, 'Hz')}"
                   + ("" if tf.b12_u_v is None else ", with b12_u_v"))
        cm = cfg.cmds
        out.append("    cmds: absent" if cm is None else
                   f"    cmds: {cm.nu_hz.size} points, widths "
                   + ("present" if cm.width_hz is not None else "absent"))
    return "\n".join(out)


def main_validate(path) -> int:
    """``bayes-tfcrds validate FILE``: print the summary and warnings and return 0 for a
    good bundle; print every violation with its path and return 1 otherwise."""
    name = os.fspath(path)
    bundle, errors, warnings = validate_file(name)
    if errors:
        print(f"{name}: REFUSED, {len(errors)} problem(s):")
        for v in errors:
            print(f"  error: {v}")
    else:
        print(summarize(bundle))
    if warnings:
        print(f"{len(warnings)} warning(s):")
        for v in warnings:
            print(f"  warning: {v}")
    if not errors:
        print(f"{name}: OK")
    return 1 if errors else 0


# --------------------------------------------------------------------------- writing


def _utf8_lcpl():
    lcpl = h5py.h5p.create(h5py.h5p.LINK_CREATE)
    lcpl.set_char_encoding(h5py.h5t.CSET_UTF8)
    return lcpl


def _group(parent, name: str, ordered: bool = False) -> h5py.Group:
    """A new group without timestamps (byte-identical output); ``ordered`` keeps creation
    order so readers see configurations in the writer's order."""
    gcpl = h5py.h5p.create(h5py.h5p.GROUP_CREATE)
    gcpl.set_obj_track_times(False)
    if ordered:
        gcpl.set_link_creation_order(h5py.h5p.CRT_ORDER_TRACKED | h5py.h5p.CRT_ORDER_INDEXED)
    return h5py.Group(h5py.h5g.create(parent.id, name.encode("utf-8"),
                                      lcpl=_utf8_lcpl(), gcpl=gcpl))


def _dataset(group, name: str, data) -> None:
    group.create_dataset(name, data=data, track_times=False)


def _write_optional(group, name: str, data) -> None:
    if data is not None:
        _dataset(group, name, data)


def _write_ringdowns(cg, rd: RingdownData) -> None:
    g = _group(cg, "ringdowns")
    g.attrs["dt_s"] = float(rd.dt_s)
    g.attrs["t0_s"] = float(rd.t0_s)
    _dataset(g, "nu_hz", rd.nu_hz)
    _dataset(g, "signal_v", rd.signal_v)
    _write_optional(g, "n_avg", rd.n_avg)
    _write_optional(g, "noise_v", rd.noise_v)


def _write_tf(cg, tf: TransferFunctionData) -> None:
    g = _group(cg, "transfer_function")
    _dataset(g, "f_hz", tf.f_hz)
    _dataset(g, "b12_v", tf.b12_v)
    _write_optional(g, "b12_u_v", tf.b12_u_v)
    _dataset(g, "i1_v", np.float64(tf.i1_v) if np.ndim(tf.i1_v) == 0 else tf.i1_v)
    _dataset(g, "i2_v", np.float64(tf.i2_v) if np.ndim(tf.i2_v) == 0 else tf.i2_v)


def _write_cmds(cg, cm: CmdsData) -> None:
    g = _group(cg, "cmds")
    for f in dataclasses.fields(cm):
        _write_optional(g, f.name, getattr(cm, f.name))


def _write_truth(group, truth: Mapping, where: str) -> None:
    for key, value in truth.items():
        if not isinstance(key, str):
            raise TypeError(f"truth key {key!r} at {where} is not a str")
        here = _join(where, key)
        if isinstance(value, Mapping):
            _write_truth(_group(group, key), value, here)
        elif isinstance(value, (str, bool, int, float, np.generic)) or (
                isinstance(value, np.ndarray) and value.ndim == 0):
            group.attrs[key] = value
        elif isinstance(value, (np.ndarray, list, tuple)):
            array = np.asarray(value)
            if array.dtype.kind == "U":
                group.create_dataset(key, data=array.astype(object),
                                     dtype=h5py.string_dtype(), track_times=False)
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
    for name in ("nu0_hz", "pressure_pa", "pressure_u_pa", "temperature_k", "temperature_u_k",
                 "mole_fraction", "mass_u"):
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
    """Write ``bundle`` (SI units) to ``path`` exactly as FORMAT.md, with optional ``truth``
    (nested dict: scalars/str -> attributes, arrays -> datasets, dicts -> groups) under
    /truth.

    Atomic: written to a temporary file in the same directory, checked with the reader
    (so nothing is written that load_bundle would refuse: BundleError), then moved into
    place with os.replace; on any failure no file is left behind and an existing file at
    ``path`` is untouched. Deterministic: no HDF5 timestamps, so equal inputs give equal
    bytes.
    """
    target = os.fspath(path)
    directory, base = os.path.split(os.path.abspath(target))
    tmp = os.path.join(directory, f".{base}.{secrets.token_hex(6)}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    os.close(fd)
    try:
        fcpl = h5py.h5p.create(h5py.h5p.FILE_CREATE)
        fcpl.set_obj_track_times(False)
        with h5py.File(h5py.h5f.create(tmp.encode(), h5py.h5f.ACC_TRUNC, fcpl=fcpl)) as f:
            _write_file(f, bundle, truth)
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        _, errors, _ = validate_file(tmp)
        if errors:
            raise BundleError(target, errors)
        os.replace(tmp, target)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def _read_truth(g: h5py.Group, where: str, file: str) -> dict:
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
            out[key] = _read_truth(obj, here, file)
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
    """The simulator's /truth as a nested dict (None if absent). For tests and studies
    only: analyses must never read it. Raises BundleError if the file cannot be opened."""
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
