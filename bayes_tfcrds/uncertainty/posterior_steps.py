"""The posteriors the budget samples.

H (beat note, then the ring-down refinement update), the line parameters given a spectrum (CRDS or
CMDS), and their Laplace (least-squares) stand-ins.

Each returns draws in SI units and, for MCMC, the
:class:`~bayes_tfcrds.inference.result.SamplingResult`
whose gates decide whether the budget may be shown.
"""

from __future__ import annotations

import numpy as np

from bayes_tfcrds.fit.h_calibration import BEAT_FREE, beat_note_fit, select_refinement_points
from bayes_tfcrds.fit.refine import refine_transfer_function
from bayes_tfcrds.inference.posteriors import BeatNotePosterior, LinePosterior
from bayes_tfcrds.inference.runner import run_ensembles
from bayes_tfcrds.uncertainty.propagate import model_of


def sampler_moves():
    """Differential-evolution proposals (with snooker updates).

    On these correlated, bounded posteriors they cut the integrated autocorrelation time about
    threefold against emcee's default stretch move (measured: tau_int 100 -> 35 steps on the CMDS
    line posterior).
    """
    import emcee

    return [(emcee.moves.DEMove(), 0.8), (emcee.moves.DESnookerMove(), 0.2)]


def n_walkers(ndim: int) -> int:
    # the gates count chain length in autocorrelation times (steps), not draws, so a few walkers
    # per dimension suffice and each step is cheaper; ESS stays far above the 400 gate
    return max(3 * ndim, 16)


def _sample(post, p0, names, ndim, rng, options, backend, progress, label):
    """emcee on ``post`` with the budget's ensembles, walkers, lengths and moves."""
    return run_ensembles(
        post,
        p0,
        names,
        rng,
        n_ensembles=options.n_ensembles,
        n_walkers=n_walkers(ndim),
        n_steps=options.n_steps,
        max_steps=options.max_steps,
        vectorize=True,
        backend_path=backend,
        progress=progress,
        label=label,
        moves=sampler_moves(),
    )


def h_posterior(config, options, rng, backend, progress):
    """Beat-note MCMC, then the refinement update of ``refine_free``.

    Returns (beat-note fit, refinement or None, H*, H draws (n, 4), sampler run or None, the draw's
    decomposition into beat-note and refined parts).
    """
    beat = beat_note_fit(config, free=BEAT_FREE, window=options.window)
    tfd = config.transfer_function
    post = BeatNotePosterior(
        f_hz=np.asarray(tfd.f_hz),
        h_mag=np.asarray(tfd.h_mag),
        h_mag_u=np.asarray(tfd.h_mag_u),
        free=BEAT_FREE,
        fixed=beat.params,
    )
    x0 = post.to_sample(beat.params, beat.scale)
    sd0 = np.sqrt(np.diag(beat.cov))
    # initial spread: the least-squares covariance, in sample space (log params: relative sd)
    nat = np.append(beat.params.as_vector(BEAT_FREE), beat.scale)
    spread = np.where([n.startswith("log_") for n in post.sample_names], sd0 / np.abs(nat), sd0)

    def p0(r, n):
        return x0 + spread * r.standard_normal((n, x0.size))

    if options.posterior == "laplace":
        run = None
        draws = rng.multivariate_normal(
            nat, 0.5 * (beat.cov + beat.cov.T), size=options.n_h_draws, method="eigh"
        )[:, : len(BEAT_FREE)]
    else:
        run = _sample(
            post, p0, post.sample_names, x0.size, rng, options, backend, progress, "H | beat note"
        )
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
        refined = refine_transfer_function(
            rd.time_s,
            rd.signal_v[idx],
            np.tile(t_cuts, idx.size),
            beat.params,
            free=options.refine_free,
            window=options.window,
            noise_v=noise,
            rows_of=rows,
            sens_names=BEAT_FREE,
        )
        others = tuple(n for n in BEAT_FREE if n not in options.refine_free)
        gain, _ = refined.conditional({n: None for n in others})
        io = [BEAT_FREE.index(n) for n in others]
        ir = [BEAT_FREE.index(n) for n in options.refine_free]
        centre = refined.params.as_vector(BEAT_FREE)
        delta_o = draws[:, io] - centre[io]
        noise_r = rng.multivariate_normal(np.zeros(len(ir)), refined.cov, size=draws.shape[0])
        draws[:, ir] = centre[ir] + delta_o @ gain.T + noise_r
        h_star = refined.params
        parts = {
            "others": others,
            "refined": tuple(options.refine_free),
            "gain": gain,
            "records": idx,
        }
    else:
        h_star = beat.params
        parts = {
            "others": BEAT_FREE,
            "refined": (),
            "gain": np.zeros((0, len(BEAT_FREE))),
            "records": None,
        }
    return beat, refined, h_star, draws, run, parts


def fit_transients_noise(rd, records, t_cut_s, tf, window):
    """Per-record noise (V) estimated from TF-CRDS residuals, for bundles without noise_v."""
    from bayes_tfcrds.fit.ringdown import fit_transients

    f = fit_transients(
        rd.time_s, rd.signal_v[records], np.full(len(records), t_cut_s), "tf-crds", tf, window
    )
    return f.noise_v


def line_draws(lsq, rng, n=4000):
    """Laplace posterior: draws of the line parameters from the least-squares solution."""
    cov = 0.5 * (lsq.cov + lsq.cov.T)  # parameters at a bound have zero rows: singular, still PSD
    return rng.multivariate_normal(lsq.values, cov, size=n, method="eigh")


def line_mcmc(spectra, profile, gd, nu_ref, lsq, rng, options, backend, progress, label):
    """emcee on the line parameters given ``spectra``.

    Walkers start inside the physical prior around the least-squares solution ``lsq``.
    """
    model = model_of(lsq)
    post = LinePosterior(model=model, spectra=tuple(spectra), names=lsq.names)
    sd = np.sqrt(np.diag(lsq.cov))
    sd = np.where(
        sd > 0,
        sd,
        np.abs(lsq.values) * 1e-3
        + 1e-3 * lsq.doppler_hwhm_hz * (np.array(lsq.names) != "line_area"),
    )
    x0 = lsq.values.copy()
    for i, n in enumerate(lsq.names):  # start strictly inside the prior
        if n in ("gamma2_hz", "nu_vc_hz") and x0[i] <= sd[i]:
            x0[i] = sd[i]
    # the prior also caps Gamma2 at 2/3 Gamma0 (no negative width in any speed class); the
    # unbounded least-squares estimate and its sd can lie beyond it
    i2 = lsq.names.index("gamma2_hz") if "gamma2_hz" in lsq.names else None
    cap = (
        (2.0 / 3.0) * abs(x0[lsq.names.index("gamma0_hz")])
        if i2 is not None and "gamma0_hz" in lsq.names
        else np.inf
    )
    if i2 is not None and x0[i2] >= cap:
        x0[i2] = 0.5 * cap

    def p0(r, n):
        x = x0 + 0.5 * sd * r.standard_normal((n, x0.size))
        for i, name in enumerate(lsq.names):
            if name in ("gamma2_hz", "nu_vc_hz", "line_area", "gamma0_hz"):
                x[:, i] = np.abs(x[:, i])
        if np.isfinite(cap):  # each walker's own Gamma0 sets its cap
            cap_w = (2.0 / 3.0) * x[:, lsq.names.index("gamma0_hz")]
            over = x[:, i2] >= cap_w
            x[over, i2] = cap_w[over] * r.uniform(0.1, 0.9, int(over.sum()))
        return x

    return _sample(post, p0, lsq.names, x0.size, rng, options, backend, progress, label)
