"""Performance targets on reference problem R1, each printed with its measured value and PASS/FAIL.

R1: one configuration (letter-D2), 101 spectral points, transients of 16384 samples at 20 ns,
six t_cut values (606 transient fits). Ratios are measured within one run (the machine is
noisy); memory is the peak resident set of a child process doing the R1 TF-CRDS fit.

The full run (without --quick) also times `bayes-tfcrds budget` on one letter configuration on
both cores (target 30 s) and the four-configuration budget study on both cores (target 20 min),
and measures how time and memory grow with points, samples and H draws.

Usage:  python benchmarks/run.py [--seed N] [--quick]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import replace

import numpy as np
from scipy import fft as sfft
from scipy import optimize

from bayes_tfcrds.core.constants import line_area_from_cm2
from bayes_tfcrds.fit.h_calibration import calibrate
from bayes_tfcrds.fit.line_analysis import doppler_of
from bayes_tfcrds.fit.ringdown import fit_ringdowns
from bayes_tfcrds.fit.spectrum import crds_spectrum
from bayes_tfcrds.physics.transfer_function import transfer_function
from bayes_tfcrds.simulate.campaign import Campaign, simulate_campaign

T_CUTS = (2e-6, 3e-6, 4e-6, 5e-6, 6e-6, 8e-6)
RESULTS = []


def report(name, value, target, ok, unit=""):
    RESULTS.append({"target": name, "value": value, "limit": target, "pass": bool(ok)})
    print(f"{'PASS' if ok else 'FAIL'}  {name}: {value:.3g}{unit} (target {target})", flush=True)


def r1_bundle(seed, points=101, samples=16384, n_avg=20):
    """A letter-D2 campaign of exactly `points` (odd) adjacent cavity modes centred on the line."""
    camp = replace(Campaign(), n_points=points, n_samples=samples, n_avg=n_avg)
    # a span of (points - 1)/2 FSR each side holds exactly `points` modes, all of them taken
    camp = replace(camp, span_hz=(points // 2 + 0.5) * camp.fsr_hz)
    b, truth = simulate_campaign(["letter-D2"], np.random.default_rng(seed), camp)
    return b, truth


def naive_fit(t, y, t_cut, tf, tau0):
    """The straightforward way: least_squares per transient over (B, b, tau), the model built by
    an FFT of the sampled exponential with history (extinction window) at every evaluation."""
    dt = t[1] - t[0]
    n_hist = 8000
    n = sfft.next_fast_len(n_hist + t.size + 600)
    s = t[0] + dt * (np.arange(n) - n_hist)
    h = transfer_function(np.fft.rfftfreq(n, dt), tf)
    sel = t >= t_cut

    def model(p):
        amp, off, tau = p
        x = np.where(s < 0, 1.0, np.exp(-np.clip(s, 0, None) / tau))
        g = np.fft.irfft(np.fft.rfft(x) * h, n)[n_hist : n_hist + t.size]
        return off + amp * g

    sol = optimize.least_squares(
        lambda p: (model(p) - y)[sel], [y[sel][0], 0.0, tau0], x_scale="jac"
    )
    return sol.x[2]


def peak_memory_child(seed, points, samples):
    """(peak resident set of the whole process, peak memory allocated by the fit itself), MiB.

    The first is the target (it includes Python, the imports and the simulated bundle); the
    second, traced by tracemalloc (numpy reports its buffers to it), is what grows with the size
    of the problem.
    """
    code = (
        "import numpy as np, resource, sys, tracemalloc; sys.path.insert(0, 'benchmarks');from "
        "run import r1_bundle, T_CUTS; from bayes_tfcrds.fit.h_calibration import calibrate;from "
        f"bayes_tfcrds.fit.ringdown import fit_ringdowns;b, _ = r1_bundle({seed}, {points}, "
        f"{samples}, 2); c = b.configs['D2'];cal = calibrate(c, "
        "window='extinction');tracemalloc.start();fit_ringdowns(c.ringdowns, T_CUTS, 'tf-crds', "
        "cal.params, 'extinction');print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, "
        "tracemalloc.get_traced_memory()[1])"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    rss_kib, fit_bytes = out.stdout.strip().splitlines()[-1].split()
    return int(rss_kib) / 1024.0, int(fit_bytes) / 2**20  # ru_maxrss is KiB on Linux


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="skip the scaling series")
    args = ap.parse_args(argv)
    b, truth = r1_bundle(args.seed)
    cfg = b.configs["D2"]
    rd = cfg.ringdowns
    print(
        f"R1: {rd.n_points} points x {rd.n_samples} samples x {len(T_CUTS)} t_cut = "
        f"{rd.n_points * len(T_CUTS)} fits"
    )
    cal = calibrate(cfg, window="extinction")
    tf = cal.params

    t0 = time.perf_counter()
    crds = fit_ringdowns(rd, T_CUTS, "crds")
    t_crds = time.perf_counter() - t0
    t0 = time.perf_counter()
    tfc = fit_ringdowns(rd, T_CUTS, "tf-crds", tf, "extinction")
    t_tf = time.perf_counter() - t0
    print(f"  CRDS {t_crds:.2f} s, TF-CRDS {t_tf:.2f} s (H given)")
    report("TF-CRDS / CRDS time on R1", t_tf / t_crds, "<= 3", t_tf / t_crds <= 3.0, "x")

    # straightforward implementation on a subset, scaled to 606 fits
    sub = np.arange(0, rd.n_points, max(1, rd.n_points // 8))[:8]
    t0 = time.perf_counter()
    naive = [naive_fit(rd.time_s, rd.signal_v[i], 4e-6, tf, crds.tau_s[i, 2]) for i in sub]
    t_naive = (time.perf_counter() - t0) / sub.size * rd.n_points * len(T_CUTS)
    agree = np.max(np.abs(np.array(naive) / tfc.tau_s[sub, 2] - 1))
    print(
        f"  straightforward least_squares: {t_naive:.0f} s for R1 (from {sub.size} fits); max "
        f"|tau/tau - 1| against ours {agree:.1e}"
    )
    report(
        "speed-up over straightforward least_squares",
        t_naive / t_tf,
        ">= 20",
        t_naive / t_tf >= 20,
        "x",
    )

    # propagation of 1000 H draws into A, against full refits
    from bayes_tfcrds.uncertainty.line_budget import BudgetOptions, run_budget

    opts = BudgetOptions(posterior="laplace", n_h_draws=1000)
    t0 = time.perf_counter()
    res = run_budget(b, cfg, opts, np.random.default_rng(args.seed))
    t_prop = time.perf_counter() - t0
    report(
        "1000 H draws propagated into A for R1 (whole Laplace budget)",
        t_prop,
        "<= 60 s",
        t_prop <= 60,
        " s",
    )
    gd = doppler_of(b.sample)
    sens = {k: float(line_area_from_cm2(v)) for k, v in res.summary["sensitivities_cm2"].items()}
    from bayes_tfcrds.fit.h_calibration import BEAT_FREE

    h_star = replace(tf)
    from bayes_tfcrds.physics.transfer_function import TFParams

    hs = res.summary["transfer_function"]
    h_star = TFParams(
        **{k: hs[k] for k in ("f_c_hz", "a_r", "f_r_hz", "gamma_r", "n_r", "variant")}
    )
    draws = res.samples["h_draws"]
    pick = np.random.default_rng(args.seed).choice(draws.shape[0], 6, replace=False)

    from bayes_tfcrds.uncertainty.line_shape_models import fit_candidates

    weights = {
        c["label"]: c["weight"]
        for c in res.summary["line_shape_models"]["candidates"]
        if c["weight"] > 0
    }

    def area(p):
        """The reported A at H = p: the weighted candidates refitted, at the budget's weights."""
        f = fit_ringdowns(rd, [4e-6], "tf-crds", p, "extinction")
        spec = crds_spectrum(f.nu_hz, f.tau_s[:, 0], f.tau_u_s[:, 0])
        fits = fit_candidates(spec, gd, b.sample.nu0_hz, tuple(weights))
        return sum(weights[c.candidate.label] * c.line_area for c in fits) / sum(weights.values())

    a0 = area(h_star)
    shifts = res.samples["a_shift_h"]  # first order in H(f), as the budget propagates each draw
    centre = h_star.as_vector(BEAT_FREE)
    worst = worst_lin = 0.0
    for k in pick:
        p = h_star.with_vector(draws[k], BEAT_FREE)
        full = area(p) - a0
        d = draws[k] - centre
        lin = sum(sens[n] * d[i] for i, n in enumerate(BEAT_FREE))
        worst_lin = max(worst_lin, abs(full - lin))
        worst = max(worst, abs(full - shifts[k]))
    u_a = res.budget_a.combined_u
    print(
        f"  tangent in the parameters alone: max |dA_lin - dA_full| / u(A) = {worst_lin / u_a:.4f}"
    )
    report(
        "propagation (first order in H(f)) vs full refits (max |dA_prop - dA_full| / u(A), 6 "
        "draws)",
        worst / u_a,
        "<= 0.02",
        worst / u_a <= 0.02,
    )

    mem, fit_mem = peak_memory_child(args.seed, 101, 16384)
    print(f"  memory allocated by the R1 TF-CRDS fit itself (tracemalloc peak): {fit_mem:.0f} MiB")
    report(
        "peak memory of the R1 TF-CRDS fit (child process)", mem, "< 2048 MiB", mem < 2048, " MiB"
    )

    if not args.quick:
        print(
            "\nscaling (TF-CRDS fits of six t_cut, best of 3; time s / fit's own peak allocation "
            "MiB):"
        )
        for label, sizes in (("points", (25, 51, 101)), ("samples", (4096, 8192, 16384))):
            ts, ms = [], []
            for v in sizes:
                n_pts, n_smp = (v, 16384) if label == "points" else (101, v)
                c = r1_bundle(args.seed, points=n_pts, samples=n_smp, n_avg=2)[0].configs["D2"]
                runs = []
                for _ in range(3):
                    t0 = time.perf_counter()
                    fit_ringdowns(c.ringdowns, T_CUTS, "tf-crds", tf, "extinction")
                    runs.append(time.perf_counter() - t0)
                ts.append(min(runs))
                ms.append(peak_memory_child(args.seed, n_pts, n_smp)[1])
            x = np.array(sizes, float)
            t_slope = np.polyfit(np.log(x), np.log(ts), 1)[0]
            m_slope = np.polyfit(np.log(x), np.log(ms), 1)[0]
            print(
                f"  {label:8s} {sizes}: time {np.round(ts, 3)} s (~{label}^{t_slope:.2f}), memory "
                f"{np.round(ms, 1)} MiB (~{label}^{m_slope:.2f})"
            )
        import tracemalloc

        ts, ms = [], []
        for n in (250, 500, 1000):
            t0 = time.perf_counter()
            run_budget(b, cfg, replace(opts, n_h_draws=n), np.random.default_rng(1))
            ts.append(time.perf_counter() - t0)
            tracemalloc.start()  # a second, traced run: tracing slows allocation
            run_budget(b, cfg, replace(opts, n_h_draws=n), np.random.default_rng(1))
            ms.append(tracemalloc.get_traced_memory()[1] / 2**20)
            tracemalloc.stop()
        print(
            f"  draws    (250, 500, 1000): whole Laplace budget {np.round(ts, 1)} s, peak "
            f"allocation {np.round(ms)} MiB (the draws are O(n) and cheap beside the fits and "
            "refits)"
        )
        with tempfile.TemporaryDirectory() as tmp:
            exe = [sys.executable, "-m", "bayes_tfcrds.cli"]
            bundle = os.path.join(tmp, "d2.h5")
            subprocess.run(
                exe + ["simulate", "--preset", "letter-D2", "--seed", str(args.seed), "-o", bundle],
                check=True,
                capture_output=True,
            )
            t0 = time.perf_counter()
            subprocess.run(
                exe
                + [
                    "budget",
                    bundle,
                    "--config",
                    "D2",
                    "--quiet",
                    "--seed",
                    str(args.seed),
                    "--workers",
                    "2",
                    "-o",
                    os.path.join(tmp, "budget"),
                ],
                check=True,
                capture_output=True,
            )
            t_b = time.perf_counter() - t0
            report(
                "bayes-tfcrds budget, one letter configuration (MCMC, default steps, --workers 2)",
                t_b,
                "<= 30 s (issue 16; benchmarks/budget_speed.py times it alone)",
                t_b <= 30,
                " s",
            )
            t0 = time.perf_counter()
            subprocess.run(
                exe
                + [
                    "study",
                    "studies/budget_D1_D4.toml",
                    "--quiet",
                    "--workers",
                    "2",
                    "-o",
                    os.path.join(tmp, "study"),
                ],
                check=True,
                capture_output=True,
            )
            t_s = time.perf_counter() - t0
            report(
                "four-configuration budget study, 2 workers",
                t_s / 60,
                "<= 20 min",
                t_s <= 1200,
                " min",
            )
    n_fail = sum(not r["pass"] for r in RESULTS)
    print(f"\n{len(RESULTS) - n_fail} passed, {n_fail} failed")
    with open("benchmarks/last_run.json", "w") as fh:
        json.dump(RESULTS, fh, indent=2)


if __name__ == "__main__":
    main()
