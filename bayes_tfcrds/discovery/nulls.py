"""Null distributions of the gap metrics, by parametric bootstrap under the current model.

A gap metric (:mod:`bayes_tfcrds.discovery.workflow`) is written as a z-score from an analytic
null: the transient chi2 against its degrees of freedom, the binned residual means, the largest
periodogram ordinate, tau and A against t_cut, the spectrum's chi2 and strongest sinusoid. Those
nulls assume white noise and efficient, nested estimators; on data with nothing missing they can
sit at z = 4-5 (a clean campaign: tau(t_cut) z = 5.5, time structure z = 4.4). Here each metric's
null is measured instead: ring-downs are simulated from the fitted model itself (decay times from
the fitted line, the fitted offsets, amplitudes and extension parameters, the fitted H) with noise
of the recorded colour, and every metric is computed on them by the same
:func:`~bayes_tfcrds.discovery.workflow.evaluate` that computed it on the data, with an H drawn
from H's uncertainty (the data were analysed with an estimated H, not the true one).

A metric's calibrated score is ``z_cal = (z - mean*) / (sd* sqrt(1 + 1/B))``, the analytic z
corrected for the location and scale the bootstrap finds (its B replicates: mean*, sd*), referred to
Student's t with B - 1 degrees of freedom: the predictive law of one more draw from a normal null
whose mean and sd are estimated from B draws. The analytic form supplies the shape of the tail, the
bootstrap its location and scale. The beat note's chi2 and A/A_ref - 1 are not resampled (the
ring-downs do not enter the beat note, and the CMDS reference is another instrument): their analytic
z stands, referred to the normal law.

The noise of the simulated ring-downs has the recorded colour: an autoregressive model fitted to
the pre-extinction samples, where the signal is constant and only noise varies, scaled to each
transient's stated noise level. Its order (at most :data:`MAX_AR_ORDER`) is chosen by BIC: AIC
picked order 5 on white noise in one of three campaigns, which moved the time-structure null by
2.5. Fewer than :data:`MIN_PRE_SAMPLES` such samples: white noise.

Units: SI (s, V); the metrics are dimensionless.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import linalg, signal, stats

from bayes_tfcrds.core.constants import C
from bayes_tfcrds.fit.spectrum import absorption_from_tau
from bayes_tfcrds.fit.transient_model import model_transients
from bayes_tfcrds.physics.transfer_function import outside_support

#: metrics whose null is measured by the bootstrap (the ring-downs and what is fitted from them)
RESAMPLED = (
    "transient_chi2",
    "transient_time_structure",
    "transient_freq_structure",
    "tau_tcut",
    "area_tcut",
    "spectrum_chi2",
    "spectrum_structure",
)
#: replicates per model state: sd* known to 1/sqrt(2 (B - 1)) ~ 11 %, accounted for by Student's t
N_BOOT = 40
MAX_AR_ORDER = 6
MIN_PRE_SAMPLES = 256


@dataclass(frozen=True)
class NoiseModel:
    """Autoregressive noise of unit variance: x_t = sum_i phi_i x_(t-i) + e_t."""

    phi: np.ndarray  # (p,)

    def draw(self, shape: tuple, rng: np.random.Generator) -> np.ndarray:
        """Unit-variance noise of this colour, ``shape`` = (rows, samples)."""
        n_rows, n = shape
        if self.phi.size == 0:
            return rng.standard_normal(shape)
        burn = 20 * self.phi.size + 50
        a = np.concatenate([[1.0], -self.phi])
        x = signal.lfilter([1.0], a, rng.standard_normal((n_rows, n + burn)), axis=-1)[:, burn:]
        return x / np.sqrt(self.variance_per_innovation())

    def variance_per_innovation(self) -> float:
        """Stationary variance of the process for unit innovation variance."""
        p = self.phi.size
        # Yule-Walker: the impulse response's energy is the stationary variance
        h = signal.lfilter([1.0], np.concatenate([[1.0], -self.phi]), np.r_[1.0, np.zeros(4096)])
        return float(h @ h) if p else 1.0


def pre_extinction_noise(ringdowns) -> NoiseModel:
    """AR noise model from the samples before extinction (each transient demeaned), order by BIC."""
    t = ringdowns.time_s
    pre = np.asarray(ringdowns.signal_v, float)[:, t < 0]
    if pre.size < MIN_PRE_SAMPLES or pre.shape[1] < 4 * MAX_AR_ORDER:
        return NoiseModel(np.zeros(0))
    x = pre - pre.mean(axis=1, keepdims=True)
    n_eff = x.size - x.shape[0]
    acov = np.array([np.sum(x[:, : x.shape[1] - k] * x[:, k:]) for k in range(MAX_AR_ORDER + 1)])
    acov = acov / x.size
    best, best_bic = np.zeros(0), n_eff * np.log(acov[0])
    for p in range(1, MAX_AR_ORDER + 1):
        phi = linalg.solve_toeplitz(acov[:p], acov[1 : p + 1])
        s2 = acov[0] - phi @ acov[1 : p + 1]
        if s2 <= 0:
            break
        bic = n_eff * np.log(s2) + p * np.log(n_eff)
        if bic < best_bic:
            best, best_bic = phi, bic
    return NoiseModel(np.asarray(best, float))


def simulated_ringdowns(config, ev, noise: NoiseModel, rng):
    """Ring-downs drawn from the model fitted in ``ev`` (the parametric bootstrap's data).

    Decay times come from the line fit at the first t_cut (so the spectrum's null is the fitted
    line, not the measured decay times with their noise), offsets, amplitudes and extension
    parameters from the transient fits there; samples before that t_cut are the measured ones
    (no fit reads them).
    """
    rd = config.ringdowns
    lf = ev.lines[0]
    a, ua = absorption_from_tau(ev.tau[:, 0], ev.tau_u[:, 0])
    a_model = a + lf.residuals_norm * ua  # residuals_norm = (model - data) / u
    tau_model = 1.0 / (C * a_model)
    spec = ev.state.spec()
    nu = np.asarray(rd.nu_hz, float)[ev.good]
    v, mask = model_transients(
        rd.time_s, float(ev.t_cuts[0]), spec, tau_model, ev.coef_first, nu_hz=nu
    )
    level = np.asarray(rd.noise_v, float)[ev.good]
    level = level[:, None] if level.ndim == 1 else level
    noisy = v + level * noise.draw(v.shape, rng)
    sig = np.array(rd.signal_v, float)
    sig[ev.good] = np.where(mask, noisy, sig[ev.good])
    return replace(rd, signal_v=sig)


def _inside_support(draw, free, tries: int = 20):
    """The first of ``tries`` calls of ``draw()`` (a TFParams) inside H's support in ``free``.

    None when every draw leaves it: the caller keeps its H undrawn.
    """
    for _ in range(tries):
        p = draw()
        if not outside_support(p, free):
            return p
    return None


def _draw_params(params, free, cov, rng, tries: int = 20):
    """``params`` with ``free`` drawn from N(their values, cov), inside H's support (or None)."""
    k = len(free)
    cov = np.asarray(cov, float)[:k, :k]
    if k == 0 or not np.all(np.isfinite(cov)):
        return None
    mean = params.as_vector(free)
    return _inside_support(
        lambda: params.with_vector(rng.multivariate_normal(mean, cov, method="eigh"), free),
        free,
        tries,
    )


def h_drawn_state(state, rng):
    """``state`` with its H drawn from H's uncertainty (TF-CRDS models; others unchanged).

    The data were analysed with an H that errs by a draw from its posterior; a replicate
    analysed with the H it was simulated from would not see the decay-time distortion that error
    causes, and its null would be too narrow (after H was found, the spectrum's null missed the
    H-driven structure and a line-narrowing term was added at z_cal 3.4 in one seed of five).
    The beat-note parameters are drawn from the beat fit's covariance; the refined ones around
    their conditional mean given the drawn others (the refinement's gain: the refined f_c follows
    the resonance the beat note states), with the refinement's covariance given the others. Their
    joint law is then :meth:`Calibration.covariance`'s; drawn independently of the others, f_c's
    sd was 0.72 of the joint one on a D2 campaign and its correlation with a_r (-0.69) was lost.
    """
    cal = state.calibration
    if cal is None or state.model.method != "tf-crds":
        return state
    beat = cal.beat
    p = _draw_params(beat.params, beat.free, beat.cov, rng)
    if p is None:
        return state
    if cal.refined is None:
        return replace(state, calibration=replace(cal, beat=replace(beat, params=p)))
    ref = cal.refined
    others = cal.others
    base = ref.params.with_vector(p.as_vector(others), others)
    try:
        q = _draw_refined(cal, base, rng)
    except ValueError:  # no gain (a calibration not made for discovery): f_c drawn alone
        q = _draw_params(base, ref.free, ref.cov, rng)
    if q is None:
        return state
    return replace(state, calibration=replace(cal, refined=replace(ref, params=q)))


def _draw_refined(cal, base, rng, tries: int = 20):
    """``base`` with the refined parameters drawn given its others, inside H's support (or None).

    Raises ValueError when the calibration has no gain on the others.
    """
    free, others = cal.refined.free, cal.others
    return _inside_support(
        lambda: base.with_vector(cal.refined_given(base.as_vector(others), rng)[0], free),
        free,
        tries,
    )


@dataclass(frozen=True)
class GapNull:
    """The bootstrap null of one gap metric: its replicates and the calibrated score of the data."""

    z_data: float
    replicates: np.ndarray  # analytic z of each bootstrap replicate
    resampled: bool

    @property
    def n(self) -> int:
        return int(self.replicates.size)

    @property
    def location(self) -> float:
        return float(np.mean(self.replicates)) if self.resampled else 0.0

    @property
    def scale(self) -> float:
        """sd* sqrt(1 + 1/B): the spread of one more null draw around the bootstrap mean."""
        if not self.resampled:
            return 1.0
        sd = float(np.std(self.replicates, ddof=1))
        return max(sd, 1e-12) * np.sqrt(1.0 + 1.0 / self.n)

    @property
    def z_cal(self) -> float:
        return (self.z_data - self.location) / self.scale

    def p_value(self) -> float:
        """One-sided p of the data's metric under the null (large = a misfit)."""
        if not self.resampled:
            return float(stats.norm.sf(self.z_data))
        return float(stats.t.sf(self.z_cal, self.n - 1))

    def band(self, p: float) -> tuple[float, float]:
        """Central null interval of the analytic z with tail probability ``p`` on each side."""
        q = stats.t.isf(p, self.n - 1) if self.resampled else stats.norm.isf(p)
        return (self.location - q * self.scale, self.location + q * self.scale)


def gap_nulls(bundle, config, ev, evaluate, rng, n_boot: int = N_BOOT, noise=None) -> dict:
    """Bootstrap nulls of every gap of ``ev``: name -> :class:`GapNull`.

    ``evaluate`` is the discovery's own evaluation function (passed in, so the replicates are
    scored by exactly the code that scored the data).
    """
    noise = pre_extinction_noise(config.ringdowns) if noise is None else noise
    reps = {k: [] for k in ev.gaps}
    for _ in range(n_boot):
        rd = simulated_ringdowns(config, ev, noise, rng)
        ev_b = evaluate(
            bundle,
            replace(config, ringdowns=rd),
            h_drawn_state(ev.state, rng),
            ev.t_cuts,
            ev.tau[:, 0],
            False,
        )
        for k in reps:
            reps[k].append(ev_b.gaps[k]["z"] if k in ev_b.gaps else np.nan)
    out = {}
    for k, g in ev.gaps.items():
        r = np.asarray(reps[k], float)
        resampled = k in RESAMPLED and np.all(np.isfinite(r)) and np.ptp(r) > 0
        out[k] = GapNull(float(g["z"]), r if resampled else np.zeros(0), bool(resampled))
    return out
