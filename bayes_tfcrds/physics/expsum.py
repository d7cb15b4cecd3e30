"""Weighted sums of exponential-sum ring-down models on a uniform grid, without forming the model.

When the detection chain is rational (poles p, residues r; ``physics/detection_chain.py``) its
response to the ring-down input ``x = 1`` (t < 0), ``exp(-t/tau)`` (t >= 0) is, for t >= 0, exactly

    g(t) = Re[ H(-1/tau) exp(-t/tau) + sum_p C_p(tau) exp(p t) ],  C_p = r_p (1/(p + 1/tau) - 1/p),

and plain CRDS is the single term exp(-(t - t_cut)/tau). The variable-projection Gauss-Newton step
needs only weighted sums of g, dg/dtau, 1 and the data y (``fit.ringdown._gauss_newton``). On a
uniform grid with one weight per transient every such sum is a sum of ``u^m exp(lam u)`` (u = time
after the first fitted sample), with or without y. Splitting the sample index into blocks,
``j = B b + i``, turns the data sums into one small matrix product per iteration and the model sums
into O(B + n/B) closed sums per row, so a fit costs one pass over the data per iteration, the same
for TF-CRDS as for CRDS, and no FFT.

This is not an approximation of the FFT model of ``physics/forward.py``: it is the continuous-time
convolution that the FFT model discretises, exact for the rational chains of Eq. 2 with n_r = 2.

Units: time and tau in s, lam and poles in 1/s, data in V, weights in 1/V^2.
"""

from __future__ import annotations

import numpy as np

BLOCK = 128
TAYLOR_TERMS = 13  # moments kept for the data sums at a moved tau
TAYLOR_RADIUS = 0.05  # |(lam - lam0) / lam0| beyond which the moments are recomputed


def powers(lam, dt_s, n_blocks, block=BLOCK):
    """exp(lam u) on the block grid u = (B b + i) dt, split as (z_i (..., B), z_b (..., n_blocks)).

    ``lam`` (...,) in 1/s, real or complex with Re(lam) <= 0 (u >= 0, so nothing overflows).
    The product of two splits is the split of the summed exponents.
    """
    lam = np.asarray(lam)[..., None]
    return np.exp(lam * dt_s * np.arange(block)), np.exp(lam * (block * dt_s) * np.arange(n_blocks))


def model_sums(z_i, z_b, n, dt_s, max_order=2):
    """sum_{j < n} (j dt)^m exp(lam j dt) for m = 0..max_order (units s^m), from a split.

    ``z_i`` (..., B) and ``z_b`` (..., nb) from :func:`powers`, ``n`` broadcastable to (...).
    Exact block decomposition of the geometric-type series: no 1/(1 - z) cancellation as
    lam dt -> 0, and O(B + nb) work per sum.
    """
    B, nb = z_i.shape[-1], z_b.shape[-1]
    i = np.arange(B, dtype=float)
    b = np.arange(nb, dtype=float)
    shape = np.broadcast_shapes(z_i.shape[:-1], z_b.shape[:-1], np.shape(n))
    z_i = np.broadcast_to(z_i, shape + (B,))
    z_b = np.broadcast_to(z_b, shape + (nb,))
    n = np.broadcast_to(np.asarray(n), shape)
    full, rem = n // B, n % B
    ip = [z_i * i**k for k in range(max_order + 1)]
    p = [x.sum(-1) for x in ip]
    r = [
        np.take_along_axis(np.cumsum(x, -1), np.maximum(rem - 1, 0)[..., None], -1)[..., 0]
        * (rem > 0)
        for x in ip
    ]  # partial last block
    in_full = b < full[..., None]
    q = [np.where(in_full, z_b * b**k, 0.0).sum(-1) for k in range(max_order + 1)]
    tail = np.where(
        full < nb, np.take_along_axis(z_b, np.minimum(full, nb - 1)[..., None], -1)[..., 0], 0.0
    )
    nf = full.astype(float)
    out = [q[0] * p[0] + tail * r[0]]
    if max_order >= 1:
        out.append((B * q[1] * p[0] + q[0] * p[1] + tail * (B * nf * r[0] + r[1])) * dt_s)
    if max_order >= 2:
        out.append(
            (
                B * B * q[2] * p[0]
                + 2 * B * q[1] * p[1]
                + q[0] * p[2]
                + tail * (B * B * nf * nf * r[0] + 2 * B * nf * r[1] + r[2])
            )
            * dt_s**2
        )
    return out


class BlockedData:
    """Rows of weighted data ``w y`` on t >= t_first, laid out as (rows, blocks, BLOCK).

    ``y`` (m, k) V, ``first`` (n,) index of each row's first fitted sample, ``rows_of`` (n,)
    transient of each row, ``weight`` (n,) 1/V^2 (one per row), ``dt_s`` s. Row r's sample
    ``first[r] + j`` sits at block ``j // BLOCK``, slot ``j % BLOCK``; the padding is zero.
    """

    def __init__(self, y, first, rows_of, weight, dt_s, block: int = BLOCK):
        y = np.asarray(y, float)
        first = np.asarray(first, int)
        w = np.asarray(weight, float)
        self.dt = float(dt_s)
        self.block = block
        self.n = y.shape[1] - first  # fitted samples per row
        self.n_blocks = int(-(-self.n.max() // block))
        data = np.zeros((first.size, self.n_blocks * block))
        for f in np.unique(first):  # one copy per distinct t_cut
            sel = np.nonzero(first == f)[0]
            data[sel, : y.shape[1] - f] = y[rows_of[sel], f:] * w[sel, None]
        self.weight = w
        self.sum_wy = data.sum(-1)  # sum w y
        self.sum_wyy = np.einsum("ij,ij->i", data, data) / w  # sum w y^2
        self.data = data.reshape(first.size, self.n_blocks, block)

    def _rows(self, rows):
        return (
            self.data
            if rows.size == self.data.shape[0] and np.all(rows == np.arange(rows.size))
            else self.data[rows]
        )

    def project(self, cols, rows):
        """sum_i (w y)[r, b, i] cols[r, i, c] -> (rows, blocks, c); complex cols as two reals."""
        d = self._rows(rows)
        if np.iscomplexobj(cols):
            c = cols.shape[-1]
            out = d @ np.concatenate([cols.real, cols.imag], -1)
            return out[..., :c] + 1j * out[..., c:]
        return d @ cols

    def data_sums(self, lam, rows):
        """sum_j w y_j exp(lam u_j) per row and per lam column: ``lam`` (len(rows), c) 1/s."""
        z_i, z_b = powers(lam, self.dt, self.n_blocks, self.block)  # (r, c, B), (r, c, nb)
        prod = self.project(np.swapaxes(z_i, -1, -2), rows)  # (r, nb, c)
        return np.einsum("rcb,rbc->rc", z_b, prod)

    def moments(self, lam0, rows, n_terms=TAYLOR_TERMS + 1):
        """M_k = sum_j w y_j (u_j/s)^k exp(lam0 u_j), k < n_terms, s = -1/lam0 (rows, n_terms).

        One pass over the data for all k: (u/s)^k is expanded binomially over the block split
        u = (B b + i) dt, every term non-negative, so nothing cancels.
        """
        lam0 = np.asarray(lam0, float)
        s = -1.0 / lam0
        z_i, z_b = powers(lam0, self.dt, self.n_blocks, self.block)
        x_i = (self.dt * np.arange(self.block))[None, :] / s[:, None]
        x_b = (self.block * self.dt * np.arange(self.n_blocks))[None, :] / s[:, None]
        cols = np.stack([z_i * x_i**j for j in range(n_terms)], -1)  # (r, B, K)
        prod = self.project(cols, rows)  # (r, nb, K)
        out = np.zeros((lam0.size, n_terms))
        binom = [[1.0]]
        for k in range(1, n_terms):
            prev = binom[-1]
            binom.append([1.0] + [prev[j - 1] + prev[j] for j in range(1, k)] + [1.0])
        xb_pow = [np.ones_like(x_b)]
        for _ in range(1, n_terms):
            xb_pow.append(xb_pow[-1] * x_b)
        for k in range(n_terms):
            acc = np.zeros_like(x_b)
            for j in range(k + 1):
                acc = acc + binom[k][j] * xb_pow[k - j] * prod[..., j]
            out[:, k] = np.einsum("rb,rb->r", z_b, acc)
        return out


def chain_coefficients(chain, tau_s, t_first_s):
    """Coefficients of g(t_first + u) = a e^{-u/tau} + sum_p c_p e^{p u} and their tau derivatives.

    ``chain`` a ``RationalChain``, ``tau_s`` (n,) s, ``t_first_s`` (n,) s after extinction (>= 0).
    Returns a, da (n,), c, dc (n, poles) complex (dimensionless, per s for the derivatives).
    """
    p = np.asarray(chain.poles, complex)[None, :]
    r = np.asarray(chain.residues, complex)[None, :]
    tau = np.asarray(tau_s, float)[:, None]
    tf = np.asarray(t_first_s, float)[:, None]
    inv = 1.0 / (p + 1.0 / tau)
    h_at = chain.direct - np.sum(r * inv, -1)  # H(s = -1/tau), real for real tau
    dh_at = -np.sum(r * inv * inv, -1) / tau[:, 0] ** 2
    e = np.exp(-tf[:, 0] / tau[:, 0])
    a = (h_at * e).real
    da = (dh_at * e + h_at * e * tf[:, 0] / tau[:, 0] ** 2).real
    ep = np.exp(p * tf)
    c = r * (inv - 1.0 / p) * ep
    dc = r * inv * inv / tau**2 * ep
    return a, da, c, dc


NEAR_POLE = 0.05  # |1 + p tau| below which a row's sums are formed densely (see SumsModel)


class SumsModel:
    """The seven weighted sums of the Gauss-Newton step for g = a e^{-u/tau} + sum_p c_p e^{p u}.

    ``chain`` None is plain CRDS, g = exp(-(t - t_cut)/tau); otherwise a ``RationalChain`` and
    g is its exact ring-down response. ``t_first_s`` (n,) s is the time of each row's first
    fitted sample, ``t_cut_s`` (n,) s its truncation time.

    The data sums at -1/tau come from Taylor moments about a centre tau0 per row, recomputed
    (one data pass) only when tau has moved by more than TAYLOR_RADIUS of it; between
    recentrings a Gauss-Newton iteration touches no data at all.
    """

    def __init__(self, data: BlockedData, chain, t_first_s, t_cut_s):
        self.d = data
        self.chain = chain
        self.t_first = np.asarray(t_first_s, float)
        self.t_cut = np.asarray(t_cut_s, float)
        n_rows = self.t_first.size
        self.lam0 = np.full(n_rows, np.nan)
        self.mom = np.zeros((n_rows, TAYLOR_TERMS + 1))
        self.p = np.zeros(0, complex)
        if chain is not None and len(chain.poles):
            p = np.asarray(chain.poles, complex)
            self.p = p
            self.zp = powers(p, data.dt, data.n_blocks, data.block)  # (np, B), (np, nb)
            rows = np.arange(n_rows)
            # tau-independent sums, once: the data against every pole (one pass), the model
            # against pole pairs (they depend on the row only through its sample count)
            self.dp = data.data_sums(np.broadcast_to(p, (n_rows, p.size)), rows)
            n_u, inv = np.unique(data.n, return_inverse=True)
            pq = p[:, None] + p[None, :]
            zi, zb = powers(pq, data.dt, data.n_blocks, data.block)
            self.mpq = model_sums(zi[None], zb[None], n_u[:, None, None], data.dt, 0)[0][inv]
            self.mp = model_sums(self.zp[0][None], self.zp[1][None], n_u[:, None], data.dt, 0)[0][
                inv
            ]

    def coefficients(self, tau, rows):
        if self.chain is None:
            lag = self.t_first[rows] - self.t_cut[rows]
            a = np.exp(-lag / tau)
            z = np.zeros((tau.size, 0), complex)
            return a, a * lag / tau**2, z, z
        return chain_coefficients(self.chain, tau, self.t_first[rows])

    def _data_at(self, tau, rows):
        """sum w y e^{-u/tau} and sum w y u e^{-u/tau} from the moments (recentred where needed)."""
        lam = -1.0 / tau
        far = ~(np.abs(lam / self.lam0[rows] - 1.0) <= TAYLOR_RADIUS)
        if np.any(far):
            sel = rows[far]
            self.lam0[sel] = lam[far]
            self.mom[sel] = self.d.moments(lam[far], sel)
        s = -1.0 / self.lam0[rows]
        x = (lam - self.lam0[rows]) * s
        k = np.arange(TAYLOR_TERMS)
        fact = np.cumprod(np.concatenate([[1.0], np.arange(1.0, TAYLOR_TERMS)]))
        coef = x[:, None] ** k / fact  # (r, K)
        m = self.mom[rows]
        return np.einsum("rk,rk->r", coef, m[:, :-1]), s * np.einsum("rk,rk->r", coef, m[:, 1:])

    def _dense_near_pole(self, tau, rows):
        """The seven sums from g and dg/dtau on the sample grid (rows with tau near a pole)."""
        d, w = self.d, self.d.weight[rows]
        u = d.dt * np.arange(d.n_blocks * d.block)
        t = self.t_first[rows, None] + u[None, :]
        g, dg = self.chain.ringdown_response(t, tau, derivative=True)
        inside = np.arange(u.size)[None, :] < d.n[rows, None]
        g, dg = np.where(inside, g, 0.0), np.where(inside, dg, 0.0)
        wy = d.data[rows].reshape(rows.size, -1)  # w y, zero-padded
        return (
            w * g.sum(-1),
            w * np.einsum("rj,rj->r", g, g),
            np.einsum("rj,rj->r", wy, g),
            w * dg.sum(-1),
            w * np.einsum("rj,rj->r", dg, g),
            np.einsum("rj,rj->r", wy, dg),
            w * np.einsum("rj,rj->r", dg, dg),
        )

    def __call__(self, tau, rows):
        """(sg, sgg, sgy, sd, sdg, sdy, sdd) per row: weighted sums of g, dg/dtau and y.

        Where tau is within NEAR_POLE of a real chain pole (|1 + p tau| small) the closed sums
        lose about eps/|1 + p tau|^4 to cancellation between the two coincident exponentials;
        those rows (rare: one tau value per pole) are summed densely over their samples instead.
        """
        near = np.zeros(rows.size, bool)
        if self.p.size:
            near = np.min(np.abs(1.0 + self.p[None, :] * tau[:, None]), -1) < NEAR_POLE
        if np.any(near):
            out = [np.empty(rows.size) for _ in range(7)]
            for o, v in zip(out, self._dense_near_pole(tau[near], rows[near])):
                o[near] = v
            if np.any(~near):
                for o, v in zip(out, self._closed(tau[~near], rows[~near])):
                    o[~near] = v
            return tuple(out)
        return self._closed(tau, rows)

    def _closed(self, tau, rows):
        d, w = self.d, self.d.weight[rows]
        a, da, c, dc = self.coefficients(tau, rows)
        it2 = 1.0 / tau**2
        n = d.n[rows]
        y0, y1 = self._data_at(tau, rows)
        e_i, e_b = powers(-1.0 / tau, d.dt, d.n_blocks, d.block)
        e0, e1 = model_sums(e_i, e_b, n, d.dt, 1)
        f0, f1, f2 = model_sums(e_i * e_i, e_b * e_b, n, d.dt, 2)
        sg = w * a * e0
        sd = w * (da * e0 + a * it2 * e1)
        sgy = a * y0
        sdy = da * y0 + a * it2 * y1
        sgg = w * a * a * f0
        sdg = w * (a * da * f0 + a * a * it2 * f1)
        sdd = w * (da * da * f0 + 2 * a * da * it2 * f1 + a * a * it2 * it2 * f2)
        if self.p.size:
            zi = e_i[:, None, :] * self.zp[0][None]  # e^{(p - 1/tau) u}
            zb = e_b[:, None, :] * self.zp[1][None]
            m0, m1 = model_sums(zi, zb, n[:, None], d.dt, 1)  # (r, np)
            mp, dp, mpq = self.mp[rows], self.dp[rows], self.mpq[rows]
            a_, da_, it2_ = a[:, None], da[:, None], it2[:, None]
            sg = sg + w * np.real(np.sum(c * mp, -1))
            sd = sd + w * np.real(np.sum(dc * mp, -1))
            sgy = sgy + np.real(np.sum(c * dp, -1))
            sdy = sdy + np.real(np.sum(dc * dp, -1))
            sgg = sgg + w * np.real(
                2 * a * np.sum(c * m0, -1) + np.einsum("rp,rpq,rq->r", c, mpq, c)
            )
            sdg = sdg + w * np.real(
                np.sum((a_ * dc + da_ * c) * m0 + a_ * c * it2_ * m1, -1)
                + np.einsum("rp,rpq,rq->r", c, mpq, dc)
            )
            sdd = sdd + w * np.real(
                2 * np.sum(dc * (da_ * m0 + a_ * it2_ * m1), -1)
                + np.einsum("rp,rpq,rq->r", dc, mpq, dc)
            )
        return sg, sgg, sgy, sd, sdg, sdy, sdd

    def response(self, t_s, tau, rows):
        """Dense g (rows, k) at times t_s (s), zero before each row's first fitted sample."""
        t = np.asarray(t_s, float)[None, :]
        if self.chain is None:
            g = np.exp(-np.clip(t - self.t_cut[rows, None], 0, None) / tau[:, None])
        else:
            g = self.chain.ringdown_response(
                np.broadcast_to(
                    np.clip(t, self.t_first[rows, None], None), (rows.size, t.shape[1])
                ),
                tau,
            )
        return np.where(t >= self.t_first[rows, None] - 1e-3 * self.d.dt, g, 0.0)
