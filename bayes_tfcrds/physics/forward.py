"""Distorted ring-down forward model S_fit = IFFT(FFT(S_ed) H) (letter Eqs. 3-4, Appendix A).

The modelled optical signal is flat before a kink and decays exponentially after it,
``x(t) = 1`` for t < 0 and ``exp(-t/tau)`` for t >= 0, so that S_ed = b + B x and, since H is
normalised to unit DC gain, ``S_fit = b + B g`` with ``g = IFFT(FFT(x) H)``. The model is linear
in b and B; only ``g(t; tau, H)`` needs the FFT.

Two windows place the kink and the periodic FFT grid:

* ``letter`` (Appendix A as written): the time axis is shifted so the analysed part starts at
  the first sample at or after t_cut (T = its length); x is flat for -T <= t < 0 and decays over
  0 <= t < 2T. The history before t_cut is therefore modelled as flat, which it is not.
* ``extinction``: the kink is laser extinction (t = 0 of the bundle's time axis), the grid holds
  enough history before the record (and lead after it, for a non-causal H) that the DFT's
  wrap-around stays below 1e-7 of B, and the model covers the whole record, so any
  t_cut compares it with data on [t_cut, end]. The grid closes with a smooth (C-infinity) ramp
  from the decayed level back to the steady level: a jump there would ring (Gibbs, decaying
  only as 1/n samples) through a chain whose H is not band-limited, while the smooth ramp's
  influence dies as fast as H's own tails.

The DFT of the sampled x is a geometric series, evaluated in closed form (with its tau
derivative), so each evaluation costs one inverse real FFT per transient, batched.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy import fft as sfft

from bayes_tfcrds.physics.transfer_function import (
    TFParams,
    settling_times,
    transfer_function,
    transfer_function_derivatives,
)

WINDOWS = ("extinction", "letter")
WRAP_TOL = 1e-7
RAMP_SAMPLES = 256


def ramp_shape(n: int) -> np.ndarray:
    """Smooth step from 0 to 1 over n samples, all derivatives continuous at both ends."""
    u = (np.arange(n) + 0.5) / n
    with np.errstate(over="ignore"):
        return 1.0 / (1.0 + np.exp(1.0 / u - 1.0 / (1.0 - u)))


@dataclass(frozen=True)
class Grid:
    """A periodic FFT grid for one window.

    ``start_s`` is the time of grid sample 0 relative to the kink (s), ``dt_s`` the sample
    interval (s), ``n_fft`` the grid length; data sample j sits at grid index
    ``j + data_offset`` and is covered for ``first_data <= j < n_data``.
    """

    n_fft: int
    start_s: float
    dt_s: float
    data_offset: int
    first_data: int
    n_data: int
    n_ramp: int = 0

    @property
    def m_ramp(self) -> int:
        """First grid index of the closing ramp (``n_fft`` when there is none)."""
        return self.n_fft - self.n_ramp

    @property
    def m0(self) -> int:
        """First grid index at or after the kink (ties to the decaying side)."""
        return int(np.ceil(-self.start_s / self.dt_s - 1e-9))


def first_index_at(t0_s: float, dt_s: float, t_s: float) -> int:
    """Index of the first sample at or after time ``t_s`` on the axis t0 + j dt (s)."""
    return max(0, int(np.ceil((t_s - t0_s) / dt_s - 1e-9)))


def extinction_grid(t0_s: float, dt_s: float, n_samples: int, tf: TFParams | None) -> Grid:
    """Grid for the ``extinction`` window: whole record plus settled history and lead."""
    if tf is None:
        hist, lead = dt_s, dt_s
    else:
        hist, lead = settling_times(tf, dt_s, WRAP_TOL)
    n_hist = int(np.ceil(hist / dt_s)) + 1
    # the record must also start after the kink's history: if it starts before t = 0,
    # the flat part inside the record counts as history too, but we pad regardless
    n_lead = int(np.ceil(lead / dt_s)) + 1
    n_fft = sfft.next_fast_len(n_hist + n_samples + n_lead + RAMP_SAMPLES, real=True)
    return Grid(
        n_fft=n_fft,
        start_s=t0_s - n_hist * dt_s,
        dt_s=dt_s,
        data_offset=n_hist,
        first_data=0,
        n_data=n_samples,
        n_ramp=n_fft - n_hist - n_samples - n_lead,
    )


def letter_grid(t0_s: float, dt_s: float, n_samples: int, t_cut_s: float) -> Grid:
    """Grid for the ``letter`` window at one t_cut: [-T, 2T] around the first analysed sample.

    The length is rounded up to a fast FFT size by continuing the decay past 2T (the
    exponential there is below exp(-2T/tau) of B, so this does not change the model).
    """
    j_a = first_index_at(t0_s, dt_s, t_cut_s)
    n_a = n_samples - j_a
    if n_a < 4:
        raise ValueError(f"t_cut = {t_cut_s:g} s leaves {n_a} samples of the record")
    n_fft = sfft.next_fast_len(3 * n_a, real=True)
    return Grid(
        n_fft=n_fft,
        start_s=-n_a * dt_s,
        dt_s=dt_s,
        data_offset=n_a - j_a,
        first_data=j_a,
        n_data=n_samples,
    )


@lru_cache(maxsize=32)
def _grid_terms(grid: Grid):
    """tau-independent pieces of the closed-form spectrum on one grid (cached)."""
    k = np.arange(grid.n_fft // 2 + 1)
    phase = -2.0 * np.pi * k / grid.n_fft
    wk = np.exp(1j * phase)
    m0 = grid.m0
    wkm0 = np.exp(1j * phase * m0)
    wkmr = np.exp(1j * phase * grid.m_ramp)
    with np.errstate(invalid="ignore", divide="ignore"):
        flat = np.where(k == 0, float(m0), (1.0 - wkm0) / (1.0 - wk))
    # closing ramp x = v_e (1 - c) + c: its two fixed spectra, scaled by v_e at run time
    c = np.zeros(grid.n_fft)
    c1 = np.zeros(grid.n_fft)
    if grid.n_ramp:
        shape = ramp_shape(grid.n_ramp)
        c[grid.m_ramp :] = shape
        c1[grid.m_ramp :] = 1.0 - shape
    fixed = flat + sfft.rfft(c)
    ramp_ve = sfft.rfft(c1)
    # 1 - q w^k = -(expm1(x) cos(phase) + cosm1(phase)) - i e^x sin(phase), x = -dt/tau:
    # exact near k = 0 and tau >> dt, where the plain difference would cancel
    trig = (np.cos(phase), -2.0 * np.sin(0.5 * phase) ** 2, np.sin(phase))
    f_hz = k / (grid.n_fft * grid.dt_s)
    return fixed, wkm0, wkmr, ramp_ve, trig, f_hz


def input_spectrum(tau_s, grid: Grid, derivative: bool = False):
    """rfft of the sampled x(t) on ``grid`` for each tau (s), in closed form.

    Returns X with shape (n_tau, n_fft//2 + 1) and, with ``derivative``, dX/dtau (1/s).
    """
    tau = np.asarray(tau_s, float).reshape(-1, 1)
    fixed, wkm0, wkmr, ramp_ve, (cos_p, cosm1_p, sin_p), _ = _grid_terms(grid)
    dt = grid.dt_s
    m0 = grid.m0
    s_m0 = grid.start_s + m0 * dt  # time of the first decaying sample (>= 0)
    big_m = grid.m_ramp - m0  # number of decaying samples before the ramp
    a = np.exp(-s_m0 / tau)
    q_m = np.exp(-big_m * dt / tau)
    v_e = a * q_m  # the exponential's value where the ramp starts
    x = -dt / tau
    d = -(np.expm1(x) * cos_p + cosm1_p) - 1j * (np.exp(x) * sin_p)  # 1 - q w^k
    inv_d = 1.0 / d
    num = wkm0 - q_m * wkmr
    a_num_d = (a * num) * inv_d
    spec = fixed + a_num_d + v_e * ramp_ve
    if not derivative:
        return spec
    inv_t2 = 1.0 / tau**2
    dx = ((a * s_m0 * inv_t2) * num - (a * q_m * big_m * dt * inv_t2) * wkmr) * inv_d
    dx += a_num_d * ((1.0 - d) * inv_d) * (dt * inv_t2)
    dx += (v_e * (s_m0 + big_m * dt) * inv_t2) * ramp_ve
    return spec, dx


def _chunks(n_rows: int, n_fft: int, budget: int = 1 << 18):
    step = max(1, budget // max(n_fft, 1))
    for i in range(0, n_rows, step):
        yield slice(i, min(n_rows, i + step))


def filtered_response(
    tau_s, grid: Grid, h_k, derivative: bool = False, dh_k=None, fill: float = np.nan
):
    """g(t; tau) = IFFT(X H) at the data samples covered by ``grid``, batched over tau.

    ``h_k`` is H at the grid's rfft frequencies (from :func:`grid_transfer_function`), or None
    for H = 1. Returns arrays of shape (n_tau, n_data) with NaN where the grid does not cover
    a sample (or ``fill``); with ``derivative`` also dg/dtau (1/s); with ``dh_k`` (shape
    (p, n_freq), the H-parameter derivatives) also dg/dtheta with shape (n_tau, p, n_data).
    """
    tau = np.atleast_1d(np.asarray(tau_s, float))
    n = tau.size
    lo = grid.first_data
    cols = np.arange(lo, grid.n_data) + grid.data_offset
    alloc = np.empty if lo == 0 else (lambda shape: np.full(shape, fill))
    g = alloc((n, grid.n_data))
    dg = alloc((n, grid.n_data)) if derivative else None
    dgt = None
    if dh_k is not None:
        dgt = np.full((n, dh_k.shape[0], grid.n_data), fill)
    for sl in _chunks(n, grid.n_fft * (2 + (0 if dh_k is None else dh_k.shape[0]))):
        if derivative:
            x, dx = input_spectrum(tau[sl], grid, derivative=True)
        else:
            x = input_spectrum(tau[sl], grid)
        spec = x if h_k is None else x * h_k
        stack = [spec]
        if derivative:
            stack.append(dx if h_k is None else dx * h_k)
        if dh_k is not None:
            stack.append((x[:, None, :] * dh_k[None, :, :]).reshape(-1, x.shape[1]))
        # one FFT thread: the batches are small (threads gained nothing in one process: two
        # Laplace budgets took 15.6 s with one thread, 16.6 s with all), and the budget, the
        # studies and the tests run in parallel processes, where threads per process would
        # oversubscribe the cores. The result is the same to the bit.
        out = sfft.irfft(np.concatenate(stack, axis=0), n=grid.n_fft, axis=-1)
        nb = x.shape[0]
        g[sl, lo:] = out[:nb, cols]
        pos = nb
        if derivative:
            dg[sl, lo:] = out[pos : pos + nb, cols]
            pos += nb
        if dh_k is not None:
            dgt[sl, :, lo:] = out[pos:].reshape(nb, dh_k.shape[0], -1)[:, :, cols]
    res = [g]
    if derivative:
        res.append(dg)
    if dh_k is not None:
        res.append(dgt)
    return res[0] if len(res) == 1 else tuple(res)


def grid_transfer_function(grid: Grid, tf: TFParams | None, derivative_names=()):
    """H (normalised) at the grid's rfft frequencies, and optionally dH/dtheta."""
    f_hz = _grid_terms(grid)[-1]
    if tf is None:
        return None if not derivative_names else (None, None)
    h = transfer_function(f_hz, tf)
    if not derivative_names:
        return h
    return h, transfer_function_derivatives(f_hz, tf, tuple(derivative_names))


def model_grids(
    t0_s: float, dt_s: float, n_samples: int, t_cuts_s, tf: TFParams | None, window: str
):
    """One grid per t_cut (``letter``) or one shared grid (``extinction``), aligned with t_cuts."""
    if window not in WINDOWS:
        raise ValueError(f"window must be one of {WINDOWS}, got {window!r}")
    if window == "extinction":
        g = extinction_grid(t0_s, dt_s, n_samples, tf)
        return [g for _ in t_cuts_s]
    return [letter_grid(t0_s, dt_s, n_samples, tc) for tc in t_cuts_s]


def ringdown_model(
    time_s,
    tau_s,
    amplitude_v,
    offset_v,
    tf: TFParams | None,
    window: str = "extinction",
    t_cut_s: float = 0.0,
):
    """S_fit(t) in volts at the uniformly spaced ``time_s`` (s, relative to extinction).

    ``tau_s`` (s), ``amplitude_v`` (V) and ``offset_v`` (V) broadcast over transients. For the
    ``letter`` window B is the amplitude at the first analysed sample and samples before
    t_cut are NaN; for ``extinction`` B is the steady pre-extinction amplitude.
    """
    t = np.asarray(time_s, float)
    dt = float(t[1] - t[0])
    grid = model_grids(t[0], dt, t.size, [t_cut_s], tf, window)[0]
    g = filtered_response(tau_s, grid, grid_transfer_function(grid, tf))
    return (
        np.asarray(offset_v, float).reshape(-1, 1)
        + np.asarray(amplitude_v, float).reshape(-1, 1) * g
    )
