"""Family B of hidden effects: each effect written from its physics, in a form our candidates do
not assume (a test fixture, shared with ``benchmarks/discovery_confusion.py``).

Family A (:mod:`tests.discovery.hidden_cases`) hides each effect with the simulator's own code,
which is the form the discovery candidates (:mod:`bayes_tfcrds.fit.extensions`) were written for.
Here every effect is written again from the physics, with nothing imported from the simulator's
effect code or the candidates: a clean campaign is simulated (ideal detector, Voigt line, 306 K
rather than 296 K) and the effect is then put into its records:

========================  ===================================================================
hidden effect             form written here
========================  ===================================================================
extinction_tail           residual input power leaking after extinction with a hyperbolic
                          decay eps/(1 + t/t_s)^2 (a semiconductor amplifier's carriers), fed
                          through the cavity's own build-up equation dP/dt = (g - P)/tau
second_mode               a transverse mode 61 MHz above the TEM00 one, with 1.5x its
                          diffraction losses: it samples the line elsewhere, so its decay
                          time is not a fixed fraction of tau
static_nonlinearity       an amplifier that saturates symmetrically, V' = V_s tanh(V/V_s)
                          (odd, so no quadratic term at all), on ring-downs and beat note
baseline_drift            the photodiode's dark offset relaxing after the light goes off,
                          -delta (1 - exp(-t/tau_th)) (thermal, not a ramp)
mode_beating              field interference with a weak higher-order mode of larger loss: it
                          decays at the mean of the two rates and its frequency chirps
transfer_function         an Eq. 2 chain from the other regime (a fast 6 MHz main pole beside
                          a weak resonant path at 150 kHz), integrated in the time domain as a
                          state-space model (not by FFT or residues)
window_history            the same chain, starting from a model that has H but the letter's
                          window
speed_dependence          power-law speed dependence Gamma(v) ~ v^m of width and shift,
                          integrated over the Maxwell speed distribution (not quadratic)
hard_collisions           soft collisions: the Galatry profile (Brownian velocity diffusion),
                          by numerical Fourier transform of its correlation function
etalon                    an Airy (multiple-beam) parasitic etalon in the loss, not a sinusoid
neighbour_line            a line of another molecule (mass 44 u), with its own Doppler and
                          collisional widths, in absorption and in the CMDS dispersion
========================  ===================================================================

Sizes are set so that each effect moves the data about as much as its family-A counterpart
(benchmarks/discovery_confusion.py compares runs of the two families); line-shape effects
change the CMDS mode shifts and widths as well, as they would in the gas.

Each entry of ``HIDDEN_CASES_B`` is (builder, start model); a builder takes (rng, campaign) and
returns (bundle, truth).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy import integrate, signal, special

from bayes_tfcrds.core.constants import C
from bayes_tfcrds.physics.linedata import load_line
from bayes_tfcrds.simulate.campaign import simulate_campaign

CONFIG = "D2"
#: family B's gas temperature (K): not the 296 K of the presets and of the line data
TEMPERATURE_K = 306.0
K_B = 1.380649e-23
AMU = 1.66053906660e-27


# --------------------------------------------------------------------------- line shapes


def voigt_complex(delta_hz, gamma_hz, doppler_hwhm_hz):
    """Complex Voigt profile (1/Hz) at detunings ``delta_hz`` from the shifted centre.

    g = w(z) / (sqrt(pi) sigma) with z = (delta + i gamma)/sigma and sigma = doppler_hwhm /
    sqrt(ln 2): its real part has unit area and its imaginary part is the dispersion, positive
    above the centre (the sign of (1/pi)/(gamma - i delta)).
    """
    sigma = doppler_hwhm_hz / np.sqrt(np.log(2.0))
    z = (np.asarray(delta_hz, float) + 1j * gamma_hz) / sigma
    return special.wofz(z) / (np.sqrt(np.pi) * sigma)


def speed_dependent_complex(delta_hz, gamma0_hz, delta0_hz, doppler_hwhm_hz, m, n_speed=4000):
    """Complex speed-dependent Voigt profile (1/Hz) with power-law speed dependence.

    Width and shift go as (v/v_p)^m, scaled so that their averages over the Maxwell speed
    distribution are gamma0 and delta0. For each speed the average over directions of
    (1/pi)/(Gamma(v) - i(delta - Delta(v) - k v mu)), mu uniform on [-1, 1], is
    ln((a + i k v)/(a - i k v)) / (2 pi i k v) with a = Gamma - i(delta - Delta); the speeds are
    then integrated with P(x) = 4 x^2 exp(-x^2)/sqrt(pi), x = v/v_p (Simpson, x up to 6). With
    m = 0 it is the Voigt profile.
    """
    x = np.linspace(1e-6, 6.0, n_speed)
    p = 4.0 / np.sqrt(np.pi) * x * x * np.exp(-x * x)
    scale = 1.0 / integrate.simpson(p * x**m, x=x)  # <(v/v_p)^m> = 1 after scaling
    k_vp = doppler_hwhm_hz / np.sqrt(np.log(2.0))  # (nu0/c) v_p in Hz
    d = np.asarray(delta_hz, float)[:, None]
    gam = gamma0_hz * scale * x**m
    shift = delta0_hz * scale * x**m
    a = gam - 1j * (d - shift)
    kv = k_vp * x
    term = np.log((a + 1j * kv) / (a - 1j * kv)) / (2j * np.pi * kv)
    return integrate.simpson(term * p, x=x, axis=1)


def galatry_complex(delta_hz, gamma0_hz, delta0_hz, doppler_hwhm_hz, beta_per_s, t_max_s=None):
    """Complex Galatry (soft-collision) profile (1/Hz), by quadrature of its correlation function.

    g(delta) = 2 int_0^inf Phi(t) exp(2 pi i delta t) dt with
    Phi = exp(-2 pi (gamma0 + i delta0) t) exp(-(k v_p)^2 / (2 beta^2) (beta t - 1 + e^{-beta t})),
    k v_p = 2 pi doppler_hwhm / sqrt(ln 2) (rad/s) and beta the velocity-diffusion rate (1/s).
    beta -> 0 gives the Voigt profile; large beta narrows the Doppler part (Dicke).
    """
    kvp = 2 * np.pi * doppler_hwhm_hz / np.sqrt(np.log(2.0))
    gam = 2 * np.pi * gamma0_hz
    if t_max_s is None:
        t_max_s = 40.0 / gam
    # the integrand oscillates at up to 2 pi max|delta|: 40 points a period
    d = np.asarray(delta_hz, float)
    dt = min(1.0 / (40.0 * max(np.max(np.abs(d - delta0_hz)), 1.0)), 0.02 / kvp)
    t = np.arange(0.0, t_max_s, dt)
    bt = beta_per_s * t
    if beta_per_s > 0:
        dopp = np.exp(-(kvp**2) / (2 * beta_per_s**2) * (bt - 1.0 + np.exp(-bt)))
    else:
        dopp = np.exp(-((kvp * t) ** 2) / 4.0)
    phi = np.exp(-(gam + 2j * np.pi * delta0_hz) * t) * dopp
    out = np.empty(d.size, complex)
    for i, di in enumerate(d):
        out[i] = 2.0 * integrate.simpson(phi * np.exp(2j * np.pi * di * t), x=t)
    return out


# --------------------------------------------------------------------------- the base campaign


def _base(rng, campaign):
    """A clean campaign at TEMPERATURE_K: ideal detector, Voigt line, white noise."""
    camp = replace(campaign, temperature_k=TEMPERATURE_K)
    bundle, truth = simulate_campaign(["letter-D2"], rng, camp, {}, line_effects_default=False)
    return bundle, truth, camp


def _with(bundle, signal_v=None, cmds=None, beat=None):
    cfg = bundle.configs[CONFIG]
    rd = cfg.ringdowns
    new = replace(cfg)
    if signal_v is not None:
        new = replace(new, ringdowns=replace(rd, signal_v=signal_v))
    if cmds is not None:
        new = replace(new, cmds=cmds)
    if beat is not None:
        new = replace(new, transfer_function=beat)
    return replace(bundle, configs={**bundle.configs, CONFIG: new})


def _ideal_records(t_s, tau_s):
    """Ideal-detector ring-downs (steady level 1): 1 before extinction, exp(-t/tau) after."""
    tp = np.clip(t_s, 0.0, None)[None, :]
    return np.where(np.asarray(t_s)[None, :] < 0, 1.0, np.exp(-tp / np.asarray(tau_s)[:, None]))


def _clean_parts(bundle, truth, camp):
    """Sample times (s), true decay times (s) and the noise-free ideal record (V)."""
    rd = bundle.configs[CONFIG].ringdowns
    t = rd.time_s
    tau = np.asarray(truth["configs"][CONFIG]["tau_s"], float)
    return t, tau, camp.amplitude_v * _ideal_records(t, tau)


# --------------------------------------------------------------------------- transient effects


def cavity_fed_by(t_s, tau_s, g):
    """Intracavity power (steady level 1) fed by the input power g(t) (same grid) after t = 0.

    dP/dt = (g - P)/tau with P(0) = 1: P = exp(-t/tau) + (1/tau) int_0^t exp(-(t - s)/tau) g(s) ds
    (trapezoid rule on the sample grid), 1 before extinction. Shape (n_tau, n_samples).
    """
    tp = np.clip(np.asarray(t_s, float), 0.0, None)
    tau = np.asarray(tau_s, float)[:, None]
    inner = integrate.cumulative_trapezoid(np.exp(tp / tau) * g, tp, axis=1, initial=0.0)
    p = np.exp(-tp / tau) * (1.0 + inner / tau)
    return np.where(np.asarray(t_s)[None, :] < 0, 1.0, p)


def extinction_tail(rng, campaign, eps=4e-3, t_s=8e-6):
    """Input power eps/(1 + t/t_s)^2 left after extinction, built up by the cavity."""
    bundle, truth, camp = _base(rng, campaign)
    t, tau, clean = _clean_parts(bundle, truth, camp)
    leak = eps / (1.0 + np.clip(t, 0.0, None) / t_s) ** 2 * (t >= 0)
    sig = (
        bundle.configs[CONFIG].ringdowns.signal_v
        + camp.amplitude_v * cavity_fed_by(t, tau, leak)
        - clean
    )
    return _with(bundle, signal_v=sig), truth


def second_mode(rng, campaign, fraction=1e-2, offset_hz=61e6, loss_factor=1.5):
    """A weak transverse mode offset_hz above TEM00 with loss_factor x its diffraction losses."""
    bundle, truth, camp = _base(rng, campaign)
    t, tau, clean = _clean_parts(bundle, truth, camp)
    lt, rd = truth["line"], bundle.configs[CONFIG].ringdowns
    loss = truth["alpha_loss_per_m"]
    alpha2 = _voigt_alpha(rd.nu_hz + offset_hz, lt)
    tau2 = 1.0 / (C * (loss_factor * loss + alpha2))
    sig = rd.signal_v + fraction * (camp.amplitude_v * _ideal_records(t, tau2) - clean)
    return _with(bundle, signal_v=sig), truth


def static_nonlinearity(rng, campaign, v_sat=11.0):
    """A symmetrically saturating amplifier V' = V_s tanh(V/V_s), beat note included."""
    bundle, truth, camp = _base(rng, campaign)
    cfg = bundle.configs[CONFIG]

    def f(v):
        return v_sat * np.tanh(np.asarray(v) / v_sat)

    sig = f(cfg.ringdowns.signal_v)
    tf = cfg.transfer_function
    off = camp.offset_v
    i1, i2 = np.asarray(tf.i1_v, float), np.asarray(tf.i2_v, float)
    slope = 1.0 / np.cosh((i1 + i2 + off) / v_sat) ** 2  # small-signal gain of the beat
    beat = replace(
        tf,
        b12_v=tf.b12_v * slope,
        b12_u_v=None if tf.b12_u_v is None else tf.b12_u_v * slope,
        i1_v=f(i1 + off) - f(off),
        i2_v=f(i2 + off) - f(off),
    )
    return _with(bundle, signal_v=sig, beat=beat), truth


def baseline_drift(rng, campaign, delta_v=4e-4, tau_th_s=120e-6):
    """The dark offset relaxing after extinction: -delta (1 - exp(-t/tau_th)) for t >= 0."""
    bundle, truth, camp = _base(rng, campaign)
    rd = bundle.configs[CONFIG].ringdowns
    t = rd.time_s
    drift = -delta_v * (1.0 - np.exp(-np.clip(t, 0.0, None) / tau_th_s))
    return _with(bundle, signal_v=rd.signal_v + drift[None, :]), truth


def mode_beating(rng, campaign, amp=2e-3, f_hz=1.3e6, chirp_hz_per_s=2e10, tau_ratio=0.8):
    """Interference with a weak mode of larger loss: decays at the mean rate, chirped frequency."""
    bundle, truth, camp = _base(rng, campaign)
    t, tau, _ = _clean_parts(bundle, truth, camp)
    tp = np.clip(t, 0.0, None)[None, :]
    rate = 0.5 * (1.0 / tau + 1.0 / (tau_ratio * tau))[:, None]
    phase = 2 * np.pi * (f_hz * tp + 0.5 * chirp_hz_per_s * tp**2) + 0.3
    beat = amp * np.exp(-rate * tp) * np.cos(phase) * (t >= 0)[None, :]
    sig = bundle.configs[CONFIG].ringdowns.signal_v + camp.amplitude_v * beat
    return _with(bundle, signal_v=sig), truth


# --------------------------------------------------------------------------- a detection chain


#: Eq. 2 (n_r = 2) in the other regime than the presets': a fast main pole beside a weak
#: resonant path at 150 kHz (the presets: a slow tail beside a fast resonance). f_r, Q = Gamma_r.
CHAIN = {"f_c_hz": 6e6, "a_r": 0.05, "f_r_hz": 150e3, "q": 0.7}


def chain_tf(c=CHAIN):
    """(num, den) in s (rad/s) of Eq. 2 with n_r = 2, unit DC gain.

    H = [1/(1 + s/w_c) + A_r/(1 + s/(w_r Q) + s^2/w_r^2)] / (1 + A_r): letter Eq. 2 with
    i f/f_c = s/w_c and -(f/f_r)^2 = (s/w_r)^2, written over one common denominator.
    """
    wc, wr, q, ar = 2 * np.pi * c["f_c_hz"], 2 * np.pi * c["f_r_hz"], c["q"], c["a_r"]
    res = [1.0 / wr**2, 1.0 / (wr * q), 1.0]
    pole = [1.0 / wc, 1.0]
    num = np.polyadd(res, ar * np.array(pole)) / (1.0 + ar)
    return num, np.polymul(pole, res)


def chain_response(t_s, tau_s, c=CHAIN):
    """Detector output (steady level 1) for input 1 before t = 0 and exp(-t/tau) after.

    Integrated as a state-space model from its steady state at extinction (scipy.signal.lsim,
    input linear between samples); the record needs a sample at extinction.
    """
    sys = signal.StateSpace(*signal.tf2ss(*chain_tf(c)))
    x0 = -np.linalg.solve(sys.A, sys.B[:, 0])  # steady state for input 1
    t = np.asarray(t_s, float)
    dt = t[1] - t[0]
    i0 = int(np.argmin(np.abs(t)))
    if abs(t[i0]) > 1e-6 * dt:
        raise ValueError("the record needs a sample at extinction (t = 0)")
    tt = t[i0:] - t[i0]
    out = np.ones((np.size(tau_s), t.size))
    for j, tj in enumerate(np.atleast_1d(tau_s)):
        _, y, _ = signal.lsim(sys, np.exp(-tt / tj), tt, X0=x0, interp=True)
        out[j, i0:] = y
    return out


def transfer_function(rng, campaign):
    """The Eq. 2 chain (hidden from a model without H, or with H and the letter window)."""
    bundle, truth, camp = _base(rng, campaign)
    t, tau, clean = _clean_parts(bundle, truth, camp)
    cfg = bundle.configs[CONFIG]
    sig = cfg.ringdowns.signal_v + camp.amplitude_v * chain_response(t, tau) - clean
    tf = cfg.transfer_function
    num, den = chain_tf()
    _, h = signal.freqs(num, den, worN=2 * np.pi * tf.f_hz)
    # the base beat note measured an ideal detector: its noise is relative, so scale it
    beat = replace(tf, b12_v=tf.b12_v * np.abs(h), b12_u_v=tf.b12_u_v * np.abs(h))
    return _with(bundle, signal_v=sig, beat=beat), truth


# --------------------------------------------------------------------------- spectrum effects


def _voigt_alpha(nu_hz, lt):
    g = voigt_complex(
        nu_hz - lt["nu0_hz"] - lt["delta0_hz"], lt["gamma0_hz"], lt["doppler_hwhm_hz"]
    )
    return lt["line_area_hz_per_m"] * g.real


def _with_spectrum(bundle, truth, camp, d_alpha, d_shift_hz):
    """Records whose absorption changed by d_alpha (1/m) and CMDS shifts by d_shift_hz (Hz)."""
    t, tau, clean = _clean_parts(bundle, truth, camp)
    cfg = bundle.configs[CONFIG]
    tau_new = 1.0 / (1.0 / tau + C * d_alpha)
    sig = cfg.ringdowns.signal_v + camp.amplitude_v * _ideal_records(t, tau_new) - clean
    cm = cfg.cmds
    cmds = replace(
        cm,
        shift_hz=cm.shift_hz + d_shift_hz,
        width_hz=None if cm.width_hz is None else cm.width_hz + C * d_alpha / (4 * np.pi),
    )
    return _with(bundle, signal_v=sig, cmds=cmds)


def _line_change(rng, campaign, g_new):
    """Replace the Voigt line by the complex profile g_new(delta from nu0, lt) (1/Hz)."""
    bundle, truth, camp = _base(rng, campaign)
    lt = truth["line"]
    nu = bundle.configs[CONFIG].ringdowns.nu_hz
    d = nu - lt["nu0_hz"]
    g_old = voigt_complex(d - lt["delta0_hz"], lt["gamma0_hz"], lt["doppler_hwhm_hz"])
    dg = g_new(d, lt) - g_old
    area = lt["line_area_hz_per_m"]
    d_shift = C * area * dg.imag / (4 * np.pi)
    return _with_spectrum(bundle, truth, camp, area * dg.real, d_shift), truth


def speed_dependence(rng, campaign, m=0.2):
    """Power-law speed dependence of width and shift, Gamma(v) ~ (v/v_p)^m.

    m = 0.2 gives dGamma/d(v/v_p) = 0.198 Gamma0 at the most probable speed, the slope 2 Gamma2
    of the line data's quadratic Gamma2 = 0.1 Gamma0 (family A): the same speed dependence there,
    another form away from it (Gamma -> 0 as v^m at low speeds).
    """

    def g(d, lt):
        return speed_dependent_complex(
            d, lt["gamma0_hz"], lt["delta0_hz"], lt["doppler_hwhm_hz"], m
        )

    return _line_change(rng, campaign, g)


def hard_collisions(rng, campaign):
    """Soft collisions (Galatry), with the line data's kinetic diffusion rate.

    beta = k_B T/(m D) = 2 pi nu_VC, nu_VC being the line data's kinetic-theory estimate (the
    rate family A gives the hard-collision model).
    """
    beta = 2 * np.pi * load_line().shape_at(campaign.pressure_pa, TEMPERATURE_K)["nu_vc_hz"]

    def g(d, lt):
        return galatry_complex(d, lt["gamma0_hz"], lt["delta0_hz"], lt["doppler_hwhm_hz"], beta)

    return _line_change(rng, campaign, g)


def etalon(rng, campaign, amp_per_m=6e-7, finesse_coef=2.0, period_hz=3.3e9, phase_rad=0.4):
    """An Airy parasitic etalon in the loss, a [1/(1 + F sin^2(pi nu/P + phi)) - its mean]."""
    bundle, truth, camp = _base(rng, campaign)
    lt = truth["line"]
    nu = bundle.configs[CONFIG].ringdowns.nu_hz
    s = np.sin(np.pi * (nu - lt["nu0_hz"]) / period_hz + phase_rad)
    airy = 1.0 / (1.0 + finesse_coef * s * s) - 1.0 / np.sqrt(1.0 + finesse_coef)
    return _with_spectrum(bundle, truth, camp, amp_per_m * airy, 0.0), truth


def neighbour_line(
    rng, campaign, offset_hz=-0.85e9, area_ratio=2.5e-3, mass_u=44.0, width_ratio=0.7
):
    """A line of another molecule (mass_u) offset_hz away, with its own widths."""
    bundle, truth, camp = _base(rng, campaign)
    lt = truth["line"]
    nu = bundle.configs[CONFIG].ringdowns.nu_hz
    nu0 = lt["nu0_hz"] + offset_hz
    # Doppler HWHM = nu0/c sqrt(2 ln2 k_B T/m), written out here
    dop = nu0 / C * np.sqrt(2 * np.log(2.0) * K_B * camp.temperature_k / (mass_u * AMU))
    g = voigt_complex(nu - nu0, width_ratio * lt["gamma0_hz"], dop)
    area = area_ratio * lt["line_area_hz_per_m"]
    out = _with_spectrum(bundle, truth, camp, area * g.real, C * area * g.imag / (4 * np.pi))
    return out, truth


def nothing(rng, campaign):
    """The clean campaign at TEMPERATURE_K."""
    bundle, truth, _ = _base(rng, campaign)
    return bundle, truth


HIDDEN_CASES_B = {
    "transfer_function": (transfer_function, None),
    "window_history": (transfer_function, "transfer_function"),
    "static_nonlinearity": (static_nonlinearity, None),
    "extinction_tail": (extinction_tail, None),
    "second_mode": (second_mode, None),
    "baseline_drift": (baseline_drift, None),
    "mode_beating": (mode_beating, None),
    "speed_dependence": (speed_dependence, None),
    "hard_collisions": (hard_collisions, None),
    "etalon": (etalon, None),
    "neighbour_line": (neighbour_line, None),
}
