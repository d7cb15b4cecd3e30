"""Multi-ring-down refinement of H(f) (letter Appendix B).

One transfer function is shared by many truncated transients (several tau, several t_cut
each); the chosen H parameters (default f_c) are free, and each truncated transient has its
own tau, B and b. B and b are solved exactly and tau is re-fitted for every H step, so the
outer Gauss-Newton works in the few H dimensions only; its Jacobian is the exact reduced one
(the H derivatives projected orthogonally to each transient's own B, b, tau directions).

The same record enters once per t_cut, so the rows share noise: the parameter covariance is
the sandwich A^-1 (sum over records of s_i s_i^T) A^-1 with s_i the record's score summed over
its truncations, not the naive A^-1 that would count the same noise up to c times.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bayes_tfcrds.core.linalg import covariance_from_fisher
from bayes_tfcrds.fit.ringdown import (
    _dense_sums,
    _gauss_newton,
    _solve_linear,
    _TfCrds,
    fit_transients,
    noise_rows,
)
from bayes_tfcrds.physics.forward import filtered_response, first_index_at, grid_transfer_function
from bayes_tfcrds.physics.transfer_function import PARAM_NAMES, TFParams


@dataclass(frozen=True)
class RefinedTF:
    """Refined H.

    ``params``, covariance ``cov`` of ``free`` (natural units), the naive covariance that ignores
    shared noise (``cov_naive``, for comparison), chi2 and the per-row fits at the optimum.
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
    sens_names: tuple = ()
    a_full: np.ndarray | None = None
    b_full: np.ndarray | None = None
    influence: np.ndarray | None = None  # d theta_free / d y: (records, n_free, samples)

    def conditional(self, others: dict):
        """Linear map of the refined parameters on the others held fixed in the refinement.

        For the ``sens_names`` not refined, a change delta_O moves the refined optimum by
        ``-A_RR^-1 A_RO delta_O`` (Gauss-Newton on the estimating equations), and the refined
        estimate scatters with the sandwich covariance ``cov`` around it. Returns
        (gain matrix (n_free, n_others), names of the others) for the names in ``others``.
        """
        if self.a_full is None:
            raise ValueError("refinement was run without sensitivity names")
        idx_r = [self.sens_names.index(n) for n in self.free]
        idx_o = [self.sens_names.index(n) for n in others]
        a_rr = self.a_full[np.ix_(idx_r, idx_r)]
        a_ro = self.a_full[np.ix_(idx_r, idx_o)]
        return -np.linalg.solve(a_rr, a_ro), tuple(others)

    @property
    def stderr(self) -> dict:
        return dict(zip(self.free, np.sqrt(np.diag(self.cov))))

    @property
    def chi2_red(self) -> float:
        return self.chi2 / max(self.dof, 1)


def _evaluate(t, y, wm, t_cut, tf, free, window, tau_start):
    """Re-fit tau per row under ``tf``; return chi2, tau, residuals and reduced Jacobian."""
    model = _TfCrds(t, t_cut, tf, window, wm > 0)
    tau, conv = _gauss_newton(
        _dense_sums(model, y, wm), wm.sum(-1), np.einsum("ij,ij->i", wm, y), tau_start
    )
    n, k = y.shape
    p = len(free)
    uniq, group = np.unique(t_cut, return_inverse=True)
    grids = model.grids
    resid = np.zeros((n, k))
    jred = np.zeros((n, p, k))
    for gi in np.unique(group):
        sel = np.nonzero(group == gi)[0]
        h, dh = grid_transfer_function(grids[gi], tf, free)
        g, dg, dgt = filtered_response(tau[sel], grids[gi], h, derivative=True, dh_k=dh, fill=0.0)
        w = wm[sel]
        amp, off = _solve_linear(w, g, y[sel])
        resid[sel] = np.where(w > 0, y[sel] - amp[:, None] * g - off[:, None], 0.0)
        cols = np.stack([g, np.ones_like(g), amp[:, None] * dg], axis=1)  # (n, 3, k)
        jth = amp[:, None, None] * dgt  # (n, p, k)
        ctc = np.einsum("nak,nbk,nk->nab", cols, cols, w)
        ctj = np.einsum("nak,npk,nk->nap", cols, jth, w)
        coef = np.linalg.solve(ctc, ctj)  # (n, 3, p)
        jred[sel] = jth - np.einsum("nak,nap->npk", cols, coef)
    chi2 = float((wm * resid**2).sum())
    return chi2, tau, conv, resid, jred


def _levenberg_marquardt(t, y, wm, t_cut, start, free, window, tau, max_iter, rtol):
    """Damped Gauss-Newton (Levenberg-Marquardt) on the ``free`` H parameters.

    tau is re-fitted per row at every trial. Returns (H, chi2, tau, converged per row, reduced
    Jacobian, iterations, converged).
    """
    tf = start
    chi2, tau, conv, resid, jred = _evaluate(t, y, wm, t_cut, tf, free, window, tau)
    lam = 1e-3
    converged = False
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 - the count is returned
        a = np.einsum("npk,nqk,nk->pq", jred, jred, wm)
        grad = np.einsum("npk,nk,nk->p", jred, wm, resid)
        scale = np.sqrt(np.diag(a))
        a_s = a / np.outer(scale, scale)
        g_s = grad / scale
        theta = tf.as_vector(free)
        accepted = False
        for _ in range(12):
            step = np.linalg.solve(a_s + lam * np.diag(np.diag(a_s)), g_s) / scale
            try:
                trial = tf.with_vector(theta + step, free)
            except ValueError:
                lam *= 10
                continue
            c2, tau2, conv2, resid2, jred2 = _evaluate(t, y, wm, t_cut, trial, free, window, tau)
            if c2 <= chi2:
                accepted = True
                tf, chi2, tau, conv, resid, jred = trial, c2, tau2, conv2, resid2, jred2
                lam = max(lam / 10, 1e-9)
                break
            lam *= 10
        rel = np.max(np.abs(step) / np.maximum(np.abs(theta), 1e-12))
        if not accepted or rel < rtol:
            converged = accepted or rel < 1e-6
            break

    return tf, chi2, tau, conv, jred, it, converged


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
) -> RefinedTF:
    """Refine the ``free`` H parameters jointly over many truncated transients.

    ``time_s`` (k,) s; ``signal_v`` (m, k) V; ``t_cut_s`` (n,) s and ``rows_of`` (n,) as in
    :func:`bayes_tfcrds.fit.ringdown.fit_transients`; ``noise_v`` None, (m,) or (m, k) V (when None,
    each record's noise is estimated from a first TF-CRDS fit and then held fixed).
    ``start`` is usually the beat-note fit.
    """
    free = tuple(free)
    for name in free:
        if name not in PARAM_NAMES:
            raise ValueError(
                f"unknown transfer-function parameter {name!r}; choose from {PARAM_NAMES}"
            )
    t = np.asarray(time_s, float)
    sig = np.asarray(signal_v, float)
    t_cut = np.atleast_1d(np.asarray(t_cut_s, float))
    rows_of = np.arange(t_cut.size) if rows_of is None else np.asarray(rows_of)
    first = fit_transients(
        t, sig, t_cut, method="tf-crds", tf=start, window=window, noise_v=noise_v, rows_of=rows_of
    )
    if noise_v is None:
        # one noise level per record: the mean over its truncations of the residual RMS
        rec = np.zeros(sig.shape[0])
        cnt = np.zeros(sig.shape[0])
        np.add.at(rec, rows_of, first.noise_v**2)
        np.add.at(cnt, rows_of, 1)
        noise_v = np.sqrt(rec / np.maximum(cnt, 1))
    n, k = t_cut.size, t.size
    y = sig[rows_of]
    firsts = np.array([first_index_at(t[0], t[1] - t[0], tc) for tc in t_cut])
    mask = np.arange(k)[None, :] >= firsts[:, None]
    noise = noise_rows(noise_v, n, k, rows_of)
    wm = mask / noise**2

    tf, chi2, tau, conv, jred, it, converged = _levenberg_marquardt(
        t, y, wm, t_cut, start, free, window, first.tau_s, max_iter, rtol
    )

    m = sig.shape[0]
    var = noise_rows(noise_v, m, k, np.arange(m)) ** 2

    def fisher_meat_score(j):
        a_ = np.einsum("npk,nqk,nk->pq", j, j, wm)
        # score of each record summed over its truncations, then its noise variance
        u = np.zeros((m, j.shape[1], k))
        np.add.at(u, rows_of, j * wm[:, None, :])
        return a_, np.einsum("mpk,mqk,mk->pq", u, u, var), u

    a, b, score = fisher_meat_score(jred)
    a_inv = covariance_from_fisher(a)
    cov = a_inv @ b @ a_inv
    # influence of each record's samples on the refined parameters (delta method): lets callers
    # correlate the refinement's noise with other uses of the same records
    influence = np.einsum("pq,mqk->mpk", a_inv, score)
    sens_names = tuple(sens_names) or free
    a_full = b_full = None
    if sens_names != free:
        missing = [nm for nm in free if nm not in sens_names]
        if missing:
            raise ValueError(f"sens_names must include the refined parameters {missing}")
        _, _, _, _, jfull = _evaluate(t, y, wm, t_cut, tf, sens_names, window, tau)
        a_full, b_full, _ = fisher_meat_score(jfull)
    else:
        a_full, b_full = a, b
    dof = int(mask.sum() - 3 * n - len(free))
    return RefinedTF(
        params=tf,
        start=start,
        free=free,
        cov=cov,
        cov_naive=a_inv,
        chi2=chi2,
        dof=dof,
        n_iter=it,
        converged=bool(converged and conv.all()),
        tau_s=tau,
        t_cut_s=t_cut,
        rows_of=rows_of,
        sens_names=sens_names,
        a_full=a_full,
        b_full=b_full,
        influence=influence,
    )
