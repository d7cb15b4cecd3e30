"""Bundle records: the frozen dataclasses of FORMAT.md, their QC flags and the errors.

Everything is SI, as in the file: Hz, s, V, Pa, K. A record never changes after it is made
(arrays are read-only), so a bundle can be shared between fits and processes.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property

import numpy as np

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
        return all(
            _same(getattr(self, f.name), getattr(other, f.name)) for f in dataclasses.fields(self)
        )


def _same(a, b) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return isinstance(a, np.ndarray) and isinstance(b, np.ndarray) and np.array_equal(a, b)
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
    """Sample conditions.

    nu0_hz (Hz), pressure (Pa), temperature (K), each with its standard uncertainty; mole_fraction
    of the absorber (1); mass_u in u (Doppler width).
    """

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
        _set(
            self,
            molecule=str(self.molecule),
            line=str(self.line),
            **{
                n: float(getattr(self, n))
                for n in (
                    "nu0_hz",
                    "pressure_pa",
                    "pressure_u_pa",
                    "temperature_k",
                    "temperature_u_k",
                    "mole_fraction",
                )
            },
            mass_u=_opt_float(self.mass_u),
        )


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
        _set(
            self,
            f_hz=_frozen(self.f_hz),
            b12_v=_frozen(self.b12_v),
            i1_v=_scalar_or_array(self.i1_v),
            i2_v=_scalar_or_array(self.i2_v),
            b12_u_v=_frozen(self.b12_u_v),
        )

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

    ``noise_kappa`` (m,) is not part of the file: an analysis sets it
    (:func:`bayes_tfcrds.fit.noise.with_noise_colour`) when the noise is coloured. It is the
    factor by which correlated samples raise the variance of a slowly varying fitted quantity
    (tau) over the independent-sample formula; every likelihood then weights the record with
    ``fit_noise_v`` = noise_v sqrt(noise_kappa).
    """

    nu_hz: np.ndarray
    signal_v: np.ndarray
    dt_s: float
    t0_s: float
    n_avg: np.ndarray | None = None
    noise_v: np.ndarray | None = None
    noise_kappa: np.ndarray | None = None

    def __post_init__(self):
        if self.n_avg is not None and np.any(np.mod(self.n_avg, 1) != 0):
            raise ValueError("n_avg must hold whole numbers")
        _set(
            self,
            nu_hz=_frozen(self.nu_hz),
            signal_v=_frozen(self.signal_v),
            dt_s=float(self.dt_s),
            t0_s=float(self.t0_s),
            n_avg=_frozen(self.n_avg, np.int64),
            noise_v=_frozen(self.noise_v),
            noise_kappa=_frozen(self.noise_kappa),
        )

    @property
    def n_points(self) -> int:
        """Number of spectral points m (transients)."""
        return self.signal_v.shape[0]

    @property
    def fit_noise_v(self) -> np.ndarray | None:
        """The noise (V) every likelihood weights with: noise_v, times sqrt(noise_kappa) if set."""
        if self.noise_v is None or self.noise_kappa is None:
            return self.noise_v
        k = np.sqrt(self.noise_kappa)
        return self.noise_v * (k if self.noise_v.ndim == 1 else k[:, None])

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
    def saturation(self) -> Saturation:
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
    """Flat-top detection per transient.

    ``flags`` (m,) bool; ``end_s`` (m,) time (s) of the last flat sample after extinction (NaN if
    none); ``scatter_v`` (m,) standard deviation of the flattest window at the top (V); ``noise_v``
    (m,) the record's noise scale (V).
    """

    flags: np.ndarray
    end_s: np.ndarray
    scatter_v: np.ndarray
    noise_v: np.ndarray


def _noise_scale(signal: np.ndarray) -> np.ndarray:
    """Robust white-noise sigma (V) per row from second differences of the record's second half.

    A decay's curvature per sample is negligible there and a flat top early on is excluded.
    """
    tail = signal[:, signal.shape[1] // 2 :]
    d2 = np.diff(tail, n=2, axis=1)
    mad = np.median(np.abs(d2 - np.median(d2, axis=1, keepdims=True)), axis=1)
    return 1.482602218505602 * mad / np.sqrt(6.0)  # var(second difference) = 6 sigma^2


def _saturation(signal: np.ndarray, t: np.ndarray) -> Saturation:
    m, k = signal.shape
    w = SAT_WINDOW
    nan = np.full(m, np.nan)
    if m == 0 or k < 2 * w:
        empty = np.zeros(m, dtype=bool)
        return Saturation(empty, nan, nan.copy(), nan.copy())
    sigma = _noise_scale(signal)
    y = signal - signal.mean(axis=1, keepdims=True)  # centred: the running sums stay accurate
    zero = np.zeros((m, 1))
    c1 = np.concatenate([zero, np.cumsum(y, axis=1)], axis=1)
    c2 = np.concatenate([zero, np.cumsum(y * y, axis=1)], axis=1)
    mean = (c1[:, w:] - c1[:, :-w]) / w
    sd = np.sqrt(np.maximum((c2[:, w:] - c2[:, :-w]) / w - mean**2, 0.0) * (w / (w - 1)))
    ends = t[w - 1 :]  # time of each window's last sample
    # at the top, or at the bottom for a chain that inverts (the clipping rule checks both too)
    at_top = (mean >= (y.max(axis=1) - 5.0 * sigma)[:, None]) | (
        mean <= (y.min(axis=1) + 5.0 * sigma)[:, None]
    )
    flat = at_top & (sd < SAT_FLATNESS * sigma[:, None]) & (sigma > 0)[:, None]
    # a saturated output is pinned through extinction: the flat run must hold a window that
    # starts at or before it (or at the first sample) and ends after it. Only these few windows
    # are tested, so a long quiet baseline late in the record cannot raise a false alarm.
    i_ext = int(np.searchsorted(t, 0.0))  # first sample at t >= 0
    starts = np.arange(ends.size)
    candidates = at_top & ((starts <= i_ext) & (ends > 0))[None, :]
    seeds = flat & candidates
    flags = seeds.any(axis=1)
    first = np.argmax(seeds, axis=1)
    # the plateau goes on while the following windows stay flat: its end is the last of them
    after = (~flat) & (starts[None, :] > first[:, None])
    stop = np.where(after.any(axis=1), np.argmax(after, axis=1), ends.size) - 1
    end_s = np.where(flags, ends[np.clip(stop, 0, ends.size - 1)], np.nan)
    scatter = np.where(
        candidates.any(axis=1), np.min(np.where(candidates, sd, np.inf), axis=1), np.nan
    )
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
        start = np.logical_and.reduce([at[:, j : j + width] for j in range(CLIP_RUN)])
        in_run = np.zeros_like(at)
        for j in range(CLIP_RUN):
            in_run[:, j : j + width] |= start
        flags |= (in_run & late).any(axis=1)
    return flags


@dataclass(frozen=True, eq=False)
class CmdsData(_Record):
    """Cavity mode dispersion spectroscopy, p points.

    nu_hz empty-cavity mode frequency, shift_hz mode shift and shift_u_hz its standard uncertainty;
    optional width_hz mode half width at half maximum and width_u_hz its uncertainty. All Hz, shape
    (p,).
    """

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
    """One measurement campaign.

    ``configs`` maps name -> Config in file order (a sequence of Config is accepted and keyed by
    name).
    """

    sample: Sample
    cavity: Cavity
    configs: dict[str, Config]
    description: str | None = None

    def __post_init__(self):
        items = (
            self.configs.items()
            if isinstance(self.configs, Mapping)
            else ((c.name, c) for c in self.configs)
        )
        configs = dict(items)
        for key, cfg in configs.items():
            if key != cfg.name:
                raise ValueError(f"configs key {key!r} differs from its Config.name {cfg.name!r}")
        _set(self, configs=configs)

    @classmethod
    def from_arrays(cls, sample, cavity, configs, description: str | None = None) -> Bundle:
        """A bundle from plain values and numpy arrays, all SI (Hz, s, V, Pa, K).

        ``sample`` and ``cavity`` are :class:`Sample`/:class:`Cavity` or dicts of their fields;
        ``configs`` maps a name to a dict with ``ringdowns`` (the fields of
        :class:`RingdownData`: nu_hz, signal_v, dt_s, t0_s, optional n_avg, noise_v) and,
        optionally, ``transfer_function`` (f_hz, b12_v, i1_v, i2_v, b12_u_v), ``cmds``
        (nu_hz, shift_hz, shift_u_hz, width_hz, width_u_hz) and ``description``. Example::

            Bundle.from_arrays(
                dict(molecule="CO", line="(3-0) R(23)", nu0_hz=1.9e14, pressure_pa=666.6,
                     pressure_u_pa=0.3, temperature_k=296.0, temperature_u_k=0.03, mass_u=28.0),
                dict(fsr_hz=203e6),
                {"D1": dict(ringdowns=dict(nu_hz=nu, signal_v=v, dt_s=20e-9, t0_s=-2e-6))},
            )

        A misspelt field raises ValueError naming it and the known ones. ``save_bundle`` checks
        the values against FORMAT.md when it writes the file.
        """
        built = {}
        for name, spec in dict(configs).items():
            if isinstance(spec, Config):
                built[name] = spec
                continue
            where = f"configs[{name!r}]"
            _known_keys(spec, ("ringdowns", "transfer_function", "cmds", "description"), where)
            if "ringdowns" not in spec:
                raise ValueError(f"{where} has no 'ringdowns' (nu_hz, signal_v, dt_s, t0_s)")
            parts = {
                key: _record(kind, spec.get(key), f"{where}[{key!r}]")
                for key, kind in (
                    ("ringdowns", RingdownData),
                    ("transfer_function", TransferFunctionData),
                    ("cmds", CmdsData),
                )
            }
            built[name] = Config(name, description=spec.get("description"), **parts)
        return cls(
            _record(Sample, sample, "sample"),
            _record(Cavity, cavity, "cavity"),
            built,
            description,
        )


def _known_keys(spec, known, where: str) -> None:
    import difflib

    for key in spec:
        if key not in known:
            hit = difflib.get_close_matches(str(key), known, n=1, cutoff=0.5)
            raise ValueError(
                f"{where}: unknown field {key!r}"
                + (f" (did you mean {hit[0]!r}?)" if hit else "")
                + f"; known: {', '.join(known)}"
            )


def _record(kind, spec, where: str):
    """``spec`` as a ``kind`` record: already one, None, or a dict of its fields."""
    if spec is None or isinstance(spec, kind):
        return spec
    _known_keys(spec, tuple(f.name for f in dataclasses.fields(kind)), where)
    missing = [
        f.name
        for f in dataclasses.fields(kind)
        if f.default is dataclasses.MISSING and f.name not in spec
    ]
    if missing:
        raise ValueError(f"{where}: missing {', '.join(missing)}")
    return kind(**spec)


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
        lines = [
            f"{self.file}: not a valid {FORMAT_NAME} v{FORMAT_VERSION} file "
            f"({len(self.violations)} problem(s)):"
        ]
        lines += [f"{self.file}: {v}" for v in self.violations]
        super().__init__("\n".join(lines))

    def one_line(self, shown: int = 3) -> str:
        """The refusal on one line, for an error line: the file and its first ``shown`` problems.

        The full list stays in the exception (and ``bayes-tfcrds validate FILE`` prints it).
        """
        more = len(self.violations) - shown
        return (
            f"{self.file}: not a valid bundle: "
            + "; ".join(str(v) for v in self.violations[:shown])
            + (
                f"; and {more} more (bayes-tfcrds validate {self.file} lists them)"
                if more > 0
                else ""
            )
        )
