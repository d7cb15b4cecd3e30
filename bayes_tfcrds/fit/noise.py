"""Coloured detector noise: whiteness tests and the variance factor it implies for tau.

Detector noise reaches the digitizer through the detection chain, so consecutive samples are
correlated while each keeps the standard deviation the bundle states. chi2_red sees only that
per-sample variance and stays at 1. A least-squares fit that treats the samples as independent
still finds an unbiased tau, but its Fisher u(tau) is wrong: by the sandwich covariance of least
squares the variance of tau is raised by

    kappa = j' C j / (c(0) j' j),

where j is the fit's tau direction with the amplitude and offset profiled out, C the noise
covariance and c(0) the per-sample variance. For noise through a 5 MHz low-pass sampled at
50 MHz kappa is about 4.5 (u(tau) 2.1x too small); for white noise it is 1.

The noise power spectral density (PSD) is estimated from the pooled periodogram of the residuals
of every transient of a configuration, each normalised by its own RMS (so only the shape is
estimated; the level stays the bundle's). A fit's residuals lack the noise along the fitted
directions (1, exp(-t/tau), t exp(-t/tau)), all slow, exactly where the decay's information
lives. Above the lowest bins the periodogram is divided by the share 1 - sum_c |Q_c(f)|^2 / n
of a flat noise's power that survives (Q an orthonormal basis of the fitted directions). The
lowest bins are a model, flat or flat + flicker (f_1/f)^alpha, fitted to the raw periodogram
through the projection's exact expectation (:func:`expected_periodogram`), which holds for steep
spectra too (the flat share misstates what the projection leaves of 1/f^2 noise: kappa 5-20 %
high on few records). No correction at all left kappa 30 % low on low-passed noise and half on
flicker noise.

Two tests flag coloured noise, each at a false-alarm rate of :data:`WHITENESS_ALPHA`: Box-Pierce
on the first residual lags (correlation at short lags, exact chi2 null) and the kappa test
(kappa against 1 with its sampling sd under white noise, which catches power at low frequency
that short lags hide), with a third on the low band's flicker term. When one fires, or when a
flicker term passes Akaike's criterion (:data:`FLICKER_AIC`; a weak 1/f excess still raises
the variance of tau), :func:`with_noise_colour` sets the records'
``noise_kappa`` and every fit and likelihood downstream weights a record with
``fit_noise_v`` = noise_v sqrt(kappa): decay-time fits, the multi-ring-down refinement and the
budget's ring-down likelihoods. That effective white level is exact for the sandwich variance of
tau; the offset b, whose direction is flat, is not reported by the analyses.

Units: s, V; kappa is dimensionless.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import nnls
from scipy.stats import chi2 as chi2_dist

from bayes_tfcrds.fit.ringdown import fit_transients
from bayes_tfcrds.physics.forward import first_index_at

WHITENESS_LAGS = 20  # lags of the Box-Pierce statistic (the correlation time of a ~MHz chain)
WHITENESS_ALPHA = 1e-3  # false-alarm rate of each of the two colour tests per configuration
Z_KAPPA = 3.29  # two-sided normal quantile of WHITENESS_ALPHA, for the kappa test
DIAGNOSIS_T_CUT_S = 4e-6  # the letter's middle truncation time (s)
PAIR_TAU_REL = 0.03  # records paired for the noise estimate differ in tau by at most 3 %
MIN_PAIRS = 4
MIN_KEPT = 0.5  # bins that kept less of the noise's power are modelled, not divided
MIN_LOW_BINS = 4  # low bins the two PSD models of the low band are fitted to, at least
# The lowest bins of the twice-padded grid are modelled as flat or flat + flicker: 64 bins span
# 1/(2 n dt) ... 32/(n dt), about 200 kHz for 16384 samples at 20 ns, beyond the bandwidth
# 1/(2 pi tau) of every decay the letter's cavity gives (tau >= 3.7 us: 43 kHz).
LOW_BINS = 64
KEPT_ROWS = 16  # rows over which the projection's share of each bin is averaged
FLICKER_ALPHAS = (0.5, 1.0, 1.5, 2.0)
# chi2 gain for the flicker term: the 1e-3 point of chi2 with 2 dof (b, and alpha from 4 values)
FLICKER_DCHI2 = 13.8
# chi2 gain above which the flicker term enters the estimate of kappa: Akaike's criterion, 2 per
# added parameter. Estimating is not testing: a weak 1/f excess that the 1e-3 test misses still
# raises the variance of tau (a knee near the decay's bandwidth: kappa ~ 1.5-2).
FLICKER_AIC = 4.0


@dataclass(frozen=True)
class NoiseDiagnosis:
    """Whiteness of one configuration's ring-down residuals and the variance factor of tau.

    ``rho`` (WHITENESS_LAGS + 1,) the pooled residual autocorrelation at lags 0, 1, ...;
    ``q`` the Box-Pierce statistic n_tot sum rho_k^2 (chi2 with ``dof`` under white noise) and
    ``p_value``; ``kappa`` (m,) the variance factor of tau per record (the median where a record
    was not diagnosed); ``z_kappa`` the low band's flat level over the mean PSD, minus 1, in its
    white-noise sd; ``low_band`` the PSD model of the lowest bins;
    ``level_v`` (m,) the residual RMS per record (V, NaN where not diagnosed);
    ``residual_model`` the fit whose residuals were used.
    """

    rho: np.ndarray
    q: float
    dof: int
    p_value: float
    kappa: np.ndarray
    z_kappa: float
    low_band: LowBand
    level_v: np.ndarray
    n_samples: int
    t_cut_s: float
    residual_model: str

    @property
    def white(self) -> bool:
        """True unless a test rejects white noise (each at a false-alarm rate of about 1e-3).

        Box-Pierce (short-lag correlation), the low band's level against the mean PSD (low-pass
        colour), the low band's flicker term (1/f noise).
        """
        return (
            self.p_value >= WHITENESS_ALPHA
            and abs(self.z_kappa) < Z_KAPPA
            and not self.low_band.flicker_significant
        )

    @property
    def kappa_applied(self) -> bool:
        """True when the fits must weight with kappa: coloured, or a flicker term Akaike keeps.

        The tests warn at a 1e-3 false-alarm rate; the estimate of kappa keeps a flicker term
        on weaker evidence (:data:`FLICKER_AIC`), because on a few dozen records a knee near
        the decay's bandwidth (kappa ~ 1.5-2) is missed by the test half the time and u(tau)
        would be 20-30 % short. The flicker term enters kappa with its Akaike weight
        (:attr:`LowBand.flicker_weight`, 0.5 at the criterion). On 150 simulated white-noise
        configurations of 8 record pairs this applied kappa on 7 (kappa 1.1-1.4: u(tau) up to
        20 % conservative), and on 125 of 150 with a flicker knee at 8 kHz (kappa ~ 1.7).
        """
        return not self.white or self.low_band.has_flicker

    @property
    def kappa_median(self) -> float:
        return float(np.median(self.kappa))

    def summary_line(self) -> str:
        """One line for a reader: white, or coloured and what that does to u(tau)."""
        head = (
            f"noise: Box-Pierce ({self.dof} lags, {self.n_samples} residual samples of "
            f"{self.residual_model}) p = {self.p_value:.3g}, rho(1) = {self.rho[1]:+.3f}; "
            f"kappa = {self.kappa_median:.3g} (z = {self.z_kappa:+.1f})"
        )
        if not self.kappa_applied:
            return head + "; white: u(tau) from the stated noise"
        k = self.kappa
        verdict = (
            "COLOURED"
            if not self.white
            else f"white at the 1e-3 tests, but a flicker term improves the low band by "
            f"dchi2 = {self.low_band.dchi2:.1f} > {FLICKER_AIC:g} (Akaike)"
        )
        return (
            head + f"; {verdict}: every fit and likelihood weights with noise_v sqrt(kappa), "
            f"kappa {k.min():.3g}-{k.max():.3g} over the records (u(tau) x {np.sqrt(k.min()):.2f}"
            f"-{np.sqrt(k.max()):.2f})"
        )

    def to_dict(self) -> dict:
        return {
            "white": bool(self.white),
            "kappa_applied": bool(self.kappa_applied),
            "flicker_dchi2": float(self.low_band.dchi2),
            "box_pierce": {"lags": self.dof, "q": float(self.q), "p_value": float(self.p_value)},
            "rho_1": float(self.rho[1]),
            "kappa_median": self.kappa_median,
            "kappa_min": float(np.min(self.kappa)),
            "kappa_max": float(np.max(self.kappa)),
            "z_kappa": float(self.z_kappa),
            "alpha": WHITENESS_ALPHA,
            "t_cut_s": self.t_cut_s,
            "residual_model": self.residual_model,
        }


def _two_sided(x: np.ndarray) -> np.ndarray:
    """Sum over a full FFT grid of a real signal's quantity given on its rfft grid (last axis)."""
    return x[..., 0] + 2.0 * x[..., 1:-1].sum(-1) + x[..., -1]


def fitted_basis(t_s: np.ndarray, tau_s: np.ndarray) -> np.ndarray:
    """Orthonormal basis (rows, n, 3) of each row's fitted directions 1, e, t e (e = exp(-t/tau)).

    ``t_s`` (n,) fitted sample times from extinction (s); ``tau_s`` (rows,). The H filter, near 1
    where the decay's spectrum lives, is left out: only the span matters.
    """
    e = np.exp(-t_s[None, :] / tau_s[:, None])
    x = np.stack([np.ones_like(e), e, t_s[None, :] / tau_s[:, None] * e], axis=-1)
    return np.linalg.qr(x)[0]


def profiled_tau_direction(basis: np.ndarray) -> np.ndarray:
    """The tau column (t e) with 1 and e projected out: the third basis vector, per row."""
    return basis[..., 2]


@dataclass(frozen=True)
class LowBand:
    """The PSD model of the lowest bins, where the slow decays' information lives.

    Two models of bins 1..``n_bins`` (f_1 the first bin, PSD units of the normalised residuals):
    flat, S(f) = ``flat``; and flat + flicker, S(f) = ``level`` + ``flicker`` (f_1/f)^``alpha``.
    ``dchi2`` the improvement of the second over the first; ``rel_sd`` the relative sd of the
    flat level under white noise (the kappa test's scale). The PSD used for kappa averages the
    two with their Akaike weights (:attr:`flicker_weight`), so a flicker term the data barely
    support raises kappa only in part; it is significant (a colour flag) above
    :data:`FLICKER_DCHI2`.
    """

    flat: float
    level: float
    flicker: float
    alpha: float
    dchi2: float
    n_bins: int
    rel_sd: float

    @property
    def flicker_weight(self) -> float:
        """Akaike weight of flat + flicker against flat: 1 / (1 + exp(-(dchi2 - 2k) / 2)), k 2."""
        if self.flicker <= 0:
            return 0.0
        return float(1.0 / (1.0 + np.exp(-(self.dchi2 - FLICKER_AIC) / 2.0)))

    @property
    def has_flicker(self) -> bool:
        """Akaike prefers the flicker model (dchi2 > :data:`FLICKER_AIC`): kappa applies."""
        return self.flicker > 0 and self.dchi2 > FLICKER_AIC

    @property
    def flicker_significant(self) -> bool:
        """The flicker term passes the 1e-3 test: the noise is flagged coloured."""
        return self.flicker > 0 and self.dchi2 > FLICKER_DCHI2

    def psd(self, bins: np.ndarray) -> np.ndarray:
        """The model-averaged PSD at rfft ``bins`` (bin 0 takes bin 1's value)."""
        f = np.maximum(np.asarray(bins, float), 1.0)
        w = self.flicker_weight
        if w == 0.0:
            return np.full(f.shape, self.flat)
        return (1.0 - w) * self.flat + w * (self.level + self.flicker * f**-self.alpha)


def expected_periodogram(psd: np.ndarray, basis: np.ndarray, qf=None) -> np.ndarray:
    """E[:func:`pooled_periodogram`] of fit residuals (I - Q Q') x, x noise with PSD ``psd``.

    ``psd`` on the rfft grid of n_fft >= 2n (its autocovariance c = irfft(psd) is the model's:
    the same C as :func:`colour_factors`), ``basis`` (rows, n, 3) each residual's fitted
    directions Q; the mean over rows. Per frequency, with F the DFT on the grid and P = Q Q',

        E|F (I - P) x|^2 / n = [F C F' - 2 Re F P C F' + F P C P F'] / n   (diagonals),

    exactly, whatever the PSD's shape: the share 1 - sum_c |Q_c(f)|^2 / n that a flat PSD
    keeps is the special case C = I. Where the PSD is steep across the fitted directions'
    narrow spectrum (flicker noise with a knee near the decay's bandwidth) that share is wrong,
    and kappa with it; this expectation is what the low band is fitted through. ``qf`` is
    rfft(basis, n_fft, axis=1) when the caller has it (one per basis, whatever the PSD).
    """
    n_fft = 2 * (psd.size - 1)
    rows, n, _ = basis.shape
    c = np.fft.irfft(psd, n_fft)
    lag = np.minimum(np.arange(n_fft), n_fft - np.arange(n_fft))
    tri = np.where(lag < n, (n - lag) * c, 0.0)  # sum_k (n - |k|) c(k) e^{-i w k}
    direct = np.fft.rfft(tri).real
    qf = np.fft.rfft(basis, n_fft, axis=1) if qf is None else qf  # (rows, nf, 3)
    cq = np.fft.irfft(psd[None, :, None] * qf, n_fft, axis=1)[:, :n, :]  # C Q
    cqf = np.fft.rfft(cq, n_fft, axis=1)
    cross = np.sum(qf.real * cqf.real + qf.imag * cqf.imag, axis=-1)
    m = np.einsum("rnc,rnd->rcd", basis, cq)  # Q' C Q
    quad = np.einsum("rfc,rcd,rfd->rf", qf, m, qf.conj()).real
    return (direct[None, :] - 2.0 * cross + quad).mean(axis=0) / n


def _band_shapes(n_fft: int, n_bins: int, alpha) -> np.ndarray:
    """PSD on the rfft grid: 1 on bins 0..n_bins (alpha None), else (1/max(k, 1))^alpha there."""
    k = np.arange(n_fft // 2 + 1, dtype=float)
    shape = np.ones_like(k) if alpha is None else np.maximum(k, 1.0) ** -alpha
    return np.where(k <= n_bins, shape, 0.0)


def _weighted_nnls(g: np.ndarray, y: np.ndarray, sd: np.ndarray) -> tuple[np.ndarray, float]:
    """(coefficients >= 0, chi2) of y ~ g @ coef with per-bin sd."""
    coef = nnls(g / sd[:, None], y / sd)[0]
    return coef, float(np.sum(((y - g @ coef) / sd) ** 2))


def low_band(
    pgram: np.ndarray,
    kept: np.ndarray,
    basis: np.ndarray,
    high: np.ndarray,
    n_rows: int,
    qf=None,
) -> LowBand:
    """Fit S(f) = a and S(f) = a + b (f_1/f)^alpha on bins 0..L to the raw low periodogram.

    ``pgram`` the pooled periodogram of the residuals, ``kept`` the share of a flat noise's
    power their fits kept per bin, ``basis`` (rows, n, 3) their fitted directions, ``high`` the
    PSD above bin L (zero at and below it), L = :data:`LOW_BINS`. Each model is carried through
    the fit's projection exactly (:func:`expected_periodogram`), so bins 1..L that kept at least
    :data:`MIN_KEPT` of a flat noise's power are compared with what the model predicts there,
    not divided by a share that holds for flat spectra only.
    Each bin's variance is 2 E^2 / n_rows (a pooled periodogram; neighbours of the padded grid
    correlated), E the flat model's expectation. alpha is chosen from :data:`FLICKER_ALPHAS`,
    a and b >= 0. ``qf`` is rfft(basis, n_fft, axis=1) when the caller has it.
    """
    n_fft = 2 * (pgram.size - 1)
    n_low = min(LOW_BINS, pgram.size - 2)
    qf = np.fft.rfft(basis, n_fft, axis=1) if qf is None else qf
    g_flat = expected_periodogram(_band_shapes(n_fft, n_low, None), basis, qf)
    g_high = expected_periodogram(high, basis, qf)
    bins = np.arange(1, n_low + 1)
    bins = bins[kept[bins] >= MIN_KEPT]
    if bins.size < MIN_LOW_BINS:
        raise ValueError(
            f"noise diagnosis: {bins.size} low-frequency bins survive the fit's projection, "
            f"{MIN_LOW_BINS} needed (records of {basis.shape[1]} samples after t_cut are too short)"
        )
    y = pgram[bins] - g_high[bins]
    gf = g_flat[bins, None]
    # the null level: the mean PSD with the flat share divided out (1 for white noise)
    null = _two_sided(pgram / np.maximum(kept, MIN_KEPT)) / n_fft
    sd_null = np.sqrt(2.0 / n_rows) * (null * g_flat[bins] + g_high[bins])
    # the flat level, then its expectation as the variance model of the model comparison (two
    # passes suffice: the variance only weights bins); never below a tenth of the null level
    sd = sd_null
    for _ in range(2):
        (flat,), _ = _weighted_nnls(gf, y, sd)
        sd = np.sqrt(2.0 / n_rows) * (max(flat, 0.1 * null) * g_flat[bins] + g_high[bins])
    (flat,), chi2_flat = _weighted_nnls(gf, y, sd)
    best = (chi2_flat, flat, 0.0, 1.0)
    for alpha in FLICKER_ALPHAS:
        g = np.column_stack(
            [gf[:, 0], expected_periodogram(_band_shapes(n_fft, n_low, alpha), basis, qf)[bins]]
        )
        coef, chi2 = _weighted_nnls(g, y, sd)
        if chi2 < best[0]:
            best = (chi2, float(coef[0]), float(coef[1]), alpha)
    chi2, a, b, alpha = best
    # the kappa test's scale: the sd of the flat level under white noise at the null level
    info = np.sum((g_flat[bins] / sd_null) ** 2)
    return LowBand(
        flat=float(flat),
        level=a,
        flicker=b,
        alpha=alpha,
        dchi2=chi2_flat - chi2,
        n_bins=int(bins.size),
        rel_sd=float(1.0 / (np.sqrt(info) * null)),
    )


def pooled_periodogram(z: np.ndarray, n_fft: int) -> np.ndarray:
    """sum_rows |rfft(z, n_fft)|^2 / (rows n): the spectrum of the pooled autocovariance of ``z``.

    Zero-padding to ``n_fft`` >= 2n keeps the implied autocovariance linear (no circular wrap).
    """
    zf = np.fft.rfft(z, n_fft, axis=-1)
    return np.mean(zf.real**2 + zf.imag**2, axis=0) / z.shape[1]


def noise_spectrum(z: np.ndarray, basis: np.ndarray, n_fft: int, pgram=None) -> tuple:
    """(PSD shape on the rfft grid of ``n_fft``, LowBand) of the noise behind residuals ``z``.

    ``z`` (rows, n) normalised residuals, ``basis`` their fits' directions. Above bin
    :data:`LOW_BINS` the pooled periodogram is divided by the share of a flat noise's power that
    survived the fit's projection, 1 - sum_c |Q_c(f)|^2 / n averaged over rows (near 1 there,
    where the PSD is smooth on the scale of Q's spectrum). The lowest bins, where the slow decays'
    information lives and the projection removed most, are the :class:`LowBand` model fitted
    through the projection's exact expectation. ``pgram`` is :func:`pooled_periodogram` of ``z``
    when the caller has it already.
    """
    n = z.shape[1]
    pgram = pooled_periodogram(z, n_fft) if pgram is None else pgram
    # the projection is a mean over rows of smooth functions of tau: 16 rows spanning them suffice
    some = np.unique(np.linspace(0, basis.shape[0] - 1, min(KEPT_ROWS, basis.shape[0])).astype(int))
    qf = np.fft.rfft(basis[some], n_fft, axis=1)
    kept = 1.0 - np.mean(np.sum(qf.real**2 + qf.imag**2, axis=-1), axis=0) / n
    psd = pgram / np.maximum(kept, MIN_KEPT)
    low = np.arange(0, min(LOW_BINS, psd.size - 2) + 1)
    high = psd.copy()
    high[low] = 0.0
    band = low_band(pgram, kept, basis[some], high, z.shape[0], qf)
    psd[low] = band.psd(low)
    return psd, band


def colour_factors(psd: np.ndarray, j: np.ndarray) -> np.ndarray:
    """kappa = j' C j / (c(0) j' j) per row of ``j`` (rows, n), C the noise with PSD ``psd``.

    On the rfft grid of length n_fft >= 2n: j' C j = sum_f PSD(f) |J(f)|^2 / n_fft over the full
    grid and c(0) = sum_f PSD(f) / n_fft.
    """
    n_fft = 2 * (psd.size - 1)
    spec = np.fft.rfft(j, n_fft, axis=-1)
    power = spec.real**2 + spec.imag**2
    return _two_sided(power * psd) / (_two_sided(psd) * _two_sided(power) / n_fft)


def record_pairs(tau_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Disjoint pairs of records with nearly equal decay times: (first indices, second indices).

    A model error (an H a little off, an effect the model lacks) leaves the same slow shape, per
    unit amplitude, in the residuals of every record with the same tau, and the colour tests
    would take it for 1/f noise. The difference of two such records' residuals cancels it and
    keeps the noise: two independent draws of one stationary process, so the same PSD shape.
    Records are sorted by tau and paired in turn; pairs whose taus differ by more than
    :data:`PAIR_TAU_REL` are dropped unless fewer than :data:`MIN_PAIRS` would remain.
    """
    order = np.argsort(tau_s)
    n = order.size // 2
    a, b = order[0 : 2 * n : 2], order[1 : 2 * n : 2]
    close = np.abs(tau_s[a] - tau_s[b]) <= PAIR_TAU_REL * tau_s[a]
    if np.sum(close) >= MIN_PAIRS:
        a, b = a[close], b[close]
    return a, b


def diagnose_noise(
    ringdowns, tf=None, window: str = "extinction", t_cut_s: float = DIAGNOSIS_T_CUT_S
) -> NoiseDiagnosis:
    """Whiteness tests and tau variance factors from one fit of every usable transient.

    The residuals come from TF-CRDS at ``tf`` (the detector's noise is best seen through the best
    model of the transients) or, without ``tf``, from plain CRDS, at ``t_cut_s`` (s; at most half
    the record).
    """
    t = ringdowns.time_s
    t_cut = min(float(t_cut_s), float(t[-1]) / 2)
    good = np.nonzero(~np.asarray(ringdowns.clipped, bool))[0]
    m = ringdowns.signal_v.shape[0]
    noise = ringdowns.noise_v
    method = "crds" if tf is None else "tf-crds"
    fits = fit_transients(
        t,
        ringdowns.signal_v[good],
        np.full(good.size, t_cut),
        method=method,
        tf=tf,
        window=window,
        noise_v=None if noise is None else np.asarray(noise)[good],
        keep_residuals=True,
    )
    use = np.nonzero(fits.converged & (fits.tau_s > 0))[0]
    if use.size < 4:
        raise ValueError("noise diagnosis: fewer than four transients could be fitted")
    first = int(first_index_at(t[0], ringdowns.dt_s, t_cut))
    r = fits.residuals_v[use, first:]
    level = np.sqrt(np.mean(r**2, axis=-1))
    a, b = record_pairs(fits.tau_s[use])
    amp = fits.amplitude_v[use, None]
    d = r[a] / amp[a] - r[b] / amp[b]
    z = d / np.sqrt(np.mean(d**2, axis=-1))[:, None]
    n_fft = 1 << int(np.ceil(np.log2(2 * z.shape[1])))
    basis = fitted_basis(t[first:], fits.tau_s[use])
    pgram = pooled_periodogram(z, n_fft)
    psd, band = noise_spectrum(z, basis[np.concatenate([a, b])], n_fft, pgram)
    j = profiled_tau_direction(basis)
    kappa_used = colour_factors(psd, j)
    acov = np.fft.irfft(pgram, n_fft)[: WHITENESS_LAGS + 1]
    rho = acov / acov[0]
    q = float(z.size * np.sum(rho[1:] ** 2))
    kappa = np.full(m, float(np.median(kappa_used)))
    kappa[good[use]] = kappa_used
    level_v = np.full(m, np.nan)
    level_v[good[use]] = level
    return NoiseDiagnosis(
        rho=rho,
        q=q,
        dof=WHITENESS_LAGS,
        p_value=float(chi2_dist.sf(q, WHITENESS_LAGS)),
        kappa=kappa,
        z_kappa=float((band.flat / (_two_sided(psd) / n_fft) - 1.0) / band.rel_sd),
        low_band=band,
        level_v=level_v,
        n_samples=int(z.size),
        t_cut_s=t_cut,
        residual_model=method,
    )


def with_noise_colour(ringdowns, diagnosis: NoiseDiagnosis):
    """``ringdowns`` with ``noise_kappa`` set where kappa applies (else unchanged).

    Setting it twice replaces, never compounds. A bundle without noise_v gets the residual RMS of
    the diagnosis as its noise level, since a level estimated per fit could not carry kappa.
    """
    if not diagnosis.kappa_applied:
        return ringdowns
    noise = ringdowns.noise_v
    if noise is None:
        level = diagnosis.level_v
        noise = np.where(np.isfinite(level), level, np.nanmedian(level))
    return replace(ringdowns, noise_v=noise, noise_kappa=diagnosis.kappa)


def account_for_noise(config, tf=None, window: str = "extinction", t_cut_s=DIAGNOSIS_T_CUT_S):
    """(config with its ring-downs' noise colour accounted for, its NoiseDiagnosis).

    ``tf`` the beat-note H for TF-CRDS residuals; None for plain CRDS residuals.
    """
    diagnosis = diagnose_noise(config.ringdowns, tf=tf, window=window, t_cut_s=t_cut_s)
    return replace(config, ringdowns=with_noise_colour(config.ringdowns, diagnosis)), diagnosis
