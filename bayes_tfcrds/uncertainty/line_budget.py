"""The line-area uncertainty budget of one configuration, and its comparison with CMDS.

Pipeline (each step a function of the bundle, the options and the seed):

1. **H posterior** (:mod:`bayes_tfcrds.uncertainty.posterior_steps`). emcee on the beat-note
   likelihood; the refined parameters (default f_c) of each draw follow from their ring-down update
   given the others (the beat note as prior, the multi-ring-down composite likelihood adjusted to
   its sandwich curvature); the draws are weighted by the ring-down likelihood and resampled, so
   the draws are of one posterior from all the evidence.
2. **Decay times** at every spectral point and t_cut with the refined H; a draw of H moves them
   all at once through its H(f) (:mod:`bayes_tfcrds.uncertainty.propagate`).
3. **Line posterior.** emcee on the line parameters given the spectrum at the chosen t_cut; each
   posterior sample is shifted by the change of the line estimate that one H draw causes, so the
   H uncertainty enters as a correlated shift of the whole spectrum, never as independent noise.
   A_ref: emcee on the CMDS shifts.
4. **Budget** (GUM, JCGM 100): ring-down noise, the beat-note posterior of H (one row: all its
   parameters through H(f)), each refined H parameter (correlated with the noise through the
   shared records), the t_cut choice and the line-shape model (candidate profiles weighted by
   their predictive evidence, :mod:`~bayes_tfcrds.uncertainty.line_shape_models`); pressure,
   temperature and mole fraction for the line intensity S at T_ref = 296 K (from S(T) = A/N at
   the sample's T through Q(T), E'' and stimulated emission); the CMDS reference for A/A_ref
   and E_n. Every row carries its degrees of freedom (Type A: n_points - n_params of its fit;
   Type B: GUM G.4.2), so nu_eff and k = t_95(nu_eff) are those of the data.
5. **JCGM 101 Monte Carlo** of the same model for A, S and A/A_ref (:mod:`.monte_carlo`): the
   coverage interval and its k beside the GUM result.

The samplers' convergence gates are part of the result: a run that fails them is reported as
failed, and its numbers are never given as a result.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from bayes_tfcrds._version import __version__
from bayes_tfcrds.core.constants import (
    EDGE_UNITS,
    C,
    edge_keys,
    line_area_to_cm2,
)
from bayes_tfcrds.core.fingerprint import content_hash
from bayes_tfcrds.core.gum import Budget, Component, dof_from_relative_u, normalized_error
from bayes_tfcrds.core.quantity import Quantity
from bayes_tfcrds.fit.h_calibration import (
    BEAT_FREE,
    DEFAULT_T_CUTS,
    AnalysisError,
    HModelForms,
    account_for_noise_colour,
    beat_note_fit,
    free_order_weight,
    h_model_forms,
)
from bayes_tfcrds.fit.h_identification import identification_grid, identify_h
from bayes_tfcrds.fit.line import fit_line
from bayes_tfcrds.fit.line_analysis import check_overlap, check_t_cuts, doppler_of
from bayes_tfcrds.fit.ringdown import fit_ringdowns
from bayes_tfcrds.fit.spectrum import cmds_spectrum, crds_spectrum
from bayes_tfcrds.inference.posteriors import H_PRIOR
from bayes_tfcrds.output.files import atomic_write_text, folder_lock
from bayes_tfcrds.output.progress import StageClock
from bayes_tfcrds.physics.linedata import load_line
from bayes_tfcrds.uncertainty.doppler import (
    ROW_NAME,
    DopplerSensitivity,
    doppler_sensitivity,
    temperature_row,
    without_temperature_row,
)
from bayes_tfcrds.uncertainty.instrument import cmds_type_b, instrument_rows
from bayes_tfcrds.uncertainty.line_shape_models import (
    DEFAULT_CANDIDATES,
    ModelAverage,
    average_candidates,
    averaged_area_gain,
    fit_candidates,
)
from bayes_tfcrds.uncertainty.monte_carlo import (
    BudgetMonteCarlo,
    add_to_summary,
    budget_monte_carlo,
)
from bayes_tfcrds.uncertainty.posterior_steps import (
    IS_ESS_MIN,
    fit_transients_noise,
    h_posterior,
    line_draws,
    line_mcmc,
    priors_summary,
    ring_down_update,
)
from bayes_tfcrds.uncertainty.propagate import (
    TauKernels,
    h_change,
    tau_h_kernels,
    tau_influence,
    tau_sensitivities,
)

log = logging.getLogger(__name__)

H_UNITS = {"f_c_hz": "Hz", "a_r": "1", "f_r_hz": "Hz", "gamma_r": "1", "n_r": "1"}
# judged relative uncertainty of the Type B u's (GUM G.4.2, dof = 1/2 (du/u)^-2): a width from the
# spread of a few alternatives (t_cut) is known to about 25 % (8 dof); a width set by a single
# difference or weight (line-shape model, H model form) to about 50 % (2 dof); u(p), u(T) stated
# by calibration certificates to two digits to about 10 % (50 dof)
REL_U_SPREAD, REL_U_ONE_DIFFERENCE, REL_U_CERTIFICATE = 0.25, 0.5, 0.10

#: what each posterior option is, as budget.json and budget.md state it
POSTERIORS = {
    "mcmc": "sampled: emcee on the H, line and CMDS posteriors, every run gated by R-hat, ESS "
    "and chain length in autocorrelation times",
    "laplace": "Laplace approximation: Gaussian posteriors at the least-squares optima "
    "(covariances from the fits), no sampler and no convergence gates; it misstates u where a "
    "posterior is skewed, bounded or multimodal (a line-shape parameter near 0, a second H mode)",
}


@dataclass(frozen=True)
class BudgetOptions:
    """What the budget analysis does (SI: t_cut in s)."""

    method: str = "tf-crds"
    window: str = "extinction"
    t_cut_s: float = 4e-6
    t_cuts_s: tuple = DEFAULT_T_CUTS
    profile: str = "qsdhcp"
    shape_candidates: tuple = DEFAULT_CANDIDATES  # labels of line_shape_models.CANDIDATES
    refine_free: tuple = ("f_c_hz",)
    n_refine_points: int = 6
    posterior: str = "mcmc"  # or "laplace": Gaussian posteriors from the least-squares fits
    n_ensembles: int = 4
    n_steps: int = 2500
    max_steps: int = 24000
    n_h_draws: int = 1000
    free_order: bool = True  # sample n_r when the data ask for a free order (weight > 1/2)

    def __post_init__(self):
        if self.posterior not in POSTERIORS:
            raise ValueError(
                f"posterior must be one of {sorted(POSTERIORS)}, got {self.posterior!r}"
            )
        bad = [n for n in self.refine_free if n not in BEAT_FREE]
        if bad:
            raise ValueError(
                f"the budget refines a subset of the beat-note parameters {BEAT_FREE}; got {bad}"
            )

    def with_steps(self, n_steps: int | None = None, max_steps: int | None = None) -> BudgetOptions:
        """These options with other sampler lengths.

        ``n_steps`` per ensemble before the gates are checked and at most ``max_steps`` (default
        max(8 n_steps, the current max_steps)); refuses n_steps outside [1, max_steps].
        """
        n = self.n_steps if n_steps is None else int(n_steps)
        most = max(n * 8, self.max_steps) if max_steps is None else int(max_steps)
        if not 1 <= n <= most:
            raise ValueError(f"need 1 <= --steps ({n}) <= --max-steps ({most})")
        return replace(self, n_steps=n, max_steps=most)


class BudgetSummary(dict):
    """The ``budget.json`` payload (a dict); calling it, ``result.summary()``, gives it as text.

    A dict, so that ``result.summary["line_area"]`` reads the record as before; callable, so that
    a notebook has the same ``summary()`` as every other result object.
    """

    def __call__(self) -> str:
        from bayes_tfcrds.uncertainty.views import budget_text

        return budget_text(self)


@dataclass(frozen=True)
class BudgetResult:
    """Everything the budget run produced: the JSON summary and the artefacts behind it.

    ``summary`` is the ``budget.json`` record (a :class:`BudgetSummary`: ``summary()`` gives it
    as text); :meth:`to_dict` adds the GUM budgets, :meth:`plot` draws the shares of u_c^2(A).
    """

    summary: dict
    budget_a: Budget
    budget_s: Budget
    budget_ratio: Budget | None
    samples: dict = field(repr=False)
    runs: dict = field(repr=False)
    tau_table: list = field(default_factory=list, repr=False)
    refined: object = field(default=None, repr=False)  # the refinement update (tf-crds)
    monte_carlo: BudgetMonteCarlo | None = None  # JCGM 101 of A, S(T_ref), A/A_ref (SI)
    # which H parameters the data identify (tf-crds): fit.h_identification.HIdentification
    identification: object = field(default=None, repr=False)

    def __post_init__(self):
        object.__setattr__(self, "summary", BudgetSummary(self.summary))

    def to_dict(self) -> dict:
        """JSON-ready: the ``budget.json`` record and the GUM budgets of A, S and A/A_ref."""
        from bayes_tfcrds.uncertainty.views import budget_dict

        return budget_dict(self)

    def _repr_html_(self) -> str:
        from bayes_tfcrds.uncertainty.views import budget_html

        return budget_html(self.summary)

    def plot(self, ax=None):
        """Bar chart of each component's share of u_c^2(A) (%); a matplotlib Figure."""
        from bayes_tfcrds.uncertainty.views import plot_budget

        return plot_budget(self, ax)

    @property
    def status(self) -> str:
        """``ok``, or why the result must not be used (e.g. convergence gates not met)."""
        return self.summary["status"]

    @property
    def passed(self) -> bool:
        """True when every sampler met its convergence gates (always for the Laplace posterior)."""
        return self.status == "ok"

    def _quantity(self, key: str) -> Quantity | None:
        entry = self.summary.get(key)
        return (
            None if entry is None else Quantity(entry["value"], entry["u"], entry.get("unit", ""))
        )

    @property
    def line_area(self) -> Quantity | None:
        """A (cm^-2) with its combined standard uncertainty u_c; None for a failed run."""
        return self._quantity("line_area")

    @property
    def reference_area(self) -> Quantity | None:
        """A_ref (cm^-2) from the CMDS posterior; None without CMDS or for a failed run."""
        return self._quantity("reference_area")

    @property
    def ratio(self) -> Quantity | None:
        """A/A_ref with its combined standard uncertainty; None without CMDS or for a failed run."""
        return self._quantity("ratio")

    @property
    def intensity(self) -> Quantity | None:
        """S at T_ref = 296 K (cm/molecule) with its combined u; None for a failed run.

        S(T) = A/N at the sample's T referred to T_ref through Q(T), E'' and stimulated emission
        (step 8); ``summary["intensity"]`` also gives S at the sample's T.
        """
        return self._quantity("intensity")

    @property
    def en(self) -> float | None:
        """E_n of A against A_ref (k = 2); None without CMDS or for a failed run."""
        return self.summary.get("en")


@dataclass(frozen=True)
class _Inputs:
    """What every step reads.

    The configuration (its ring-downs carrying their noise colour), the line's Doppler width and
    centre (Hz), the random streams, the chain files' stem (None: chains in memory), the
    ring-downs' NoiseDiagnosis and the beat-note fit.
    """

    config: object
    sample: object
    options: BudgetOptions
    gd: float
    nu_ref: float
    streams: dict
    backend: str | None
    progress: bool
    noise: object = None
    beat: object = None  # the beat-note fit (made once, for the noise diagnosis and H)

    def chain_file(self, key: str) -> str | None:
        return None if self.backend is None else self.backend.replace(".h5", f"_{key}.h5")


@dataclass(frozen=True)
class _DecayTimes:
    """Step 2: decay times at every t_cut, A per t_cut (Hz/m), the line fits at the chosen one.

    ``shapes``: the candidate profiles' fits to that spectrum, weighted (the model average).
    """

    fits: object
    t_cuts: np.ndarray
    j0: int
    area_by_tcut: dict
    spec: object
    lsq: object
    shapes: ModelAverage


@dataclass(frozen=True)
class _HSensitivity:
    """Step 4.

    How A moves with H: the first-order kernel in H(f) (``area_kernel``, what a draw of H does to A
    through every tau), the gradient in the H parameters (Hz/m per unit, for the refined rows and
    the breakdown), and the pieces of the chain rule through each tau (the usable rows ``good``,
    dA/d(alpha), d(alpha)/d(tau)).
    """

    good: np.ndarray
    k_gain: np.ndarray
    dalpha_dtau: np.ndarray
    grad_a: np.ndarray
    area_kernel: TauKernels


@dataclass(frozen=True)
class _HSplit:
    """One H draw is (beat-note draw of the others O, refined R | O).

    R | O is the refined parameters' conditional posterior: its mean moves with O (part of the
    beat-note row), its scatter eps is ring-down noise acting through H (the refined rows).
    """

    others: tuple
    refined: tuple
    io: list
    ir: list
    centre: np.ndarray


CHAINS_MANIFEST = "chains.json"
# sampler lengths only extend a chain (it is a deterministic function of the seed), so a rerun
# with more steps may resume; every other option defines the posterior
_EXTENDS_ONLY = ("n_steps", "max_steps")


def run_fingerprint(bundle, config, options) -> dict:
    """What the chains of one budget depend on: code version, data and every defining option.

    The seed is checked by the chain stores themselves (each ensemble's seed is in its file).
    """
    opts = {k: v for k, v in asdict(options).items() if k not in _EXTENDS_ONLY}
    return {
        "code_version": __version__,
        "configuration": config.name,
        "data_sha256": content_hash([bundle.sample, config]),
        "options_sha256": content_hash(opts),
        "options": json.loads(json.dumps(opts, default=str)),
    }


def claim_chains(outdir, fingerprint: dict) -> None:
    """Refuse to resume chains in ``outdir`` written for another posterior; record this one's.

    Chains are matched by seed and shape in their files; this adds the data, the options and the
    code version (``chains.json`` beside them). A folder with chains but no record, or a record
    that differs, is refused with the differences named: the chains are never reused silently and
    never deleted here.
    """
    out = Path(outdir)
    manifest = out / CHAINS_MANIFEST
    chains = sorted(p.name for p in out.glob("chains*.h5"))
    old = None
    if manifest.exists():
        try:
            old = json.loads(manifest.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            old = {}
    if chains and old != fingerprint:
        if old is None:
            why = f"no {CHAINS_MANIFEST} records what they were sampled for"
        else:
            keys = [k for k in fingerprint if k != "options" and old.get(k) != fingerprint[k]]
            opts = [
                k
                for k in fingerprint["options"]
                if (old.get("options") or {}).get(k) != fingerprint["options"][k]
            ]
            why = "they differ in " + ", ".join(
                [k for k in keys if k != "options_sha256"] + [f"option {k}" for k in opts]
            )
        raise AnalysisError(
            f"{out} holds MCMC chains ({', '.join(chains)}) of another budget: {why}. "
            "Give another output folder, or delete those files to sample afresh"
        )
    atomic_write_text(manifest, json.dumps(fingerprint, indent=1))


def _inputs(bundle, config, options, rng, outdir, progress) -> _Inputs:
    """Check the inputs, spawn the five random streams, place the chain files.

    Refuses what cannot work before minutes of sampling (t_cut outside the record, CMDS
    elsewhere).
    """
    check_t_cuts(config, (options.t_cut_s, *options.t_cuts_s))
    check_overlap(config)
    config, noise, beat = account_for_noise_colour(config, options.window)
    # appended in turn: spawning more children leaves the earlier streams as they were
    streams = dict(zip(("h", "line", "cmds", "pair", "mc", "shapes"), rng.spawn(6)))
    backend = None
    if outdir is not None:  # made and claimed by run_budget, under the folder's lock
        backend = str(Path(outdir) / "chains.h5")
    return _Inputs(
        config,
        bundle.sample,
        options,
        doppler_of(bundle.sample),
        bundle.sample.nu0_hz,
        streams,
        backend,
        progress,
        noise,
        beat,
    )


def _converged_only(fits):
    """``fits.converged_only()``: unconverged decay times left out of every later step, said.

    Every later step (spectra, the sensitivity of A to H, the tau table) skips NaN entries, so an
    unconverged fit never reaches a line fit; ``unconverged`` counts them per t_cut.
    """
    kept = fits.converged_only()
    bad = kept.unconverged
    if bad.any():
        log.warning(
            "%d decay-time fits did not converge and were left out (%s)",
            int(bad.sum()),
            ", ".join(
                f"{int(n)} at t_cut {tc * 1e6:g} us"
                for tc, n in zip(fits.t_cut_s, bad.sum(axis=0))
                if n
            ),
        )
    return kept


def _decay_times(inp: _Inputs, h_star) -> _DecayTimes:
    """Step 2.

    Decay times at all t_cuts with H*, a least-squares line fit per t_cut (for the t_cut row) and,
    at the chosen t_cut, the profile and the candidate profiles (model average).
    """
    options, gd, nu_ref = inp.options, inp.gd, inp.nu_ref
    t_cuts = np.asarray(sorted(set(options.t_cuts_s) | {options.t_cut_s}), float)
    fits = _converged_only(
        fit_ringdowns(
            inp.config.ringdowns, t_cuts, method=options.method, tf=h_star, window=options.window
        )
    )
    j0 = int(np.nonzero(np.isclose(t_cuts, options.t_cut_s))[0][0])
    spectra = [
        crds_spectrum(fits.nu_hz, fits.tau_s[:, j], fits.tau_u_s[:, j]) for j in range(t_cuts.size)
    ]
    line_fits = [fit_line([sp], options.profile, gd, nu_ref) for sp in spectra]
    area_by_tcut = {float(tc): lf.line_area for tc, lf in zip(t_cuts, line_fits)}
    spec, lsq = spectra[j0], line_fits[j0]
    shapes = average_candidates(
        fit_candidates(spec, gd, nu_ref, options.shape_candidates, primary=lsq),
        inp.streams["shapes"],
    )
    return _DecayTimes(fits, t_cuts, j0, area_by_tcut, spec, lsq, shapes)


def _line_posterior(inp: _Inputs, dt: _DecayTimes, runs: dict) -> np.ndarray:
    """Step 3: draws of the line parameters given H* (Laplace, or emcee stored in ``runs``)."""
    if inp.options.posterior == "laplace":
        return line_draws(dt.lsq, inp.streams["line"])
    runs["line"] = line_mcmc(
        [dt.spec],
        inp.options.profile,
        inp.gd,
        inp.nu_ref,
        dt.lsq,
        inp.streams["line"],
        inp.options,
        inp.chain_file("line"),
        inp.progress,
        "line | CRDS",
    )
    return runs["line"].flat()


def _h_sensitivity(inp: _Inputs, dt: _DecayTimes, h_star, names=BEAT_FREE) -> _HSensitivity:
    """Step 4: the sensitivity of A to H.

    dA/dH(f) through every tau (implicit-function derivatives in the function H, then the gain
    of the reported, model-averaged A), and dA/dtheta_H from the same chain rule with dH/dtheta
    (theta: ``names``).
    """
    options, rd, fits, j0 = inp.options, inp.config.ringdowns, dt.fits, dt.j0
    ok = (
        np.isfinite(fits.tau_s[:, j0])
        & np.isfinite(fits.tau_u_s[:, j0])
        & (fits.tau_u_s[:, j0] > 0)
    )
    good = np.nonzero(ok)[0]
    rows = dict(
        t_cut_s=np.full(good.size, options.t_cut_s),
        tau_s=fits.tau_s[good, j0],
        amplitude_v=fits.amplitude_v[good, j0],
        tf=h_star,
        window=options.window,
        noise_v=rd.fit_noise_v,
        rows_of=good,
    )
    s_tau = tau_sensitivities(rd.time_s, rd.signal_v, names=names, **rows)
    k_gain = averaged_area_gain(dt.shapes, dt.lsq)  # dA_bar/d(1/(c tau)): the reported A
    dalpha_dtau = -1.0 / (C * fits.tau_s[good, j0] ** 2)
    grad_a = (k_gain * dalpha_dtau) @ s_tau  # dA/dtheta_H (Hz/m per unit)
    kernel = tau_h_kernels(rd.time_s, **rows).combine(k_gain * dalpha_dtau)
    return _HSensitivity(good, k_gain, dalpha_dtau, grad_a, kernel)


def h_shifts(
    kernels: TauKernels, draws, h_star, n_rows: int, chunk: int = 100, names=BEAT_FREE
) -> np.ndarray:
    """First-order shifts (n_draws, n_rows) that H draws (natural, columns ``names``) cause.

    Through each draw's H(f) (function space), in chunks of draws to bound memory.
    """
    return h_shifts_many([(kernels, n_rows)], draws, h_star, chunk, names)[0]


def h_shifts_many(kernel_rows, draws, h_star, chunk: int = 100, names=BEAT_FREE) -> list:
    """:func:`h_shifts` for several ``(kernels, n_rows)`` over the same H draws, in one pass.

    Each chunk of draws has its H(f) evaluated once per frequency grid, however many kernels use
    that grid (the decay-time table's t_cuts share the ``extinction`` window's grid); the shifts
    are those of :func:`h_shifts` to the bit.
    """
    if not kernel_rows:  # plain CRDS: no H draws
        return []
    draws = np.atleast_2d(draws)
    outs = [np.zeros((draws.shape[0], n_rows)) for _, n_rows in kernel_rows]
    for i in range(0, draws.shape[0], chunk):
        h_of = _once_per_grid(h_change(draws[i : i + chunk], names, h_star))
        for (kernels, n_rows), out in zip(kernel_rows, outs):
            out[i : i + chunk] = kernels.shifts(h_of, n_rows)
    return outs


def _once_per_grid(h_of):
    """``h_of`` (f_hz -> delta_H of a chunk of draws) remembered per frequency grid."""
    seen = {}

    def of(f_hz):
        key = (f_hz.size, f_hz.tobytes())
        if key not in seen:
            seen[key] = h_of(f_hz)
        return seen[key]

    return of


def _h_split(h_star, h_parts: dict) -> _HSplit:
    """The decomposition of an H draw into beat-note and refinement parts (see :class:`_HSplit`)."""
    others, refd, names = h_parts["others"], h_parts["refined"], h_parts["names"]
    io = [names.index(n) for n in others]
    ir = [names.index(n) for n in refd]
    return _HSplit(others, refd, io, ir, h_star.as_vector(names))


def _noise_refinement_correlation(
    inp: _Inputs,
    dt: _DecayTimes,
    sens: _HSensitivity,
    h_star,
    refined,
    h_parts: dict,
    split: _HSplit,
    u_dir: float,
) -> dict:
    """Ring-down noise reaches A twice: through each tau (the line fit) and through the refined H.

    The refinement records are also in the line fit, so the two are correlated; the delta method
    (influence functions of both estimators on those records) gives r per refined parameter.
    """
    options, rd, fits, j0 = inp.options, inp.config.ringdowns, dt.fits, dt.j0
    recs = h_parts["records"]
    pos = {int(g): i for i, g in enumerate(sens.good)}
    in_fit = [j for j in range(recs.size) if int(recs[j]) in pos]
    rec = recs[in_fit]
    noise_rec = None if rd.fit_noise_v is None else np.asarray(rd.fit_noise_v)[rec]
    if noise_rec is None:
        noise_rec = fit_transients_noise(rd, rec, options.t_cut_s, h_star, options.window)
    infl = tau_influence(
        rd.time_s,
        rd.signal_v[rec],
        options.t_cut_s,
        fits.tau_s[rec, j0],
        fits.amplitude_v[rec, j0],
        h_star,
        options.window,
        noise_v=noise_rec,
    )
    da_dtau = np.array([sens.k_gain[pos[int(g)]] * sens.dalpha_dtau[pos[int(g)]] for g in rec])
    g_dir = da_dtau[:, None] * infl  # dA/dy via tau
    var = np.broadcast_to(np.asarray(noise_rec, float).reshape(rec.size, -1) ** 2, g_dir.shape)
    u_r = np.sqrt(np.diag(refined.cov))
    r_noise_ref = {}
    for p_i, name in enumerate(split.refined):
        infl_p = refined.influence[in_fit, p_i, :]
        r = float(np.sum(g_dir * infl_p * var) / (u_dir * u_r[p_i])) if u_dir > 0 else 0.0
        r_noise_ref[name] = float(np.clip(r, -1.0, 1.0))
    return r_noise_ref


def _refinement_shifts(
    inp: _Inputs, refined, split: _HSplit, grad_a, a_noise, u_dir: float, r_noise_ref: dict
) -> np.ndarray:
    """Refinement shifts of A, correlated with the line-fit noise as computed.

    D_ref = rho u_ref z_noise + sqrt(1 - rho^2) (independent draw with sd u_ref).
    """
    ir, refd = split.ir, split.refined
    u_r = np.sqrt(np.diag(refined.cov))
    d_ref = np.zeros(a_noise.size)
    lr = np.linalg.cholesky(refined.cov + 1e-300 * np.eye(len(ir)))
    z = inp.streams["pair"].standard_normal((a_noise.size, len(ir)))
    eps = z @ lr.T
    c_r = grad_a[ir]
    u_ref = float(np.sqrt(c_r @ refined.cov @ c_r))
    if u_ref > 0 and u_dir > 0:
        cov_ar = sum(r_noise_ref[n] * u_dir * u_r[i] * c_r[i] for i, n in enumerate(refd))
        rho = float(np.clip(cov_ar / (u_dir * u_ref), -1.0, 1.0))
        zn = (a_noise - a_noise.mean()) / u_dir
        d_ref = rho * u_ref * zn + np.sqrt(1 - rho**2) * (eps @ c_r)
    return d_ref


def _h_shifted_areas(inp, dt, sens, split, h_star, refined, h_parts, a_noise, u_dir):
    """Step 5.

    Each line-posterior draw of A shifted by one H draw: the beat-note part through its H(f), the
    refinement part correlated with the noise. Returns (A draws, noise-refinement correlations,
    beat-note shifts).
    """
    d_beat = h_shifts(sens.area_kernel, h_parts["beat_draws"], h_star, 1, names=h_parts["names"])
    d_beat = d_beat[:, 0]
    d_ref = np.zeros(a_noise.size)
    r_noise_ref = {}
    if split.ir:
        r_noise_ref = _noise_refinement_correlation(
            inp, dt, sens, h_star, refined, h_parts, split, u_dir
        )
        d_ref = _refinement_shifts(inp, refined, split, sens.grad_a, a_noise, u_dir, r_noise_ref)
    pair = inp.streams["pair"].integers(0, d_beat.size, size=a_noise.size)
    return a_noise + d_ref + d_beat[pair], r_noise_ref, d_beat


def _doppler(inp: _Inputs, dt: _DecayTimes) -> DopplerSensitivity:
    """Step 6d: dA/dT and dA_ref/dT through the fits' Doppler width (least squares, at T +- 1 K)."""
    cm = ref = None
    if inp.config.cmds is not None:
        cm = cmds_spectrum(inp.config.cmds)
        ref = fit_line([cm], inp.options.profile, inp.gd, inp.nu_ref)
    return doppler_sensitivity(dt.spec, dt.lsq, cm, ref, inp.options.profile, inp.sample)


def _reference_area(inp: _Inputs, runs: dict):
    """Step 6: A_ref draws from the CMDS shifts (Laplace or emcee) and the fit's dof.

    (None, inf) without CMDS.
    """
    config, options = inp.config, inp.options
    if config.cmds is None:
        return None, np.inf
    cm = cmds_spectrum(config.cmds)
    ref_lsq = fit_line([cm], options.profile, inp.gd, inp.nu_ref)
    if options.posterior == "laplace":
        ref_flat = line_draws(ref_lsq, inp.streams["cmds"])
    else:
        runs["cmds"] = line_mcmc(
            [cm],
            options.profile,
            inp.gd,
            inp.nu_ref,
            ref_lsq,
            inp.streams["cmds"],
            options,
            inp.chain_file("cmds"),
            inp.progress,
            "A_ref | CMDS",
        )
        ref_flat = runs["cmds"].flat()
    return ref_flat[:, ref_lsq.names.index("line_area")], max(float(ref_lsq.dof), 1.0)


def reference_area_task(inp: _Inputs) -> tuple:
    """Step 6 on its own (in a second process): (A_ref draws, dof, the CMDS sampling run or None).

    The CMDS reference does not depend on H, so it can be sampled while the H and line posteriors
    are; it draws from its own stream (``streams["cmds"]``), so the result is the same bit for bit
    as in turn. Its progress bar is off: two processes' bars would overwrite each other.
    """
    runs = {}
    a_ref, dof = _reference_area(replace(inp, progress=False), runs)
    return a_ref, dof, runs.get("cmds")


class _Now:
    """A finished computation with a Future's ``result()`` (the in-turn path of :class:`_Side`)."""

    def __init__(self, value):
        self._value = value

    def result(self):
        return self._value


class _Side:
    """Deterministic steps submitted to a process pool, or run at once without one."""

    def __init__(self, pool):
        self.pool = pool

    def submit(self, fn, *args):
        return _Now(fn(*args)) if self.pool is None else self.pool.submit(fn, *args)


def _start_reference(inp: _Inputs, pool) -> Future | None:
    """Submit step 6 to ``pool`` when it samples (MCMC with CMDS); None: it runs in turn."""
    if pool is None or inp.config.cmds is None or inp.options.posterior != "mcmc":
        return None
    return pool.submit(reference_area_task, inp)


def _collect_reference(inp: _Inputs, job: Future | None, runs: dict):
    """Step 6's (A_ref draws, dof): from the second process, or computed now."""
    if job is None:
        return _reference_area(inp, runs)
    a_ref, dof, run = job.result()
    if run is not None:
        runs["cmds"] = run
    return a_ref, dof


def _h_components(
    split: _HSplit, grad_a, d_beat, refined, r_noise_ref: dict, noise_name: str, beat_dof=np.inf
):
    """The H rows of the A budget and their correlations.

    One row for the posterior of the parameters not refined (all at once, through H(f)), one per
    refined parameter (its ring-down scatter given the others). Type A dof (GUM G.3.3): the
    refinement's and the beat-note fit's n_points - n_params (``beat_dof``).
    """
    comps, corr = [], {}
    ir, refd, others, centre = split.ir, split.refined, split.others, split.centre
    for k, n in enumerate(refd):
        comps.append(
            Component(
                f"H: {n} (refined on ring-downs)",
                float(centre[ir[k]]),
                float(np.sqrt(refined.cov[k, k])),
                float(grad_a[ir[k]]),
                H_UNITS[n],
                dof=max(float(refined.dof), 1.0),
                note="Type A: posterior u of the ring-down update of the beat note given the other "
                "H parameters (ring-down noise acting through H); dof = ring-down samples - "
                "parameters of the refinement",
            )
        )
    comps.append(
        Component(
            f"H: posterior of {', '.join(others)} (beat note, weighted by the ring-downs)",
            None,
            float(np.std(d_beat)),
            1.0,
            "Hz/m",
            dof=max(float(beat_dof), 1.0),
            note="Type A: sd of A over the joint posterior draws of these H parameters (the "
            "refined ones at their conditional mean), each propagated through its H(f) into "
            "every tau (first order in H, exact in the parameters); dof = beat-note points - "
            "parameters of its fit",
        )
    )
    rc = refined.cov / np.outer(np.sqrt(np.diag(refined.cov)), np.sqrt(np.diag(refined.cov)))
    for n, r in consistent_correlations(r_noise_ref, refd, rc).items():
        corr[(noise_name, f"H: {n} (refined on ring-downs)")] = r
    if len(refd) > 1:
        for a in range(len(refd)):
            for b in range(a + 1, len(refd)):
                corr[
                    (
                        f"H: {refd[a]} (refined on ring-downs)",
                        f"H: {refd[b]} (refined on ring-downs)",
                    )
                ] = float(rc[a, b])
    return comps, corr


def consistent_correlations(r_noise: dict, refd, rc) -> dict:
    """r(noise, refined p) shrunk, if need be, to be consistent with the refined ones' own rc.

    The two come from different estimators (influence functions for r(noise, p), the
    refinement's covariance for rc); with two or more refined parameters they can contradict each
    other (e.g. r = 0.9 with both of two parameters that are anticorrelated), and the budget's
    correlation matrix would not be positive semi-definite. Consistency needs
    c^T rc^-1 c <= 1 for the vector c of r(noise, p); above it c is scaled down to the boundary
    (the smallest change along c), otherwise returned as it is.
    """
    names = [n for n in refd if n in r_noise]
    if len(names) < 2:
        return dict(r_noise)
    idx = [list(refd).index(n) for n in names]
    c = np.array([r_noise[n] for n in names])
    q = float(c @ np.linalg.solve(rc[np.ix_(idx, idx)], c))
    if q <= 1.0:
        return dict(r_noise)
    c = c / np.sqrt(q) * (1.0 - 1e-9)
    return {**r_noise, **{n: float(v) for n, v in zip(names, c)}}


FORM_WEIGHT_MIN = 1e-4  # BIC weight below which the other H form is not even evaluated


@dataclass(frozen=True)
class _FormChoice:
    """Eq. 2 with n_r = 2 against n_r free (step 1a), and the form the budget samples.

    ``beat_2`` the n_r = 2 beat-note fit; ``sampled`` the beat-note fit whose form is sampled;
    ``weight_free`` the weight of the n_r-free form (from the beat note and the ring-downs where
    both forms were updated, ``updates`` = (n_r = 2, n_r free) RefinedTF; else the beat note's
    BIC weight, ``updates`` None); ``record`` what budget.json says of it.
    """

    forms: HModelForms
    beat_2: object
    sampled: object
    weight_free: float
    updates: tuple | None
    record: dict


def _form_update(inp: _Inputs, beat, free: tuple, noise_v=None):
    """The ring-down update of one form of H (its beat-note TFFit ``beat``); None if it fails."""
    options = inp.options
    try:
        r = ring_down_update(inp.config, options, beat, free, noise_v=noise_v)[0]
    except (AnalysisError, ValueError, np.linalg.LinAlgError) as exc:
        log.info("H model form: the update of %s failed (%s)", free, exc)
        return None
    return r if r.converged else None


def _form_updates(inp: _Inputs, forms: HModelForms, beat_2):
    """Both forms updated on the same records over every H parameter the beat note fitted.

    n_r is among them in the free form; the beat note as prior keeps a parameter the ring-downs
    do not constrain where it puts it. Updating only some parameters would let n_r absorb the
    others' misfit and make a form difference out of it. Returns (r_2, r_free) or None when
    the options ask for no refinement or an update fails.
    """
    if not inp.options.refine_free:
        return None
    r_2 = _form_update(inp, beat_2, tuple(beat_2.free))
    if r_2 is None:
        return None
    # the same records' noise for both (estimated at the n_r = 2 form when the bundle has none)
    r_f = _form_update(inp, forms.free_fit, tuple(beat_2.free) + ("n_r",), r_2.noise_v)
    return None if r_f is None else (r_2, r_f)


def _h_forms(inp: _Inputs) -> _FormChoice:
    """Step 1a: Eq. 2 with n_r = 2 and with n_r free, weighed by the data, and the form to sample.

    Each form is fitted to the beat note (:func:`h_model_forms`). Unless the beat note alone
    settles it (BIC weight of either form below FORM_WEIGHT_MIN), both are updated by the
    ring-downs (:func:`_form_updates`) and weighed by all the data (:func:`free_order_weight`);
    the beat note alone cannot see what the ring-downs know, and on a weak slow resonance it
    leaves n_r loose. n_r is sampled (the beat-note posterior over BEAT_FREE + n_r, started from
    the n_r-free fit) when the options allow it, the data ask for a free order (weight > 1/2)
    and that fit lies inside the posterior's causal support (H_PRIOR: n_r < 2); else n_r = 2, as
    a rational chain.
    """
    beat = inp.beat
    if beat is None:
        beat = beat_note_fit(inp.config, free=BEAT_FREE, window=inp.options.window)
    forms = h_model_forms(inp.config, beat)
    w_free, updates = forms.weight_free, None
    record = {
        "weight_source": "beat note alone (BIC): "
        + ("it settles the form" if forms.free_fit is not None else "the n_r-free fit failed")
    }
    if forms.free_fit is not None and FORM_WEIGHT_MIN < w_free < 1.0 - FORM_WEIGHT_MIN:
        updates = _form_updates(inp, forms, beat)
        w_all = np.nan if updates is None else free_order_weight(forms, beat, *updates)
        if not np.isfinite(w_all):
            updates = None
            record = {"weight_source": "beat note alone (BIC): no ring-down update of both forms"}
        else:
            r_2, r_f = updates
            w_free = w_all
            i = r_f.free.index("n_r")
            record = {
                "weight_source": "beat note and ring-downs (Laplace evidence)",
                "n_r_refined": float(r_f.params.n_r),
                "n_r_refined_u": float(np.sqrt(r_f.cov[i, i])),
                "updated": list(r_f.free),
            }
    lo, hi = H_PRIOR["n_r"]
    free = inp.options.free_order and w_free > 0.5 and lo < forms.free_fit.params.n_r < hi
    record["weight_n_r_free_all_data"] = w_free
    return _FormChoice(forms, beat, forms.free_fit if free else beat, w_free, updates, record)


def _form_area(inp: _Inputs, h) -> float:
    """The line area (Hz/m) from the decay times at t_cut with the transfer function ``h``."""
    options = inp.options
    f = fit_ringdowns(inp.config.ringdowns, [options.t_cut_s], "tf-crds", h, options.window)
    f = f.converged_only()  # as for the A it is compared with
    spec = crds_spectrum(f.nu_hz, f.tau_s[:, 0], f.tau_u_s[:, 0])
    return fit_line([spec], options.profile, inp.gd, inp.nu_ref).line_area


def _h_model_form(inp: _Inputs, choice: _FormChoice, n_r_sampled: bool):
    """Step 6b: the H model-form row (Eq. 2 with n_r = 2 against n_r free), sized by the data.

    The two forms (updated by the ring-downs alike where ``choice`` has the updates, else at
    their beat-note fits) give A; the form not sampled enters with its weight w:
    u = sqrt(w) |A_other - A_used|, the between-model sd about the form used, with the
    difference taken between the two forms alone. A form the data reject (w -> 0) contributes
    nothing; one the beat note alone rejects (w < FORM_WEIGHT_MIN) is not even evaluated.
    Returns (Component, record).
    """
    forms = choice.forms
    w_free = choice.weight_free
    w = 1.0 - w_free if n_r_sampled else w_free
    d_a = None
    record = dict(choice.record)
    if forms.free_fit is not None and w > FORM_WEIGHT_MIN:
        if choice.updates is None:
            h_2, h_f = choice.beat_2.params, forms.free_fit.params
        else:
            h_2, h_f = (r.params for r in choice.updates)
        a_2, a_f = _form_area(inp, h_2), _form_area(inp, h_f)
        d_a = a_2 - a_f if n_r_sampled else a_f - a_2
        record.update(a_n_r_2_hz_per_m=a_2, a_n_r_free_hz_per_m=a_f)
    u = 0.0 if d_a is None else float(np.sqrt(w) * abs(d_a))
    record.update(
        bic_n_r_2=forms.bic_fixed,
        bic_n_r_free=forms.bic_free,
        weight_n_r_free=forms.weight_free,
        n_r_free_fit=None if forms.free_fit is None else forms.free_fit.params.n_r,
        asks_for_free_order=w_free > 0.5,
        form_sampled="n_r free" if n_r_sampled else "n_r = 2",
        row_weight=w,
        a_other_minus_a_used_hz_per_m=d_a,
    )
    used, other = ("n_r free", "n_r = 2") if n_r_sampled else ("n_r = 2", "n_r free")
    source = record["weight_source"].split(" (")[0]
    comp = Component(
        "H model form (Eq. 2: n_r = 2 vs n_r free)",
        None,
        u,
        1.0,
        "Hz/m",
        dof=dof_from_relative_u(REL_U_ONE_DIFFERENCE),
        note=f"from the data: weight of {other} from the {source} w = {w:.3g}; "
        f"u = sqrt(w) |A({other}) - A({used})|, both forms updated alike; "
        "dof 2: u judged reliable to 50 % (GUM G.4.2)",
    )
    return comp, record


def _budget_a(
    options, dt: _DecayTimes, a_total, u_dir, h_rows, instrument=(), temperature=None
) -> Budget:
    """Step 7.

    The GUM budget of A: ring-down noise, the H rows (``h_rows`` = (components, correlations), empty
    for CRDS), the t_cut choice, the line-shape model, the instrument rows (``instrument``:
    InstrumentRow list) and T through the fit's Doppler width (``temperature``: a Component,
    :func:`~bayes_tfcrds.uncertainty.doppler.temperature_row`).
    """
    comps = [
        Component(
            "ring-down noise (line fit given H)",
            None,
            u_dir,
            1.0,
            "Hz/m",
            dof=max(float(dt.lsq.dof), 1.0),
            note="Type A: sd of the line posterior given the refined H; dof = spectral points - "
            "line parameters of the fit",
        )
    ]
    h_comps, corr = h_rows
    comps += h_comps
    spread = max(dt.area_by_tcut.values()) - min(dt.area_by_tcut.values())
    comps.append(
        Component(
            "t_cut choice",
            None,
            float(spread / np.sqrt(12)),
            1.0,
            "Hz/m",
            dof=dof_from_relative_u(REL_U_SPREAD),
            note="Type B: rectangular over the A(t_cut) range, t_cut = "
            f"{', '.join(f'{t * 1e6:g}' for t in dt.t_cuts)} µs; dof 8: u judged reliable to 25 %",
        )
    )
    shapes = dt.shapes
    weights = ", ".join(f"{k} {w:.2g}" for k, w in shapes.weights.items())
    comps.append(
        Component(
            f"line-shape model (average of {len(shapes.candidates)} profiles)",
            None,
            shapes.u_between,
            1.0,
            "Hz/m",
            dof=dof_from_relative_u(REL_U_ONE_DIFFERENCE),
            note="between-model sd sqrt(sum w_k (A_k - A_bar)^2), pseudo-BMA+ (Akaike) weights "
            f"of the profiles fitted to the spectrum: {weights}; dof 2: u judged reliable to 50 %",
        )
    )
    comps += [row.component for row in instrument]
    if temperature is not None:
        comps.append(temperature)
    return Budget(
        quantity="line area A",
        # the model-averaged A: the profile's posterior mean moved by A_bar - A(profile)
        value=float(np.mean(a_total) + shapes.line_area - dt.lsq.line_area),
        unit="Hz/m",
        components=tuple(comps),
        correlations=corr,
    )


def _budget_s(
    sample, a_hat: float, u_a: float, line=None, dof_a: float = np.inf, da_dt: float = 0.0
) -> Budget:
    """Step 8: the line intensity at the line data's T_ref (296 K) from A, p, x and T.

    S(T_ref) = A k_B T/(p x) Q(T)/Q(T_ref) exp(E''/k_B (1/T - 1/T_ref)) times the
    stimulated-emission ratio (LineData.reference_intensity_from_area), so that it compares
    with the reference intensity at 296 K whatever T the campaign ran at. Sensitivities:
    c_A = S/A, c_p = -S/p, c_x = -S/x and c_T = S d ln S(T_ref)/dT with
    d ln S(T_ref)/dT = 1/T + d ln Q/dT - E''/(k_B T^2) (+ the stimulated-emission term), which
    is -0.0107 /K for CO (3-0) R(23) at 296 K: the lower-state population dominates the 1/T of
    the number density. u(p), u(T) from the bundle; it has no u(x). dof: A's effective dof
    (``dof_a``), p and T 50 (u judged reliable to 10 %, GUM G.4.2). The model is
    :func:`intensity_model`, which the Monte Carlo of the budget evaluates too.

    The line fit also reads T (its Doppler width), so A = A(T): ``da_dt`` (Hz/m per K) is that
    derivative, and ``u_a`` must then be A's u without its T row (``doppler``). T's sensitivity
    is the total one, S (d ln S(T_ref)/dT + d ln A/dT): one input, one row, no double count.
    """
    line = load_line() if line is None else line
    t, p, x = sample.temperature_k, sample.pressure_pa, sample.mole_fraction
    s_ref = float(intensity_model(line)(a_hat, p, t, x))
    dlns_dt = 1.0 / t - float(line.intensity_log_derivative(t))
    dlna_dt = da_dt / a_hat
    through_a = (
        f"; + d ln A/dT = {dlna_dt:+.4g} /K through the line fit's Doppler width" if da_dt else ""
    )
    return Budget(
        quantity=f"line intensity S(T_ref = {line.temperature_k:g} K)",
        value=s_ref,
        unit="cm/molecule",
        components=(
            Component(
                "line area A",
                a_hat,
                u_a,
                s_ref / a_hat,
                "Hz/m",
                dof=dof_a,
                note="combined u(A) from the A budget"
                + (" without its T row (T is the row below)" if da_dt else "")
                + "; dof = its effective dof",
            ),
            Component(
                "pressure p",
                p,
                sample.pressure_u_pa,
                -s_ref / p,
                "Pa",
                dof=dof_from_relative_u(REL_U_CERTIFICATE),
                note="Type B, normal: bundle /sample@pressure_u_pa; dof 50 (u reliable to 10 %)",
            ),
            Component(
                "temperature T",
                t,
                sample.temperature_u_k,
                s_ref * (dlns_dt + dlna_dt),
                "K",
                dof=dof_from_relative_u(REL_U_CERTIFICATE),
                note="Type B, normal: bundle /sample@temperature_u_k; dof 50; "
                "d ln S(T_ref)/dT = 1/T + d ln Q/dT - "
                f"E''/(k_B T^2) = {dlns_dt:+.4g} /K (Q: TIPS-2021)" + through_a,
            ),
            Component(
                "mole fraction x",
                x,
                0.0,
                -s_ref / x,
                "1",
                note="bundle /sample@mole_fraction; the bundle gives no u(x), taken as exact",
            ),
        ),
    )


def _budgets_s_and_ratio(sample, budget_a: Budget, a_ref, dof_ref, doppler):
    """Steps 8-9: the budgets of S(T_ref) and A/A_ref from A's budget (with its T row).

    Both models read T a second time (S's conversion; A_ref's fit), so A enters them with u and
    effective dof of its budget *without* the T row, and T has one row of total sensitivity.
    """
    a_but_t = without_temperature_row(budget_a)
    u_a, nu_a = a_but_t.combined_u, a_but_t.effective_dof
    budget_s = _budget_s(sample, budget_a.value, u_a, dof_a=nu_a, da_dt=doppler.da_dt)
    budget_ratio = _budget_ratio(budget_a.value, u_a, a_ref, nu_a, dof_ref, doppler)
    return budget_s, budget_ratio


def intensity_model(line):
    """S(T_ref) (cm/molecule) = f(A [Hz/m], p [Pa], T [K], x): the budget's measurement model.

    Vectorised (the GUM budget evaluates it at the estimates, the Monte Carlo at every draw):
    ``line.reference_intensity_from_area``.
    """
    return line.reference_intensity_from_area


def _budget_ratio(
    a_hat: float,
    u_a: float,
    a_ref,
    dof_a: float = np.inf,
    dof_ref: float = np.inf,
    doppler: DopplerSensitivity | None = None,
) -> Budget | None:
    """Step 9: A/A_ref with the CMDS posterior's u; None without CMDS.

    dof: A's effective dof and the CMDS fit's n_points - n_params (``dof_ref``). With
    ``doppler`` both fits read T (their Doppler width): ``u_a`` is then A's u without its T row,
    and T has its own row, c = (dA/dT - r dA_ref/dT)/A_ref, in which the two fits' shifts
    largely cancel.
    """
    if a_ref is None:
        return None
    a_ref_hat = float(np.mean(a_ref))
    u_ref = float(np.std(a_ref))
    r = a_hat / a_ref_hat
    t_row = ()
    if doppler is not None:
        # without the CMDS fit's derivative, A's own path only (u_a lacks it)
        da_ref_dt = 0.0 if doppler.da_ref_dt is None else doppler.da_ref_dt
        c_t = (doppler.da_dt - r * da_ref_dt) / a_ref_hat
        t_row = (
            Component(
                ROW_NAME,
                doppler.temperature_k,
                doppler.temperature_u_k,
                c_t,
                "K",
                dof=dof_from_relative_u(REL_U_CERTIFICATE),
                note="Type B, normal: bundle /sample@temperature_u_k; both fits hold the "
                "Doppler HWHM at GammaD(T): c = (dA/dT - (A/A_ref) dA_ref/dT)/A_ref, "
                f"d ln A/d ln T = {doppler.da_dt * doppler.temperature_k / a_hat:+.3g}, "
                f"d ln A_ref/d ln T = {da_ref_dt * doppler.temperature_k / a_ref_hat:+.3g}",
            ),
        )
    return Budget(
        quantity="A/A_ref",
        value=r,
        unit="1",
        components=(
            Component(
                "line area A (CRDS)",
                a_hat,
                u_a,
                1.0 / a_ref_hat,
                "Hz/m",
                dof=dof_a,
                note="combined u(A) from the A budget without its T row (T is its own row)"
                if t_row
                else "",
            ),
            Component(
                "reference area A_ref (CMDS)",
                a_ref_hat,
                u_ref,
                -r / a_ref_hat,
                "Hz/m",
                dof=dof_ref,
                note="Type A: CMDS posterior; dof = CMDS points - line parameters of the fit",
            ),
            cmds_type_b(a_ref_hat, r),
            *t_row,
        ),
    )


def _summary(
    inp: _Inputs,
    dt: _DecayTimes,
    budget_a: Budget,
    budget_s: Budget,
    budget_ratio,
    a_total,
    sens_a: dict,
    h_star,
    doppler: DopplerSensitivity | None = None,
) -> dict:
    """The ``budget.json`` payload (cm^-2 and cm/molecule at this edge, SI beside them).

    ``doppler``: how A and A_ref move with T (their fits' Doppler width), for E_n, whose
    A - A_ref then carries T once, through dA/dT - dA_ref/dT.
    """
    options = inp.options
    a_hat, u_a = budget_a.value, budget_a.combined_u
    s_val = budget_s.value
    line = load_line()
    s_ref, u_s_ref = line.intensity_cm_per_molecule, line.intensity_u_cm_per_molecule
    t_sample = inp.sample.temperature_k
    summary = {
        "configuration": inp.config.name,
        "method": options.method,
        "window": options.window if options.method == "tf-crds" else None,
        "t_cut_s": options.t_cut_s,
        "profile": options.profile,
        "posterior": {
            "method": options.posterior,
            "approximation": options.posterior == "laplace",
            "description": POSTERIORS[options.posterior],
        },
        "line_area": {
            "value": float(line_area_to_cm2(a_hat)),
            "u": float(line_area_to_cm2(u_a)),
            "unit": "cm^-2",
            "value_si": a_hat,
            "u_si": u_a,
            "unit_si": "Hz/m",
            "u_statistical": float(line_area_to_cm2(np.std(a_total))),
            "u_statistical_note": "posterior sd of A from ring-down noise and H (no Type B rows)",
        },
        "intensity": {
            "value": s_val,
            "u": budget_s.combined_u,
            "unit": "cm/molecule",
            "t_ref_k": line.temperature_k,
            "model": "S(T_ref) = A k_B T/(p x) Q(T)/Q(T_ref) exp(c2 E'' (1/T - 1/T_ref)) "
            "[1 - exp(-c2 nu0/T_ref)]/[1 - exp(-c2 nu0/T)], Q from TIPS-2021",
            "sample_temperature_k": t_sample,
            "value_at_sample_temperature": s_val * float(line.intensity_ratio(t_sample)),
            "reference": s_ref,
            "reference_u": u_s_ref,
            "en": normalized_error(s_val, 2 * budget_s.combined_u, s_ref, 2 * u_s_ref),
        },
        "components": [
            {
                "name": c.name,
                "u": float(line_area_to_cm2(c.contribution)),
                "unit": "cm^-2",
                "share": float(budget_a.shares()[c.name]),
            }
            for c in budget_a.components
        ],
        "line_shape_models": {
            **dt.shapes.to_dict(),
            "line_area_of_profile": float(line_area_to_cm2(dt.lsq.line_area)),
        },
        "a_by_t_cut": {
            f"{k * 1e6:g}us": float(line_area_to_cm2(v)) for k, v in dt.area_by_tcut.items()
        },
        # fits that did not converge, left out of every spectrum (per t_cut, all points)
        "unconverged_decay_times": {
            f"{tc * 1e6:g}us": int(n) for tc, n in zip(dt.t_cuts, dt.fits.unconverged.sum(axis=0))
        },
        # dA/d(theta_H) in cm^-2 per unit of each H parameter, as the GUM tables' coefficients
        "sensitivities_cm2": {k: EDGE_UNITS["Hz/m"][1] * float(v) for k, v in sens_a.items()},
        "h_propagation": (
            "each H draw through its H(f) into every tau, first order in H (function space)"
            if options.method == "tf-crds"
            else None
        ),
    }
    if inp.noise is not None:
        summary["noise"] = inp.noise.to_dict()
    if h_star is not None:
        summary["transfer_function"] = {
            "f_c_hz": h_star.f_c_hz,
            "a_r": h_star.a_r,
            "f_r_hz": h_star.f_r_hz,
            "gamma_r": h_star.gamma_r,
            "n_r": h_star.n_r,
            "variant": h_star.variant,
            "refined": list(options.refine_free),
        }
    if budget_ratio is not None:
        # A_ref's u: the CMDS posterior and the CMDS Type B row together, as in the ratio table
        # (T, the ratio's last row, acts on A and A_ref together: in E_n below)
        a_ref_hat, u_ref = reference_value_and_u(budget_ratio)
        summary["reference_area"] = {
            "value": float(line_area_to_cm2(a_ref_hat)),
            "u": float(line_area_to_cm2(u_ref)),
            "unit": "cm^-2",
            "value_si": a_ref_hat,
            "u_si": u_ref,
            "unit_si": "Hz/m",
        }
        summary["ratio"] = {"value": budget_ratio.value, "u": budget_ratio.combined_u, "unit": "1"}
        summary["en"] = normalized_error(a_hat, 2 * _u_a_for_en(budget_a, doppler), a_ref_hat,
                                         2 * u_ref)  # fmt: skip
    else:
        summary["reference_area"] = summary["ratio"] = summary["en"] = None
    return summary


#: the ratio table's rows of A_ref (its CMDS posterior and the CMDS Type B)
REFERENCE_ROWS = "reference area A_ref (CMDS)"


def reference_value_and_u(budget_ratio: Budget) -> tuple:
    """(A_ref, u(A_ref)) in Hz/m from the ratio table: its CMDS posterior and Type B rows."""
    rows = [c for c in budget_ratio.components if c.name.startswith(REFERENCE_ROWS)]
    return rows[0].value, float(np.hypot.reduce([c.u for c in rows]))


def _u_a_for_en(budget_a: Budget, doppler: DopplerSensitivity | None) -> float:
    """u(A) for E_n = (A - A_ref)/sqrt(U_A^2 + U_ref^2), T's part moved onto A - A_ref.

    Both fits read the same T, so T enters A - A_ref once, as (dA/dT - dA_ref/dT) u(T); the
    rest of u(A) is A's budget without its T row. Without the CMDS derivative: u_c(A).
    """
    if doppler is None or doppler.da_ref_dt is None:
        return budget_a.combined_u
    u_t = (doppler.da_dt - doppler.da_ref_dt) * doppler.temperature_u_k
    return float(np.hypot(without_temperature_row(budget_a).combined_u, u_t))


def _n_r_record(h_draws, names) -> dict:
    """Whether the order n_r was sampled and, if so, its posterior mean and sd (budget.json)."""
    if "n_r" not in names:
        return {"n_r_sampled": False, "n_r_posterior": None}
    n_r = np.asarray(h_draws)[:, list(names).index("n_r")]
    return {
        "n_r_sampled": True,
        "n_r_posterior": {"mean": float(np.mean(n_r)), "sd": float(np.std(n_r))},
    }


def _refinement_summary(refined, region: str | None = None) -> dict:
    """How the ring-downs updated the beat note: per parameter values, u, shift and tension z.

    ``region``: why the refinement was not made about the least-squares beat note, or why the
    H draws are not the MCMC's (posterior_steps.refinement_region); None in the usual case.
    """
    c2, dof, p = refined.tension_chi2
    return {
        "parameters": refined.tension(),
        "tension_chi2": c2,
        "tension_dof": dof,
        "tension_p": p,
        "in_tension": bool(refined.in_tension),
        "composite_weight": float(refined.weight),
        "converged": bool(refined.converged),
        # the prior the ring-downs updated: the least-squares beat note, or the sampled beat-note
        # posterior's moments where the refinement could not be linearised about the former
        "beat_note_prior": None if refined.prior is None else refined.prior.source,
        "region": region,
        "note": "z: shift of the refined value from the beat note over its expected scatter when "
        "both agree; |z| > 3 is reported as a finding",
    }


def _apply_gates(
    summary: dict, options: BudgetOptions, runs: dict, h_weights=None, refined=None
) -> None:
    """Step 10.

    The samplers' diagnostics into the summary; a failed run is never shown as a result (its numbers
    move out of the result keys into ``unconverged_estimates``). A ring-down refinement of H that
    did not converge fails the budget too, whatever the samplers say.
    """
    if options.posterior == "laplace":
        # no sampler ran: nothing to diagnose, and the summary says which posterior was used
        passed = True
        summary["diagnostics"] = {
            "posterior": "laplace",
            "rhat_max": None,
            "ess_min": None,
            "passed": True,
            "runs": {},
        }
    else:
        rhat = max(run.rhat_max for run in runs.values())
        ess = min(run.ess_min for run in runs.values())
        passed = all(run.passed for run in runs.values())
        summary["diagnostics"] = {
            "posterior": "mcmc",
            "rhat_max": float(rhat),
            "ess_min": float(ess),
            "passed": bool(passed),
            "runs": {
                k: {
                    "rhat_max": float(v.rhat_max),
                    "ess_min": float(v.ess_min),
                    "passed": bool(v.passed),
                    "status": v.status,
                    "n_steps": int(v.n_steps),
                }
                for k, v in runs.items()
            },
        }
    weights = h_weights
    if weights is not None:
        summary["diagnostics"]["h_ring_down_weights"] = {
            "pool": weights.pool,
            "ess": weights.ess,
            "passed": weights.passed,
            "note": "beat-note draws weighted by the ring-down likelihood (the joint posterior of "
            "H); a low ESS means the ring-downs overrule the beat note on parameters not refined",
        }
        passed = passed and weights.passed
        summary["diagnostics"]["passed"] = bool(passed)
    refinement_failed = refined is not None and not refined.converged
    if refinement_failed:
        summary["diagnostics"]["refinement_converged"] = False
        passed = False
        summary["diagnostics"]["passed"] = False
    if not passed:
        failed = {
            k: summary.pop(k) for k in ("line_area", "reference_area", "ratio", "en", "intensity")
        }
        summary.update({k: None for k in failed})
        summary["unconverged_estimates"] = failed
        summary["status"] = (
            "failed: the ring-down refinement of H did not converge (try --refine with fewer "
            "parameters, or check the ring-downs with bayes-tfcrds fit)"
            if refinement_failed
            else "failed: convergence gates not met"
            if weights is None or weights.passed
            else f"failed: the ring-downs overrule the beat note (importance ESS {weights.ess:.0f} "
            f"< {IS_ESS_MIN}); refine more H parameters (--refine)"
        )
    else:
        summary["status"] = "ok"


def _tau_table(inp: _Inputs, dt: _DecayTimes, h_star, h_draws, names=BEAT_FREE) -> list:
    """Step 11.

    Decay-time posteriors at every point and t_cut: the mean and sd over the H draws (each through
    its H(f), first order) about the fit at H*, and the fit's noise u; seconds.
    """
    options, rd, fits = inp.options, inp.config.ringdowns, dt.fits
    rows = [
        np.nonzero(np.isfinite(fits.tau_s[:, j]) & np.isfinite(fits.tau_u_s[:, j]))[0]
        for j in range(len(dt.t_cuts))
    ]
    shifted = [j for j, rows_j in enumerate(rows) if options.method == "tf-crds" and rows_j.size]
    kernels = [
        (
            tau_h_kernels(
                rd.time_s,
                np.full(rows[j].size, dt.t_cuts[j]),
                fits.tau_s[rows[j], j],
                fits.amplitude_v[rows[j], j],
                h_star,
                options.window,
                noise_v=rd.fit_noise_v,
                rows_of=rows[j],
            ),
            rows[j].size,
        )
        for j in shifted
    ]
    shifts = dict(zip(shifted, h_shifts_many(kernels, h_draws, h_star, names=names)))
    tau_table = []
    for j, tc in enumerate(dt.t_cuts):
        rows_j = rows[j]
        u_h = np.zeros(rows_j.size)
        if j in shifts:
            u_h, mean_h = np.std(shifts[j], axis=0), np.mean(shifts[j], axis=0)
        else:
            mean_h = np.zeros(rows_j.size)
        for i, uh, dh in zip(rows_j, u_h, mean_h):
            un = fits.tau_u_s[i, j]
            tau_table.append(
                (
                    float(fits.nu_hz[i]),
                    float(tc),
                    float(fits.tau_s[i, j] + dh),  # the posterior mean over H, first order
                    float(un),
                    float(uh),
                    float(np.hypot(un, uh)),
                )
            )
    return tau_table


def run_budget(
    bundle,
    config,
    options: BudgetOptions = BudgetOptions(),
    rng: np.random.Generator | None = None,
    outdir: str | Path | None = None,
    progress: bool = False,
    workers: int = 1,
    pool=None,
    on_run=None,
) -> BudgetResult:
    """Posteriors, propagation and the GUM budget for one configuration (see module doc).

    The steps, in order (each a function of this module): inputs and checks; the H posterior
    (tf-crds); decay times and line fits at every t_cut; the line posterior given H*; the
    sensitivity of A to H and the H-shifted draws of A (tf-crds); A_ref from CMDS; the budgets of
    A, S and A/A_ref; the summary with its convergence gates; the decay-time table.

    Parameters
    ----------
    bundle : Bundle
        The measurement.
    config : Configuration
        The configuration (``bundle.configs["D2"]``).
    options : BudgetOptions
        Method, t_cut (s), profile, posterior (``mcmc`` or ``laplace``, seconds) and sampler
        lengths.
    rng : numpy.random.Generator, optional
        The only source of randomness (default seed 0).
    outdir : str or pathlib.Path, optional
        Folder for the chains (a rerun resumes them); None keeps everything in memory.
    progress : bool
        Show the samplers' progress.
    workers : int
        Processes to use: with 2 or more, the CMDS reference is sampled in a second process
        while H and the line are (the same result bit for bit; MCMC only).
    pool : concurrent.futures.Executor, optional
        A process pool of the caller's (:func:`side_pool`) to use instead of making one from
        ``workers``: the CLI shares it with the corner plots.
    on_run : callable, optional
        ``on_run(key, run)`` with each posterior run (``h``, ``line``, ``cmds``) as soon as it is
        sampled, in this process: the CLI starts its corner plot in the pool meanwhile.

    Returns
    -------
    BudgetResult
        ``line_area``, ``ratio``, ``intensity`` (Quantity, cm^-2 and cm/molecule), ``en``,
        ``passed``; the GUM budgets; ``summary()``, ``to_dict()``, ``plot()`` (shares of u_c^2).
    """
    rng = np.random.default_rng(0) if rng is None else rng
    log.debug(f"budget of {config.name}: {options}")
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    inp = _inputs(bundle, config, options, rng, outdir, progress)
    if outdir is None:
        return _budget_with(inp, workers, pool, on_run)
    # one run at a time resumes the chains of a folder (a second one is refused, FolderBusyError)
    with folder_lock(outdir):
        claim_chains(outdir, run_fingerprint(bundle, config, options))
        return _budget_with(inp, workers, pool, on_run)


@contextlib.contextmanager
def side_pool(workers: int):
    """A pool of ``workers`` - 1 processes for the side steps (None when workers < 2).

    If the main process fails or is interrupted, the pool's processes get SIGINT: a sampler there
    commits its chains and stops at its next chunk, instead of the error waiting for it to finish.
    """
    if workers < 2:
        yield None
        return
    pool = ProcessPoolExecutor(max_workers=workers - 1)
    try:
        yield pool
    except BaseException:
        interrupt_pool(pool)
        raise
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def interrupt_pool(pool) -> None:
    """SIGINT to every process of ``pool``: a sampler there commits its chains and stops."""
    for proc in list(getattr(pool, "_processes", {}).values()):
        with contextlib.suppress(OSError):
            os.kill(proc.pid, signal.SIGINT)


def _budget_with(inp: _Inputs, workers: int, pool=None, on_run=None) -> BudgetResult:
    """:func:`_budget` in the caller's ``pool``, or in a :func:`side_pool` of ``workers``.

    A failure interrupts the caller's pool too, here, while the chain folder is still locked.
    """
    if pool is None:
        with side_pool(workers) as own:
            return _budget(inp, own, on_run)
    try:
        return _budget(inp, pool, on_run)
    except BaseException:
        interrupt_pool(pool)
        raise


def _budget(inp: _Inputs, pool=None, on_run=None) -> BudgetResult:
    """Steps 1-10 of :func:`run_budget` on checked inputs (the chain folder claimed).

    With a ``pool`` (a process pool), the CMDS reference (step 6) is sampled there meanwhile.
    ``on_run(key, run)`` hears of each posterior run when it is sampled.
    """
    options, config = inp.options, inp.config
    announce = on_run if on_run is not None else (lambda key, run: None)
    ref_job = _start_reference(inp, pool)
    tf = options.method == "tf-crds"
    clock = StageClock(9 if tf else 6, f"budget {config.name} ({options.posterior})")
    runs = {}
    h_star = h_draws = refined = h_parts = beat = ident = None
    names = BEAT_FREE  # the sampled H parameters (n_r too when the beat note asks for it)
    if tf:  # 1. H
        choice = _h_forms(inp)
        beat = choice.sampled
        beat, refined, h_star, h_draws, h_run, h_parts = h_posterior(
            config, options, inp.streams["h"], inp.chain_file("h"), inp.progress, beat
        )
        names = h_parts["names"]
        if h_run is not None:
            runs["h"] = h_run
        # the other descriptions of Eq. 2 that give this H(f): which parameters are identified
        ident = identify_h(
            h_star,
            h_draws,
            names,
            identification_grid(config.ringdowns.time_s),
            starts=tuple(f.params for f in (beat, *beat.alternatives)),
        )
        clock.done("H posterior")
    dt = _decay_times(inp, h_star)  # 2. decay times
    clock.done("decay times")
    # deterministic steps that need only H* and the decay times: beside the line posterior
    side = _Side(pool)
    instrument_job = side.submit(
        instrument_rows, config, options, h_star, dt.spec, inp.gd, inp.nu_ref
    )  # 6c.
    form_job = side.submit(_h_model_form, inp, choice, "n_r" in names) if tf else None  # 6b.
    doppler_job = side.submit(_doppler, inp, dt)  # 6d.
    tau_job = side.submit(_tau_table, inp, dt, h_star, h_draws, names)  # 11.
    if "h" in runs:  # after the side steps, which this process will wait for
        announce("h", runs["h"])
    line_flat = _line_posterior(inp, dt, runs)  # 3. line | H*
    clock.done("line posterior")
    if "line" in runs:
        announce("line", runs["line"])
    a_noise = line_flat[:, dt.lsq.names.index("line_area")]
    u_dir = float(np.std(a_noise))
    sens_a, h_rows, d_h = {}, ([], {}), None
    if options.method == "tf-crds":  # 4-5. H into A
        sens = _h_sensitivity(inp, dt, h_star, names)
        split = _h_split(h_star, h_parts)
        a_total, r_noise_ref, d_beat = _h_shifted_areas(
            inp, dt, sens, split, h_star, refined, h_parts, a_noise, u_dir
        )
        sens_a = dict(zip(names, sens.grad_a))
        h_rows = _h_components(
            split,
            sens.grad_a,
            d_beat,
            refined,
            r_noise_ref,
            "ring-down noise (line fit given H)",
            beat.dof,
        )
        d_h = h_shifts(sens.area_kernel, h_draws, h_star, 1, names=names)[:, 0]
        clock.done("H into A")
    else:
        a_total = a_noise.copy()
    a_ref, dof_ref = _collect_reference(inp, ref_job, runs)  # 6. A_ref
    clock.done("A_ref from CMDS")
    if "cmds" in runs:
        announce("cmds", runs["cmds"])
    form = None
    if tf:  # 6b. the form of the H model
        form_row, form = form_job.result()
        h_rows = (h_rows[0] + [form_row], h_rows[1])
        clock.done("H model form")
    instrument = instrument_job.result()  # 6c.
    clock.done("instrument rows")
    doppler = doppler_job.result()  # 6d.
    t_row = temperature_row(doppler, dt.lsq.line_area, dof_from_relative_u(REL_U_CERTIFICATE))
    budget_a = _budget_a(options, dt, a_total, u_dir, h_rows, instrument, t_row)  # 7-9. budgets
    budget_s, budget_ratio = _budgets_s_and_ratio(inp.sample, budget_a, a_ref, dof_ref, doppler)
    summary = _summary(inp, dt, budget_a, budget_s, budget_ratio, a_total, sens_a, h_star, doppler)
    mc = budget_monte_carlo(
        budget_a,
        a_total,
        inp.sample,
        a_ref,
        inp.streams["mc"],
        intensity_model(load_line()),
        doppler=doppler,
    )
    budgets = {"line_area": budget_a, "intensity": budget_s, "ratio": budget_ratio}
    add_to_summary(summary, budgets, mc)
    summary["instrument"] = {row.component.name: edge_keys(row.detail) for row in instrument}
    if refined is not None:
        summary["transfer_function"]["refinement"] = _refinement_summary(
            refined, (h_parts or {}).get("region")
        )
    if form is not None:
        summary["transfer_function"]["model_form"] = edge_keys(form)
        # the ring-downs may have asked for more parameters than the options named
        summary["transfer_function"]["refined"] = list(refined.free)
        summary["transfer_function"]["refined_asked"] = list(options.refine_free)
        summary["transfer_function"].update(_n_r_record(h_draws, names))
    if ident is not None:
        summary["transfer_function"]["identification"] = ident.to_dict()
    _apply_gates(summary, options, runs, (h_parts or {}).get("weights"), refined)  # 10. gates
    summary["priors"] = priors_summary(runs, EDGE_UNITS)  # line areas in cm^-2
    summary["doppler_width"] = doppler.to_dict(
        dt.lsq.line_area, None if a_ref is None else float(np.mean(a_ref))
    )
    clock.done("budgets")
    samples = {
        "a_total": a_total,
        "a_noise": a_noise,
        "a_ref": a_ref,
        "h_draws": h_draws,
        "h_names": names,  # the columns of h_draws
        "a_shift_h": d_h,  # first-order shift of A (Hz/m) that each H draw causes
    }
    tau_table = tau_job.result()
    clock.done("decay-time table")
    return BudgetResult(
        summary=summary,
        budget_a=budget_a,
        budget_s=budget_s,
        budget_ratio=budget_ratio,
        samples=samples,
        runs=runs,
        tau_table=tau_table,
        refined=refined,
        monte_carlo=mc,
        identification=ident,
    )
