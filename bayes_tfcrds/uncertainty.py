"""The line-area uncertainty budget of one configuration, and its comparison with CMDS.

Pipeline (each step a function of the bundle, the options and the seed):

1. **H posterior.** emcee on the beat-note likelihood gives the H parameters; the letter's
   refinement then updates the refined ones (default f_c): each posterior draw of the others is
   followed by a draw of f_c from its conditional given the ring-downs (linearised on the
   refinement's estimating equations, with its sandwich covariance, because the same record enters
   once per t_cut).
2. **Decay times** at every spectral point and t_cut with the refined H; a draw of H moves them
   all at once through d tau/d theta (:mod:`bayes_tfcrds.propagate`).
3. **Line posterior.** emcee on the line parameters given the spectrum at the chosen t_cut; each
   posterior sample is shifted by the change of the line estimate that one H draw causes, so the
   H uncertainty enters as a correlated shift of the whole spectrum, never as independent noise.
   A_ref: emcee on the CMDS shifts.
4. **Budget** (GUM, JCGM 100): ring-down noise, each H parameter (with their posterior
   correlations), the t_cut choice and the line-shape model choice for u(A); pressure and
   temperature for S = A/N; the CMDS reference for A/A_ref and E_n.

The samplers' convergence gates are part of the result: a run that fails them is reported as
failed, and its numbers are never given as a result.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from .analysis import BEAT_FREE, DEFAULT_T_CUTS, beat_note_fit, select_refinement_points
from .budget import Budget, Component, normalized_error
from .constants import C, intensity_to_cm_per_molecule, line_area_to_cm2, number_density
from .linedata import load_line
from .linalg import central_hessian
from .linefit import check_overlap, check_t_cuts, doppler_of
from .posterior import BeatNotePosterior, LinePosterior
from .propagate import _model_of, line_gain, tau_influence, tau_sensitivities
from .refine import refine_transfer_function
from .ringdown import fit_ringdowns
from .sampling import Gates, run_ensembles
from .spectrum import cmds_spectrum, crds_spectrum, fit_line


def _moves():
    """Differential-evolution proposals (with snooker updates): on these correlated, bounded
    posteriors they cut the integrated autocorrelation time about threefold against emcee's
    default stretch move (measured: tau_int 100 -> 35 steps on the CMDS line posterior)."""
    import emcee
    return [(emcee.moves.DEMove(), 0.8), (emcee.moves.DESnookerMove(), 0.2)]


def _walkers(ndim: int) -> int:
    # the gates count chain length in autocorrelation times (steps), not draws, so a few walkers
    # per dimension suffice and each step is cheaper; ESS stays far above the 400 gate
    return max(3 * ndim, 16)


@dataclass(frozen=True)
class BudgetOptions:
    """What the budget analysis does (SI: t_cut in s)."""

    method: str = "tf-crds"
    window: str = "extinction"
    t_cut_s: float = 4e-6
    t_cuts_s: tuple = DEFAULT_T_CUTS
    profile: str = "qsdhcp"
    alt_profile: str = "sdvp"
    refine_free: tuple = ("f_c_hz",)
    n_refine_points: int = 6
    posterior: str = "mcmc"          # or "laplace": Gaussian posteriors from the least-squares fits
    n_ensembles: int = 4
    n_steps: int = 2500
    max_steps: int = 24000
    n_h_draws: int = 1000


@dataclass(frozen=True)
class BudgetResult:
    """Everything the budget run produced: the JSON summary and the artefacts behind it."""

    summary: dict
    budget_a: Budget
    budget_s: Budget
    budget_ratio: Budget
    samples: dict = field(repr=False)
    runs: dict = field(repr=False)
    tau_table: list = field(default_factory=list, repr=False)


def _h_posterior(config, options: BudgetOptions, rng, backend, progress):
    """Beat-note MCMC, then the refinement update of ``refine_free``; returns draws (n, 4)."""
    beat = beat_note_fit(config, free=BEAT_FREE, window=options.window)
    tfd = config.transfer_function
    post = BeatNotePosterior(f_hz=np.asarray(tfd.f_hz), h_mag=np.asarray(tfd.h_mag),
                             h_mag_u=np.asarray(tfd.h_mag_u), free=BEAT_FREE, fixed=beat.params)
    x0 = post.to_sample(beat.params, beat.scale)
    sd0 = np.sqrt(np.diag(beat.cov))
    # initial spread: the least-squares covariance, in sample space (log params: relative sd)
    nat = np.append(beat.params.as_vector(BEAT_FREE), beat.scale)
    spread = np.where([n.startswith("log_") for n in post.sample_names], sd0 / np.abs(nat), sd0)

    def p0(r, n):
        return x0 + spread * r.standard_normal((n, x0.size))

    if options.posterior == "laplace":
        run = None
        draws = rng.multivariate_normal(nat, 0.5 * (beat.cov + beat.cov.T), size=options.n_h_draws,
                                        method="eigh")[:, :len(BEAT_FREE)]
    else:
        run = run_ensembles(post, p0, post.sample_names, rng, n_ensembles=options.n_ensembles,
                            n_walkers=_walkers(x0.size), n_steps=options.n_steps, max_steps=options.max_steps,
                            vectorize=True, backend_path=backend, progress=progress, label="H | beat note",
                            moves=_moves())
        flat = run.flat()
        pick = rng.choice(flat.shape[0], size=min(options.n_h_draws, flat.shape[0]), replace=False)
        nat_draws = post.to_params(flat[pick])
        draws = np.column_stack([nat_draws[n] for n in BEAT_FREE])
    refined = None
    if options.method == "tf-crds" and options.refine_free:
        rd = config.ringdowns
        idx = select_refinement_points(rd, options.n_refine_points)
        t_cuts = np.asarray(options.t_cuts_s, float)
        rows = np.repeat(np.arange(idx.size), t_cuts.size)
        noise = None if rd.noise_v is None else np.asarray(rd.noise_v)[idx]
        refined = refine_transfer_function(rd.time_s, rd.signal_v[idx], np.tile(t_cuts, idx.size), beat.params,
                                           free=options.refine_free, window=options.window, noise_v=noise,
                                           rows_of=rows, sens_names=BEAT_FREE)
        others = tuple(n for n in BEAT_FREE if n not in options.refine_free)
        gain, _ = refined.conditional({n: None for n in others})
        io = [BEAT_FREE.index(n) for n in others]
        ir = [BEAT_FREE.index(n) for n in options.refine_free]
        centre = refined.params.as_vector(BEAT_FREE)
        delta_o = draws[:, io] - centre[io]
        noise_r = rng.multivariate_normal(np.zeros(len(ir)), refined.cov, size=draws.shape[0])
        draws[:, ir] = centre[ir] + delta_o @ gain.T + noise_r
        h_star = refined.params
        parts = {"others": others, "refined": tuple(options.refine_free), "gain": gain, "records": idx}
    else:
        h_star = beat.params
        parts = {"others": BEAT_FREE, "refined": (), "gain": np.zeros((0, len(BEAT_FREE))), "records": None}
    return beat, refined, h_star, draws, run, parts


def fit_transients_noise(rd, records, t_cut_s, tf, window):
    """Per-record noise (V) estimated from TF-CRDS residuals, for bundles without noise_v."""
    from .ringdown import fit_transients
    f = fit_transients(rd.time_s, rd.signal_v[records], np.full(len(records), t_cut_s), "tf-crds", tf, window)
    return f.noise_v


def _line_draws(lsq, rng, n=4000):
    """Laplace posterior: draws of the line parameters from the least-squares solution."""
    cov = 0.5 * (lsq.cov + lsq.cov.T)       # parameters at a bound have zero rows: singular, still PSD
    return rng.multivariate_normal(lsq.values, cov, size=n, method="eigh")


def _line_mcmc(spectra, profile, gd, nu_ref, lsq, rng, options, backend, progress, label):
    model = _model_of(lsq)
    post = LinePosterior(model=model, spectra=tuple(spectra), names=lsq.names)
    sd = np.sqrt(np.diag(lsq.cov))
    sd = np.where(sd > 0, sd, np.abs(lsq.values) * 1e-3 + 1e-3 * lsq.doppler_hwhm_hz * (np.array(lsq.names) != "line_area"))
    x0 = lsq.values.copy()
    for i, n in enumerate(lsq.names):           # start strictly inside the prior
        if n in ("gamma2_hz", "nu_vc_hz") and x0[i] <= sd[i]:
            x0[i] = sd[i]
    # the prior also caps Gamma2 at 2/3 Gamma0 (no negative width in any speed class); the
    # unbounded least-squares estimate and its sd can lie beyond it
    i2 = lsq.names.index("gamma2_hz") if "gamma2_hz" in lsq.names else None
    cap = (2.0 / 3.0) * abs(x0[lsq.names.index("gamma0_hz")]) if i2 is not None and "gamma0_hz" in lsq.names \
        else np.inf
    if i2 is not None and x0[i2] >= cap:
        x0[i2] = 0.5 * cap

    def p0(r, n):
        x = x0 + 0.5 * sd * r.standard_normal((n, x0.size))
        for i, name in enumerate(lsq.names):
            if name in ("gamma2_hz", "nu_vc_hz", "line_area", "gamma0_hz"):
                x[:, i] = np.abs(x[:, i])
        if np.isfinite(cap):                   # each walker's own Gamma0 sets its cap
            cap_w = (2.0 / 3.0) * x[:, lsq.names.index("gamma0_hz")]
            over = x[:, i2] >= cap_w
            x[over, i2] = cap_w[over] * r.uniform(0.1, 0.9, int(over.sum()))
        return x

    return run_ensembles(post, p0, lsq.names, rng, n_ensembles=options.n_ensembles,
                         n_walkers=_walkers(x0.size), n_steps=options.n_steps, max_steps=options.max_steps,
                         vectorize=True, backend_path=backend, progress=progress, label=label, moves=_moves())


def run_budget(bundle, config, options: BudgetOptions = BudgetOptions(), rng: np.random.Generator | None = None,
               outdir: str | Path | None = None, progress: bool = False) -> BudgetResult:
    """Posteriors, propagation and the GUM budget for one configuration (see module doc)."""
    rng = np.random.default_rng(0) if rng is None else rng
    # refuse what cannot work before minutes of sampling: t_cut outside the record, CMDS elsewhere
    check_t_cuts(config, (options.t_cut_s, *options.t_cuts_s))
    check_overlap(config)
    streams = dict(zip(("h", "line", "cmds", "pair"), rng.spawn(4)))
    backend = None
    if outdir is not None:
        Path(outdir).mkdir(parents=True, exist_ok=True)
        backend = str(Path(outdir) / "chains.h5")
    sample = bundle.sample
    gd = doppler_of(sample)
    nu_ref = sample.nu0_hz
    rd = config.ringdowns

    # 1. H
    runs = {}
    beat = refined = None
    h_star = None
    h_draws = None
    if options.method == "tf-crds":
        beat, refined, h_star, h_draws, h_run, h_parts = _h_posterior(
            config, options, streams["h"], None if backend is None else backend.replace(".h5", "_h.h5"), progress)
        if h_run is not None:
            runs["h"] = h_run

    # 2. decay times at all t_cuts (LSQ line fit per t_cut for the t_cut row)
    t_cuts = np.asarray(sorted(set(options.t_cuts_s) | {options.t_cut_s}), float)
    fits = fit_ringdowns(rd, t_cuts, method=options.method, tf=h_star, window=options.window)
    j0 = int(np.nonzero(np.isclose(t_cuts, options.t_cut_s))[0][0])
    area_by_tcut = {}
    for j, tc in enumerate(t_cuts):
        sp = crds_spectrum(fits.nu_hz, fits.tau_s[:, j], fits.tau_u_s[:, j])
        area_by_tcut[float(tc)] = fit_line([sp], options.profile, gd, nu_ref).line_area
    spec = crds_spectrum(fits.nu_hz, fits.tau_s[:, j0], fits.tau_u_s[:, j0])
    lsq = fit_line([spec], options.profile, gd, nu_ref)
    alt = fit_line([spec], options.alt_profile, gd, nu_ref)

    # 3. line posterior given H*, then the H shifts
    if options.posterior == "laplace":
        line_flat = _line_draws(lsq, streams["line"])
    else:
        runs["line"] = _line_mcmc([spec], options.profile, gd, nu_ref, lsq, streams["line"], options,
                                  None if backend is None else backend.replace(".h5", "_line.h5"), progress,
                                  "line | CRDS")
        line_flat = runs["line"].flat()
    ia = lsq.names.index("line_area")
    a_noise = line_flat[:, ia]
    sens_a = {}
    if options.method == "tf-crds":
        ok = np.isfinite(fits.tau_s[:, j0]) & np.isfinite(fits.tau_u_s[:, j0]) & (fits.tau_u_s[:, j0] > 0)
        good = np.nonzero(ok)[0]
        s_tau = tau_sensitivities(rd.time_s, rd.signal_v, np.full(good.size, options.t_cut_s),
                                  fits.tau_s[good, j0], fits.amplitude_v[good, j0], h_star, BEAT_FREE,
                                  options.window, noise_v=rd.noise_v, rows_of=good)
        k_gain = line_gain(lsq)[ia]                                   # dA/d(1/(c tau))
        dalpha_dtau = -1.0 / (C * fits.tau_s[good, j0] ** 2)
        grad_a = (k_gain * dalpha_dtau) @ s_tau                       # dA/dtheta_H (Hz/m per unit)
        sens_a = dict(zip(BEAT_FREE, grad_a))
        # second order: a 1-sigma H draw bends A by ~2 % of u(A) beyond the tangent; the
        # curvature, from full refits at +-1 sd of each parameter, carries it into the draws
        h_centre = h_star.as_vector(BEAT_FREE)
        h_sd = np.std(h_draws, axis=0)

        def area_at(v):
            f = fit_ringdowns(rd, [options.t_cut_s], method="tf-crds", tf=h_star.with_vector(v, BEAT_FREE),
                              window=options.window)
            return fit_line([crds_spectrum(f.nu_hz, f.tau_s[:, 0], f.tau_u_s[:, 0])], options.profile, gd,
                            nu_ref).line_area
        hess_a = central_hessian(area_at, h_centre, np.where(h_sd > 0, h_sd, 1e-6 * np.abs(h_centre)))
    u_dir = float(np.std(a_noise))
    r_noise_ref = {}
    if options.method == "tf-crds":
        others, refd, gain = h_parts["others"], h_parts["refined"], h_parts["gain"]
        io = [BEAT_FREE.index(n) for n in others]
        ir = [BEAT_FREE.index(n) for n in refd]
        centre = h_star.as_vector(BEAT_FREE)
        total_o = grad_a[io] + (grad_a[ir] @ gain if ir else 0.0)
        d_beat = (h_draws[:, io] - centre[io]) @ total_o         # the beat-note part of each draw
        d_full = h_draws - centre
        d_beat = d_beat + 0.5 * np.einsum("ni,ij,nj->n", d_full, hess_a, d_full)
        d_ref = np.zeros(a_noise.size)
        if ir:
            # ring-down noise reaches A twice: through each tau (the line fit) and through the refined
            # H. The refinement records are also in the line fit, so the two are correlated; the
            # delta method (influence functions of both estimators on those records) gives it.
            recs = h_parts["records"]
            pos = {int(g): i for i, g in enumerate(good)}
            in_fit = [j for j in range(recs.size) if int(recs[j]) in pos]
            rec = recs[in_fit]
            noise_rec = None if rd.noise_v is None else np.asarray(rd.noise_v)[rec]
            if noise_rec is None:
                noise_rec = fit_transients_noise(rd, rec, options.t_cut_s, h_star, options.window)
            infl = tau_influence(rd.time_s, rd.signal_v[rec], options.t_cut_s, fits.tau_s[rec, j0],
                                 fits.amplitude_v[rec, j0], h_star, options.window, noise_v=noise_rec)
            da_dtau = np.array([k_gain[pos[int(g)]] * dalpha_dtau[pos[int(g)]] for g in rec])
            g_dir = da_dtau[:, None] * infl                                   # dA/dy via tau
            var = np.broadcast_to(np.asarray(noise_rec, float).reshape(rec.size, -1) ** 2, g_dir.shape)
            u_r = np.sqrt(np.diag(refined.cov))
            for p_i, name in enumerate(refd):
                infl_p = refined.influence[in_fit, p_i, :]
                r = float(np.sum(g_dir * infl_p * var) / (u_dir * u_r[p_i])) if u_dir > 0 else 0.0
                r_noise_ref[name] = float(np.clip(r, -1.0, 1.0))
            # refinement shifts of A, correlated with the line-fit noise as computed
            lr = np.linalg.cholesky(refined.cov + 1e-300 * np.eye(len(ir)))
            z = streams["pair"].standard_normal((a_noise.size, len(ir)))
            eps = z @ lr.T
            c_r = grad_a[ir]
            u_ref = float(np.sqrt(c_r @ refined.cov @ c_r))
            if u_ref > 0 and u_dir > 0:
                cov_ar = sum(r_noise_ref[n] * u_dir * u_r[i] * c_r[i] for i, n in enumerate(refd))
                rho = float(np.clip(cov_ar / (u_dir * u_ref), -1.0, 1.0))
                # d_ref = rho u_ref z_noise + sqrt(1 - rho^2) (independent draw with sd u_ref)
                zn = (a_noise - a_noise.mean()) / u_dir
                d_ref = rho * u_ref * zn + np.sqrt(1 - rho**2) * (eps @ c_r)
        pair = streams["pair"].integers(0, d_beat.size, size=a_noise.size)
        a_total = a_noise + d_ref + d_beat[pair]
    else:
        a_total = a_noise.copy()
    # CMDS reference
    ref_lsq = ref_run = None
    ref_flat = None
    if config.cmds is not None:
        cm = cmds_spectrum(config.cmds)
        ref_lsq = fit_line([cm], options.profile, gd, nu_ref)
        if options.posterior == "laplace":
            ref_flat = _line_draws(ref_lsq, streams["cmds"])
        else:
            ref_run = _line_mcmc([cm], options.profile, gd, nu_ref, ref_lsq, streams["cmds"], options,
                                 None if backend is None else backend.replace(".h5", "_cmds.h5"), progress,
                                 "A_ref | CMDS")
            runs["cmds"] = ref_run
            ref_flat = ref_run.flat()
    a_ref = ref_flat[:, ref_lsq.names.index("line_area")] if ref_lsq is not None else None

    # 4. budgets
    a_hat = float(np.mean(a_total))
    comps = [Component("ring-down noise (line fit given H)", None, u_dir, 1.0, "Hz/m",
                       note="Type A: sd of the line posterior given the refined H")]
    corr = {}
    if options.method == "tf-crds":
        # one H draw is delta = (G delta_O + eps_refine, delta_O): the beat-note parameters O enter
        # with total derivatives (directly and through the refined parameters' conditional), the
        # refined ones with their refinement scatter eps (ring-down noise acting through H)
        # (others, refd, io, ir, centre, total_o: the decomposition of step 3)
        units = {"f_c_hz": "Hz", "a_r": "1", "f_r_hz": "Hz", "gamma_r": "1"}
        delta_o = h_draws[:, io] - centre[io]
        for k, n in enumerate(refd):
            u_r = float(np.sqrt(refined.cov[k, k]))
            comps.append(Component(f"H: {n} (refined on ring-downs)", float(centre[ir[k]]), u_r, float(grad_a[ir[k]]),
                                   units[n], note="Type A: sandwich u of the multi-ring-down refinement given the "
                                                  "other H parameters (ring-down noise acting through H)"))
        osd = delta_o.std(axis=0)
        oc = np.atleast_2d(np.corrcoef(delta_o.T)) if len(io) > 1 else np.ones((1, 1))
        for k, n in enumerate(others):
            note = "Type A: beat-note posterior" + (f"; sensitivity includes the shift of the refined "
                                                    f"{', '.join(refd)} it causes" if refd else "")
            comps.append(Component(f"H: {n}", float(centre[io[k]]), float(osd[k]), float(total_o[k]), units[n],
                                   note=note))
        for a in range(len(others)):
            for b in range(a + 1, len(others)):
                corr[(f"H: {others[a]}", f"H: {others[b]}")] = float(oc[a, b])
        noise_name = comps[0].name
        for n, r in r_noise_ref.items():
            corr[(noise_name, f"H: {n} (refined on ring-downs)")] = r
        if len(refd) > 1:
            rc = refined.cov / np.outer(np.sqrt(np.diag(refined.cov)), np.sqrt(np.diag(refined.cov)))
            for a in range(len(refd)):
                for b in range(a + 1, len(refd)):
                    corr[(f"H: {refd[a]} (refined on ring-downs)", f"H: {refd[b]} (refined on ring-downs)")] = float(rc[a, b])
        # GUM 5.1.2: the second-order term's own variance, 1/2 tr((Hess Sigma)^2) for Gaussian
        # H draws (its mean shift, 1/2 tr(Hess Sigma), is already in the mean of the draws)
        sig_h = np.atleast_2d(np.cov(h_draws.T))
        hs = hess_a @ sig_h
        comps.append(Component("H: curvature of A (second order)", None, float(np.sqrt(0.5 * np.trace(hs @ hs))), 1.0,
                               "Hz/m", note="Type A: 1/2 tr((d2A/dH2 Sigma_H)^2), GUM 5.1.2; the first-order H rows "
                                            "above miss it"))
    spread = max(area_by_tcut.values()) - min(area_by_tcut.values())
    comps.append(Component("t_cut choice", None, float(spread / np.sqrt(12)), 1.0, "Hz/m",
                           note=f"Type B: rectangular over the A(t_cut) range, t_cut = "
                                f"{', '.join(f'{t * 1e6:g}' for t in t_cuts)} us"))
    comps.append(Component(f"line-shape model ({options.profile} vs {options.alt_profile})", None,
                           float(abs(lsq.line_area - alt.line_area) / np.sqrt(12)), 1.0, "Hz/m",
                           note="Type B: rectangular over the difference of the two profiles' A"))
    budget_a = Budget(quantity="line area A", value=a_hat, unit="Hz/m", components=tuple(comps), correlations=corr)
    u_a = budget_a.combined_u

    n_dens = float(number_density(sample.pressure_pa, sample.temperature_k, sample.mole_fraction))
    s_val = float(intensity_to_cm_per_molecule(a_hat, n_dens))
    budget_s = Budget(quantity="line intensity S = A/N", value=s_val, unit="cm/molecule", components=(
        Component("line area A", a_hat, u_a, s_val / a_hat, "Hz/m", note="combined u(A) from the A budget"),
        Component("pressure p", sample.pressure_pa, sample.pressure_u_pa, -s_val / sample.pressure_pa, "Pa",
                  note="bundle /sample@pressure_u_pa"),
        Component("temperature T", sample.temperature_k, sample.temperature_u_k, s_val / sample.temperature_k, "K",
                  note="bundle /sample@temperature_u_k"),
    ))
    line = load_line()
    s_ref, u_s_ref = line.intensity_cm_per_molecule, line.intensity_u_cm_per_molecule

    summary = {
        "configuration": config.name, "method": options.method,
        "window": options.window if options.method == "tf-crds" else None,
        "t_cut_s": options.t_cut_s, "profile": options.profile,
        "line_area": {"value": float(line_area_to_cm2(a_hat)), "u": float(line_area_to_cm2(u_a)), "unit": "cm^-2",
                      "value_si": a_hat, "u_si": u_a, "unit_si": "Hz/m",
                      "u_statistical": float(line_area_to_cm2(np.std(a_total))),
                      "u_statistical_note": "posterior sd of A from ring-down noise and H (no Type B rows)"},
        "intensity": {"value": s_val, "u": budget_s.combined_u, "unit": "cm/molecule",
                      "reference": s_ref, "reference_u": u_s_ref,
                      "en": normalized_error(s_val, 2 * budget_s.combined_u, s_ref, 2 * u_s_ref)},
        "components": [{"name": c.name, "u": float(line_area_to_cm2(c.contribution)), "unit": "cm^-2",
                        "share": float(budget_a.shares()[c.name])} for c in comps],
        "a_by_t_cut": {f"{k * 1e6:g}us": float(line_area_to_cm2(v)) for k, v in area_by_tcut.items()},
        "sensitivities_hz_per_m": {k: float(v) for k, v in sens_a.items()},
        "hessian_hz_per_m": ({"names": list(BEAT_FREE), "matrix": hess_a.tolist()}
                             if options.method == "tf-crds" else None),
    }
    if h_star is not None:
        summary["transfer_function"] = {"f_c_hz": h_star.f_c_hz, "a_r": h_star.a_r, "f_r_hz": h_star.f_r_hz,
                                        "gamma_r": h_star.gamma_r, "n_r": h_star.n_r, "variant": h_star.variant,
                                        "refined": list(options.refine_free)}
    budget_ratio = None
    if a_ref is not None:
        a_ref_hat = float(np.mean(a_ref))
        u_ref = float(np.std(a_ref))
        r = a_hat / a_ref_hat
        budget_ratio = Budget(quantity="A/A_ref", value=r, unit="1", components=(
            Component("line area A (CRDS)", a_hat, u_a, 1.0 / a_ref_hat, "Hz/m"),
            Component("reference area A_ref (CMDS)", a_ref_hat, u_ref, -r / a_ref_hat, "Hz/m",
                      note="Type A: CMDS posterior"),
        ))
        summary["reference_area"] = {"value": float(line_area_to_cm2(a_ref_hat)), "u": float(line_area_to_cm2(u_ref)),
                                     "unit": "cm^-2", "value_si": a_ref_hat, "u_si": u_ref, "unit_si": "Hz/m"}
        summary["ratio"] = {"value": r, "u": budget_ratio.combined_u}
        summary["en"] = normalized_error(a_hat, 2 * u_a, a_ref_hat, 2 * u_ref)
    else:
        summary["reference_area"] = summary["ratio"] = summary["en"] = None
    if options.posterior == "laplace":
        # no sampler ran: nothing to diagnose, and the summary says which posterior was used
        passed = True
        summary["diagnostics"] = {"posterior": "laplace", "rhat_max": None, "ess_min": None, "passed": True,
                                  "runs": {}}
    else:
        rhat = max(run.rhat_max for run in runs.values())
        ess = min(run.ess_min for run in runs.values())
        passed = all(run.passed for run in runs.values())
        summary["diagnostics"] = {"posterior": "mcmc", "rhat_max": float(rhat), "ess_min": float(ess),
                                  "passed": bool(passed),
                                  "runs": {k: {"rhat_max": float(v.rhat_max), "ess_min": float(v.ess_min),
                                               "passed": bool(v.passed), "status": v.status,
                                               "n_steps": int(v.n_steps)} for k, v in runs.items()}}
    if not passed:
        # a failed run is never shown as a result: the numbers move out of the result keys
        failed = {k: summary.pop(k) for k in ("line_area", "reference_area", "ratio", "en", "intensity")}
        summary.update({k: None for k in failed})
        summary["unconverged_estimates"] = failed
        summary["status"] = "failed: convergence gates not met"
    else:
        summary["status"] = "ok"
    samples = {"a_total": a_total, "a_noise": a_noise, "a_ref": a_ref, "h_draws": h_draws}
    # decay-time posteriors at every point and t_cut: noise (the fit's u) and H (one draw moves
    # every tau through S; its covariance is S Sigma_H S^T), first order
    tau_table = []
    cov_h = np.cov(h_draws.T) if options.method == "tf-crds" else None
    for j, tc in enumerate(t_cuts):
        ok_j = np.isfinite(fits.tau_s[:, j]) & np.isfinite(fits.tau_u_s[:, j])
        rows_j = np.nonzero(ok_j)[0]
        u_h = np.zeros(rows_j.size)
        if cov_h is not None and rows_j.size:
            s_j = tau_sensitivities(rd.time_s, rd.signal_v, np.full(rows_j.size, tc), fits.tau_s[rows_j, j],
                                    fits.amplitude_v[rows_j, j], h_star, BEAT_FREE, options.window,
                                    noise_v=rd.noise_v, rows_of=rows_j)
            u_h = np.sqrt(np.maximum(np.einsum("ip,pq,iq->i", s_j, cov_h, s_j), 0.0))
        for i, uh in zip(rows_j, u_h):
            un = fits.tau_u_s[i, j]
            tau_table.append((float(fits.nu_hz[i]), float(tc), float(fits.tau_s[i, j]), float(un), float(uh),
                              float(np.hypot(un, uh))))
    return BudgetResult(summary=summary, budget_a=budget_a, budget_s=budget_s, budget_ratio=budget_ratio,
                        samples=samples, runs=runs, tau_table=tau_table)


def write_outputs(result: BudgetResult, outdir, seed: int | None = None) -> list:
    """budget.json, budget tables (Markdown, CSV), posteriors (arviz netCDF) and corner plots.

    Every file goes through a temporary name and a rename, so none is ever half-written.
    """
    import matplotlib
    matplotlib.use("Agg")
    import corner
    import matplotlib.pyplot as plt
    from .cli import atomic_write_text

    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    # temporary files left by an earlier run that was killed while writing (names as below)
    for stale in [*out.glob(".*.tmp"), *out.glob(".corner_*.png.tmp.png")]:
        stale.unlink(missing_ok=True)
    written = []
    summary = dict(result.summary)
    if seed is not None:
        summary["seed"] = seed
    atomic_write_text(out / "budget.json", json.dumps(summary, indent=2, default=float) + "\n")
    written.append(out / "budget.json")
    tables = [result.budget_a, result.budget_s] + ([result.budget_ratio] if result.budget_ratio is not None else [])
    md = "\n\n".join(f"## {b.quantity}\n\n{b.to_markdown()}" for b in tables)
    atomic_write_text(out / "budget.md", md + "\n")
    atomic_write_text(out / "budget.csv", result.budget_a.to_csv())
    lines = ["nu_hz,t_cut_s,tau_s,u_noise_s,u_h_s,u_s"] + [
        f"{nu:.9f},{tc:.6e},{tau:.10e},{un:.4e},{uh:.4e},{u:.4e}" for nu, tc, tau, un, uh, u in result.tau_table]
    atomic_write_text(out / "tau_posterior.csv", "\n".join(lines) + "\n")
    written += [out / "budget.md", out / "budget.csv", out / "tau_posterior.csv"]
    for key, run in result.runs.items():
        path = out / f"posterior_{key}.nc"
        run.save_netcdf(path)
        written.append(path)
        fig = corner.corner(run.flat(), labels=list(run.names), show_titles=True, title_fmt=".3g")
        tmp = out / f".corner_{key}.png.tmp.png"
        fig.savefig(tmp, dpi=70)
        plt.close(fig)
        tmp.replace(out / f"corner_{key}.png")
        written.append(out / f"corner_{key}.png")
    return written
