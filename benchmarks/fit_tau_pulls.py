"""Pulls of ``fit``'s decay times (tau at the centre of H's posterior, u(tau) = noise + H) and of
``linefit``'s line area (A from those decay times, u(A) = line fit + H) against the simulated
truth, on random chains and on detector noise whose shapes and generator are not the
simulator's.

Each campaign: a random chain (chain zoo, both regimes of Eq. 2, or one of the letter's four
presets), 41 cavity modes of 16384 samples, 20 averages. The transients are simulated without
noise (a 24-bit digitizer, so no rounding) and a noise made here is added, with the record's
stated sd: white, Butterworth low-pass (order 2-6, 1-12 MHz), a resonant AR(2) (0.3-8 MHz,
pole radius 0.8-0.97), white + Ornstein-Uhlenbeck (corner 10 kHz-1 MHz, 10-60 % of the
variance), white + random walk (non-stationary) and differenced white noise (less power at low
frequency than at high). Each is a time-domain recursion (scipy.signal.lfilter), not the
simulator's FFT shaping.

``--kinds`` (comma-separated) picks other noise kinds; campaign ``index`` gets
``kinds[index % len(kinds)]``. The default is the six above in that order, which reproduces the
previous campaigns exactly (same kind at the same index, same random streams). Four further
kinds, also not the simulator's, can be chosen:

- ``pink``: 1/f flicker of the detector / amplifier, FFT-shaped 1/f^alpha noise (alpha
  0.7-1.5) making up 20-80 % of the variance, the rest white;
- ``pickup``: an RF pickup line, a sinusoid (0.1-5 MHz, random phase per record) making up
  10-50 % of the variance, plus white;
- ``bandpass``: a resonant amplifier stage, white noise through ``scipy.signal.iirpeak``
  (centre 0.2-5 MHz, Q 1-20) making up 20-80 % of the variance, plus white;
- ``student``: heavy-tailed bursts, Student-t white noise (nu 3-8) scaled to unit variance.

All kinds are normalised as the others: the record's per-sample sd is that of the white noise
they replace. The analysis is the shipped one of ``bayes-tfcrds fit``
(:func:`~bayes_tfcrds.fit.h_calibration.account_for_noise_colour`,
:func:`~bayes_tfcrds.fit.h_calibration.calibrate`,
:func:`~bayes_tfcrds.uncertainty.decay_times.fit_decay_times`; for A, ``linefit``'s
:func:`~bayes_tfcrds.uncertainty.line_area.analyse_line_with_h` with the same H draws, qsdhcp).

The statistics are A's pull and the line-centre tau's pull (one per campaign and t_cut: the H
error is common to a campaign's points, so their pulls are not independent), with the total u.
PASS when its root mean square over the campaigns (bias and scatter) is within 1 +/- 0.2 at
every t_cut, for tau and for A (with 60 campaigns its sampling sd is 0.09: the band is 2.2 of
them). For comparison the same pulls at the letter's H (f_c refined, the rest at the beat note;
same total u) are shown.

Usage:  python benchmarks/fit_tau_pulls.py --campaigns 60 --seed 11 --workers 2
        python benchmarks/fit_tau_pulls.py --kinds pink,pickup,bandpass,student --campaigns 60
"""

from __future__ import annotations

import argparse
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace

import numpy as np
from scipy import signal

KINDS = ("white", "butterworth", "ar2", "ou", "random-walk", "differenced")  # the default
EXTRA_KINDS = ("pink", "pickup", "bandpass", "student")
ALL_KINDS = KINDS + EXTRA_KINDS
PRESETS = ("letter-D1", "letter-D2", "letter-D3", "letter-D4")
T_CUTS_S = (2e-6, 4e-6, 8e-6)
FS_HZ = 50e6  # the simulated digitizer's rate (20 ns)
BURN = 4096  # samples a recursion runs before the record starts (stationary start)
BAND = 0.2


def _shape(kind: str, rng) -> dict:
    """Random parameters of one noise shape (SI)."""
    log_uniform = lambda a, b: float(np.exp(rng.uniform(np.log(a), np.log(b))))  # noqa: E731
    if kind == "butterworth":
        return {"order": int(rng.integers(2, 7)), "f_hz": log_uniform(1e6, 12e6)}
    if kind == "ar2":
        return {"r": float(rng.uniform(0.8, 0.97)), "f_hz": log_uniform(3e5, 8e6)}
    if kind == "ou":
        return {"f_hz": log_uniform(1e4, 1e6), "share": float(rng.uniform(0.1, 0.6))}
    if kind == "random-walk":
        return {"step": log_uniform(1e-3, 2e-2)}
    if kind == "differenced":
        return {"c": float(rng.uniform(0.3, 0.9))}
    if kind == "pink":
        return {"alpha": float(rng.uniform(0.7, 1.5)), "share": float(rng.uniform(0.2, 0.8))}
    if kind == "pickup":
        return {"f_hz": log_uniform(1e5, 5e6), "share": float(rng.uniform(0.1, 0.5))}
    if kind == "bandpass":
        return {
            "f_hz": log_uniform(2e5, 5e6),
            "q": float(rng.uniform(1.0, 20.0)),
            "share": float(rng.uniform(0.2, 0.8)),
        }
    if kind == "student":
        return {"nu": float(rng.uniform(3.0, 8.0))}
    return {}


def noise(kind: str, par: dict, shape, rng) -> np.ndarray:
    """Unit-variance noise of one shape (records x samples): time-domain recursions, except
    ``pink`` (FFT-shaped), ``pickup`` (a sinusoid) and ``student`` (heavy-tailed white)."""
    m, k = shape
    w = rng.standard_normal((m, k + BURN))
    if kind == "butterworth":
        b, a = signal.butter(par["order"], par["f_hz"] / (FS_HZ / 2))
        y = signal.lfilter(b, a, w, axis=-1)
    elif kind == "ar2":
        r, f0 = par["r"], par["f_hz"]
        y = signal.lfilter([1.0], [1.0, -2 * r * np.cos(2 * np.pi * f0 / FS_HZ), r * r], w, axis=-1)
    elif kind == "ou":
        phi = np.exp(-2 * np.pi * par["f_hz"] / FS_HZ)
        ou = signal.lfilter([np.sqrt(1 - phi**2)], [1.0, -phi], rng.standard_normal(w.shape), -1)
        y = np.sqrt(1 - par["share"]) * w + np.sqrt(par["share"]) * ou
    elif kind == "random-walk":
        walk = np.cumsum(rng.standard_normal(w.shape), axis=-1)
        y = w + par["step"] * (walk - walk[:, BURN : BURN + 1])
    elif kind == "differenced":
        y = w - par["c"] * np.roll(w, 1, axis=-1)
    elif kind == "pink":  # 1/f^alpha power: amplitude f^(-alpha/2), no DC
        f = np.fft.rfftfreq(k + BURN, 1 / FS_HZ)
        gain = np.zeros_like(f)
        gain[1:] = (f[1:] / f[1]) ** (-par["alpha"] / 2)
        spec = np.fft.rfft(rng.standard_normal(w.shape), axis=-1) * gain
        pink = np.fft.irfft(spec, n=k + BURN, axis=-1)
        pink /= np.sqrt(np.mean(pink**2))
        y = np.sqrt(1 - par["share"]) * w + np.sqrt(par["share"]) * pink
    elif kind == "pickup":  # unit-variance sinusoid, random phase per record
        t = np.arange(k + BURN) / FS_HZ
        phase = rng.uniform(0, 2 * np.pi, (m, 1))
        line = np.sqrt(2) * np.sin(2 * np.pi * par["f_hz"] * t + phase)
        y = np.sqrt(1 - par["share"]) * w + np.sqrt(par["share"]) * line
    elif kind == "bandpass":
        b, a = signal.iirpeak(par["f_hz"], par["q"], fs=FS_HZ)
        peak = signal.lfilter(b, a, rng.standard_normal(w.shape), axis=-1)
        peak /= np.sqrt(np.mean(peak[:, BURN:] ** 2))
        y = np.sqrt(1 - par["share"]) * w + np.sqrt(par["share"]) * peak
    elif kind == "student":  # sd of t_nu is sqrt(nu / (nu - 2))
        nu = par["nu"]
        y = rng.standard_t(nu, w.shape) * np.sqrt((nu - 2) / nu)
    else:
        y = w
    y = y[:, BURN:]
    return y / np.sqrt(np.mean(y**2))


def one_campaign(args) -> dict:
    """Simulate, add the noise, analyse as ``fit`` does; the line-centre pulls."""
    from bayes_tfcrds.fit.h_calibration import account_for_noise_colour, calibrate
    from bayes_tfcrds.fit.line_analysis import analyse_line
    from bayes_tfcrds.fit.ringdown import fit_ringdowns
    from bayes_tfcrds.simulate.campaign import PRESETS as PRESET_TABLE
    from bayes_tfcrds.simulate.campaign import (
        Campaign,
        ChainPreset,
        record_noise_v,
        simulate_campaign,
    )
    from bayes_tfcrds.simulate.zoo import draw_chain
    from bayes_tfcrds.uncertainty.decay_times import fit_decay_times, h_part_of_tau_u
    from bayes_tfcrds.uncertainty.line_area import analyse_line_with_h

    index, seed, kinds = args
    rng = np.random.default_rng([seed, index])
    kind = kinds[index % len(kinds)]
    par = _shape(kind, rng)
    campaign = Campaign(n_points=41, n_avg=20, adc_bits=24)
    # every noise kind meets every chain kind: the kind cycles with index, the chain with
    # index // len(kinds)
    cycle = (index // len(kinds)) % 3
    if cycle == 2:
        chain = PRESETS[int(rng.integers(len(PRESETS)))]
        key, single_v = chain, PRESET_TABLE[chain].noise_v
        preset = chain
    else:
        chain = ("tail", "pole")[cycle]
        preset = ChainPreset("Z", "zoo", draw_chain(rng, chain))
        key, single_v = "Z", preset.noise_v
    # without the simulator's noise; the record's sd is the preset's, the noise is added below
    bundle, truth = simulate_campaign([preset], rng, campaign, noise_v={key: 0.0})
    name = next(iter(bundle.configs))
    cfg = bundle.configs[name]
    tau_true = np.asarray(truth["configs"][name]["tau_s"])
    level = record_noise_v(single_v, campaign)
    rd = cfg.ringdowns
    y = noise(kind, par, rd.signal_v.shape, np.random.default_rng([seed, index, 1]))
    rd = replace(rd, signal_v=rd.signal_v + level * y, noise_v=np.full(rd.nu_hz.size, level))
    cfg = replace(cfg, ringdowns=rd)
    t0 = time.perf_counter()
    prepared, diagnosis, beat = account_for_noise_colour(cfg)
    cal = calibrate(prepared, beat=beat)
    fits, h = fit_decay_times(prepared, T_CUTS_S, cal, np.random.default_rng([seed, index, 2]))
    seconds = time.perf_counter() - t0
    centre = int(np.argmin(tau_true))
    letter = fit_ringdowns(prepared.ringdowns, T_CUTS_S, "tf-crds", tf=cal.params)
    letter_u = np.hypot(letter.tau_u_s, h_part_of_tau_u(prepared, letter, h))
    a_true = truth["line"]["line_area_hz_per_m"]
    measured = replace(bundle, configs={name: prepared})
    lines = [
        analyse_line_with_h(measured, prepared, cal, None, tc, h=h, noise=diagnosis)[0]
        for tc in T_CUTS_S
    ]
    at_letter = [
        analyse_line(measured, prepared, t_cut_s=tc, calibration=cal, noise=diagnosis)
        for tc in T_CUTS_S
    ]
    return {
        "kind": kind,
        "chain": chain,
        "pull": ((fits.tau_s[centre] - tau_true[centre]) / fits.tau_u_total_s[centre]).tolist(),
        "pull_letter": ((letter.tau_s[centre] - tau_true[centre]) / letter_u[centre]).tolist(),
        "u_h_share": (fits.tau_u_h_s[centre] / fits.tau_u_s[centre]).tolist(),
        "pull_a": [(la.line_fit.line_area - a_true) / la.line_area_u_si for la in lines],
        "pull_a_letter": [  # the letter's H, u(A) with the same H part
            (old.line_fit.line_area - a_true)
            / np.hypot(old.line_fit.line_area_u, la.line_area_u_h_si)
            for old, la in zip(at_letter, lines)
        ],
        "a_h_share": [la.line_area_u_h_si / la.line_fit.line_area_u for la in lines],
        "kappa": diagnosis.kappa_median,
        "seconds": seconds,
    }


def _rms(pulls: np.ndarray) -> np.ndarray:
    """Root mean square over campaigns (axis 0): 1 for unbiased pulls of a calibrated u."""
    return np.sqrt(np.mean(np.asarray(pulls, float) ** 2, axis=0))


def _kinds(text: str) -> tuple[str, ...]:
    """``--kinds``: comma-separated noise kinds, each known, none twice."""
    kinds = tuple(k.strip() for k in text.split(",") if k.strip())
    unknown = [k for k in kinds if k not in ALL_KINDS]
    if unknown:
        raise argparse.ArgumentTypeError(
            f"unknown noise kind(s) {', '.join(unknown)}; choose from {', '.join(ALL_KINDS)}"
        )
    if not kinds or len(set(kinds)) != len(kinds):
        raise argparse.ArgumentTypeError("give at least one noise kind, none twice")
    return kinds


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--campaigns", type=int, default=60)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument(
        "--kinds",
        type=_kinds,
        default=KINDS,
        help=f"comma-separated noise kinds of {', '.join(ALL_KINDS)} (default: "
        f"{','.join(KINDS)}, the previous campaigns)",
    )
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    with ProcessPoolExecutor(a.workers) as pool:
        recs = list(pool.map(one_campaign, [(i, a.seed, a.kinds) for i in range(a.campaigns)]))
    print(f"{len(recs)} campaigns in {time.perf_counter() - t0:.0f} s ({a.workers} workers)")
    print(
        "| noise | campaigns | line-centre tau pull rms at t_cut 2 / 4 / 8 us | A pull rms "
        "| kappa range |"
    )
    print("|---|---|---|---|---|")
    for kind in a.kinds:
        rs = [r for r in recs if r["kind"] == kind]
        if rs:
            rms = _rms(np.array([r["pull"] for r in rs]))
            rms_a = _rms(np.array([r["pull_a"] for r in rs]))
            kap = [r["kappa"] for r in rs]
            print(f"| {kind} | {len(rs)} | {' / '.join(f'{v:.2f}' for v in rms)} "
                  f"| {' / '.join(f'{v:.2f}' for v in rms_a)} "
                  f"| {min(kap):.2f}-{max(kap):.2f} |")  # fmt: skip
    se = 1.0 / np.sqrt(2 * len(recs))
    ok = True
    for what, key in (("line-centre tau", "pull"), ("line area A", "pull_a")):
        pulls = np.array([r[key] for r in recs])
        letter = np.array([r[key + "_letter"] for r in recs])
        rms = _rms(pulls)
        ok &= bool(np.all(np.abs(rms - 1) <= BAND))
        for j, tc in enumerate(T_CUTS_S):
            print(
                f"{what}, t_cut {tc * 1e6:g} us: pull rms {rms[j]:.3f} +/- {se:.3f} "
                f"(mean {pulls[:, j].mean():+.2f}); at the letter's H {_rms(letter)[j]:.2f}; "
                f"|pull| > 3: {np.sum(np.abs(pulls[:, j]) > 3)} of {len(recs)}"
            )
    print(
        f"median u_H / u_noise at the line centre: {np.median([r['u_h_share'] for r in recs]):.2f}"
        f"; of A, u_H / u_fit: {np.median([r['a_h_share'] for r in recs]):.2f}"
    )
    print(
        "PASS" if ok else "FAIL", f"(pull rms of tau and of A within 1 +/- {BAND} at every t_cut)"
    )
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
