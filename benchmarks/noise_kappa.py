"""The noise-colour factor kappa on record pairs of a reduced campaign: white and weak 1/f noise.

Residuals of b + B exp(-t/tau) + C t exp(-t/tau) fits of pure noise (decays 3-12 us, t_cut 4 us,
8192 samples at 20 ns, paired differences as :func:`bayes_tfcrds.fit.noise.diagnose_noise` makes
them) go through :func:`~bayes_tfcrds.fit.noise.noise_spectrum`; kappa is applied as the shipped
diagnosis applies it (colour flagged at 1e-3, or a flicker term Akaike keeps) and compared with
the true kappa of the simulated PSD. PASS when, on white noise, kappa is applied to at most 8 %
of configurations and stays below 1.6 where it is, and, on 1/f noise with an 8 kHz knee (true
kappa ~ 1.7, which the 1e-3 test misses about half the time on 8 pairs), it is applied to at
least 75 % and the median of used/true kappa is within 0.85-1.15.

Usage:  python benchmarks/noise_kappa.py --configs 150 --pairs 8 --seed 7
"""

from __future__ import annotations

import argparse

import numpy as np

from bayes_tfcrds.fit import noise as fn
from bayes_tfcrds.simulate.noise import coloured_noise, parse_noise, shaping_filter

DT = 20e-9
N_SAMPLES = 8192
FIRST = 200  # t_cut = 4 us


def one_config(filt, true_psd, pairs: int, rng) -> tuple[float, float, bool]:
    """(kappa used, true kappa, applied) for one configuration of ``pairs`` record pairs."""
    n = N_SAMPLES - FIRST
    n_fft = 2 * (true_psd.size - 1)
    t = FIRST * DT + DT * np.arange(n)
    tau = np.repeat(rng.uniform(3e-6, 12e-6, pairs), 2)
    basis = fn.fitted_basis(t, tau)
    j = fn.profiled_tau_direction(basis)
    x = coloured_noise((2 * pairs, N_SAMPLES), filt, rng)[:, FIRST:]
    r = x - np.einsum("rnc,rc->rn", basis, np.einsum("rnc,rn->rc", basis, x))
    d = r[0::2] - r[1::2]
    z = d / np.sqrt(np.mean(d**2, -1))[:, None]
    psd, band = fn.noise_spectrum(z, basis, n_fft)
    z_kappa = (band.flat / (fn._two_sided(psd) / n_fft) - 1.0) / band.rel_sd
    white = abs(z_kappa) < fn.Z_KAPPA and not band.flicker_significant
    applied = (not white) or band.has_flicker
    kappa = float(np.median(fn.colour_factors(psd, j))) if applied else 1.0
    return kappa, float(np.median(fn.colour_factors(true_psd, j))), applied


def run(kind: str, index: int, configs: int, pairs: int, seed: int) -> dict:
    colour = parse_noise(kind)
    filt = shaping_filter(colour, N_SAMPLES, DT)
    true_psd = filt**2
    rng = np.random.default_rng([seed, index])
    rows = np.array([one_config(filt, true_psd, pairs, rng) for _ in range(configs)])
    used, true, applied = rows[:, 0], rows[:, 1], rows[:, 2].astype(bool)
    return {
        "kind": kind,
        "applied": int(applied.sum()),
        "ratio": used / true,
        "applied_kappa": used[applied],
        "true_median": float(np.median(true)),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", type=int, default=150, help="configurations per noise kind")
    ap.add_argument("--pairs", type=int, default=8, help="record pairs per configuration")
    ap.add_argument("--seed", type=int, default=7)
    a = ap.parse_args(argv)
    white = run("white", 0, a.configs, a.pairs, a.seed)
    pink = run("pink:f_knee_hz=8e3,alpha=1.15", 1, a.configs, a.pairs, a.seed)
    print("| noise | true kappa | applied | used/true median (p10-p90) | kappa where applied |")
    print("|---|---|---|---|---|")
    for r in (white, pink):
        k = r["applied_kappa"]
        print(
            f"| {r['kind']} | {r['true_median']:.2f} | {r['applied']}/{a.configs} | "
            f"{np.median(r['ratio']):.3f} ({np.percentile(r['ratio'], 10):.2f}-"
            f"{np.percentile(r['ratio'], 90):.2f}) | "
            + (f"{np.median(k):.2f} median, {np.max(k):.2f} max |" if k.size else "- |")
        )
    ok_white = white["applied"] <= 0.08 * a.configs and np.all(white["applied_kappa"] < 1.6)
    ok_pink = pink["applied"] >= 0.75 * a.configs and 0.85 <= np.median(pink["ratio"]) <= 1.15
    print(
        f"white: {'PASS' if ok_white else 'FAIL'}; 1/f knee 8 kHz: {'PASS' if ok_pink else 'FAIL'}"
    )
    print("PASS" if ok_white and ok_pink else "FAIL")
    return 0 if ok_white and ok_pink else 1


if __name__ == "__main__":
    raise SystemExit(main())
