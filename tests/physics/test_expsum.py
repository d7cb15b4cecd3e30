"""The exponential-sum fit path (physics/expsum.py) against direct sums and the dense FFT path."""

import numpy as np
import pytest

from bayes_tfcrds.fit.ringdown import fit_transients
from bayes_tfcrds.physics.detection_chain import chain_from_tf
from bayes_tfcrds.physics.expsum import TAYLOR_RADIUS, BlockedData, SumsModel, model_sums, powers
from bayes_tfcrds.physics.transfer_function import TFParams

DT, K, T0 = 20e-9, 3000, -1.01e-6  # K not a multiple of the block; t0 off the grid
T = T0 + DT * np.arange(K)
D2_LIKE = TFParams(f_c_hz=6.0e4, a_r=15.0, f_r_hz=6.0e6, gamma_r=0.7, n_r=2.0, variant="causal")


@pytest.mark.parametrize("lam", [-1 / 4e-6, -1 / 3e-3, -2.0e7 + 3.0e7j, -1.0])
@pytest.mark.parametrize("n", [1, 127, 128, 129, 2999])
def test_model_sums_equal_direct_sums(lam, n):
    # lam = -1 s^-1 makes z = exp(lam dt) = 1 - 2e-8: the closed geometric form would lose ~8 digits
    j = np.arange(n)
    u = j * DT
    direct = [np.sum(u**m * np.exp(lam * u)) for m in range(3)]
    zi, zb = powers(np.array([lam]), DT, int(np.ceil(K / 128)))
    got = model_sums(zi, zb, np.array([n]), DT, 2)
    for m in range(3):
        # summation order differs: a few ulps per term, relative to the sum of |terms|
        scale = np.sum(np.abs(u**m * np.exp(lam * u)))
        assert abs(got[m][0] - direct[m]) <= 1e-13 * scale * np.sqrt(n)


def test_data_sums_and_moments_equal_direct_sums():
    rng = np.random.default_rng(1)
    y = rng.normal(size=(3, K)) + 2.0
    first = np.array([0, 57, 400])
    rows_of = np.array([0, 1, 2])
    w = np.array([1.0, 4.0, 0.25])
    d = BlockedData(y, first, rows_of, w, DT)
    lam = np.array([[-1 / 2e-6, -3e6 + 1e7j], [-1 / 9e-6, -1e5], [-1 / 30e-6, -2e7]])
    got = d.data_sums(lam, np.arange(3))
    lam0 = lam[:, 0].real
    mom = d.moments(lam0, np.arange(3))
    for r in range(3):
        u = DT * np.arange(K - first[r])
        yy = w[r] * y[r, first[r] :]
        for c in range(2):
            ref = np.sum(yy * np.exp(lam[r, c] * u))
            assert abs(got[r, c] - ref) <= 1e-13 * np.sum(np.abs(yy * np.exp(lam[r, c].real * u)))
        s = -1 / lam0[r]
        for k in range(mom.shape[1]):
            ref = np.sum(yy * (u / s) ** k * np.exp(lam0[r] * u))
            assert abs(mom[r, k] - ref) <= 1e-12 * np.sum(
                np.abs(yy) * (u / s) ** k * np.exp(lam0[r] * u)
            )
    assert d.sum_wy == pytest.approx([np.sum(w[r] * y[r, first[r] :]) for r in range(3)], rel=1e-13)


def test_taylor_moments_give_the_data_sums_inside_their_radius():
    rng = np.random.default_rng(2)
    y = 0.5 * np.exp(-np.clip(T, 0, None) / 5e-6) + 1e-3 * rng.normal(size=K)
    first = np.array([200])
    d = BlockedData(y[None], first, np.array([0]), np.array([1.0]), DT)
    m = SumsModel(d, None, T[first], np.array([3e-6]))
    rows = np.array([0])
    m._data_at(np.array([5e-6]), rows)  # centre the moments at 5 us
    for tau in (5e-6 / (1 + 0.9 * TAYLOR_RADIUS), 5e-6 / (1 - 0.9 * TAYLOR_RADIUS)):
        y0, y1 = m._data_at(np.array([tau]), rows)
        assert m.lam0[0] == pytest.approx(-1 / 5e-6)  # no recentring inside the radius
        u = DT * np.arange(K - first[0])
        e = y[first[0] :] * np.exp(-u / tau)
        assert y0[0] == pytest.approx(e.sum(), rel=1e-13)
        assert y1[0] == pytest.approx((u * e).sum(), rel=1e-12)


def _exact_transients(chain, taus, amp=0.6, off=2e-3):
    return off + amp * chain.ringdown_response(T, taus)


def test_exact_chain_data_recovered_exactly_by_the_sum_path():
    # the sum path is the continuous convolution itself: noiseless exact-chain data must give
    # tau to rounding (the FFT path errs by its discretisation, ~1e-8 relative)
    chain = chain_from_tf(D2_LIKE)
    taus = np.array([1.5e-6, 4e-6, 12e-6])
    y = _exact_transients(chain, taus)
    tc = np.array([2e-6, 3e-6, 4e-6])
    f = fit_transients(T, y, tc, "tf-crds", D2_LIKE, "extinction", noise_v=np.full(3, 1e-4))
    np.testing.assert_allclose(f.tau_s, taus, rtol=1e-10)
    np.testing.assert_allclose(f.amplitude_v, 0.6, rtol=1e-9)
    # chi2 = y'Wy - beta'X'Wy cancels to ~1e-16 y'Wy (~1e-8 here), far below any dof
    assert np.all(f.converged) and np.all(f.chi2 < 1e-6)


def test_sum_path_equals_dense_path():
    rng = np.random.default_rng(3)
    chain = chain_from_tf(D2_LIKE)
    taus = rng.uniform(1e-6, 15e-6, 8)
    sigma = 2e-4
    y = _exact_transients(chain, taus) + sigma * rng.normal(size=(8, K))
    rows = np.repeat(np.arange(8), 3)
    tc = np.tile([2e-6, 4e-6, 6e-6], 8)
    one = np.full(8, sigma)
    per_sample = np.full((8, K), sigma)  # takes the dense (FFT) path
    for method in ("crds", "tf-crds"):
        fast = fit_transients(
            T, y, tc, method, D2_LIKE, "extinction", noise_v=one, rows_of=rows, keep_residuals=True
        )
        dense = fit_transients(
            T,
            y,
            tc,
            method,
            D2_LIKE,
            "extinction",
            noise_v=per_sample,
            rows_of=rows,
            keep_residuals=True,
        )
        # CRDS: the same model, so agreement to rounding; TF-CRDS: exact convolution vs the DFT
        # model, whose discretisation (H aliased above Nyquist) moves tau by ~1e-4 u(tau)
        tol = 1e-8 if method == "crds" else 2e-3
        assert np.max(np.abs(fast.tau_s - dense.tau_s) / dense.tau_u_s) < tol
        np.testing.assert_allclose(fast.tau_u_s, dense.tau_u_s, rtol=1e-6)
        np.testing.assert_allclose(fast.chi2, dense.chi2, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(fast.residuals_v, dense.residuals_v, atol=1e-3 * sigma)
        # chi2 from the sums equals the sum of squared residuals
        np.testing.assert_allclose(fast.chi2, (fast.residuals_v**2).sum(-1) / sigma**2, rtol=1e-8)


def test_letter_window_and_fractional_order_keep_the_fft_path():
    chain = chain_from_tf(D2_LIKE)
    y = _exact_transients(chain, np.array([4e-6]))
    ext = fit_transients(T, y, [3e-6], "tf-crds", D2_LIKE, "extinction", noise_v=[1e-4])
    let = fit_transients(T, y, [3e-6], "tf-crds", D2_LIKE, "letter", noise_v=[1e-4])
    # the letter window models the history before t_cut as flat: a visible tau bias (Fig. 3)
    assert abs(let.tau_s[0] / ext.tau_s[0] - 1) > 1e-3
    frac = fit_transients(
        T,
        y,
        [3e-6],
        "tf-crds",
        TFParams(**{**D2_LIKE.__dict__, "n_r": 1.9}),
        "extinction",
        noise_v=[1e-4],
    )
    assert np.isfinite(frac.tau_s[0]) and frac.converged[0]


# --- where tau meets a real pole of the chain (p -> -1/tau) ---------------------------------
# The two exponentials of the closed form coincide there and their coefficients diverge and
# cancel; the chain's response and the fit's sums must stay exact (review finding: a fit with
# |1 + p tau| <= 1e-4 used to return NaN).
SLOW = TFParams(
    f_c_hz=1.938e4, a_r=19.28, f_r_hz=7e6, gamma_r=0.7, n_r=2.0, variant="causal"
)  # letter-D3


def _tau_at_real_pole(chain):
    p = min(chain.poles, key=lambda q: abs(complex(q).imag))
    return -1.0 / complex(p).real


def _quadrature_response(chain, t, tau):
    """D x(t) + int_0^inf h(s) x(t - s) ds by adaptive quadrature (not the closed form)."""
    from scipy import integrate

    def h(s):
        return float(chain.impulse_response(np.array([s]))[0])

    def x(v):
        return 1.0 if v < 0 else np.exp(-v / tau)

    def q(f, lo, hi):
        cuts = [lo] + [v for v in (1e-6, 50e-6) if lo < v < hi] + [hi]
        return sum(
            integrate.quad(f, a, b, limit=400, epsabs=1e-15, epsrel=1e-13)[0]
            for a, b in zip(cuts, cuts[1:])
        )

    return (
        chain.direct * x(t)
        + (q(lambda s: h(s) * x(t - s), 0.0, t) if t > 0 else 0.0)
        + q(h, t, 600e-6)
    )


@pytest.mark.parametrize("delta", [0.0, 1e-9, -1e-5, 1e-3, 0.3])
def test_ringdown_response_is_exact_at_a_real_pole(delta):
    chain = chain_from_tf(SLOW)
    tau = _tau_at_real_pole(chain) * (1 + delta)
    ts = np.array([0.0, 0.3e-6, 2e-6, 8e-6, 30e-6])
    g, dg = chain.ringdown_response(ts, [tau], derivative=True)
    ref = [_quadrature_response(chain, t, tau) for t in ts]
    # quadrature to ~1e-13 absolute; the closed form was off by ~eps/|1 + p tau| before
    np.testing.assert_allclose(g[0], ref, rtol=0, atol=1e-12)
    h = 1e-5 * tau  # central difference: O(h^2) ~ 1e-10 relative
    fd = (chain.ringdown_response(ts, [tau + h]) - chain.ringdown_response(ts, [tau - h])) / (2 * h)
    np.testing.assert_allclose(dg, fd, rtol=0, atol=1e-8 * np.max(np.abs(dg)))


def test_fits_with_tau_at_a_real_pole_converge_to_the_truth():
    chain = chain_from_tf(SLOW)
    tau_p = _tau_at_real_pole(chain)
    taus = tau_p * (1 + np.array([0.0, 1e-6, -1e-4, 1e-3, 3e-2]))
    t = T0 + DT * np.arange(16384)
    y = 2e-3 + 0.6 * chain.ringdown_response(t, taus)
    tc = np.full(taus.size, 4e-6)
    f = fit_transients(t, y, tc, "tf-crds", SLOW, "extinction", noise_v=np.full(taus.size, 1e-4))
    assert np.all(f.converged)
    np.testing.assert_allclose(f.tau_s, taus, rtol=1e-10)  # noiseless exact data: to rounding
    rng = np.random.default_rng(5)
    sigma = 1e-4
    noisy = y + sigma * rng.standard_normal(y.shape)
    fast = fit_transients(
        t, noisy, tc, "tf-crds", SLOW, "extinction", noise_v=np.full(taus.size, sigma)
    )
    dense = fit_transients(
        t, noisy, tc, "tf-crds", SLOW, "extinction", noise_v=np.full(y.shape, sigma)
    )
    assert np.all(fast.converged) and np.all(np.isfinite(fast.tau_u_s))
    # against the FFT path (a different evaluation of the same model): its discretisation, ~1e-3 u
    assert np.max(np.abs(fast.tau_s - dense.tau_s) / dense.tau_u_s) < 1e-2
    np.testing.assert_allclose(fast.tau_u_s, dense.tau_u_s, rtol=1e-4)


@pytest.mark.parametrize("method", ["crds", "tf-crds"])
def test_chi2_stays_right_at_very_high_signal_to_noise(method):
    # chi2 = y'Wy - beta'X'Wy carries ~eps y'Wy; at sigma = 1e-8 V that is ~1e4 x chi2, so the
    # rows that need it get chi2 from their residuals instead
    rng = np.random.default_rng(2)
    chain = chain_from_tf(D2_LIKE)
    taus = np.array([3e-6, 9e-6])
    sigma = 1e-8
    y = (
        1.0 + chain.ringdown_response(T, taus)
        if method == "tf-crds"
        else 1.0 + np.exp(-np.clip(T, 0, None) / taus[:, None])
    ) + sigma * rng.standard_normal((2, K))
    f = fit_transients(
        T,
        y,
        [2e-6, 2e-6],
        method,
        D2_LIKE,
        "extinction",
        noise_v=np.full(2, sigma),
        keep_residuals=True,
    )
    direct = (f.residuals_v**2).sum(-1) / sigma**2
    np.testing.assert_allclose(f.chi2, direct, rtol=1e-6)
    # and chi2/dof is what white noise gives: 1 +/- 5 sd of sqrt(2/dof)
    assert np.all(np.abs(f.chi2 / f.dof - 1) < 5 * np.sqrt(2 / f.dof))
