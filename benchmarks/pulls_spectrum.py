"""Line-area pulls of the spectrum fits over many noise draws (issue acceptance: mean 0 +/- 0.1,
sd 1 +/- 0.15 over >= 200 draws), for CRDS absorption, CMDS dispersion and the joint fit, and
the area bias of a Voigt fitted to qSDHCP data.

Each fit is also compared, draw by draw, with the linearised (Gauss-Markov) estimator
A0 + (J+ noise)_A, J the Jacobian at the truth: that estimator is exactly unbiased with
pull sd 1, so its sample mean is the part of the fit's pull mean that belongs to this noise
realisation (se 1/sqrt(draws)), and "fit - linear", the mean of (A_fit - A)/sd(A) minus the
linear pull, is the estimator's own bias in units of sd(A). The table
also gives the fraction of fits with a shape estimate outside the physical domain
(Gamma2 < 0 or nu_VC < 0, on the profile's continuation) and the pull mean of those fits.

Usage:  python benchmarks/pulls_spectrum.py [--draws 1000] [--seed 42]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bayes_tfcrds.core.constants import C, wavenumber_cm_to_hz
from bayes_tfcrds.core.linalg import central_jacobian
from bayes_tfcrds.fit.line import fit_line
from bayes_tfcrds.fit.spectrum import SpectrumData, crds_spectrum
from bayes_tfcrds.physics.lineshape import doppler_hwhm_hz, profile


def _linear_gain(spectra, gd, nu0):
    """Row of (J^T J)^-1 J^T for A divided by sd(A), and sd(A) (Hz/m), at the noiseless fit
    (which is the truth to 1e-15)."""
    f = fit_line(spectra, "qsdhcp", gd, nu0)
    model_u = np.concatenate([s.u for s in spectra])
    from bayes_tfcrds.fit.line import LineModel

    model = LineModel(
        "qsdhcp",
        ("gamma0_hz", "gamma2_hz", "nu_vc_hz"),
        tuple(s.kind for s in spectra),
        tuple(s.kind == "dispersion" for s in spectra),
        nu0,
        gd,
        {},
    )
    steps = 1e-6 * np.maximum(np.abs(f.values), 1e-3 * gd)
    jac = (
        central_jacobian(lambda th: np.concatenate(model.predict(th, spectra)), f.values, steps)
        / model_u[:, None]
    )
    fisher = jac.T @ jac
    sd = np.sqrt(np.linalg.inv(fisher)[0, 0])
    return np.linalg.solve(fisher, jac.T)[0] / sd, sd


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
    clean = {
        "CRDS (absorption)": [SpectrumData("absorption", nu, alpha, u_a)],
        "CMDS (dispersion)": [SpectrumData("dispersion", nu, shift + 3.0, u_s)],
    }
    clean["joint"] = clean["CRDS (absorption)"] + clean["CMDS (dispersion)"]
    gains = {key: _linear_gain(spectra, gd, nu0) for key, spectra in clean.items()}
    rng = np.random.default_rng(args.seed)
    rows = {key: [] for key in clean}
    t0 = time.perf_counter()
    for _ in range(args.draws):
        ea, es = rng.standard_normal(nu.size), rng.standard_normal(nu.size)
        a = SpectrumData("absorption", nu, alpha + u_a * ea, u_a)
        d = SpectrumData("dispersion", nu, shift + 3.0 + u_s * es, u_s)
        for key, spectra, e in (
            ("CRDS (absorption)", [a], ea),
            ("CMDS (dispersion)", [d], es),
            ("joint", [a, d], np.concatenate([ea, es])),
        ):
            f = fit_line(spectra, "qsdhcp", gd, nu0)
            gain, sd = gains[key]
            rows[key].append(
                (
                    (f.line_area - area) / f.line_area_u,
                    gain @ e,
                    bool(f.unphysical),
                    (f.line_area - area) / sd,
                )
            )
    print(
        f"{args.draws} draws, seed {args.seed}, {time.perf_counter() - t0:.0f} s; standard error "
        f"of a pull mean {1 / np.sqrt(args.draws):.3f}"
    )
    print(
        "| fit | pull mean | pull sd | PASS (mean 0 +/- 0.1, sd 1 +/- 0.15) | linear-estimator "
        "pull mean | fit - linear | Gamma2 or nu_VC < 0 | pull mean there "
        "|\n|---|---|---|---|---|---|---|---|"
    )
    for key, r in rows.items():
        p, lin, out, dev = (np.array([x[i] for x in r]) for i in range(4))
        ok = abs(p.mean()) < 0.1 and abs(p.std() - 1) < 0.15
        there = f"{p[out].mean():+.3f}" if out.any() else "-"
        print(
            f"| {key} | {p.mean():+.3f} | {p.std():.3f} | {'PASS' if ok else 'FAIL'} | "
            f"{lin.mean():+.3f} | {np.mean(dev - lin):+.3f} | {out.mean():.1%} | {there} |"
        )
    tau = 1 / (C * alpha)
    s = crds_spectrum(nu, tau, 2e-5 * tau)
    v = fit_line([s], "voigt", gd, nu0)
    print(
        "Voigt fitted to noiseless qSDHCP CRDS data: A/A_true - 1 = "
        f"{100 * (v.line_area / area - 1):+.3f} %, chi2_red = {v.chi2_red:.0f} (W-shaped residual)"
    )


if __name__ == "__main__":
    main()
