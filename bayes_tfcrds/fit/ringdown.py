"""Ring-down fits: plain CRDS (b + B exp(-t/tau)) and TF-CRDS (S_fit), batched.

Both models are ``b + B g(t; tau)``: linear in the offset b and amplitude B, which are solved
exactly inside the fit (variable projection), so the nonlinear search is one-dimensional per
transient. All transients (spectral points x truncation times) are iterated together with a
damped Gauss-Newton step on tau; the TF-CRDS fit starts from the CRDS solution.

The step needs only weighted sums of g, dg/dtau and the data. With one noise level per
transient, plain CRDS and TF-CRDS with a rational H (Eq. 2 with n_r = 2) in the extinction
window get them in closed form from ``physics/expsum.py`` (g never formed, no FFT); otherwise
(per-sample noise, the letter window, fractional n_r) g comes from the FFT model of
``physics/forward.py``.

Units: time and tau in s, signals and noise in V.
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass, field, replace

import numpy as np

from bayes_tfcrds.core.linalg import covariance_from_fisher
from bayes_tfcrds.physics.detection_chain import chain_from_tf
from bayes_tfcrds.physics.expsum import BlockedData, SumsModel
from bayes_tfcrds.physics.forward import (
    WINDOWS,
    filtered_response,
    first_index_at,
    grid_transfer_function,
    model_grids,
)
from bayes_tfcrds.physics.transfer_function import TFParams

METHODS = ("crds", "tf-crds")


@dataclass(frozen=True)
class TransientFits:
    """Fits of n transients (flattened rows). ``cov`` is over (B, b, tau) per row.

    ``noise_v`` is the per-sample standard deviation used for the weights: the supplied one,
    or, where none was supplied (``noise_estimated``), the residual RMS, in which case chi2_red
    is 1 by construction and the covariance is scaled by it.
    """

    tau_s: np.ndarray
    tau_u_s: np.ndarray
    amplitude_v: np.ndarray
    offset_v: np.ndarray
    cov: np.ndarray
    chi2: np.ndarray
    dof: np.ndarray
    noise_v: np.ndarray
    noise_estimated: bool
    converged: np.ndarray
    t_cut_s: np.ndarray
    method: str
    window: str | None
    residuals_v: np.ndarray | None = field(default=None, repr=False)

    @property
    def chi2_red(self) -> np.ndarray:
        return self.chi2 / np.maximum(self.dof, 1)


def _dot(a, b):
    """Row-wise dot product in one pass (no temporaries)."""
    return np.einsum("ij,ij->i", a, b)


def _solve_linear(wm, g, y):
    """Weighted least-squares B, b for y ~ B g + b on the masked samples (rows batched)."""
    wg = wm * g
    s1, sg, sy = wm.sum(-1), wg.sum(-1), _dot(wm, y)
    sgg, sgy = _dot(wg, g), _dot(wg, y)
    det = s1 * sgg - sg * sg
    return (s1 * sgy - sg * sy) / det, (sgg * sy - sg * sgy) / det


def _three_interval_tau(t, sig, first, rows_of):
    """Model-free starting tau.

    For y = b + B exp(-t/tau), sums over three equal consecutive intervals after each row's first
    sample satisfy (S2 - S3)/(S1 - S2) = exp(-D/tau).

    ``sig`` (m, k) transients, ``first`` (n,) first fitted index of each row, ``rows_of`` (n,).
    One cumulative sum per transient serves all its t_cut rows.
    """
    k = sig.shape[1]
    n = k - first
    n3 = np.maximum(n // 3, 1)
    cs = np.concatenate([np.zeros((sig.shape[0], 1)), np.cumsum(sig, axis=-1)], axis=-1)

    def seg(i0, i1):
        return cs[rows_of, np.minimum(i1, k)] - cs[rows_of, np.minimum(i0, k)]

    s1 = seg(first, first + n3)
    s2 = seg(first + n3, first + 2 * n3)
    s3 = seg(first + 2 * n3, first + 3 * n3)
    dt = t[1] - t[0]
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = (s2 - s3) / (s1 - s2)
        tau = -n3 * dt / np.log(rho)
    fallback = (n * dt) / 5.0
    return np.where(np.isfinite(tau) & (tau > 0), tau, fallback)


class _Crds:
    """g = exp(-(t - t_cut)/tau): B is the amplitude at t_cut; g = 0 outside the fit range."""

    def __init__(self, t, t_cut, mask):
        # zero time outside the fit range (then masked): no overflow, and no 0 * inf
        self.dtau = np.where(mask, t[None, :] - t_cut[:, None], 0.0)
        self.mask = mask

    def __call__(self, tau, rows, derivative=True):
        x = self.dtau[rows] / tau[:, None]
        g = np.exp(-x)
        g *= self.mask[rows]
        if not derivative:
            return g
        return g, g * x / tau[:, None]


class _TfCrds:
    """g = IFFT(FFT(x) H) on the window's grid, grouped by grid (one per t_cut for ``letter``)."""

    def __init__(self, t, t_cut, tf, window, mask):
        self.mask = mask
        dt = float(t[1] - t[0])
        uniq, self.group = np.unique(t_cut, return_inverse=True)
        self.grids = model_grids(float(t[0]), dt, t.size, uniq, tf, window)
        self.h = [grid_transfer_function(g, tf) for g in self.grids]

    def __call__(self, tau, rows, derivative=True):
        g = np.empty((rows.size, self.grids[0].n_data))
        dg = np.empty_like(g) if derivative else None
        grp = self.group[rows]
        for gi in np.unique(grp):
            sel = np.nonzero(grp == gi)[0]
            out = filtered_response(
                tau[sel], self.grids[gi], self.h[gi], derivative=derivative, fill=0.0
            )
            if derivative:
                g[sel], dg[sel] = out
            else:
                g[sel] = out
        m = self.mask[rows]
        g *= m
        if not derivative:
            return g
        dg *= m
        return g, dg


def _dense_sums(model, y, wm):
    """The step's weighted sums from a model that forms g and dg/dtau (0 outside the fit range)."""

    def sums(tau, idx):
        g, dg = model(tau, idx)
        w, yy = wm[idx], y[idx]
        wg, wd = w * g, w * dg
        return (
            wg.sum(-1),
            _dot(wg, g),
            _dot(wg, yy),
            wd.sum(-1),
            _dot(wd, g),
            _dot(wd, yy),
            _dot(wd, dg),
        )

    return sums


CHI2_CANCEL = 1e-9  # chi2 / y'Wy below which the closed-form chi2 is recomputed from residuals


def _gauss_newton(sums, s1_all, sy_all, tau0, max_iter=50, rtol=1e-9):
    """Damped Gauss-Newton on tau with B, b projected out (Kaufman's variable projection).

    With r = y - B g - b orthogonal to span{g, 1} at the profiled B, b, the step needs only the
    weighted sums of g, dg/dtau and y that ``sums(tau, rows)`` returns (sg, sgg, sgy, sd, sdg,
    sdy, sdd), so neither the residual nor, for the exponential-sum models, g itself is formed.
    ``s1_all`` and ``sy_all`` are the per-row sums of the weights and of w y.
    """
    tau = tau0.copy()
    n = tau.size
    rows = np.arange(n)
    active = np.ones(n, bool)
    converged = np.zeros(n, bool)
    for _ in range(max_iter):
        idx = rows[active]
        if idx.size == 0:
            break
        sg, sgg, sgy, sd, sdg, sdy, sdd = sums(tau[idx], idx)
        s1, sy = s1_all[idx], sy_all[idx]
        det = s1 * sgg - sg * sg
        amp = (s1 * sgy - sg * sy) / det
        off = (sgg * sy - sg * sgy) / det
        # v = amp dg; num = v.W r; den = v.W v minus its projection on span{g, 1}
        num = amp * (sdy - amp * sdg - off * sd)
        pa = (s1 * sdg - sg * sd) / det
        pb = (sgg * sd - sg * sdg) / det
        den = amp * amp * (sdd - pa * sdg - pb * sd)
        ok = np.isfinite(num) & np.isfinite(den) & (den > 0)
        step = np.clip(
            np.where(ok, num / np.where(ok, den, 1.0), 0.0), -0.3 * tau[idx], 0.5 * tau[idx]
        )
        tau[idx] = tau[idx] + step
        done = ok & (np.abs(step) <= rtol * tau[idx])
        converged[idx[done]] = True
        # a row whose step cannot be formed stops, unconverged (reported, never silently passed)
        active[idx[done | ~ok]] = False
    return tau, converged


def noise_rows(noise_v, n_rows, n_samples, rows_of):
    """The noise (V) of each fitted row.

    Per record or per sample, picked by ``rows_of``; None when the bundle has no noise (then it is
    estimated from the residuals).
    """
    if noise_v is None:
        return None
    nz = np.asarray(noise_v, float)
    if nz.ndim == 1:
        return np.broadcast_to(nz[rows_of][:, None], (n_rows, n_samples))
    return nz[rows_of]


def fit_transients(
    time_s,
    signal_v,
    t_cut_s,
    method="crds",
    tf: TFParams | None = None,
    window: str | None = "extinction",
    noise_v=None,
    rows_of=None,
    keep_residuals: bool = False,
    tau_start_s=None,
    warm_start: bool = False,
) -> TransientFits:
    """Fit transients; each row r fits ``signal_v[rows_of[r]]`` on t >= ``t_cut_s[r]``.

    ``time_s`` (k,) uniformly spaced (s, relative to extinction); ``signal_v`` (m, k) V;
    ``t_cut_s`` (n,) s; ``noise_v`` None, (m,) or (m, k) V; ``rows_of`` (n,) transient index of
    each row (default: row r fits transient r). ``method`` is ``crds`` or ``tf-crds`` (the latter
    needs ``tf`` and a ``window``). ``tau_start_s`` (n,) seeds the plain-exponential fit that
    starts a TF-CRDS fit; with ``warm_start`` the TF-CRDS fit starts at it directly (a decay
    time already known, e.g. the same record's at another t_cut).
    """
    t, sig, t_cut, rows_of, first = _checked_rows(
        time_s, signal_v, t_cut_s, method, tf, window, rows_of
    )
    noise = None if noise_v is None else np.asarray(noise_v, float)
    # one weight per transient: the exponential-sum path, no dense model arrays
    one_weight = noise is None or noise.ndim == 1
    fit = _fit_one_weight_per_row if one_weight else _fit_per_sample_noise
    args = (t, sig, t_cut, rows_of, first, method, tf, window)
    return fit(*args, noise if one_weight else noise_v, keep_residuals, tau_start_s, warm_start)


def _checked_rows(time_s, signal_v, t_cut_s, method, tf, window, rows_of):
    """Arrays of a batch of fits, refused with a clear message where they cannot be fitted.

    Returns (t, signal, t_cut, rows_of, index of each row's first fitted sample).
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    t = np.asarray(time_s, float)
    sig = np.asarray(signal_v, float)
    t_cut = np.atleast_1d(np.asarray(t_cut_s, float))
    rows_of = np.arange(t_cut.size) if rows_of is None else np.asarray(rows_of)
    dt = t[1] - t[0]
    if np.any(t_cut >= t[-1] - 8 * dt):
        bad = t_cut[t_cut >= t[-1] - 8 * dt][0]
        raise ValueError(f"t_cut = {bad:g} s is beyond the record (last sample at {t[-1]:g} s)")
    if np.any(t_cut < 0):
        raise ValueError("t_cut is counted from laser extinction and must be >= 0 s")
    first = np.array([first_index_at(t[0], dt, tc) for tc in t_cut])
    if method == "tf-crds" and (tf is None or window not in WINDOWS):
        raise ValueError(
            f"tf-crds needs a transfer function and a window ({WINDOWS}), got tf={tf!r}, "
            f"window={window!r}"
        )
    return t, sig, t_cut, rows_of, first


def _fit_one_weight_per_row(
    t, sig, t_cut, rows_of, first, method, tf, window, noise, keep_residuals, tau_start_s, warm
) -> TransientFits:
    """One noise level (or none) per transient.

    Weighted sums from ``expsum`` (closed form for CRDS and for a rational H in the extinction
    window; dense sums otherwise), chi2 without residuals.
    """
    n = t_cut.size
    dt = t[1] - t[0]
    w = np.ones(n) if noise is None else 1.0 / noise[rows_of] ** 2
    data = BlockedData(sig, first, rows_of, w, dt)
    t_first = t[0] + dt * first
    s1 = w * data.n
    model = SumsModel(data, None, t_first, t_cut)
    tau0 = (
        _three_interval_tau(t, sig, first, rows_of)
        if tau_start_s is None
        else np.asarray(tau_start_s, float).copy()
    )
    if warm and method == "tf-crds":
        tau, conv = tau0, np.zeros(n, bool)
    else:
        tau, conv = _gauss_newton(model, s1, data.sum_wy, tau0)
    if method == "tf-crds":
        chain = _rational_chain(tf) if window == "extinction" else None
        if chain is not None:
            model = SumsModel(data, chain, t_first, t_cut)
            tau, conv = _gauss_newton(model, s1, data.sum_wy, tau)
        else:
            # no closed form (fractional n_r, the letter window): dense model arrays; the
            # amplitude, offset, chi2 and Fisher matrix below come from these sums too
            mask = np.arange(t.size)[None, :] >= first[:, None]
            dense = _TfCrds(t, t_cut, tf, window, mask)
            model = _dense_sums(dense, sig[rows_of], mask * w[:, None])
            tau, conv = _gauss_newton(model, s1, data.sum_wy, tau)
    else:
        window = None
    sg, sgg, sgy, sd, sdg, sdy, sdd = model(tau, np.arange(n))
    det = s1 * sgg - sg * sg
    amp = (s1 * sgy - sg * data.sum_wy) / det
    off = (sgg * data.sum_wy - sg * sgy) / det

    # chi2 = y'Wy - beta' X'Wy at the least-squares beta (no residual array needed); it carries
    # an absolute error of a few eps y'Wy, so rows whose chi2 is below CHI2_CANCEL y'Wy
    # (very high signal-to-noise: a relative error above ~1e-6) get it from their residuals
    def residuals(rows):
        """y - B g - b on each row's fitted samples, zero before them (V)."""
        if method == "tf-crds" and not isinstance(model, SumsModel):
            g = dense(tau[rows], rows, derivative=False)
        else:
            g = model.response(t, tau[rows], rows)
        inside = np.arange(t.size)[None, :] >= first[rows, None]
        return np.where(inside, sig[rows_of[rows]] - amp[rows, None] * g - off[rows, None], 0.0)

    chi2 = data.sum_wyy - amp * sgy - off * data.sum_wy
    redo = np.nonzero(~(chi2 > CHI2_CANCEL * data.sum_wyy))[0]
    if redo.size:
        r = residuals(redo)
        chi2[redo] = w[redo] * np.einsum("rj,rj->r", r, r)
    fisher = np.empty((n, 3, 3))
    fisher[:, 0, 0], fisher[:, 0, 1], fisher[:, 1, 1] = sgg, sg, s1
    fisher[:, 0, 2], fisher[:, 1, 2], fisher[:, 2, 2] = amp * sdg, amp * sd, amp * amp * sdd
    fisher[:, 1, 0], fisher[:, 2, 0], fisher[:, 2, 1] = (
        fisher[:, 0, 1],
        fisher[:, 0, 2],
        fisher[:, 1, 2],
    )
    n_used = data.n
    dof = n_used - 3
    resid = None
    if keep_residuals:
        resid = residuals(np.arange(n))
    if noise is None:
        s2 = chi2 / np.maximum(dof, 1)
        noise_used = np.sqrt(s2)
        fisher = fisher / s2[:, None, None]
        chi2 = chi2 / s2
    else:
        noise_used = noise[rows_of]
    cov, singular = _row_covariances(fisher)
    conv = conv & ~singular
    return TransientFits(
        tau_s=tau,
        tau_u_s=np.sqrt(cov[:, 2, 2]),
        amplitude_v=amp,
        offset_v=off,
        cov=cov,
        chi2=chi2,
        dof=dof,
        noise_v=noise_used,
        noise_estimated=noise is None,
        converged=conv,
        t_cut_s=t_cut,
        method=method,
        window=window,
        residuals_v=resid,
    )


def _fit_per_sample_noise(
    t, sig, t_cut, rows_of, first, method, tf, window, noise_v, keep_residuals, tau_start_s, warm
) -> TransientFits:
    """Per-sample noise: dense model arrays and weights."""
    n = t_cut.size
    y = sig[rows_of]
    mask = np.arange(t.size)[None, :] >= first[:, None]
    noise = noise_rows(noise_v, n, t.size, rows_of)
    wm = mask / noise**2
    s1, sy = wm.sum(-1), _dot(wm, y)
    crds = _Crds(t, t_cut, mask)
    tau0 = (
        _three_interval_tau(t, sig, first, rows_of)
        if tau_start_s is None
        else np.asarray(tau_start_s, float).copy()
    )
    if warm and method == "tf-crds":
        tau, conv = tau0, np.zeros(n, bool)
    else:
        tau, conv = _gauss_newton(_dense_sums(crds, y, wm), s1, sy, tau0)
    model = crds
    if method == "tf-crds":
        model = _TfCrds(t, t_cut, tf, window, mask)
        tau, conv = _gauss_newton(_dense_sums(model, y, wm), s1, sy, tau)
    else:
        window = None

    g, dg = model(tau, np.arange(n))
    amp, off = _solve_linear(wm, g, y)
    resid = np.where(mask, y - amp[:, None] * g - off[:, None], 0.0)
    n_used = mask.sum(-1)
    dof = n_used - 3
    noise_used = np.sqrt((noise**2 * mask).sum(-1) / n_used)
    chi2 = (wm * resid**2).sum(-1)
    # Fisher matrix over (B, b, tau)
    cols = (g, np.ones_like(g), amp[:, None] * dg)
    fisher = np.empty((n, 3, 3))
    for i in range(3):
        wc = wm * cols[i]
        for j in range(i, 3):
            fisher[:, i, j] = fisher[:, j, i] = _dot(wc, cols[j])
    cov, singular = _row_covariances(fisher)
    conv = conv & ~singular
    return TransientFits(
        tau_s=tau,
        tau_u_s=np.sqrt(cov[:, 2, 2]),
        amplitude_v=amp,
        offset_v=off,
        cov=cov,
        chi2=chi2,
        dof=dof,
        noise_v=noise_used,
        noise_estimated=False,
        converged=conv,
        t_cut_s=t_cut,
        method=method,
        window=window,
        residuals_v=resid if keep_residuals else None,
    )


def _row_covariances(fisher):
    """Per-row inverse Fisher matrices.

    A singular row (a degenerate fit: tau collapsed or no decay left in the window) gets NaN and is
    reported unconverged instead of failing the batch.
    """
    try:
        cov = covariance_from_fisher(fisher)
        singular = np.zeros(fisher.shape[0], bool)
    except np.linalg.LinAlgError:
        cov = np.full_like(fisher, np.nan)
        singular = np.zeros(fisher.shape[0], bool)
        for i in range(fisher.shape[0]):
            try:
                cov[i] = covariance_from_fisher(fisher[i])
            except np.linalg.LinAlgError:
                singular[i] = True
    # numerically singular rows can also come back with a negative variance
    singular |= ~np.all(np.diagonal(cov, axis1=-2, axis2=-1) > 0, axis=-1)
    cov[singular] = np.nan
    return cov, singular


def _rational_chain(tf: TFParams):
    """The chain of Eq. 2 as poles and residues when it has them (n_r = 2), else None."""
    try:
        return chain_from_tf(tf)
    except ValueError:
        return None


#: columns of the decay-time table (``RingdownFits.to_csv``, ``bayes-tfcrds fit``)
CSV_COLUMNS = (
    "nu_hz", "t_cut_s", "tau_s", "tau_u_s", "tau_u_noise_s", "tau_u_h_s", "chi2_red", "noise_kappa",
    "status",
)  # fmt: skip


@dataclass(frozen=True)
class RingdownFits:
    """Fits of every spectral point at every t_cut: arrays shaped (m points, c t_cuts).

    Transients flagged as clipped are not fitted: their entries are NaN and ``clipped`` is set.
    ``tau_u_s`` is the fit's own u(tau) (ring-down noise, given H), the weight of a line fit;
    ``tau_u_h_s`` the part the uncertainty of H adds (fully correlated between points), when
    computed; :attr:`tau_u_total_s` both, which the CSV and ``to_dict`` call ``tau_u``.

    ``chi2_red`` is the residual sum of squares over the stated per-sample noise (the bundle's
    noise_v), whatever the fits weighted with: ~1 when the bundle states its noise level, white
    or coloured. ``noise_kappa`` (m,) is the variance factor of tau the noise colour implies
    (``RingdownData.noise_kappa``; None: white, 1): the fits weighted with noise_v sqrt(kappa),
    so ``tau_u_s`` holds it, and a chi2 at those weights would read ~1/kappa.
    """

    nu_hz: np.ndarray
    t_cut_s: np.ndarray
    tau_s: np.ndarray
    tau_u_s: np.ndarray
    amplitude_v: np.ndarray
    offset_v: np.ndarray
    chi2_red: np.ndarray
    converged: np.ndarray
    clipped: np.ndarray
    method: str
    window: str | None
    noise_estimated: bool
    residuals_v: np.ndarray | None = field(default=None, repr=False)

    record_end_s: float = np.inf
    saturated: np.ndarray | None = None
    # fits that did not converge and were then left out (tau NaN): points x t_cuts, or None
    unconverged: np.ndarray | None = None
    # what the fits were made of, for a look at one transient (:meth:`trace`, :meth:`plot`)
    data: object = field(default=None, repr=False, compare=False)  # the RingdownData fitted
    tf: TFParams | None = None  # H of a tf-crds fit
    # u(tau) from the uncertainty of H (s), points x t_cuts, when computed
    # (:func:`bayes_tfcrds.uncertainty.decay_times.h_part_of_tau_u`); tau_u_s is the noise's
    tau_u_h_s: np.ndarray | None = None
    noise_kappa: np.ndarray | None = None

    def with_h_uncertainty(self, tau_u_h_s) -> RingdownFits:
        """These fits with the H part of u(tau) (s, shaped like tau_s): the CSV's total u."""
        u_h = np.asarray(tau_u_h_s, float)
        if u_h.shape != np.shape(self.tau_s):
            raise ValueError(f"u_H(tau) shaped {u_h.shape}, the fits {np.shape(self.tau_s)}")
        return replace(self, tau_u_h_s=u_h)

    @property
    def tau_u_total_s(self) -> np.ndarray:
        """Standard uncertainty of tau (s): noise and H in quadrature.

        Plain CRDS has no H in its model: its H part is 0 (not modelled; the chain's bias on its
        tau, up to 16 %, is in no u). A TF-CRDS fit whose H part was not computed has NaN.
        """
        if self.tau_u_h_s is not None:
            u_h = self.tau_u_h_s
        else:
            u_h = np.where(self.method == "tf-crds", np.nan, 0.0)
        return np.hypot(self.tau_u_s, u_h)

    @property
    def kappa_per_point(self) -> np.ndarray:
        """The variance factor of tau per spectral point (m,): noise_kappa, 1 where white."""
        if self.noise_kappa is None:
            return np.ones(np.shape(self.nu_hz))
        return np.asarray(self.noise_kappa, float)

    def converged_only(self) -> RingdownFits:
        """These fits with the decay times of fits that did not converge set to NaN (left out).

        A decay time whose fit did not converge (run to 1e-14 s, say) is not a measurement;
        spectra and tables skip NaN entries. ``unconverged`` (points x t_cuts) marks them.
        """
        bad = ~self.converged & np.isfinite(self.tau_s)
        return replace(
            self,
            tau_s=np.where(bad, np.nan, self.tau_s),
            tau_u_s=np.where(bad, np.nan, self.tau_u_s),
            tau_u_h_s=None if self.tau_u_h_s is None else np.where(bad, np.nan, self.tau_u_h_s),
            unconverged=bad,
        )

    def trace(self, i: int, j: int = 0) -> dict:
        """Transient ``i`` at t_cut index ``j``: time (s), signal, fitted model and residual (V).

        ``fitted`` marks the samples the fit used (t >= t_cut); model and residual are NaN
        elsewhere. Residuals kept by the fit (``keep_residuals``) are used as they are; otherwise
        this one transient is fitted again with the same model, H and noise (the same numbers).
        """
        if self.data is None:
            raise ValueError("these fits carry no ring-down data: make them with fit_ringdowns")
        if self.clipped[i] or not np.isfinite(self.tau_s[i, j]):
            raise ValueError(f"transient {i} was not fitted (status {self.status(i, j)!r})")
        t = np.asarray(self.data.time_s, float)
        y = np.asarray(self.data.signal_v[i], float)
        if self.residuals_v is not None:
            resid = self.residuals_v[i, j]
        else:
            noise = self.data.fit_noise_v
            resid = fit_transients(
                t,
                y[None, :],
                [self.t_cut_s[j]],
                method=self.method,
                tf=self.tf,
                window=self.window or "extinction",
                noise_v=None if noise is None else np.asarray(noise)[[i]],
                keep_residuals=True,
            ).residuals_v[0]
        fitted = np.arange(t.size) >= first_index_at(t[0], t[1] - t[0], self.t_cut_s[j])
        resid = np.where(fitted, resid, np.nan)
        return {
            "time_s": t,
            "signal_v": y,
            "model_v": y - resid,
            "residual_v": resid,
            "fitted": fitted,
        }

    def summary(self) -> str:
        """Plain-text summary: method, t_cuts (µs), tau range (µs), chi2_red, statuses."""
        from bayes_tfcrds.fit.views import ringdowns_text

        return ringdowns_text(self)

    def to_dict(self) -> dict:
        """JSON-ready record of every fit, each quantity with its unit."""
        from bayes_tfcrds.fit.views import ringdowns_dict

        return ringdowns_dict(self)

    def _repr_html_(self) -> str:
        from bayes_tfcrds.fit.views import ringdowns_html

        return ringdowns_html(self)

    def plot(self, i: int | None = None, j: int = 0, ax=None):
        """One transient (default the line centre's, shortest tau) with its fit and residuals.

        Returns a matplotlib Figure; see :func:`bayes_tfcrds.fit.views.plot_ringdown`.
        """
        from bayes_tfcrds.fit.views import plot_ringdown

        return plot_ringdown(self, i, j, ax)

    def status(self, i, j) -> str:
        """``ok``, or why the fit at point i and t_cut j is not to be trusted as it stands.

        ``clipped``: the transient hit the digitizer's rails; ``saturated``: the detector pinned
        it below them (neither is fitted). ``record-short``: less than two decay times of record
        after t_cut, where the offset b and
        tau are nearly degenerate (the fit's u(tau) says so, but a reader should be told).
        """
        if self.saturated is not None and self.saturated[i]:
            return "saturated"
        if self.clipped[i]:
            return "clipped"
        if not self.converged[i, j]:
            return "not-converged"
        if self.record_end_s - self.t_cut_s[j] < 2.0 * self.tau_s[i, j]:
            return "record-short"
        return "ok"

    def rows(self):
        """(nu_hz, t_cut_s, tau_s, tau_u_s, chi2_red, status) per point and t_cut."""
        for i, nu in enumerate(self.nu_hz):
            for j, tc in enumerate(self.t_cut_s):
                yield (
                    nu,
                    tc,
                    self.tau_s[i, j],
                    self.tau_u_s[i, j],
                    self.chi2_red[i, j],
                    self.status(i, j),
                )

    def to_csv(self) -> str:
        """The fit table as CSV text (``bayes-tfcrds fit``).

        nu_hz, t_cut_s, tau_s, tau_u_s, tau_u_noise_s, tau_u_h_s, chi2_red, noise_kappa, status;
        SI units.
        tau_u_s is the standard uncertainty of tau (:attr:`tau_u_total_s`): the noise part
        tau_u_noise_s (the fit's own, given H; the attribute ``tau_u_s``) and the H part
        tau_u_h_s (fully correlated between points) in quadrature; NaN where the H part was not
        computed for a TF-CRDS fit, 0 for plain CRDS (H not modelled). chi2_red is at the stated
        noise; noise_kappa the record's variance factor of tau (1: white).
        """
        total = self.tau_u_total_s
        kappa = self.kappa_per_point
        u_h = self.tau_u_h_s if self.tau_u_h_s is not None else np.sqrt(total**2 - self.tau_u_s**2)
        buf = io.StringIO()
        w = csv.writer(buf)
        w.writerow(CSV_COLUMNS)
        for i, nu in enumerate(self.nu_hz):
            for j, tc in enumerate(self.t_cut_s):
                w.writerow(
                    [
                        f"{nu:.3f}",
                        f"{tc:.6e}",
                        f"{self.tau_s[i, j]:.10e}",
                        f"{total[i, j]:.4e}",
                        f"{self.tau_u_s[i, j]:.4e}",
                        f"{u_h[i, j]:.4e}",
                        f"{self.chi2_red[i, j]:.5f}",
                        f"{kappa[i]:.4g}",
                        self.status(i, j),
                    ]
                )
        return buf.getvalue()


def _per_fit_arrays(fits, kappa_rows) -> dict:
    """A TransientFits' per-row results under fit_ringdowns' names.

    ``kappa_rows`` the noise colour's variance factor of each row: the fits weighted with
    noise_v sqrt(kappa), so their chi2 times kappa is the chi2 at the stated noise.
    """
    return {
        "tau": fits.tau_s,
        "tau_u": fits.tau_u_s,
        "amp": fits.amplitude_v,
        "off": fits.offset_v,
        "chi2r": fits.chi2_red * kappa_rows,
    }


#: chi2_red above which a converged TF-CRDS fit is suspected of a wrong optimum and fitted again
#: from the record's best decay time at another t_cut. A right one has chi2_red ~ 1 at the stated
#: noise (sd sqrt(2/n) ~ 0.01 on 10^4 samples, white or coloured: at the kappa-inflated weights
#: the fits use it would read ~1/kappa, and a wrong optimum under kappa 4 would pass); a wrong
#: one behind a strong slow tail was 5.2 (tau 6.9 us for 3.7 us, line centre of a zoo chain with
#: f_c 10.6 kHz and tail weight 0.31, t_cut 8 us, at the chain's H).
CHI2_SUSPECT = 1.5


def _retry_from_other_t_cuts(ringdowns, t_cuts, tf, window, out, conv, resid, kappa) -> None:
    """Fit again, in place, TF-CRDS fits that did not converge or sit in a wrong optimum.

    A TF-CRDS fit starts from the plain-exponential fit of the same truncated transient; at a late
    t_cut behind a slow chain (a resonance of tens of kHz) that start can lie where the profiled
    chi2 falls towards tau -> 0, and the fit walks there, or in another local minimum of chi2 (a
    converged fit with chi2_red > :data:`CHI2_SUSPECT`). The record's own decay time, converged
    at another t_cut, is the right start: TF-CRDS decay times do not depend on t_cut. An
    unconverged fit takes the median of the record's converged ones and is replaced when the
    refit converges; a suspect one takes the decay time of the record's best fit (lowest
    chi2_red) and is replaced only when the refit converges with a lower chi2 (same samples, same
    model: the better optimum).
    """
    have = conv & np.isfinite(out["tau"])
    failed = ~conv & np.isfinite(out["tau"]) & conv.any(axis=1, keepdims=True)
    suspect = have & (out["chi2r"] > CHI2_SUSPECT) & (have.sum(axis=1, keepdims=True) > 1)
    if not (failed.any() or suspect.any()):
        return
    i, j = np.nonzero(failed | suspect)
    chi2 = np.where(have, out["chi2r"], np.inf)
    start = np.array(
        [
            out["tau"][r, np.argmin(chi2[r])]
            if suspect[r, k]
            else np.median(out["tau"][r][conv[r]])
            for r, k in zip(i, j)
        ]
    )
    keep = ~suspect[i, j] | ~np.isclose(start, out["tau"][i, j], rtol=1e-3)
    i, j, start = i[keep], j[keep], start[keep]
    if not i.size:
        return
    again = fit_transients(
        ringdowns.time_s,
        ringdowns.signal_v,
        t_cuts[j],
        method="tf-crds",
        tf=tf,
        window=window,
        noise_v=ringdowns.fit_noise_v,
        rows_of=i,
        keep_residuals=resid is not None,
        tau_start_s=start,
        warm_start=True,
    )
    arrays = _per_fit_arrays(again, kappa[i])
    ok = again.converged & (~suspect[i, j] | (arrays["chi2r"] < out["chi2r"][i, j]))
    for key, arr in arrays.items():
        out[key][i[ok], j[ok]] = arr[ok]
    conv[i[ok], j[ok]] = True
    if resid is not None:
        resid[i[ok], j[ok]] = again.residuals_v[ok]


def fit_ringdowns(
    ringdowns,
    t_cuts_s,
    method="crds",
    tf: TFParams | None = None,
    window="extinction",
    keep_residuals: bool = False,
) -> RingdownFits:
    """Fit every transient of a bundle's ``RingdownData`` at every t_cut (s).

    Clipped transients (``ringdowns.clipped``) are excluded and reported, never fitted as if
    they were fine.

    Parameters
    ----------
    ringdowns : RingdownData
        ``config.ringdowns`` of a bundle (time axis, signals in V, noise).
    t_cuts_s : sequence of float
        Truncation times (s) from laser extinction.
    method : str
        ``crds`` or ``tf-crds``.
    tf : TFParams, optional
        H for tf-crds (``calibrate(config).params``).
    window : str
        ``extinction`` or ``letter`` (tf-crds).
    keep_residuals : bool
        Keep the residuals (V) of every fit.

    Returns
    -------
    RingdownFits
        Arrays (points x t_cuts): tau_s, tau_u_s, amplitude_v, offset_v, chi2_red, status.
    """
    t_cuts = np.atleast_1d(np.asarray(t_cuts_s, float))
    m, c = ringdowns.signal_v.shape[0], t_cuts.size
    clipped = np.asarray(ringdowns.clipped, bool)
    good = np.nonzero(~clipped)[0]
    rows_of = np.repeat(good, c)
    tc = np.tile(t_cuts, good.size)
    shape = (m, c)
    out = {k: np.full(shape, np.nan) for k in ("tau", "tau_u", "amp", "off", "chi2r")}
    conv = np.zeros(shape, bool)
    resid = None
    est = ringdowns.fit_noise_v is None
    kappa = np.ones(m) if ringdowns.noise_kappa is None else np.asarray(ringdowns.noise_kappa)
    if good.size:
        fits = fit_transients(
            ringdowns.time_s,
            ringdowns.signal_v,
            tc,
            method=method,
            tf=tf,
            window=window,
            noise_v=ringdowns.fit_noise_v,
            rows_of=rows_of,
            keep_residuals=keep_residuals,
        )
        for key, arr in _per_fit_arrays(fits, kappa[rows_of]).items():
            out[key][good] = arr.reshape(good.size, c)
        conv[good] = fits.converged.reshape(good.size, c)
        est = fits.noise_estimated
        if keep_residuals:
            resid = np.full((m, c, ringdowns.signal_v.shape[1]), np.nan)
            resid[good] = fits.residuals_v.reshape(good.size, c, -1)
        if method == "tf-crds":
            _retry_from_other_t_cuts(ringdowns, t_cuts, tf, window, out, conv, resid, kappa)
    return RingdownFits(
        nu_hz=np.asarray(ringdowns.nu_hz),
        t_cut_s=t_cuts,
        tau_s=out["tau"],
        tau_u_s=out["tau_u"],
        amplitude_v=out["amp"],
        offset_v=out["off"],
        chi2_red=out["chi2r"],
        converged=conv,
        clipped=clipped,
        method=method,
        window=window if method == "tf-crds" else None,
        noise_estimated=est,
        residuals_v=resid,
        record_end_s=float(ringdowns.time_s[-1]),
        saturated=np.asarray(getattr(ringdowns, "saturated", np.zeros(m, bool)), bool),
        data=ringdowns,
        tf=tf if method == "tf-crds" else None,
        noise_kappa=None if ringdowns.noise_kappa is None else kappa,
    )
