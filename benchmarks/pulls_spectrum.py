"""Line-area pulls of the spectrum fits over many noise draws (issue acceptance: mean 0 +/- 0.1,
sd 1 +/- 0.15 over >= 200 draws), for CRDS absorption, CMDS dispersion and the joint fit, and
the area bias of a Voigt fitted to qSDHCP data.

Usage:  python benchmarks/pulls_spectrum.py [--draws 1000] [--seed 42]
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from bayes_tfcrds.constants import C, wavenumber_cm_to_hz
from bayes_tfcrds.lineshape import doppler_hwhm_hz, profile
from bayes_tfcrds.spectrum import SpectrumData, fit_line


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=42)
    args = ap.parse_args(argv)
    nu0 = float(wavenumber_cm_to_hz(6410.879558))
    gd = float(doppler_hwhm_hz(nu0, 296.0, 27.99491462))
    g0 = 0.051 * C * 100 * 5 / 760
    shape = dict(gamma0_hz=g0, gamma2_hz=0.10 * g0, nu_vc_hz=0.46 * g0)
    area = 3.93e5
    nu = nu0 + np.arange(-49, 50) * 203e6
    g = profile("qsdhcp", nu - nu0, 0.0, gd, **shape)
    alpha = area * g.real + 1.0 / (C * 32.1e-6)
    shift = C * area * g.imag / (4 * np.pi)
    u_a = 2e-5 * alpha
    u_s = 1e-3 * np.max(np.abs(shift)) * np.ones_like(shift)
    rng = np.random.default_rng(args.seed)
    pulls = {"CRDS (absorption)": [], "CMDS (dispersion)": [], "joint": []}
    t0 = time.perf_counter()
    for _ in range(args.draws):
        a = SpectrumData("absorption", nu, alpha + u_a * rng.standard_normal(nu.size), u_a)
        d = SpectrumData("dispersion", nu, shift + 3.0 + u_s * rng.standard_normal(nu.size), u_s)
        for key, spectra in (("CRDS (absorption)", [a]), ("CMDS (dispersion)", [d]), ("joint", [a, d])):
            f = fit_line(spectra, "qsdhcp", gd, nu0)
            pulls[key].append((f.line_area - area) / f.line_area_u)
    print(f"{args.draws} draws, {time.perf_counter() - t0:.0f} s")
    print("| fit | pull mean | pull sd | PASS (mean 0 +/- 0.1, sd 1 +/- 0.15) |\n|---|---|---|---|")
    for key, p in pulls.items():
        p = np.asarray(p)
        ok = abs(p.mean()) < 0.1 and abs(p.std() - 1) < 0.15
        print(f"| {key} | {p.mean():+.3f} | {p.std():.3f} | {'PASS' if ok else 'FAIL'} |")
    tau = 1 / (C * alpha)
    from bayes_tfcrds.spectrum import crds_spectrum
    s = crds_spectrum(nu, tau, 2e-5 * tau)
    v = fit_line([s], "voigt", gd, nu0)
    print(f"Voigt fitted to noiseless qSDHCP CRDS data: A/A_true - 1 = {100 * (v.line_area / area - 1):+.3f} %, "
          f"chi2_red = {v.chi2_red:.0f} (W-shaped residual)")


if __name__ == "__main__":
    main()
