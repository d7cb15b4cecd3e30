"""Coloured detector noise for the simulator.

A real detector's noise is not white at the digitizer: the photodiode's and amplifier's noise
passes through the detection chain (or the amplifier's own roll-off), and flicker (1/f) noise
adds power at low frequency. Consecutive samples are then correlated, while each sample keeps the
standard deviation the bundle states, so chi2_red cannot see it; only the correlations can.

:class:`NoiseColour` describes the power spectral density (PSD) shape of one acquisition's noise;
:func:`coloured_noise` draws noise with that shape and unit variance per sample (the caller scales
it by the acquisition's noise in V). Units: Hz, s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

NOISE_KINDS = {
    "white": "independent samples (the default)",
    "chain": "white detector noise through the configuration's detection chain: PSD |H(f)|^2",
    "lowpass": "white noise through a Butterworth low-pass of order `order` at `f_hz`: PSD "
    "1/(1 + (f/f_hz)^(2 order))",
    "pink": "flicker noise below `f_knee_hz` on a white floor: PSD 1 + (f_knee_hz/f)^alpha",
    "table": "a given PSD: `table_f_hz`, `table_psd` (Python only), interpolated in log-log",
}
NOISE_DEFAULTS = {
    "white": {},
    "chain": {},
    "lowpass": {"f_hz": 5e6, "order": 2.0},
    "pink": {"f_knee_hz": 1e5, "alpha": 1.0},
}
NOISE_DOMAINS = {
    "f_hz": (1.0, 1e12),
    "order": (0.5, 8.0),
    "f_knee_hz": (1.0, 1e12),
    "alpha": (0.1, 2.0),
}


@dataclass(frozen=True)
class NoiseColour:
    """The PSD shape of one acquisition's detector noise (scale-free: the level is noise_v).

    ``kind`` is one of :data:`NOISE_KINDS`; the other fields are that kind's parameters (SI).
    """

    kind: str = "white"
    f_hz: float = 5e6
    order: float = 2.0
    f_knee_hz: float = 1e5
    alpha: float = 1.0
    table_f_hz: tuple = ()
    table_psd: tuple = ()

    def __post_init__(self):
        if self.kind not in NOISE_KINDS:
            raise ValueError(f"noise kind {self.kind!r}: choose from {sorted(NOISE_KINDS)}")
        for key, (lo, hi) in NOISE_DOMAINS.items():
            v = getattr(self, key)
            if not (np.isfinite(v) and lo <= v <= hi):
                raise ValueError(f"noise {self.kind}: {key} = {v!r} is outside [{lo:g}, {hi:g}]")
        if self.kind == "table":
            f, p = np.asarray(self.table_f_hz, float), np.asarray(self.table_psd, float)
            if f.ndim != 1 or f.size < 2 or f.shape != p.shape:
                raise ValueError("noise table: table_f_hz and table_psd need >= 2 equal entries")
            if not (np.all(np.diff(f) > 0) and f[0] > 0 and np.all(p > 0)):
                raise ValueError("noise table: frequencies increasing and > 0, PSD > 0")

    @property
    def is_white(self) -> bool:
        return self.kind == "white"

    def describe(self) -> str:
        """``kind:key=value,...`` (the form :func:`parse_noise` reads)."""
        keys = NOISE_DEFAULTS.get(self.kind, {})
        if self.kind == "table":
            return f"table:{len(self.table_f_hz)} points"
        args = ",".join(f"{k}={getattr(self, k):g}" for k in keys)
        return self.kind + (f":{args}" if args else "")

    def psd(self, f_hz, chain=None) -> np.ndarray:
        """Relative PSD at ``f_hz`` (Hz, >= 0); ``chain`` (a RationalChain) for kind ``chain``."""
        f = np.abs(np.asarray(f_hz, float))
        if self.kind == "white":
            return np.ones_like(f)
        if self.kind == "chain":
            if chain is None:
                raise ValueError("noise kind 'chain' needs the detection chain")
            return np.abs(chain.frequency_response(f)) ** 2
        if self.kind == "lowpass":
            return 1.0 / (1.0 + (f / self.f_hz) ** (2.0 * self.order))
        if self.kind == "pink":
            # the zero-frequency bin takes the lowest nonzero bin's value (a finite record)
            f_low = np.where(f > 0, f, np.min(f[f > 0]) if np.any(f > 0) else 1.0)
            return 1.0 + (self.f_knee_hz / f_low) ** self.alpha
        lf, lp = np.log(self.table_f_hz), np.log(self.table_psd)
        return np.exp(np.interp(np.log(np.maximum(f, self.table_f_hz[0])), lf, lp))


def parse_noise(text: str) -> NoiseColour:
    """``KIND[:key=value,...]`` (the ``--noise`` option), e.g. ``lowpass:f_hz=5e6,order=2``."""
    kind, _, rest = text.strip().partition(":")
    if kind not in NOISE_DEFAULTS:
        raise ValueError(f"--noise {kind!r}: choose from {sorted(NOISE_DEFAULTS)}")
    params = dict(NOISE_DEFAULTS[kind])
    for item in filter(None, (s.strip() for s in rest.split(","))):
        key, eq, value = item.partition("=")
        if not eq or key not in params:
            raise ValueError(f"--noise {kind}: unknown parameter {item!r}; known: {list(params)}")
        try:
            params[key] = float(value)
        except ValueError:
            raise ValueError(f"--noise {kind}: {key} = {value!r} is not a number") from None
    return NoiseColour(kind=kind, **params)


def noise_grid(n_samples: int) -> int:
    """FFT length for drawing ``n_samples`` of noise: a power of two >= 2 n (no wrap-around)."""
    return 1 << int(np.ceil(np.log2(2 * n_samples)))


def shaping_filter(colour: NoiseColour, n_samples: int, dt_s: float, chain=None) -> np.ndarray:
    """sqrt(PSD) on the rfft grid of :func:`noise_grid`, scaled to unit variance per sample.

    White noise of unit variance filtered by it has variance sum_f PSD(f) / L over the two-sided
    grid of L bins: dividing by that makes every sample's variance exactly 1 in expectation.
    """
    n_fft = noise_grid(n_samples)
    f = np.fft.rfftfreq(n_fft, dt_s)
    p = colour.psd(f, chain)
    two_sided = p[0] + 2.0 * p[1:-1].sum() + p[-1]
    return np.sqrt(p * n_fft / two_sided)


def coloured_noise(shape, filt: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Noise of unit per-sample variance with the PSD shape ``filt`` (from :func:`shaping_filter`).

    White normal draws on a grid twice the record's length are filtered in the frequency domain
    and the first ``shape[-1]`` samples kept, so the record has no circular correlation.
    """
    n = shape[-1]
    n_fft = 2 * (filt.size - 1)
    white = rng.standard_normal((*shape[:-1], n_fft))
    return np.fft.irfft(np.fft.rfft(white, axis=-1) * filt, n_fft, axis=-1)[..., :n]
