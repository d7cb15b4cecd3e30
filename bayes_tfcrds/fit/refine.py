"""Multi-ring-down refinement of H(f) (letter Appendix B), as an update of the beat note.

**Appendix B as written.** One transfer function is shared by many truncated transients (several
records, several t_cut each); per record, tau, B and b are shared by all its truncations. B is the
record's amplitude at extinction, so a truncation whose model starts at a kink t_k (the ``letter``
window puts it at the first analysed sample) has amplitude B exp(-t_k/tau); in the ``extinction``
window t_k = 0 and every truncation of a record sees the same curve on a different span. B and b
are solved exactly and tau re-fitted per record for every H step (variable projection), so the
outer damped Gauss-Newton works in the few H dimensions only, with the exact reduced Jacobian.

**Composite likelihood.** A sample after the latest t_cut enters the fit once per truncation, so
the sum of squares is a composite likelihood, not the likelihood of the record. Its estimate is
sound, but its curvature over-counts the data: the honest covariance is the sandwich
A^-1 B A^-1 (A: summed Fisher information, B: variance of the per-record scores). To combine it
with other evidence the ring-down chi2 is scaled by the magnitude adjustment
w = p / tr(A^-1 B) (Pauli, Racugno & Ventura, Stat. Sinica 21 (2011) 149; Ribatet, Cooley &
Davison, Stat. Sinica 22 (2012) 813), which makes its curvature match the sandwich.

**An update, never an overwrite.** With a ``prior`` (the beat-note fit of Eq. 1-2, Gaussian in
the sampled parametrisation) the refined parameters maximise w chi2_RD/2 + beat-note penalty: a
parameter the ring-downs do not constrain stays where the beat note puts it, and its posterior
covariance is (wA + P)^-1 (w^2 B + P) (wA + P)^-1 (P: beat-note information). How far the
ring-downs moved each parameter is reported as a z-score of the shift against its own expected
scatter (the beat-note/ring-down tension; the letter's D2 shows one). Without a prior the fit is
the letter's ring-down-only estimate.

Positive parameters (f_c, f_r, Gamma_r, n_r) are refined in log space, and every step stays inside
:data:`~bayes_tfcrds.physics.transfer_function.SUPPORT` (A_r > -0.99: a positive DC gain), so no
step or draw ever leaves the physical domain. Units: natural (Hz for
frequencies) in every output; the sampled parametrisation is internal.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import fft as sfft
from scipy import stats

from bayes_tfcrds.core.linalg import covariance_from_fisher, extend_span
from bayes_tfcrds.fit.ringdown import _gauss_newton, fit_transients, noise_rows
from bayes_tfcrds.physics.forward import (
    filtered_response,
    first_index_at,
    grid_transfer_function,
    input_spectrum,
    model_grids,
)
from bayes_tfcrds.physics.transfer_function import (
    PARAM_NAMES,
    TFParams,
    outside_support,
    transfer_function,
    transfer_function_of_draws,
)

POSITIVE = frozenset({"f_c_hz", "f_r_hz", "gamma_r", "n_r"})  # refined in log space
TENSION_Z = 3.0  # |z| above which a beat-note/ring-down tension is reported as a finding
# share of a parameter's information that must come from the ring-downs for the tension test to
# have power: below it the shift is a second-order sliver of the beat-note u (0.005 u for a
# 0.5 % share, an f_c above the ring-downs' Nyquist frequency) whose linear-Gaussian scatter is
# not to be trusted (z of 5, -3, -2 over noise draws of one such chain), so no z is given
TENSION_MIN_INFO = 0.01


# --------------------------------------------------------------------------- parametrisation


def _positive(names, ndim: int) -> np.ndarray:
    """Which of ``names`` are positive, shaped to broadcast along the first axis of the values."""
    return np.array([n in POSITIVE for n in names]).reshape((-1,) + (1,) * max(ndim - 1, 0))


def sample_jacobian(names, values) -> np.ndarray:
    """d(natural)/d(sampled) for each parameter: the value itself in log space, 1 for A_r.

    ``values`` has the parameters along its first axis (any trailing shape).
    """
    v = np.asarray(values, float)
    return np.where(_positive(names, v.ndim), v, 1.0)


def to_sample(names, values) -> np.ndarray:
    """Natural values to the sampled parametrisation (log of the positive parameters)."""
    v = np.asarray(values, float)
    pos = _positive(names, v.ndim)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(pos, np.log(np.where(pos, v, 1.0)), v)


def from_sample(names, phi) -> np.ndarray:
    """The sampled parametrisation back to natural values."""
    p = np.asarray(phi, float)
    pos = _positive(names, p.ndim)
    with np.errstate(over="ignore"):
        return np.where(pos, np.exp(np.where(pos, p, 0.0)), p)


def _check_names(names) -> tuple:
    names = tuple(names)
    for name in names:
        if name not in PARAM_NAMES:
            raise ValueError(
                f"unknown transfer-function parameter {name!r}; choose from {PARAM_NAMES}"
            )
    return names


@dataclass(frozen=True)
class HPrior:
    """Gaussian knowledge of H parameters from elsewhere, in natural units (the beat note).

    ``names`` the parameters, ``mean`` their values, ``cov`` their covariance.
    """

    names: tuple
    mean: np.ndarray
    cov: np.ndarray
    source: str = "beat note"

    @classmethod
    def from_beat(cls, beat) -> HPrior:
        """The least-squares beat-note fit (:class:`~bayes_tfcrds.fit.beat_note.TFFit`)."""
        return cls(tuple(beat.free), beat.params.as_vector(beat.free), np.array(beat.param_cov))

    def conditional(self, free, start: TFParams):
        """Mean, information and regression of ``free`` given the other prior names at ``start``.

        In the sampled parametrisation. Returns (mu (n_free,), P (n_free, n_free), beta (n_free,
        n_others), others): parameters the prior does not hold get zero information.
        """
        names = self.names
        phi = to_sample(names, self.mean)
        jac = sample_jacobian(names, self.mean)
        cov = self.cov / np.outer(jac, jac)
        inr = [i for i, n in enumerate(names) if n in free]
        ino = [i for i, n in enumerate(names) if n not in free]
        others = tuple(names[i] for i in ino)
        phi_o = to_sample(others, start.as_vector(others)) if others else np.zeros(0)
        c_rr = cov[np.ix_(inr, inr)]
        if ino:
            c_ro, c_oo = cov[np.ix_(inr, ino)], cov[np.ix_(ino, ino)]
            beta_in = np.linalg.solve(c_oo, c_ro.T).T
            mu_in = phi[inr] + beta_in @ (phi_o - phi[ino])
            c_cond = c_rr - beta_in @ c_ro.T
        else:
            beta_in, mu_in, c_cond = np.zeros((len(inr), 0)), phi[inr], c_rr
        n = len(free)
        mu = to_sample(free, start.as_vector(free))
        info = np.zeros((n, n))
        beta = np.zeros((n, len(others)))
        pos = [free.index(names[i]) for i in inr]
        if pos:
            mu[pos] = mu_in
            info[np.ix_(pos, pos)] = np.linalg.inv(0.5 * (c_cond + c_cond.T))
            beta[pos] = beta_in
        return mu, info, beta, others


# --------------------------------------------------------------------------- the result


@dataclass(frozen=True)
class RefinedTF:
    """Refined H.

    ``params`` at the optimum; ``cov`` the covariance of ``free`` given the parameters held
    fixed (natural units: the posterior given the beat note when there is a prior, the ring-down
    sandwich otherwise; the held ones' own uncertainty enters through :meth:`conditional`, see
    ``Calibration.covariance``); ``cov_naive``
    the inverse of the information that counts every truncation as independent data (for
    comparison); chi2 and dof of the composite ring-down fit; tau per record (``tau_s``, s);
    ``weight`` the composite-likelihood adjustment w; with a prior, ``prior_mean`` and
    ``prior_cov`` of ``free`` given the others (natural units) and the tension ``z`` of each
    parameter's shift.
    """

    params: TFParams
    start: TFParams
    free: tuple
    cov: np.ndarray
    cov_naive: np.ndarray
    chi2: float
    dof: int
    n_iter: int
    converged: bool
    tau_s: np.ndarray
    t_cut_s: np.ndarray
    rows_of: np.ndarray
    weight: float = 1.0
    sens_names: tuple = ()
    gain_sample: np.ndarray | None = None  # d phi_free / d phi_others (sampled parametrisation)
    rd_information: np.ndarray | None = None  # w A over free + others (sampled parametrisation)
    influence: np.ndarray | None = None  # d theta_free / d y: (records, n_free, samples)
    prior: HPrior | None = None
    prior_mean: np.ndarray | None = None
    prior_cov: np.ndarray | None = None
    z: np.ndarray | None = None
    cov_sample: np.ndarray | None = None
    prior_chi2: float = 0.0  # (phi - mu)' P (phi - mu) at the optimum: the beat note's part
    noise_v: np.ndarray | None = None  # the records' noise (V) the chi2 is in units of
    layout: object = field(default=None, repr=False)  # the refinement data (composite rows)
    likelihood_layout: object = field(default=None, repr=False)  # each sample once, if it exists

    def conditional(self, others: dict):
        """Linear map of the refined parameters on the others held fixed in the refinement.

        A change delta_O of the ``sens_names`` not refined moves the refined optimum by
        ``G delta_O`` (natural units; the implicit derivative of the estimating equations, beat-note
        regression included when there is a prior). Returns (G (n_free, n_others), names).
        """
        if self.gain_sample is None:
            raise ValueError("refinement was run without sensitivity names")
        rest = [n for n in self.sens_names if n not in self.free]
        idx = [rest.index(n) for n in others]
        g = self.gain_sample[:, idx]
        jr = sample_jacobian(self.free, self.params.as_vector(self.free))
        jo = sample_jacobian(tuple(others), self.params.as_vector(tuple(others)))
        return jr[:, None] * g / jo[None, :], tuple(others)

    def information_ratio(self) -> dict:
        """Ring-down over beat-note information of each parameter not refined (sampled space).

        w A_ii times the beat note's variance of parameter i: above 1 the ring-downs know it better
        than the beat note, and it is a candidate for refinement.
        """
        if self.prior is None or self.rd_information is None:
            return {}
        names = self.free + tuple(n for n in self.sens_names if n not in self.free)
        jac = sample_jacobian(self.prior.names, self.prior.mean)
        var = np.diag(self.prior.cov) / jac**2
        out = {}
        for i, n in enumerate(names):
            if n not in self.free and n in self.prior.names:
                out[n] = float(self.rd_information[i, i] * var[self.prior.names.index(n)])
        return out

    def draw_given(
        self, others_values, others, rng: np.random.Generator | None, gain=None
    ) -> np.ndarray:
        """Draws of the refined parameters given draws of the others (natural units, (n, n_o)).

        phi_R = phi*_R + G (phi_O - phi*_O) + e, e ~ N(0, cov) in the sampled parametrisation:
        every draw is positive where it must be (the prior's other bounds are the caller's).
        With ``rng`` None, e = 0 (the conditional mean). G is the implicit derivative
        (:meth:`conditional`) unless ``gain`` gives it (natural units, (n_free, n_o)).
        """
        others = tuple(others)
        ov = np.atleast_2d(np.asarray(others_values, float))
        n = ov.shape[0]
        centre = to_sample(self.free, self.params.as_vector(self.free))
        out = np.tile(centre, (n, 1))
        if others:
            rest = [nm for nm in self.sens_names if nm not in self.free]
            if gain is None:
                g = self.gain_sample[:, [rest.index(nm) for nm in others]]
            else:  # natural units to the sampled parametrisation's
                jr = sample_jacobian(self.free, self.params.as_vector(self.free))
                jo = sample_jacobian(others, self.params.as_vector(others))
                g = np.asarray(gain, float) * jo[None, :] / jr[:, None]
            here = to_sample(others, self.params.as_vector(others))
            d_o = to_sample(others, ov.T).T - here[None, :]
            out = out + d_o @ g.T
        if rng is not None:
            out = out + rng.multivariate_normal(np.zeros(len(self.free)), self.cov_sample, size=n)
        return from_sample(self.free, out.T).T

    @property
    def stderr(self) -> dict:
        return dict(zip(self.free, np.sqrt(np.diag(self.cov))))

    @property
    def chi2_red(self) -> float:
        return self.chi2 / max(self.dof, 1)

    def tension(self) -> dict:
        """Per refined parameter: beat-note value and u, refined value and u, shift, z (natural).

        z is the shift divided by its expected scatter when beat note and ring-downs agree; None
        for a parameter the prior does not hold, or of whose information the ring-downs carry
        less than TENSION_MIN_INFO (no test has power there).
        """
        out = {}
        for i, name in enumerate(self.free):
            has = self.prior is not None and name in self.prior.names
            out[name] = {
                "beat_note": float(self.prior_mean[i]) if has else None,
                "beat_note_u": float(np.sqrt(self.prior_cov[i, i])) if has else None,
                "refined": float(getattr(self.params, name)),
                "refined_u": float(np.sqrt(self.cov[i, i])),
                "shift_in_beat_u": (
                    float(
                        (getattr(self.params, name) - self.prior_mean[i])
                        / np.sqrt(self.prior_cov[i, i])
                    )
                    if has
                    else None
                ),
                "z": float(self.z[i]) if has and np.isfinite(self.z[i]) else None,
            }
        return out

    @property
    def tension_chi2(self) -> tuple:
        """(chi2 of all shifts, dof, p-value): the joint test of beat note against ring-downs."""
        if self.z is None:
            return (float("nan"), 0, float("nan"))
        z = self.z[np.isfinite(self.z)]
        c2 = float(np.sum(z**2))  # shifts of a scalar refinement, or their diagonal sum
        return c2, int(z.size), float(stats.chi2.sf(c2, max(z.size, 1)))

    @property
    def in_tension(self) -> bool:
        """True when any refined parameter moved by more than TENSION_Z of its expected scatter."""
        return self.z is not None and bool(np.any(np.abs(self.z[np.isfinite(self.z)]) > TENSION_Z))


# --------------------------------------------------------------------------- the shared fit


@dataclass(frozen=True)
class _Layout:
    """The truncated rows of the refinement: records, masks, weights and kinks."""

    t: np.ndarray
    y: np.ndarray  # (m, k) records
    wm: np.ndarray  # (n, k) weights of each row (0 before its t_cut)
    rows_of: np.ndarray  # (n,) record of each row
    t_cut: np.ndarray  # (n,)
    kink_s: np.ndarray  # (n,) time of each row's kink (0 for the extinction window)
    window: str

    @property
    def n_records(self) -> int:
        return self.y.shape[0]


def _per_record(layout: _Layout, values) -> np.ndarray:
    """Sum row quantities (n, ...) over each record's truncations."""
    out = np.zeros((layout.n_records, *np.shape(values)[1:]))
    np.add.at(out, layout.rows_of, values)
    return out


def _responses(layout: _Layout, tau, tf, names=(), rows=None):
    """g~ = exp(-t_k/tau) g and its tau (and H) derivatives for ``rows`` (masked, 0 elsewhere).

    g is computed once per record and grid (one grid in the ``extinction`` window).
    """
    rows = np.arange(layout.t_cut.size) if rows is None else rows
    t = layout.t
    uniq, group = np.unique(layout.t_cut[rows], return_inverse=True)
    grids = model_grids(float(t[0]), float(t[1] - t[0]), t.size, uniq, tf, layout.window)
    if layout.window == "extinction":
        group = np.zeros_like(group)
    k = t.size
    g = np.zeros((rows.size, k))
    dg = np.zeros((rows.size, k))
    dgt = np.zeros((rows.size, len(names), k)) if names else None
    for gi in np.unique(group):
        sel = np.nonzero(group == gi)[0]
        recs, inv = np.unique(layout.rows_of[rows[sel]], return_inverse=True)
        if names:
            h, dh = grid_transfer_function(grids[gi], tf, names)
            gg, dgg, dgtt = filtered_response(
                tau[recs], grids[gi], h, derivative=True, dh_k=dh, fill=0.0
            )
            dgt[sel] = dgtt[inv]
        else:
            h = grid_transfer_function(grids[gi], tf)
            gg, dgg = filtered_response(tau[recs], grids[gi], h, derivative=True, fill=0.0)
        g[sel], dg[sel] = gg[inv], dgg[inv]
    tr = tau[layout.rows_of[rows]][:, None]
    kink = layout.kink_s[rows][:, None]
    factor = np.exp(-kink / tr)
    dg = factor * (dg + kink / tr**2 * g)
    g = factor * g
    mask = layout.wm[rows] > 0
    g, dg = g * mask, dg * mask
    if names:
        dgt = factor[:, None, :] * dgt * mask[:, None, :]
    return g, dg, dgt


def _fit_taus(layout: _Layout, tf, tau0):
    """tau per record (B, b profiled), all truncations of a record at once."""
    y_rows = layout.y[layout.rows_of]
    wm = layout.wm
    s1_all = _per_record(layout, wm.sum(-1))
    sy_all = _per_record(layout, np.einsum("ij,ij->i", wm, y_rows))

    def sums(tau_sub, idx):
        rows = np.nonzero(np.isin(layout.rows_of, idx))[0]
        tau = np.zeros(layout.n_records)
        tau[idx] = tau_sub
        g, dg, _ = _responses(layout, tau, tf, rows=rows)
        w, yy = wm[rows], y_rows[rows]
        wg, wd = w * g, w * dg
        per_row = np.stack(
            [
                wg.sum(-1),
                np.einsum("ij,ij->i", wg, g),
                np.einsum("ij,ij->i", wg, yy),
                wd.sum(-1),
                np.einsum("ij,ij->i", wd, g),
                np.einsum("ij,ij->i", wd, yy),
                np.einsum("ij,ij->i", wd, dg),
            ],
            axis=1,
        )
        rec = np.zeros((layout.n_records, 7))
        np.add.at(rec, layout.rows_of[rows], per_row)
        return tuple(rec[idx].T)

    return _gauss_newton(sums, s1_all, sy_all, tau0)


def _profiled(layout: _Layout, g, dg):
    """B per record (shared by its truncations; b with it), the residuals and nuisance columns.

    For the model shapes g (and dg/dtau) of every row: returns (B (m,), residuals (n, k),
    columns [g, 1, B dg/dtau] (n, 3, k)).
    """
    wm, ro = layout.wm, layout.rows_of
    y_rows = layout.y[ro]
    s1, sg, sy, sgg, sgy = _per_record(
        layout,
        np.stack(
            [
                wm.sum(-1),
                np.einsum("ij,ij->i", wm, g),
                np.einsum("ij,ij->i", wm, y_rows),
                np.einsum("ij,ij,ij->i", wm, g, g),
                np.einsum("ij,ij,ij->i", wm, g, y_rows),
            ],
            axis=1,
        ),
    ).T
    det = s1 * sgg - sg * sg
    amp = (s1 * sgy - sg * sy) / det
    off = (sgg * sy - sg * sgy) / det
    resid = np.where(wm > 0, y_rows - amp[ro, None] * g - off[ro, None], 0.0)
    cols = np.stack([g, (wm > 0).astype(float), amp[ro, None] * dg], axis=1)  # (n, 3, k)
    return amp, resid, cols


def _evaluate(layout: _Layout, tf, free, tau_start):
    """Re-fit tau per record under ``tf``; return chi2, tau, converged, residuals, reduced J.

    The Jacobian is with respect to the natural parameters ``free``, projected orthogonally to
    each record's own B, b and tau directions over all its truncations.
    """
    tau, conv = _fit_taus(layout, tf, tau_start)
    g, dg, dgt = _responses(layout, tau, tf, names=free)
    wm, ro = layout.wm, layout.rows_of
    amp, resid, cols = _profiled(layout, g, dg)
    jth = amp[ro, None, None] * dgt  # (n, p, k)
    ctc = _per_record(layout, np.einsum("nak,nbk,nk->nab", cols, cols, wm))
    ctj = _per_record(layout, np.einsum("nak,npk,nk->nap", cols, jth, wm))
    coef = np.linalg.solve(ctc, ctj)  # (m, 3, p)
    jred = jth - np.einsum("nak,nap->npk", cols, coef[ro])
    chi2 = float((wm * resid**2).sum())
    return chi2, tau, conv, resid, jred


def _information(layout: _Layout, jred, var_rec):
    """A (summed Fisher information), B (variance of the per-record scores) and the scores."""
    wm = layout.wm
    a = np.einsum("npk,nqk,nk->pq", jred, jred, wm)
    score = _per_record(layout, jred * wm[:, None, :])
    b = np.einsum("mpk,mqk,mk->pq", score, score, var_rec)
    return a, b, score


def _weight(a, b) -> float:
    """Magnitude adjustment w = p / tr(A^-1 B) of the composite likelihood."""
    p = a.shape[0]
    tr = float(np.trace(covariance_from_fisher(a) @ b))
    return p / tr if tr > 0 and np.isfinite(tr) else 1.0


def _levenberg_marquardt(layout, start, free, tau, var_rec, prior_terms, max_iter, rtol):
    """Damped Gauss-Newton on the sampled ``free`` parameters.

    Minimises w chi2/2 + (phi - mu)' P (phi - mu)/2, tau re-fitted per record at every trial.
    Returns (H, chi2, tau, converged per record, reduced Jacobian (natural), iterations,
    converged, w).
    """
    mu, info = prior_terms
    tf = start
    chi2, tau, conv, resid, jred = _evaluate(layout, tf, free, tau)
    w = _weight(*_information(layout, jred, var_rec)[:2])

    def objective(c2, phi):
        d = phi - mu
        return 0.5 * w * c2 + 0.5 * d @ info @ d

    phi = to_sample(free, tf.as_vector(free))
    obj = objective(chi2, phi)
    lam = 1e-3
    converged = False
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 - the count is returned
        js = jred * sample_jacobian(free, tf.as_vector(free))[None, :, None]
        a = w * np.einsum("npk,nqk,nk->pq", js, js, layout.wm) + info
        grad = w * np.einsum("npk,nk,nk->p", js, layout.wm, resid) - info @ (phi - mu)
        scale = np.sqrt(np.diag(a))
        scale = np.where(scale > 0, scale, 1.0)
        a_s = a / np.outer(scale, scale)
        g_s = grad / scale
        accepted = False
        step = np.zeros_like(phi)
        for _ in range(12):
            step = np.linalg.solve(a_s + lam * np.diag(np.diag(a_s)), g_s) / scale
            trial_phi = phi + step
            try:
                trial = tf.with_vector(from_sample(free, trial_phi), free)
                if outside_support(trial, free):
                    raise ValueError("outside the physical domain")
            except ValueError:
                lam *= 10
                continue
            c2, tau2, conv2, resid2, jred2 = _evaluate(layout, trial, free, tau)
            o2 = objective(c2, trial_phi)
            if np.isfinite(o2) and o2 <= obj:
                accepted = True
                tf, chi2, tau, conv, resid, jred = trial, c2, tau2, conv2, resid2, jred2
                phi, obj = trial_phi, o2
                lam = max(lam / 10, 1e-9)
                break
            lam *= 10
        rel = np.max(np.abs(step))  # sampled space: relative for log parameters
        if not accepted or rel < rtol:
            converged = accepted or rel < 1e-6
            break
    return tf, chi2, tau, conv, jred, it, converged, w


def _layout(t, sig, t_cut, rows_of, noise, window):
    k = t.size
    dt = t[1] - t[0]
    firsts = np.array([first_index_at(t[0], dt, tc) for tc in t_cut])
    mask = np.arange(k)[None, :] >= firsts[:, None]
    kink = np.zeros(t_cut.size) if window == "extinction" else t[np.minimum(firsts, k - 1)]
    return _Layout(t, sig, mask / noise**2, rows_of, t_cut, kink, window)


def _collapsed(layout: _Layout, once: bool) -> _Layout:
    """The ``extinction`` layout with one row per record.

    Every truncation of a record sees the same model there, so the composite sum over its
    truncations is one row weighted by each sample's multiplicity (``once`` False: identical
    fit, six times less work); with ``once`` each sample counts once, which is the records' own
    likelihood.
    """
    m = layout.n_records
    if once:  # a record's rows share its noise: the largest weight is 1/sigma^2 where covered
        w = np.zeros((m, layout.t.size))
        np.maximum.at(w, layout.rows_of, layout.wm)
    else:
        w = _per_record(layout, layout.wm)
    t_first = np.full(m, np.inf)
    np.minimum.at(t_first, layout.rows_of, layout.t_cut)
    return _Layout(layout.t, layout.y, w, np.arange(m), t_first, np.zeros(m), layout.window)


def _start_taus(first_tau, rows_of, m):
    """One starting tau per record: the mean over its truncations' own fits."""
    tot, cnt = np.zeros(m), np.zeros(m)
    np.add.at(tot, rows_of, first_tau)
    np.add.at(cnt, rows_of, 1)
    return tot / np.maximum(cnt, 1)


def refine_transfer_function(
    time_s,
    signal_v,
    t_cut_s,
    start: TFParams,
    free=("f_c_hz",),
    window: str = "extinction",
    noise_v=None,
    rows_of=None,
    max_iter: int = 30,
    rtol: float = 1e-8,
    sens_names=(),
    prior: HPrior | None = None,
) -> RefinedTF:
    """Refine the ``free`` H parameters jointly over many truncated transients.

    ``time_s`` (k,) s; ``signal_v`` (m, k) V; ``t_cut_s`` (n,) s and ``rows_of`` (n,) as in
    :func:`bayes_tfcrds.fit.ringdown.fit_transients`; ``noise_v`` None, (m,) or (m, k) V (when
    None, each record's noise is estimated from a first TF-CRDS fit and then held fixed).
    ``start`` is usually the beat-note fit and ``prior`` its :class:`HPrior` (the update); without
    a prior the ring-downs alone decide. ``sens_names`` (a superset of ``free``) are the
    parameters whose effect on the refined ones :meth:`RefinedTF.conditional` returns.
    """
    free = _check_names(free)
    t = np.asarray(time_s, float)
    sig = np.asarray(signal_v, float)
    t_cut = np.atleast_1d(np.asarray(t_cut_s, float))
    rows_of = np.arange(t_cut.size) if rows_of is None else np.asarray(rows_of)
    first = fit_transients(
        t, sig, t_cut, method="tf-crds", tf=start, window=window, noise_v=noise_v, rows_of=rows_of
    )
    m, k = sig.shape
    if noise_v is None:
        # one noise level per record: the mean over its truncations of the residual RMS
        noise_v = np.sqrt(_start_taus(first.noise_v**2, rows_of, m))
    layout = _layout(t, sig, t_cut, rows_of, noise_rows(noise_v, t_cut.size, k, rows_of), window)
    n_fitted = int((layout.wm > 0).sum())
    likelihood_layout = None
    if window == "extinction":
        likelihood_layout = _collapsed(layout, once=True)
        layout = _collapsed(layout, once=False)
    var_rec = noise_rows(noise_v, m, k, np.arange(m)) ** 2
    n_free = len(free)
    if prior is not None:
        mu, info, beta, prior_others = prior.conditional(free, start)
    else:
        mu, info = np.zeros(n_free), np.zeros((n_free, n_free))
        beta, prior_others = np.zeros((n_free, 0)), ()
    tau0 = _start_taus(first.tau_s, rows_of, m)
    tf, chi2, tau, conv, jred, it, converged, w0 = _levenberg_marquardt(
        layout, start, free, tau0, var_rec, (mu, info), max_iter, rtol
    )
    jac = sample_jacobian(free, tf.as_vector(free))
    a_nat, b_nat, score = _information(layout, jred, var_rec)
    w = _weight(a_nat, b_nat)
    if abs(w / w0 - 1) > 0.05:  # the adjustment moved with H: one more pass at the final weight
        tf, chi2, tau, conv, jred, it2, converged, w = _levenberg_marquardt(
            layout, tf, free, tau, var_rec, (mu, info), max_iter, rtol
        )
        it += it2
        jac = sample_jacobian(free, tf.as_vector(free))
        a_nat, b_nat, score = _information(layout, jred, var_rec)
    a_s = a_nat * np.outer(jac, jac)
    b_s = b_nat * np.outer(jac, jac)
    p_tot = w * a_s + info
    p_inv = covariance_from_fisher(p_tot)
    cov_s = p_inv @ (w * w * b_s + info) @ p_inv
    cov_s = 0.5 * (cov_s + cov_s.T)
    cov = cov_s * np.outer(jac, jac)
    cov_naive = covariance_from_fisher(a_s + info) * np.outer(jac, jac)
    # influence of each record's samples on the refined parameters (delta method): lets callers
    # correlate the refinement's noise with other uses of the same records
    influence = jac[None, :, None] * np.einsum("pq,mqk->mpk", p_inv, w * jac[None, :, None] * score)
    z = prior_mean = prior_cov = None
    prior_chi2 = 0.0
    if prior is not None:
        phi = to_sample(free, tf.as_vector(free))
        prior_chi2 = float((phi - mu) @ info @ (phi - mu))
        has = np.diag(info) > 0
        c_prior = np.zeros_like(info)
        if has.any():
            c_prior[np.ix_(has, has)] = np.linalg.inv(info[np.ix_(has, has)])
        # the shift's expected scatter when both agree: P^-1 w (A C A + B) w P^-1
        var_shift = p_inv @ (w * w * (a_s @ c_prior @ a_s + b_s)) @ p_inv
        with np.errstate(invalid="ignore", divide="ignore"):
            share = w * np.diag(a_s) / np.diag(info)
            testable = has & (share >= TENSION_MIN_INFO)
            z = np.where(testable, (phi - mu) / np.sqrt(np.diag(var_shift)), np.nan)
        prior_mean = from_sample(free, mu)
        pj = sample_jacobian(free, prior_mean)
        prior_cov = c_prior * np.outer(pj, pj)
    sens_names = _check_names(sens_names) or free
    missing = [nm for nm in free if nm not in sens_names]
    if missing:
        raise ValueError(f"sens_names must include the refined parameters {missing}")
    rest = tuple(nm for nm in sens_names if nm not in free)
    gain, rd_info = _gain(layout, tf, free, rest, tau, w, info, beta, prior_others)
    dof = int(n_fitted - 3 * m - n_free)
    return RefinedTF(
        params=tf,
        start=start,
        free=free,
        cov=cov,
        cov_naive=cov_naive,
        chi2=chi2,
        dof=dof,
        n_iter=it,
        converged=bool(converged and conv.all()),
        tau_s=tau,
        t_cut_s=t_cut,
        rows_of=rows_of,
        weight=w,
        sens_names=sens_names,
        gain_sample=gain,
        rd_information=rd_info,
        influence=influence,
        prior=prior,
        prior_mean=prior_mean,
        prior_cov=prior_cov,
        z=z,
        cov_sample=cov_s,
        prior_chi2=prior_chi2,
        noise_v=np.asarray(noise_v, float),
        layout=layout,
        likelihood_layout=likelihood_layout,
    )


def _gain(layout, tf, free, rest, tau, w, info, beta, prior_others):
    """d phi_free / d phi_rest of the refined optimum (sampled parametrisation).

    From the estimating equations w s(phi) - P (phi_R - mu_R - beta (phi_O - phi_O*)) = 0:
    G = -(w A_RR + P)^-1 (w A_RO - P beta).
    """
    names = free + rest
    _, _, _, _, jfull = _evaluate(layout, tf, names, tau)
    jac = sample_jacobian(names, tf.as_vector(names))
    js = jfull * jac[None, :, None]
    a = np.einsum("npk,nqk,nk->pq", js, js, layout.wm)
    nr = len(free)
    a_rr, a_ro = a[:nr, :nr], a[:nr, nr:]
    p_beta = np.zeros((nr, len(rest)))
    for j, name in enumerate(rest):
        if name in prior_others:
            p_beta[:, j] = info @ beta[:, prior_others.index(name)]
    return -np.linalg.solve(w * a_rr + info, w * a_ro - p_beta), w * a


@dataclass(frozen=True)
class _GridPart:
    """What :func:`ringdown_log_likelihood` needs of one model grid that no H draw changes.

    ``rows`` on the grid and ``inv`` their records' positions among its records; H* at the grid's
    rfft frequencies ``f_hz`` (Hz); the records' input spectra ``x`` (r, n_freq); the grid
    columns of the data ``cols``; each row's B exp(-t_k/tau) ``scale`` (V, shape (1, rows, 1)).
    """

    grid: object
    rows: np.ndarray
    inv: np.ndarray
    f_hz: np.ndarray
    h_star: np.ndarray
    x: np.ndarray
    cols: np.ndarray
    scale: np.ndarray

    def model_change(self, dh, t_size: int) -> np.ndarray:
        """B exp(-t_k/tau) irfft(X delta_H) of every row (c, rows, t_size) for c changes ``dh``."""
        resp = sfft.irfft(dh[:, None, :] * self.x[None, :, :], n=self.grid.n_fft, axis=-1)
        block = np.zeros((dh.shape[0], self.x.shape[0], t_size))
        block[:, :, self.grid.first_data : self.grid.n_data] = resp[:, :, self.cols]
        return self.scale * block[:, self.inv]


def _grid_part(layout: _Layout, grid, in_group, tau, amp, tf) -> _GridPart:
    """The :class:`_GridPart` of ``grid`` for the rows ``in_group`` (computed once per grid)."""
    rows = np.nonzero(in_group)[0]
    ro = layout.rows_of
    recs, inv = np.unique(ro[rows], return_inverse=True)
    f_hz = np.arange(grid.n_fft // 2 + 1) / (grid.n_fft * grid.dt_s)
    kink = layout.kink_s[rows][None, :, None]
    factor = np.exp(-kink / tau[ro[rows]][None, :, None])
    return _GridPart(
        grid=grid,
        rows=rows,
        inv=inv,
        f_hz=f_hz,
        h_star=transfer_function(f_hz, tf),
        x=input_spectrum(tau[recs], grid),
        cols=np.arange(grid.first_data, grid.n_data) + grid.data_offset,
        scale=amp[ro[rows]][None, :, None] * factor,
    )


@dataclass(frozen=True)
class _Evidence:
    """The refined fit's side of :func:`ringdown_log_likelihood`, fixed for every draw.

    Layout, weight w, residuals, nuisance columns [g, 1, B dg/dtau] (n, 3, k), their inverse
    Gram matrix per record and the grid parts.
    """

    layout: _Layout
    weight: float
    resid: np.ndarray
    cols: np.ndarray
    ctc_inv: np.ndarray
    parts: tuple


def _evidence(refined: RefinedTF) -> _Evidence:
    tf, tau = refined.params, refined.tau_s
    if refined.likelihood_layout is not None:  # the records' own likelihood: no adjustment
        layout, weight = refined.likelihood_layout, 1.0
    else:  # ``letter`` window: each truncation its own model, the adjusted composite
        layout, weight = refined.layout, refined.weight
    wm, t = layout.wm, layout.t
    g, dg, _ = _responses(layout, tau, tf)
    amp, resid, cols = _profiled(layout, g, dg)
    ctc_inv = np.linalg.inv(_per_record(layout, np.einsum("nak,nbk,nk->nab", cols, cols, wm)))
    uniq, group = np.unique(layout.t_cut, return_inverse=True)
    grids = model_grids(float(t[0]), float(t[1] - t[0]), t.size, uniq, tf, layout.window)
    if layout.window == "extinction":
        group = np.zeros_like(group)
    parts = tuple(
        _grid_part(layout, grids[gi], group == gi, tau, amp, tf) for gi in np.unique(group)
    )
    return _Evidence(layout, weight, resid, cols, ctc_inv, parts)


# changes of H(f) over the draws written through a basis of at most this many vectors per grid,
# each draw's residual off it within SPAN_RTOL of its norm plus SPAN_ATOL of |H*| (the round-off
# floor of H - H*; |H*| as the norm of its (Re, Im) vector, hence sqrt(2) |H*|_rfft); the draws
# outside go through the model one by one. Measured on letter D2 and D4 (2000 draws each): 13-18
# vectors, the log-likelihood within 4e-9 of the draw-by-draw one where the weights are not
# negligible (SPAN_RTOL = 1e-10 left 8e-6: the nuisance projection amplifies the residual)
SPAN_MAX_RANK = 64
SPAN_RTOL = 1e-13
SPAN_ATOL = 1e-15
SPAN_CHUNK = 64


def _h_changes(part: _GridPart, tf, names, draws, chunk: int = SPAN_CHUNK):
    """delta_H = H(draw) - H* on ``part``'s grid through a greedy orthonormal basis.

    Returns (basis (r, n_freq) complex, coefficients (n, r) real, spanned (n,) bool); the basis
    is orthonormal in the real inner product of (Re, Im), so delta_H ~= coefficients @ basis.
    """
    nf = part.f_hz.size
    floor = SPAN_ATOL * np.linalg.norm(part.h_star) * np.sqrt(2.0)
    basis = np.zeros((0, 2 * nf))
    coefs, spanned = [], []
    for c0 in range(0, draws.shape[0], chunk):
        dh = transfer_function_of_draws(part.f_hz, tf, names, draws[c0 : c0 + chunk])
        dh -= part.h_star[None, :]
        rows = np.concatenate([dh.real, dh.imag], axis=1)
        basis, c, ok = extend_span(rows, basis, SPAN_RTOL, floor, SPAN_MAX_RANK)
        coefs.append(c)
        spanned.append(ok)
    r = basis.shape[0]
    coef = np.vstack([np.pad(c, ((0, 0), (0, r - c.shape[1]))) for c in coefs])
    return basis[:, :nf] + 1j * basis[:, nf:], coef, np.concatenate(spanned)


def _dchi2_exact(ev: _Evidence, tf, names, draws, chunk: int) -> np.ndarray:
    """chi2(H) - chi2(H*) to first order in H, re-profiled, draw by draw (chunks of ``chunk``)."""
    layout = ev.layout
    wm, ro = layout.wm, layout.rows_of
    out = np.zeros(draws.shape[0])
    for c0 in range(0, draws.shape[0], chunk):
        sl = slice(c0, c0 + chunk)
        dm = np.zeros((min(chunk, draws.shape[0] - c0), *wm.shape))
        for p in ev.parts:
            dh = transfer_function_of_draws(p.f_hz, tf, names, draws[sl]) - p.h_star[None, :]
            dm[:, p.rows] = p.model_change(dh, wm.shape[1])
        dm *= wm[None] > 0
        ctw = _per_record(layout, np.einsum("nak,cnk,nk->nca", ev.cols, dm, wm))  # (m, c, 3)
        coef = np.einsum("mab,mcb->mca", ev.ctc_inv, ctw)
        perp = dm - np.einsum("nak,nca->cnk", ev.cols, coef[ro])
        out[sl] = np.einsum("cnk,nk->c", perp * perp, wm) - 2 * np.einsum(
            "cnk,nk,nk->c", perp, wm, ev.resid
        )
    return out


def _dchi2_quadratic_form(ev: _Evidence, bases) -> tuple:
    """(G, b) with chi2(H) - chi2(H*) = a G a - 2 a b for delta_H = sum_j a_j basis_j.

    The model change is linear in delta_H, so the re-profiled chi2 change is a quadratic form in
    the coefficients: G_jl = <P m_j, P m_l>_w, b_j = <P m_j, r>_w (m_j the model change of
    basis vector j, P the projection off each record's nuisance columns, r the residuals).
    Assembled as <m_j, m_l>_w - c_j C^-1 c_l per record (c_j = the columns' products with m_j).
    """
    layout = ev.layout
    wm, ro = layout.wm, layout.rows_of
    sizes = [v.shape[0] for v in bases]
    k = int(sum(sizes))
    gram = np.zeros((k, k))
    b = np.zeros(k)
    ctm = np.zeros((layout.n_records, k, 3))
    start = 0
    for p, v in zip(ev.parts, bases):
        j = slice(start, start + v.shape[0])
        start += v.shape[0]
        if not v.shape[0]:
            continue
        dm = p.model_change(v, wm.shape[1]) * (wm[p.rows] > 0)  # (r, rows, k)
        w = wm[p.rows]
        gram[j, j] = np.einsum("jnk,lnk,nk->jl", dm, dm, w)
        b[j] = np.einsum("jnk,nk,nk->j", dm, w, ev.resid[p.rows])
        np.add.at(ctm[:, j], ro[p.rows], np.einsum("nak,jnk,nk->nja", ev.cols[p.rows], dm, w))
    ctr = _per_record(layout, np.einsum("nak,nk,nk->na", ev.cols, wm, ev.resid))  # (m, 3)
    ci_ctm = np.einsum("mab,mjb->mja", ev.ctc_inv, ctm)
    gram -= np.einsum("mja,mla->jl", ctm, ci_ctm)
    b -= np.einsum("mja,ma->j", ci_ctm, ctr)
    return 0.5 * (gram + gram.T), b


def ringdown_log_likelihood(refined: RefinedTF, draws, names, chunk: int = 32) -> np.ndarray:
    """Ring-down log-likelihood of H draws relative to the refined H, -w/2 [chi2(H) - chi2(H*)].

    ``draws`` (n, len(names)) natural units. The change of each record's model is taken to first
    order in H(f) (function space: B irfft(X delta_H), so a parameter that roams over decades
    does no harm), with its tau, B and b re-profiled (the change projected off their columns);
    w is the composite-likelihood adjustment. Used to weight beat-note posterior draws by the
    ring-down evidence (the joint posterior of H); a draw that the ring-downs exclude gets a
    large negative value, whatever the accuracy of the linearisation there.

    The chi2 change is a quadratic form in delta_H. The draws' delta_H span few dimensions, so
    they are written through a small orthonormal basis (:func:`_h_changes`) and the form is
    built once on it, for a fraction of the FFTs: the draw-by-draw values to about 1e-9 (each
    draw's residual off the basis is within SPAN_RTOL of its norm; the Gram form loses a few more
    digits to the nuisance projection than projecting first did). A draw the basis does not
    span goes through the model by itself (``chunk`` at a time).
    """
    tf = refined.params
    ev = _evidence(refined)
    draws = np.atleast_2d(np.asarray(draws, float))
    if draws.shape[0] == 0:
        return np.zeros(0)
    changes = [_h_changes(p, tf, names, draws) for p in ev.parts]
    spanned = np.logical_and.reduce([c[2] for c in changes])
    gram, b = _dchi2_quadratic_form(ev, [c[0] for c in changes])
    a = np.hstack([c[1] for c in changes])
    dchi2 = np.einsum("nj,jl,nl->n", a, gram, a) - 2 * a @ b
    if not spanned.all():
        dchi2[~spanned] = _dchi2_exact(ev, tf, names, draws[~spanned], chunk)
    return -0.5 * ev.weight * dchi2


def tension_lines(refined: RefinedTF) -> list:
    """Plain-text lines: each refined parameter from beat note to ring-down update, with z."""
    lines = []
    for name, t in refined.tension().items():
        if t["beat_note"] is None:
            lines.append(
                f"{name}: {t['refined']:.6g} +/- {t['refined_u']:.2g} (ring-downs only: no "
                "beat-note value to compare)"
            )
            continue
        z = (
            f"tension z = {t['z']:+.2f}"
            if t["z"] is not None
            else f"no tension test: the ring-downs hold < {TENSION_MIN_INFO:.0%} of its information"
        )
        lines.append(
            f"{name}: beat note {t['beat_note']:.6g} +/- {t['beat_note_u']:.2g} -> refined "
            f"{t['refined']:.6g} +/- {t['refined_u']:.2g} (moved {t['shift_in_beat_u']:+.2f} "
            f"beat-note u; {z})"
        )
    if refined.in_tension:
        worst = max(
            (n for n in refined.free if refined.tension()[n]["z"] is not None),
            key=lambda n: abs(refined.tension()[n]["z"]),
        )
        lines.append(
            f"finding: the ring-downs disagree with the beat note on {worst} "
            f"(|z| > {TENSION_Z:g}): H differs between the beat-note and ring-down conditions "
            "(static nonlinearity, alignment; the letter's D2) or Eq. 2 misses part of the chain"
        )
    return lines
