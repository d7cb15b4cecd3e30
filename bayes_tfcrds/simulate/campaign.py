"""Simulator of the letter's experiment: CRDS transients, beat-note H(f) and CMDS, with truth.

The physics, in the order the light and the signal meet it:

1. **Sample and line** (12C16O (3-0) R(23) by default): alpha(nu) = S(T) N Re g(nu) from the
   qSDHCP family, plus optional spectrum-level effects (``etalon``, ``neighbour_line``). The
   line data hold S at T_ref = 296 K; S(T) at the campaign's temperature follows from it through
   Q(T), E'' and stimulated emission (:meth:`LineData.intensity_ratio`), as N, the Doppler width
   and the air width (its temperature exponent) follow T.
2. **Cavity**: at each cavity mode the intracavity power is steady before laser extinction
   (t = 0) and decays with 1/tau = c (alpha + alpha_loss) after it; optional transient-level
   optical effects add terms (``second_mode``, ``mode_beating``, ``extinction_tail``).
3. **Detection chain**: a causal linear filter (the exact rational response of
   :mod:`bayes_tfcrds.physics.detection_chain`, no FFT), then an optional static nonlinearity, the
   detector offset (with optional ``baseline_drift``), white noise, and ADC quantisation of every
   acquisition before ``n_avg`` acquisitions are averaged.
4. **Beat note** of the same chain (same nonlinearity) with its own noise, and **CMDS**
   mode shifts (and widths) whose noise keeps the four A_ref references within the letter's
   0.06 % spread (u(A_ref) = 0.015 % each, :func:`cmds_noise`).

Every random number comes from the ``numpy.random.Generator`` passed in: the same preset,
effects and seed give the same bytes. Units are SI throughout (Hz, s, V, Pa, K, m).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np

from bayes_tfcrds.bundle.records import (
    Bundle,
    Cavity,
    CmdsData,
    Config,
    RingdownData,
    Sample,
    TransferFunctionData,
)
from bayes_tfcrds.core.constants import C, intensity_from_cm_per_molecule, number_density
from bayes_tfcrds.physics.detection_chain import IDEAL_CHAIN, RationalChain, chain_from_tf
from bayes_tfcrds.physics.linedata import load_line
from bayes_tfcrds.physics.lineshape import doppler_hwhm_hz, profile
from bayes_tfcrds.physics.transfer_function import TFParams
from bayes_tfcrds.simulate.noise import NoiseColour, coloured_noise, shaping_filter

# --------------------------------------------------------------------------- effects

EFFECTS = {
    # transient level
    "transfer_function": "the detection chain's frequency response H(f) (the preset's chain); "
    "without it the detector is ideal (H = 1)",
    "static_nonlinearity": "detector output V' = V + beta V^2 / V_ref (kind='quadratic') or V_ref "
    "(V/V_ref)^(1+gamma) (kind='power'): the gain depends on the signal level, so the decay looks "
    "slower (beta < 0) or faster",
    "extinction_tail": "the laser is not switched off at once: a fraction `fraction` of the input "
    "power remains after t = 0 and decays with `tau_s`, feeding the cavity; the ring-down carries "
    "a second exponential exp(-t/tau_s)",
    "second_mode": "a higher-order transverse mode with a fraction `fraction` of the power and "
    "decay time `tau_ratio` x tau is excited too: a weak second exponential",
    "baseline_drift": "the detector offset drifts linearly, `slope_v_per_s` (V/s), during the "
    "transient",
    "mode_beating": "two excited modes beat: a sinusoid at `freq_hz` with relative amplitude "
    "`fraction`, decaying with tau (it starts at extinction)",
    # spectrum level
    "speed_dependence": "quadratic speed dependence of the collisional width and shift (Gamma2 = "
    "`gamma2_ratio` Gamma0, Delta2 = `delta2_ratio` Delta0)",
    "hard_collisions": "velocity-changing collisions at rate nu_VC = `nu_vc_ratio` Gamma0 (Dicke "
    "narrowing, hard-collision model)",
    "etalon": "a sinusoidal baseline in alpha: `amplitude_per_m` sin(2 pi (nu - nu0)/`period_hz` "
    "+ `phase_rad`), from a parasitic etalon",
    "neighbour_line": "a weak nearby line at `offset_hz` from the main one, with "
    "`intensity_ratio` of its intensity and the same shape parameters",
}

EFFECT_DEFAULTS = {
    "transfer_function": {},
    "static_nonlinearity": {"kind": "quadratic", "beta": -2e-3, "gamma": -2e-3, "v_ref": 1.0},
    "extinction_tail": {"fraction": 2e-3, "tau_s": 10e-6},
    "second_mode": {"fraction": 3e-3, "tau_ratio": 0.7},
    "baseline_drift": {"slope_v_per_s": 2.0},
    "mode_beating": {"fraction": 2e-3, "freq_hz": 1.5e6, "phase_rad": 0.3},
    "speed_dependence": {"gamma2_ratio": None, "delta2_ratio": None},
    "hard_collisions": {"nu_vc_ratio": None},
    "etalon": {"amplitude_per_m": 2e-7, "period_hz": 2.5e9, "phase_rad": 0.7},
    "neighbour_line": {"offset_hz": 1.2e9, "intensity_ratio": 3e-3},
}


# the physical domain of each effect parameter: a fraction or ratio of a signal is not negative,
# a time or frequency is positive; values outside are refused (0 s or nan would divide by zero)
EFFECT_DOMAINS = {
    "beta": (-0.5, 0.5),
    "gamma": (-0.5, 0.5),
    "v_ref": (1e-6, 1e3),
    "fraction": (0.0, 0.99),
    "tau_s": (1e-9, 1.0),
    "tau_ratio": (1e-3, 1e3),
    "slope_v_per_s": (-1e6, 1e6),
    "freq_hz": (1.0, 1e10),
    "phase_rad": (-1e3, 1e3),
    "gamma2_ratio": (0.0, 0.99),
    "delta2_ratio": (-1.0, 1.0),
    "nu_vc_ratio": (0.0, 1e3),
    "amplitude_per_m": (-1e-2, 1e-2),
    "period_hz": (1e6, 1e13),
    "offset_hz": (-1e11, 1e11),
    "intensity_ratio": (0.0, 10.0),
}


def parse_effect(text: str):
    """``NAME[:key=value,...]`` -> (name, dict) with values as float (or str for ``kind``)."""
    name, _, rest = text.partition(":")
    name = name.strip()
    if name not in EFFECTS:
        raise ValueError(f"unknown effect {name!r}; choose from {sorted(EFFECTS)}")
    params = {}
    for item in filter(None, (s.strip() for s in rest.split(","))):
        key, eq, value = item.partition("=")
        if not eq:
            raise ValueError(f"effect {name}: expected key=value, got {item!r}")
        key = key.strip()
        if key not in EFFECT_DEFAULTS[name]:
            raise ValueError(
                f"effect {name} has no parameter {key!r}; it has {sorted(EFFECT_DEFAULTS[name])}"
            )
        if key == "kind":
            params[key] = value.strip()
            continue
        try:
            v = float(value)
        except ValueError:
            raise ValueError(f"effect {name}: {key} = {value.strip()!r} is not a number") from None
        lo, hi = EFFECT_DOMAINS[key]
        if not (np.isfinite(v) and lo <= v <= hi):
            raise ValueError(f"effect {name}: {key} = {v!r} is outside its domain [{lo:g}, {hi:g}]")
        params[key] = v
    return name, params


# --------------------------------------------------------------------------- presets


@dataclass(frozen=True)
class ChainPreset:
    """A detection configuration of the letter: its causal chain (Eq. 2, n_r = 2) and noise."""

    label: str
    description: str
    tf: TFParams
    noise_v: float = 1.3e-3  # white noise of one acquisition (V); /sqrt(100) = 0.13 mV


# Calibrated by benchmarks/calibrate_presets.py so that plain CRDS analysis reproduces the
# letter's biases; the table with the reproduced numbers is in README.md ("Simulator presets").
# Each chain: a slow first-order tail (f_c, weight 1/(1 + A_r)) beside a fast resonant main path
# (f_r ~ 5-7 MHz, the ~6 MHz bandwidth). Detector 1 (D1, D2) and detector 2 (D3, D4) each share
# one tail time; gain 300 (D2, D4) lowers the bandwidth.
PRESETS = {
    "letter-D1": ChainPreset(
        "D1",
        "detector 1 (older), gain 100, NI PCI-5122",
        TFParams(f_c_hz=5.257e4, a_r=26.34, f_r_hz=7.0e6, gamma_r=0.7, n_r=2.0),
    ),
    "letter-D2": ChainPreset(
        "D2",
        "detector 1 (older), gain 300, NI PCI-5122",
        TFParams(f_c_hz=5.257e4, a_r=24.70, f_r_hz=5.0e6, gamma_r=0.7, n_r=2.0),
    ),
    "letter-D3": ChainPreset(
        "D3",
        "detector 2 (newer), gain 100, NI PCI-5122",
        TFParams(f_c_hz=1.938e4, a_r=19.28, f_r_hz=7.0e6, gamma_r=0.7, n_r=2.0),
        noise_v=1.1e-3,
    ),
    "letter-D4": ChainPreset(
        "D4",
        "detector 2 (newer), gain 300, NI PCI-5122",
        TFParams(f_c_hz=1.938e4, a_r=20.33, f_r_hz=5.0e6, gamma_r=0.7, n_r=2.0),
        noise_v=1.1e-3,
    ),
}


# --------------------------------------------------------------------------- campaign settings


MIN_POINTS = 8  # a line fit has up to 7 parameters


@dataclass(frozen=True)
class Campaign:
    """Settings of one simulated measurement (all SI)."""

    pressure_pa: float = 666.6  # 5 Torr
    pressure_u_pa: float = 0.333  # 0.05 % capacitance manometer
    temperature_k: float = 296.0
    temperature_u_k: float = 0.03
    # the gauges' realised reading errors: the gas is at pressure_pa and temperature_k, the
    # bundle's /sample reports them plus these (a calibration study draws them from the stated
    # u to test the Type B rows; 0 in every other simulation)
    pressure_error_pa: float = 0.0
    temperature_error_k: float = 0.0
    fsr_hz: float = 203.0e6
    finesse: float = 41_000.0
    n_points: int = 101
    span_hz: float = 10.0e9  # half span of the scan (B-EOM sideband, 20 GHz)
    dt_s: float = 20e-9
    n_samples: int = 16384
    t0_s: float = -2.0e-6  # first sample relative to extinction
    n_avg: int = 100
    amplitude_v: float = 0.6  # steady pre-extinction signal (threshold trigger)
    offset_v: float = 2.0e-3  # detector dark offset
    adc_bits: int = 14
    adc_range_v: tuple = (-1.0, 1.0)
    beat_f_hz: tuple = (1e3, 4e7)
    beat_points: int = 60
    beat_rel_noise: float = 1.5e-3
    beat_dc_v: tuple = (0.20, 0.25)
    # u(A_ref)/A_ref of each configuration's CMDS reference fit. The letter: "the individual
    # CMDS-based A_ref references exhibit a spread below 0.06 %" (four configurations, the grey
    # band of its Fig. 5: max - min). The range of four normal draws has mean 2.06 sd and is
    # below 4 sd in 97.6 % of campaigns, so u = 0.015 % makes a spread below 0.06 % the typical
    # outcome (mean spread 0.031 %); it is about 1.4 Hz of shift noise per mode on the letter's
    # 101-mode grid. (6e-4 of a 3-parameter fit gave 0.094 % and a 0.18 % spread.)
    cmds_area_rel_u: float = 1.5e-4
    cmds_width_u_hz: float = 50.0
    profile: str = "qsdhcp"
    noise: NoiseColour = NoiseColour()  # PSD shape of the detector noise (white by default)

    def __post_init__(self):
        # sizes a line fit and a ring-down fit can use and memory can hold (the study files'
        # bounds), and sample conditions inside what the bundle reader accepts
        for name, lo, hi in (
            ("n_points", MIN_POINTS, 2000),
            ("n_samples", 256, 1 << 20),
            ("n_avg", 1, 100000),
            ("beat_points", 8, 100000),
        ):
            v = getattr(self, name)
            if not (isinstance(v, (int, np.integer)) and lo <= v <= hi):
                raise ValueError(f"{name} = {v!r} must be an integer in [{lo}, {hi}]")
        for name, lo, hi in (
            ("pressure_pa", 1e-6, 1e8),
            ("temperature_k", 1.0, 5000.0),
            ("dt_s", 1e-12, 1e-2),
            ("fsr_hz", 1e3, 1e12),
            ("finesse", 1.0, 1e9),
            ("span_hz", 1.0, 1e13),
        ):
            v = getattr(self, name)
            if not (np.isfinite(v) and lo <= v <= hi):
                raise ValueError(f"{name} = {v!r} must be in [{lo:g}, {hi:g}]")


def spectral_points(c: Campaign) -> np.ndarray:
    """Cavity-mode detunings (Hz) from the line: every mode near the centre, sparser outside.

    Points sit on the FSR grid (CRDS and CMDS measure at cavity modes); the density falls
    with |detuning| so that ~``n_points`` modes cover +/- ``span_hz``.
    """
    q_max = int(c.span_hz // c.fsr_hz)
    q = np.arange(-q_max, q_max + 1)
    if q.size <= c.n_points:
        return q * c.fsr_hz
    # choose modes by a density ~ 1/(1 + (q/q_core)^2) mapped through its cumulative
    q_core = max(3.0, q_max / 10)
    u = np.linspace(-1, 1, c.n_points)
    x = np.arctan(q_max / q_core)
    picked = np.unique(np.round(q_core * np.tan(u * x)).astype(int))
    return picked * c.fsr_hz


# --------------------------------------------------------------------------- line truth


@dataclass(frozen=True)
class LineTruth:
    """The absorption line the campaign is made from (SI: Hz, Hz/m, K).

    intensity_cm_per_molecule is S at the campaign's temperature (the S of A = S N),
    intensity_ref_cm_per_molecule S at the line data's reference temperature t_ref_k, the value an
    analysis that refers its S to T_ref should recover.
    """

    nu0_hz: float
    line_area_hz_per_m: float  # A = S(T) N
    intensity_cm_per_molecule: float  # S(T) (edge unit, labelled)
    intensity_ref_cm_per_molecule: float  # S(T_ref) (edge unit, labelled)
    t_ref_k: float
    doppler_hwhm_hz: float
    gamma0_hz: float
    gamma2_hz: float
    delta0_hz: float
    delta2_hz: float
    nu_vc_hz: float
    profile: str


def line_truth(c: Campaign, effects: dict, intensity_ref_cm_per_molecule=None) -> LineTruth:
    """The letter's line at the campaign's pressure and temperature, with ``effects``' shape.

    ``intensity_ref_cm_per_molecule``: S(T_ref) to use instead of the line data's (a drawn truth);
    S(T) and A = S(T) N follow from it at the campaign's T.
    """
    line = load_line()
    shape = line.shape_at(c.pressure_pa, c.temperature_k)
    g0, d0 = shape["gamma0_hz"], shape.get("delta0_hz", 0.0)
    sd = effects.get("speed_dependence")
    hc = effects.get("hard_collisions")
    g2 = d2 = nvc = 0.0
    if sd is not None:
        g2r = sd.get("gamma2_ratio") if sd.get("gamma2_ratio") is not None else line.gamma2_ratio
        d2r = sd.get("delta2_ratio") if sd.get("delta2_ratio") is not None else line.delta2_ratio
        g2, d2 = g2r * g0, d2r * d0
    if hc is not None:
        nvr = hc.get("nu_vc_ratio")
        nvc = nvr * g0 if nvr is not None else shape.get("nu_vc_hz", 0.0)
    n = number_density(c.pressure_pa, c.temperature_k)
    s_ref = (
        line.intensity_cm_per_molecule
        if intensity_ref_cm_per_molecule is None
        else float(intensity_ref_cm_per_molecule)
    )
    s_cm = s_ref * line.intensity_ratio(c.temperature_k)
    return LineTruth(
        nu0_hz=line.nu0_hz,
        line_area_hz_per_m=float(intensity_from_cm_per_molecule(s_cm, n)),
        intensity_cm_per_molecule=s_cm,
        intensity_ref_cm_per_molecule=s_ref,
        t_ref_k=line.temperature_k,
        doppler_hwhm_hz=float(doppler_hwhm_hz(line.nu0_hz, c.temperature_k, line.mass_u)),
        gamma0_hz=g0,
        gamma2_hz=g2,
        delta0_hz=d0,
        delta2_hz=d2,
        nu_vc_hz=nvc,
        profile="qsdhcp",
    )


def complex_profile(nu_hz, lt: LineTruth) -> np.ndarray:
    """g(nu) of the truth line (1/Hz)."""
    return profile(
        "qsdhcp",
        nu_hz,
        lt.nu0_hz,
        lt.doppler_hwhm_hz,
        gamma0_hz=lt.gamma0_hz,
        gamma2_hz=lt.gamma2_hz,
        delta0_hz=lt.delta0_hz,
        delta2_hz=lt.delta2_hz,
        nu_vc_hz=lt.nu_vc_hz,
    )


def absorption_truth(nu_hz, lt: LineTruth, effects: dict) -> np.ndarray:
    """alpha(nu) (1/m) of the sample, with spectrum-level effects, without the empty-cavity loss."""
    alpha = lt.line_area_hz_per_m * complex_profile(nu_hz, lt).real
    if "neighbour_line" in effects:
        e = {**EFFECT_DEFAULTS["neighbour_line"], **effects["neighbour_line"]}
        nb = replace(lt, nu0_hz=lt.nu0_hz + e["offset_hz"])
        alpha = (
            alpha + e["intensity_ratio"] * lt.line_area_hz_per_m * complex_profile(nu_hz, nb).real
        )
    if "etalon" in effects:
        e = {**EFFECT_DEFAULTS["etalon"], **effects["etalon"]}
        alpha = alpha + e["amplitude_per_m"] * np.sin(
            2 * np.pi * (nu_hz - lt.nu0_hz) / e["period_hz"] + e["phase_rad"]
        )
    return alpha


def dispersion_shift_truth(nu_hz, lt: LineTruth, effects: dict) -> np.ndarray:
    """Mode shift (Hz) = c A g_I / (4 pi), with the neighbour line if present."""
    shift = C * lt.line_area_hz_per_m * complex_profile(nu_hz, lt).imag / (4 * np.pi)
    if "neighbour_line" in effects:
        e = {**EFFECT_DEFAULTS["neighbour_line"], **effects["neighbour_line"]}
        nb = replace(lt, nu0_hz=lt.nu0_hz + e["offset_hz"])
        shift = shift + e["intensity_ratio"] * C * lt.line_area_hz_per_m * complex_profile(
            nu_hz, nb
        ).imag / (4 * np.pi)
    return shift


# --------------------------------------------------------------------------- detection


def _nonlinear(v, effects):
    if "static_nonlinearity" not in effects:
        return v
    e = {**EFFECT_DEFAULTS["static_nonlinearity"], **effects["static_nonlinearity"]}
    if e["kind"] == "quadratic":
        return v + e["beta"] * v * v / e["v_ref"]
    if e["kind"] == "power":
        return e["v_ref"] * np.sign(v) * np.abs(v / e["v_ref"]) ** (1.0 + e["gamma"])
    raise ValueError(f"static_nonlinearity kind must be 'quadratic' or 'power', got {e['kind']!r}")


def _nonlinear_slope(v, effects):
    if "static_nonlinearity" not in effects:
        return np.ones_like(v)
    e = {**EFFECT_DEFAULTS["static_nonlinearity"], **effects["static_nonlinearity"]}
    if e["kind"] == "quadratic":
        return 1.0 + 2.0 * e["beta"] * v / e["v_ref"]
    return (1.0 + e["gamma"]) * np.abs(v / e["v_ref"]) ** e["gamma"]


def detected_transients(
    t_s, tau_s, chain: RationalChain, effects: dict, amplitude_v: float
) -> np.ndarray:
    """Noise-free detector voltage (before offset, nonlinearity and ADC) for decay times tau (s).

    Shape (n_tau, n_samples). Optical terms pass through the exact chain response.
    """
    tau = np.asarray(tau_s, float)
    y = chain.ringdown_response(t_s, tau)
    if "second_mode" in effects:
        e = {**EFFECT_DEFAULTS["second_mode"], **effects["second_mode"]}
        y = (1.0 - e["fraction"]) * y + e["fraction"] * chain.ringdown_response(
            t_s, tau * e["tau_ratio"]
        )
    if "extinction_tail" in effects:
        e = {**EFFECT_DEFAULTS["extinction_tail"], **effects["extinction_tail"]}
        # cavity fed by eps exp(-t/tau_x) after t = 0: P += eps tau_x/(tau_x - tau) (e^{-t/tau_x} -
        # e^{-t/tau})
        tx = e["tau_s"]
        coef = e["fraction"] * tx / (tx - tau)
        y = y + coef[:, None] * np.real(
            chain.causal_exponential_response(t_s, np.full(tau.size, -1.0 / tx))
            - chain.causal_exponential_response(t_s, -1.0 / tau)
        )
    if "mode_beating" in effects:
        e = {**EFFECT_DEFAULTS["mode_beating"], **effects["mode_beating"]}
        lam = -1.0 / tau + 2j * np.pi * e["freq_hz"]
        y = y + e["fraction"] * np.real(
            np.exp(1j * e["phase_rad"]) * chain.causal_exponential_response(t_s, lam)
        )
    return amplitude_v * y


def acquire(
    clean_v, c: Campaign, noise_v: float, effects: dict, t_s, rng: np.random.Generator, chain=None
):
    """Average ``n_avg`` acquisitions: offset (+ drift), nonlinearity, noise, ADC quantisation.

    The noise of each acquisition has the PSD shape ``c.noise`` (``chain`` for its ``chain``
    kind) and the per-sample standard deviation ``noise_v`` (V).
    """
    v = clean_v + c.offset_v
    if "baseline_drift" in effects:
        e = {**EFFECT_DEFAULTS["baseline_drift"], **effects["baseline_drift"]}
        v = v + e["slope_v_per_s"] * (t_s - t_s[0])[None, :]
    v = _nonlinear(v, effects)
    lo, hi = c.adc_range_v
    lsb = (hi - lo) / 2**c.adc_bits
    out = np.zeros_like(v)
    if c.noise.is_white:

        def draw():
            return rng.standard_normal(v.shape)
    else:
        filt = shaping_filter(c.noise, v.shape[-1], float(t_s[1] - t_s[0]), chain)

        def draw():
            return coloured_noise(v.shape, filt, rng)

    for _ in range(c.n_avg):
        sample = v + noise_v * draw()
        out += np.clip(np.round((sample - lo) / lsb), 0, 2**c.adc_bits - 1) * lsb + lo
    return out / c.n_avg


# --------------------------------------------------------------------------- the campaign


def tf_measurement(chain: RationalChain, c: Campaign, effects, rng):
    """A simulated beat-note measurement of ``chain`` (letter Eq. 1).

    |H| at the campaign's frequencies with its noise, as the bundle's transfer-function group holds
    it.
    """
    f = np.logspace(np.log10(c.beat_f_hz[0]), np.log10(c.beat_f_hz[1]), c.beat_points)
    i1, i2 = c.beat_dc_v
    h = np.abs(chain.frequency_response(f))
    # DC levels measured through the static response; the beat's small-signal gain is its slope
    i1_m = float(
        _nonlinear(np.array(i1 + c.offset_v), effects) - _nonlinear(np.array(c.offset_v), effects)
    )
    i2_m = float(
        _nonlinear(np.array(i2 + c.offset_v), effects) - _nonlinear(np.array(c.offset_v), effects)
    )
    slope = float(_nonlinear_slope(np.array(i1 + i2 + c.offset_v), effects))
    b12 = 2 * np.sqrt(i1 * i2) * h * slope
    u = c.beat_rel_noise * b12
    b12 = b12 + u * rng.standard_normal(f.size)
    return TransferFunctionData(f_hz=f, b12_v=b12, b12_u_v=u, i1_v=i1_m, i2_v=i2_m)


def cmds_noise(nu_hz, lt, c: Campaign):
    """Shift noise (Hz) per mode giving u(A_ref)/A_ref = ``cmds_area_rel_u``.

    The relative u is that of the reference fit the package runs on the mode shifts
    (:func:`bayes_tfcrds.fit.line_analysis.fit_reference`): A, position, Gamma0, Gamma2 and
    nu_VC of the qSDHCP line free, with a sloped baseline. A Jacobian of A, position and Gamma0
    alone understates u(A_ref) by a factor 1.6 on the letter's grid (0.094 % realised for a
    0.06 % target), because Gamma2 and nu_VC correlate with A.
    """

    def shifts(area, nu0, g0, g2, nvc):
        lt2 = replace(
            lt, line_area_hz_per_m=area, nu0_hz=nu0, gamma0_hz=g0, gamma2_hz=g2, nu_vc_hz=nvc
        )
        return dispersion_shift_truth(nu_hz, lt2, {})

    theta = np.array([lt.line_area_hz_per_m, lt.nu0_hz, lt.gamma0_hz, lt.gamma2_hz, lt.nu_vc_hz])
    # Gamma2 and nu_VC may be 0 in the truth: their steps scale with Gamma0
    steps = np.array([1e-6 * theta[0], 1e3, 1e-4 * theta[2], 1e-4 * theta[2], 1e-4 * theta[2]])
    jac = np.empty((nu_hz.size, theta.size + 2))
    for j in range(theta.size):
        tp, tm = theta.copy(), theta.copy()
        tp[j] += steps[j]
        tm[j] -= steps[j]
        jac[:, j] = (shifts(*tp) - shifts(*tm)) / (2 * steps[j])
    # the sloped baseline of the dispersion fit: offset and slope in detuning
    jac[:, -2] = 1.0
    jac[:, -1] = (nu_hz - lt.nu0_hz) / np.ptp(nu_hz)
    cov_unit = np.linalg.inv(jac.T @ jac)  # for unit shift noise
    return c.cmds_area_rel_u * theta[0] / np.sqrt(cov_unit[0, 0])


@dataclass(frozen=True)
class SpectrumTruth:
    """The true spectrum every configuration of a campaign sees (SI).

    Mode frequencies (Hz), decay times (s), absorption (1/m), empty-cavity loss (1/m), CMDS shifts
    and widths (Hz), the shift noise (Hz) and the sample times (s).
    """

    nu_hz: np.ndarray
    tau_s: np.ndarray
    alpha_per_m: np.ndarray
    alpha_loss_per_m: float
    shift_hz: np.ndarray
    shift_u_hz: float
    width_hz: np.ndarray
    time_s: np.ndarray


def spectrum_truth(campaign: Campaign, lt: LineTruth, effects: dict) -> SpectrumTruth:
    """The true decay times, mode shifts and widths at the campaign's cavity modes."""
    nu_modes = lt.nu0_hz + spectral_points(campaign)
    alpha_loss = 1.0 / (C * campaign.finesse / (2 * np.pi * campaign.fsr_hz))
    alpha = absorption_truth(nu_modes, lt, effects)
    return SpectrumTruth(
        nu_hz=nu_modes,
        tau_s=1.0 / (C * (alpha + alpha_loss)),
        alpha_per_m=alpha,
        alpha_loss_per_m=alpha_loss,
        shift_hz=dispersion_shift_truth(nu_modes, lt, effects),
        shift_u_hz=cmds_noise(nu_modes, lt, campaign),
        width_hz=C * (alpha + alpha_loss) / (4 * np.pi),
        time_s=campaign.t0_s + campaign.dt_s * np.arange(campaign.n_samples),
    )


def record_noise_v(noise_single_v: float, campaign: Campaign) -> float:
    """Noise (V) of an averaged record.

    Single-acquisition noise and ADC quantisation in quadrature, over sqrt(n_avg).
    """
    lsb_term = (
        (campaign.adc_range_v[1] - campaign.adc_range_v[0]) / 2**campaign.adc_bits / np.sqrt(12)
    )
    return np.hypot(noise_single_v, lsb_term) / np.sqrt(campaign.n_avg)


def simulate_configuration(
    pre: ChainPreset,
    tf: TFParams,
    noise_single_v: float,
    campaign: Campaign,
    effects: dict,
    truth: SpectrumTruth,
    streams: tuple,
) -> Config:
    """One configuration's ring-downs, beat note and CMDS through the chain ``tf``.

    The chain acts when the transfer-function effect is on; ``streams`` = (ring-down, beat, CMDS)
    generators.
    """
    s_rd, s_beat, s_cmds = streams
    nu, t = truth.nu_hz, truth.time_s
    chain = chain_from_tf(tf) if "transfer_function" in effects else IDEAL_CHAIN
    clean = detected_transients(t, truth.tau_s, chain, effects, campaign.amplitude_v)
    signal = acquire(clean, campaign, noise_single_v, effects, t, s_rd, chain)
    rd = RingdownData(
        nu_hz=nu,
        signal_v=signal,
        dt_s=campaign.dt_s,
        t0_s=campaign.t0_s,
        n_avg=np.full(nu.size, campaign.n_avg),
        noise_v=np.full(nu.size, record_noise_v(noise_single_v, campaign)),
    )
    tfd = tf_measurement(chain, campaign, effects, s_beat)
    cm = CmdsData(
        nu_hz=nu,
        shift_hz=truth.shift_hz + truth.shift_u_hz * s_cmds.standard_normal(nu.size),
        shift_u_hz=np.full(nu.size, truth.shift_u_hz),
        width_hz=truth.width_hz + campaign.cmds_width_u_hz * s_cmds.standard_normal(nu.size),
        width_u_hz=np.full(nu.size, campaign.cmds_width_u_hz),
    )
    return Config(
        name=pre.label, ringdowns=rd, transfer_function=tfd, cmds=cm, description=pre.description
    )


def simulated_sample(campaign: Campaign, lt: LineTruth) -> Sample:
    """The bundle's /sample of a simulated campaign (CO (3-0) R(23), pure CO)."""
    return Sample(
        molecule="CO",
        line="(3-0) R(23)",
        nu0_hz=lt.nu0_hz,
        pressure_pa=campaign.pressure_pa + campaign.pressure_error_pa,
        pressure_u_pa=campaign.pressure_u_pa,
        temperature_k=campaign.temperature_k + campaign.temperature_error_k,
        temperature_u_k=campaign.temperature_u_k,
        mole_fraction=1.0,
        mass_u=load_line().mass_u,
    )


def _effects_truth(effects: dict) -> dict:
    """Each effect's parameters with defaults filled in (None values left out)."""
    return {
        k: {
            kk: (vv if isinstance(vv, str) else float(vv))
            for kk, vv in {**EFFECT_DEFAULTS[k], **v}.items()
            if vv is not None
        }
        for k, v in effects.items()
    }


def _preset_of(name) -> ChainPreset:
    """A preset by name, or a :class:`ChainPreset` given directly (e.g. a chain-zoo draw)."""
    if isinstance(name, ChainPreset):
        return name
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose from {sorted(PRESETS)}")
    return PRESETS[name]


def simulate_campaign(
    presets,
    rng: np.random.Generator,
    campaign: Campaign = Campaign(),
    effects: dict | None = None,
    line_effects_default: bool = True,
    streams: dict | None = None,
    line: LineTruth | None = None,
    chain_tf: dict | None = None,
    noise_v: dict | None = None,
    description: str | None = None,
):
    """Simulate one campaign: one configuration per preset (``letter-D1`` ... ``letter-D4``).

    ``presets`` holds preset names or :class:`ChainPreset` objects (a chain of one's own, e.g.
    from :mod:`bayes_tfcrds.simulate.zoo`, with its configuration label and noise).

    ``effects`` maps canonical effect names to parameter dicts (defaults filled in). With
    ``line_effects_default`` the letter's line (speed dependence and hard collisions on) and
    the presets' chains are used unless ``effects`` says otherwise; pass an explicit dict with
    ``line_effects_default=False`` to start from an ideal chain and a Voigt line.
    Each measurement draws its noise from its own stream, spawned from ``rng``: ``ringdown``,
    ``beat`` and ``cmds`` (one child per configuration each). ``streams`` may override any of
    them with a Generator, e.g. to repeat the beat-note measurement exactly while the ring-down
    noise changes (noise-only studies). Returns ``(Bundle, truth_dict)``.

    Drawn truths (the coverage study) replace parts of the presets: ``line`` the line's truth,
    ``chain_tf`` a preset's chain (preset name -> TFParams, used where the transfer-function
    effect is on) and ``noise_v`` its single-acquisition noise (preset name -> V);
    ``description`` the bundle's.

    Parameters
    ----------
    presets : list of str or ChainPreset
        ``letter-D1`` ... ``letter-D4`` (configuration ``D1`` ... ``D4``) or chains of one's own.
    rng : numpy.random.Generator
        The only source of randomness; the same seed gives the same bundle.
    campaign : Campaign
        Sample conditions, scan and digitizer (SI); ``Campaign(n_points=41, n_samples=8192,
        n_avg=20)`` is a quick one (seconds).
    effects, line_effects_default, streams, line, chain_tf, noise_v, description
        As above.

    Returns
    -------
    (Bundle, dict)
        The measurement bundle and the truth it was simulated from (SI).
    """
    effects = dict(effects or {})
    if line_effects_default:
        for name in ("transfer_function", "speed_dependence", "hard_collisions"):
            effects.setdefault(name, {})
    lt = line_truth(campaign, effects) if line is None else line
    chain_tf, noise_v = dict(chain_tf or {}), dict(noise_v or {})
    truth = spectrum_truth(campaign, lt, effects)
    base = dict(zip(("ringdown", "beat", "cmds"), rng.spawn(3)))
    base.update(streams or {})
    per_config = {k: g.spawn(len(presets)) for k, g in base.items()}
    configs, truth_cfg = {}, {}
    for ci, name in enumerate(presets):
        pre = _preset_of(name)
        name = name if isinstance(name, str) else pre.label
        tf = chain_tf.get(name, pre.tf)
        noise_single = noise_v.get(name, pre.noise_v)
        streams_ci = tuple(per_config[k][ci] for k in ("ringdown", "beat", "cmds"))
        configs[pre.label] = simulate_configuration(
            pre, tf, noise_single, campaign, effects, truth, streams_ci
        )
        truth_cfg[pre.label] = {
            "preset": name,
            "tau_s": truth.tau_s,
            "alpha_per_m": truth.alpha_per_m,
            **{k: float(v) for k, v in asdict(tf).items() if k != "variant"},
            "chain_variant": tf.variant,
            "chain_active": int("transfer_function" in effects),
            "noise_v_single": noise_single,
            "noise_colour": campaign.noise.describe(),
        }
    bundle = Bundle(
        sample=simulated_sample(campaign, lt),
        cavity=Cavity(fsr_hz=campaign.fsr_hz, finesse=campaign.finesse),
        configs=configs,
        description=description
        or "simulated by bayes-tfcrds: "
        + ", ".join(_preset_of(n).label if not isinstance(n, str) else n for n in presets),
    )
    truth_dict = {
        "line": {k: (float(v) if not isinstance(v, str) else v) for k, v in asdict(lt).items()},
        "alpha_loss_per_m": float(truth.alpha_loss_per_m),
        "effects": _effects_truth(effects),
        "effects_on": ",".join(sorted(effects)),
        "configs": truth_cfg,
    }
    if campaign.pressure_error_pa or campaign.temperature_error_k:
        # the gas's own conditions, where /sample reports the gauges' readings
        truth_dict["sample"] = {
            "pressure_pa": campaign.pressure_pa,
            "temperature_k": campaign.temperature_k,
        }
    return bundle, truth_dict
