"""Linear propagation of transfer-function uncertainty into decay times and line parameters.

One draw of H shifts every fitted decay time at once, so its effect on the line area is
correlated across the spectrum. For each transient the fitted (B, b, tau) solve the estimating
equations C^T W (y - model) = 0 with C = [g, 1, B dg/dtau]; differentiating them in the H
parameters theta gives (implicit function theorem)

    d(B, b, tau)/d theta = -(C^T W C)^-1 C^T W (B dg/d theta),

so a change delta_theta moves tau by S delta_theta (S: n_transients x n_theta). The budget
propagates posterior draws of H through the same derivatives taken in the function H(f) itself
(:func:`tau_h_kernels`): first order in H, exact in the parameters, so that a parameter the data
hardly constrain cannot blow the linearisation up. The line parameters follow the CRDS spectrum
through the least-squares gain K = (J^T W J)^-1 J^T W of the line fit. ``benchmarks/run.py``
compares the propagated shifts of A with full refits.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import fft as sfft

from bayes_tfcrds.fit.ringdown import noise_rows
from bayes_tfcrds.physics.forward import (
    filtered_response,
    first_index_at,
    grid_transfer_function,
    input_spectrum,
    model_grids,
)
from bayes_tfcrds.physics.transfer_function import (
    TFParams,
    transfer_function,
    transfer_function_of_draws,
)


def tau_sensitivities(
    time_s,
    signal_v,
    t_cut_s,
    tau_s,
    amplitude_v,
    tf: TFParams,
    names,
    window="extinction",
    noise_v=None,
    rows_of=None,
    chunk: int = 32,
) -> np.ndarray:
    """d tau_hat / d theta (s per unit of each H parameter in ``names``), shape (n_rows, p).

    ``time_s`` (k,) s; ``signal_v`` (m, k) V; per row: ``t_cut_s`` (s), fitted ``tau_s`` (s) and
    ``amplitude_v`` (V), record ``rows_of``. The weights only matter up to a per-row constant,
    so ``noise_v`` may be None for per-row constant noise.
    """
    t = np.asarray(time_s, float)
    t_cut = np.asarray(t_cut_s, float)
    tau = np.asarray(tau_s, float)
    amp = np.asarray(amplitude_v, float)
    n, k, p = t_cut.size, t.size, len(names)
    rows_of = np.arange(n) if rows_of is None else np.asarray(rows_of)
    dt = t[1] - t[0]
    uniq, group = np.unique(t_cut, return_inverse=True)
    grids = model_grids(float(t[0]), dt, k, uniq, tf, window)
    out = np.empty((n, p))
    noise = noise_rows(noise_v, n, k, rows_of) if noise_v is not None else None
    for gi in range(uniq.size):
        h, dh = grid_transfer_function(grids[gi], tf, tuple(names))
        first = first_index_at(t[0], dt, uniq[gi])
        sel_all = np.nonzero(group == gi)[0]
        for start in range(0, sel_all.size, chunk):
            sel = sel_all[start : start + chunk]
            g, dg, dgt = filtered_response(
                tau[sel], grids[gi], h, derivative=True, dh_k=dh, fill=0.0
            )
            w = np.zeros((sel.size, k))
            w[:, first:] = 1.0 if noise is None else 1.0 / noise[sel, first:] ** 2
            cols = np.stack([g, np.ones_like(g), amp[sel, None] * dg], axis=1)  # (c, 3, k)
            jth = amp[sel, None, None] * dgt  # (c, p, k)
            ctc = np.einsum("nak,nbk,nk->nab", cols, cols, w)
            ctj = np.einsum("nak,npk,nk->nap", cols, jth, w)
            out[sel] = -np.linalg.solve(ctc, ctj)[:, 2, :]
    return out


@dataclass(frozen=True)
class TauKernels:
    """d tau_hat / d H(f_k) for a batch of fits: first-order maps in the function H, not theta.

    Rows ``rows`` of the batch share the grid whose rfft frequencies are ``f_hz`` (Hz); for each,
    ``kernel`` (n_rows, n_freq) is complex and a change delta_H of the normalised H moves tau by
    Re(kernel @ delta_H) (s). A posterior draw of H is propagated through its H(f), so a
    parameter the data hardly constrain (a weak resonance's f_r, which may roam over decades)
    cannot blow up the propagation: only what it does to H counts.
    """

    groups: tuple  # ((rows, f_hz, kernel), ...) one per grid

    def shifts(self, h_of, n_rows: int) -> np.ndarray:
        """tau shifts (n_draws, n_rows) for ``h_of(f_hz) -> delta_H (n_draws, n_freq)``."""
        out = None
        for rows, f_hz, kern in self.groups:
            dh = h_of(f_hz)
            if out is None:
                out = np.zeros((dh.shape[0], n_rows))
            out[:, rows] = (dh @ kern.T).real
        return np.zeros((0, n_rows)) if out is None else out

    def combine(self, weights) -> TauKernels:
        """The kernel of sum_i weights_i tau_i (e.g. dA = sum_i dA/dtau_i dtau_i): one row."""
        w = np.asarray(weights, float)
        return TauKernels(
            tuple((np.zeros(1, int), f, (w[rows] @ kern)[None, :]) for rows, f, kern in self.groups)
        )


def tau_h_kernels(
    time_s,
    t_cut_s,
    tau_s,
    amplitude_v,
    tf: TFParams,
    window="extinction",
    noise_v=None,
    rows_of=None,
    chunk: int = 32,
) -> TauKernels:
    """d tau_hat / d H(f_k) on each row's model grid (see :class:`TauKernels`).

    Same arguments as :func:`tau_sensitivities` (no signal needed). With v(t) the tau row of
    -(C^T W C)^-1 C^T W B, a change delta_H moves tau by sum_t v(t) irfft(X delta_H)(t); by the
    adjoint of the inverse real FFT this is Re sum_k c_k X_k conj(V_k) delta_H_k / N with V the
    rfft of v placed on the grid and c_k = 2 (1 at k = 0 and Nyquist).
    """
    t = np.asarray(time_s, float)
    t_cut = np.asarray(t_cut_s, float)
    tau = np.asarray(tau_s, float)
    amp = np.asarray(amplitude_v, float)
    n, k = t_cut.size, t.size
    rows_of = np.arange(n) if rows_of is None else np.asarray(rows_of)
    dt = t[1] - t[0]
    uniq, group = np.unique(t_cut, return_inverse=True)
    grids = model_grids(float(t[0]), dt, k, uniq, tf, window)
    noise = noise_rows(noise_v, n, k, rows_of) if noise_v is not None else None
    by_grid = {}
    for gi in range(uniq.size):
        key = 0 if window == "extinction" else gi
        grid = grids[gi]
        h = grid_transfer_function(grid, tf)
        first = first_index_at(t[0], dt, uniq[gi])
        n_freq = grid.n_fft // 2 + 1
        c_k = np.full(n_freq, 2.0)
        c_k[0] = 1.0
        if grid.n_fft % 2 == 0:
            c_k[-1] = 1.0
        sel_all = np.nonzero(group == gi)[0]
        for start in range(0, sel_all.size, chunk):
            sel = sel_all[start : start + chunk]
            g, dg = filtered_response(tau[sel], grid, h, derivative=True, fill=0.0)
            w = np.zeros((sel.size, k))
            w[:, first:] = 1.0 if noise is None else 1.0 / noise[sel, first:] ** 2
            cols = np.stack([g, np.ones_like(g), amp[sel, None] * dg], axis=1)
            ctc = np.einsum("nak,nbk,nk->nab", cols, cols, w)
            v = -amp[sel, None] * np.einsum("nb,nbk,nk->nk", np.linalg.inv(ctc)[:, 2, :], cols, w)
            placed = np.zeros((sel.size, grid.n_fft))
            placed[:, grid.data_offset + first : grid.data_offset + k] = v[:, first:]
            x = input_spectrum(tau[sel], grid)
            kern = c_k * x * np.conj(sfft.rfft(placed, axis=-1)) / grid.n_fft
            f_hz = np.arange(n_freq) / (grid.n_fft * grid.dt_s)
            rows, fs, ks = by_grid.setdefault(key, ([], f_hz, []))
            rows.append(sel)
            ks.append(kern)
    return TauKernels(
        tuple((np.concatenate(r), f, np.concatenate(kk)) for r, f, kk in by_grid.values())
    )


def h_change(draws, names, centre: TFParams):
    """``f_hz -> H(f; draw) - H(f; centre)`` (normalised H) for draws (n, len(names))."""
    draws = np.atleast_2d(np.asarray(draws, float))

    def of(f_hz):
        h = transfer_function_of_draws(f_hz, centre, names, draws)
        return h - transfer_function(f_hz, centre)[None, :]

    return of


def tau_influence(
    time_s,
    signal_v,
    t_cut_s,
    tau_s,
    amplitude_v,
    tf: TFParams | None,
    window="extinction",
    noise_v=None,
) -> np.ndarray:
    """d tau_hat / d y_k for each record's samples (s/V), shape (n, k): the delta-method influence.

    For TF-CRDS pass ``tf``; with ``tf`` None the plain exponential (CRDS) model is used.
    """
    t = np.asarray(time_s, float)
    tau = np.atleast_1d(np.asarray(tau_s, float))
    amp = np.atleast_1d(np.asarray(amplitude_v, float))
    n, k = tau.size, t.size
    dt = t[1] - t[0]
    first = first_index_at(t[0], dt, t_cut_s)
    mask = np.zeros((n, k))
    mask[:, first:] = 1.0
    if tf is None:
        x = np.clip(t - t_cut_s, 0, None)[None, :] / tau[:, None]
        g = np.exp(-x) * mask
        dg = g * x / tau[:, None]
    else:
        grid = model_grids(float(t[0]), dt, k, [t_cut_s], tf, window)[0]
        g, dg = filtered_response(
            tau, grid, grid_transfer_function(grid, tf), derivative=True, fill=0.0
        )
        g, dg = g * mask, dg * mask
    w = (
        mask
        if noise_v is None
        else mask / np.broadcast_to(np.asarray(noise_v, float).reshape(n, -1), (n, k)) ** 2
    )
    cols = np.stack([g, mask, amp[:, None] * dg], axis=1)
    ctc = np.einsum("nak,nbk,nk->nab", cols, cols, w)
    return np.einsum("nb,nbk,nk->nk", np.linalg.inv(ctc)[:, 2, :], cols, w)


def line_gain(line_fit) -> np.ndarray:
    """K = d theta_line / d y for a :class:`bayes_tfcrds.fit.line.LineFit`, shape (n_par, n_y).

    y are the fitted spectrum values concatenated over its spectra, in their own units; the
    gain is that of weighted least squares at the solution (parameters held at a bound get
    zero rows, as in the fit's covariance). It uses the Jacobian the fit made its covariance
    from, so that the noise propagation K W^-1 K^T is that covariance. A Jacobian made here
    again, with steps relative to the values, failed for a parameter at 0 (the HTP's eta where
    the data need none: a 1e-36 step, round-off, a gain 600 times the fit's own u(A)).
    """
    u = np.concatenate([s.u for s in line_fit.spectra])
    # K = cov J^T W: the stored Jacobian is J / u
    return line_fit.cov @ (line_fit.jacobian / u[:, None]).T


def model_of(line_fit):
    from bayes_tfcrds.fit.line import LineModel

    shape_free = tuple(n for n in line_fit.names[2:] if not n.startswith(("baseline", "slope")))
    slopes = tuple(f"slope{i}" in line_fit.names for i in range(len(line_fit.spectra)))
    return LineModel(
        profile=line_fit.profile,
        shape_free=shape_free,
        kinds=tuple(s.kind for s in line_fit.spectra),
        slopes=slopes,
        nu_ref_hz=line_fit.nu_ref_hz,
        doppler_hwhm_hz=line_fit.doppler_hwhm_hz,
        fixed=line_fit.fixed,
    )
