"""Command-line interface: bayes-tfcrds COMMAND ...

Every command takes ``--seed`` (the same inputs and seed give the same numbers) and reports
bad input as one clear message naming what is wrong, with exit status 1 or 2.

Results go to stdout; progress, notes, warnings and errors to stderr through :mod:`logging`
(the package's loggers, ``bayes_tfcrds.*``), which only the command line configures: every
command takes ``--quiet`` (warnings and errors only) and ``--verbose`` (also debug lines).
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from bayes_tfcrds._version import __version__
from bayes_tfcrds.output.files import atomic_write_text


class Refused(Exception):
    """Input the command cannot work with; ``main`` prints it as one ``error:`` line."""

    def __init__(self, message: str, code: int = 1):
        super().__init__(message)
        self.code = code


def _printable(text: str) -> str:
    """A message with control characters (newlines, ANSI escapes from names) shown escaped.

    Names come from files (configuration names, paths) and may hold anything; escaped, every
    message stays one line that cannot move the cursor or recolour the terminal.
    """
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


log = logging.getLogger(__name__)

#: lines that ``--quiet`` still shows: they say something is wrong or must be read
_WARNING_PREFIXES = ("warning", "FAILED", "interrupted", "finding")


class _StderrHandler(logging.Handler):
    """Each record as one line on the current ``sys.stderr``, control characters escaped.

    The stream is looked up at each record, so a redirected stderr (a test, a notebook)
    receives the lines.
    """

    def emit(self, record: logging.LogRecord) -> None:
        try:
            text = record.getMessage()
            if record.levelno < logging.INFO:  # --verbose: say where a debug line comes from
                text = f"# debug {record.name}: {text}"
            print(_printable(text), file=sys.stderr)
        except Exception:  # logging's contract: report, never raise
            self.handleError(record)


_HANDLER = _StderrHandler()


def configure_logging(verbosity: int = 0) -> None:
    """Send the package's log records to stderr: -1 quiet (warnings), 0 notes, 1 debug too.

    Called once per command by :func:`main`; library code never configures logging.
    """
    package = logging.getLogger("bayes_tfcrds")
    if _HANDLER not in package.handlers:
        package.addHandler(_HANDLER)
    level = {-1: logging.WARNING, 0: logging.INFO}.get(verbosity, logging.DEBUG)
    package.setLevel(level)
    _HANDLER.setLevel(level)


def _say(line: str) -> None:
    """One line of progress, a note, or a warning, to stderr through logging.

    Lines that say something is wrong (warning, FAILED, ...) are warnings, shown even with
    ``--quiet``; the others are notes (level INFO).
    """
    level = logging.WARNING if line.startswith(_WARNING_PREFIXES) else logging.INFO
    log.log(level, line)


def _result(line: str) -> None:
    """One line of a command's result, on stdout (control characters escaped)."""
    print(_printable(line))


def _fail(message, code: int) -> int:
    """Report a refusal as the one line ``error: MESSAGE``; returns the exit status."""
    log.error(f"error: {message}")
    return code


def _floats(text: str):
    """Comma-separated times in s: finite, each given once (nan or a repeat is a typing slip)."""
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated numbers in seconds, got {text!r}"
        ) from None
    if not values:
        raise argparse.ArgumentTypeError(f"expected at least one number in seconds, got {text!r}")
    bad = [v for v in values if not np.isfinite(v)]
    if bad:
        raise argparse.ArgumentTypeError(f"expected finite numbers in seconds, got {text!r}")
    if len(set(values)) != len(values):
        raise argparse.ArgumentTypeError(f"a value is given more than once in {text!r}")
    return values


def _one_float(text: str):
    v = _floats(text)
    if len(v) != 1:
        raise argparse.ArgumentTypeError(f"expected one number in seconds, got {text!r}")
    return v


def _config(bundle, name):
    """The configuration a command analyses, refused (exit 1) when the bundle has no such one."""
    from bayes_tfcrds.studies.common import configuration_of

    try:
        return configuration_of(bundle, name)
    except ValueError as exc:
        raise Refused(exc) from None


def _load(path):
    from bayes_tfcrds.bundle.reader import load_bundle
    from bayes_tfcrds.bundle.records import BundleError

    try:
        return load_bundle(path)
    except BundleError as exc:
        raise Refused(exc.one_line()) from None


def cmd_validate(args) -> int:
    from bayes_tfcrds.bundle.summary import main_validate

    return main_validate(args.file)


def _decay_times(config, cal, args):
    """``fit``'s TF-CRDS table: at the centre of H's posterior with u_H(tau), or (said) without.

    When H's posterior cannot be drawn or fails its gates, the table keeps the calibration's H
    and a NaN tau_u_s: its total is not known. Returns (fits, the H they used, the H draws or
    None).
    """
    from bayes_tfcrds.fit.ringdown import fit_ringdowns
    from bayes_tfcrds.uncertainty.decay_times import fit_decay_times

    h = _h_draws_or_warn(
        config, cal, args, "tau is fitted at the calibration's H, tau_u_s is NaN and "
        "tau_u_noise_s the fit's own u(tau) given H",
    )  # fmt: skip
    if h is None:
        fits = fit_ringdowns(config.ringdowns, args.tcut, "tf-crds", cal.params, args.window)
        return fits, cal.params, None
    fits, _ = fit_decay_times(config, args.tcut, cal, None, args.window, h=h)
    return fits, h.centre, h


def _h_draws_or_warn(config, cal, args, instead: str):
    """H's posterior draws (``--seed``), or None with a warning that says what is done ``instead``.

    The posterior fails when the refinement does not converge or fails the budget's gates.
    """
    from bayes_tfcrds.fit.h_calibration import AnalysisError
    from bayes_tfcrds.uncertainty.decay_times import laplace_h_draws

    try:
        return laplace_h_draws(config, cal, np.random.default_rng(args.seed), args.window)
    except (AnalysisError, np.linalg.LinAlgError) as exc:
        _say(f"warning: no posterior of H to propagate ({exc}); {instead}")
        return None


def cmd_fit(args) -> int:
    from bayes_tfcrds.fit.h_calibration import AnalysisError, account_for_noise_colour, calibrate
    from bayes_tfcrds.fit.line_analysis import check_t_cuts
    from bayes_tfcrds.fit.refine import tension_lines
    from bayes_tfcrds.fit.ringdown import fit_ringdowns

    bundle = _load(args.file)
    config = _config(bundle, args.config)
    try:
        check_t_cuts(config, args.tcut)
        config, noise, beat = account_for_noise_colour(config, args.window)
        _say(f"# {noise.summary_line()}")
        if args.method == "tf-crds":
            cal = calibrate(
                config,
                window=args.window,
                refine=args.h == "refined",
                free=args.refine,
                beat=beat,
            )
            if cal.refined is not None:
                for line in tension_lines(cal.refined):
                    _say(f"# {line}")
            fits, p, h = _decay_times(config, cal, args)
            asked = tuple(cal.refined.free) if cal.refined is not None else ()
            if h is not None and h.refined != asked:
                _say(
                    f"# the ring-downs overrule the beat note with {', '.join(asked)} refined: "
                    f"H's posterior refines {', '.join(h.refined)}"
                )
            _say(
                f"# H: f_c={p.f_c_hz:.6g} Hz a_r={p.a_r:.6g} f_r={p.f_r_hz:.6g} Hz "
                f"gamma_r={p.gamma_r:.4g} n_r={p.n_r:.3g} ({args.h}"
                + ("" if h is None else ": the centre of its posterior, tau is fitted there")
                + ")"
            )
            if h is not None and np.isfinite(fits.tau_u_h_s).any():
                share = np.nanmedian(fits.tau_u_h_s / fits.tau_u_s)
                _say(f"# u(tau): H part / noise part, median {share:.2f} (tau_u_s: in quadrature)")
        else:
            fits = fit_ringdowns(config.ringdowns, args.tcut, "crds", window=args.window)
    except (AnalysisError, ValueError) as exc:
        return _fail(exc, 1)
    atomic_write_text(Path(args.output), fits.to_csv())
    statuses = [row[-1] for row in fits.rows()]
    n_unconv = statuses.count("not-converged")
    if n_unconv:
        tried = len(statuses) - statuses.count("clipped") - statuses.count("saturated")
        _say(
            f"{'FAILED' if n_unconv == tried else 'warning'}: {n_unconv} of {tried} decay-time "
            "fits did not converge (status not-converged in the CSV)"
        )
        if n_unconv == tried:
            return 3
    n_clip = int(fits.clipped.sum())
    n_sat = int(np.sum(config.ringdowns.saturated))
    n_short = sum(row[-1] == "record-short" for row in fits.rows())
    _say(
        f"wrote {args.output}: {fits.tau_s.size} fits "
        f"({args.method}{', ' + args.window if args.method == 'tf-crds' else ''})"
        + (
            f"; {n_clip} clipped transients not fitted (status clipped"
            + (f"; {n_sat} of them saturated below the digitizer rails" if n_sat else "")
            + "; bayes-tfcrds validate lists them)"
            if n_clip
            else ""
        )
        + (
            f"; warning: {n_short} fits have less than two decay times of record after t_cut "
            "(status record-short)"
            if n_short
            else ""
        )
    )
    return 0


def cmd_simulate(args) -> int:
    from bayes_tfcrds.bundle.writer import save_bundle
    from bayes_tfcrds.simulate.campaign import Campaign, parse_effect, simulate_campaign
    from bayes_tfcrds.simulate.noise import parse_noise

    effects = {}
    try:
        for text in args.effect or []:
            name, params = parse_effect(text)
            if name in effects:  # a second --effect NAME would silently replace the first
                raise ValueError(f"--effect {name} given more than once; give its keys in one")
            effects[name] = params
        presets = args.preset or ["letter-D2"]
        repeated = sorted({p for p in presets if presets.count(p) > 1})
        if repeated:
            raise ValueError(f"--preset {', '.join(repeated)} given more than once")
        campaign = Campaign(
            n_points=args.points, n_samples=args.samples, noise=parse_noise(args.noise)
        )
        campaign = _sample_conditions(campaign, args.temperature, args.pressure)
        rng = np.random.default_rng(args.seed)
        bundle, truth = simulate_campaign(presets, rng, campaign, effects)
    except ValueError as exc:
        return _fail(exc, 2)
    save_bundle(bundle, args.output, truth=truth)
    m = next(iter(bundle.configs.values())).ringdowns.n_points
    _say(
        f"wrote {args.output}: configurations {list(bundle.configs)}, {m} cavity modes x "
        f"{campaign.n_samples} samples, seed {args.seed}"
    )
    return 0


def _sample_conditions(campaign, temperature_k=None, pressure_pa=None):
    """``campaign`` with the gas at ``temperature_k`` (K) and ``pressure_pa`` (Pa) where given.

    The simulator makes the line of those conditions (number density, S(T) from S(296 K),
    widths, Doppler) and the bundle's /sample reports them. The pressure gauge's stated u keeps
    the campaign's relative value (0.333 Pa at 666.6 Pa: a 0.05 % manometer) instead of its
    absolute one; the temperature u (0.03 K) is absolute and stays. With neither given the
    campaign is returned unchanged (the same bundle as before for the same seed).
    """
    changes = {}
    if temperature_k is not None:
        changes["temperature_k"] = temperature_k
    if pressure_pa is not None:
        rel_u = campaign.pressure_u_pa / campaign.pressure_pa
        changes.update(pressure_pa=pressure_pa, pressure_u_pa=rel_u * pressure_pa)
    return replace(campaign, **changes) if changes else campaign


def cmd_linefit(args) -> int:
    import json

    from bayes_tfcrds.fit.h_calibration import AnalysisError
    from bayes_tfcrds.fit.line_analysis import LineFitError

    if (args.file is None) == (args.spectrum is None):
        raise Refused("give a bundle FILE or --spectrum LAB_DIR (one of them)", 2)
    try:
        if args.spectrum is not None:
            result, record = _spectrum_line(args)
        else:
            bundle = _load(args.file)
            result = _bundle_line(bundle, _config(bundle, args.config), args)
            record = result.to_dict()
    except (LineFitError, AnalysisError, ValueError, np.linalg.LinAlgError) as exc:
        return _fail(exc, 1)
    atomic_write_text(Path(args.output), json.dumps(record, indent=2) + "\n")
    for line in _linefit_warnings(result, args.tcut[0]):
        _say(line)
    la, ra, q = result.line_area, result.reference_area, result.ratio
    _result(
        f"A = {la.value:.6e} +/- {la.u:.2e} {la.unit}; "
        + (
            "no CMDS reference in this configuration"
            if ra is None
            else f"A_ref = {ra.value:.6e} +/- {ra.u:.2e}; A/A_ref = {q.value:.5f} +/- {q.u:.5f}"
        )
    )
    return 0


def _bundle_line(bundle, config, args):
    """linefit of a bundle; TF-CRDS at the centre of H's posterior with H's part of u(A).

    When H's posterior cannot be drawn or fails its gates, the line is fitted at the
    calibration's H and u(A) is the fit's alone (said, and labelled ``fit`` in the JSON).
    """
    from bayes_tfcrds.core.constants import line_area_to_cm2
    from bayes_tfcrds.fit.h_calibration import account_for_noise_colour, calibrate
    from bayes_tfcrds.fit.line_analysis import analyse_line, check_t_cuts
    from bayes_tfcrds.uncertainty.line_area import analyse_line_with_h

    options = dict(
        window=args.window,
        profile_name=args.profile,
        physical_bounds=args.shape_bounds == "physical",
    )
    check_t_cuts(config, args.tcut)
    config, noise, beat = account_for_noise_colour(config, args.window)
    if args.method != "tf-crds":
        return analyse_line(bundle, config, "crds", t_cut_s=args.tcut[0], noise=noise, **options)
    cal = calibrate(config, window=args.window, beat=beat)
    h = _h_draws_or_warn(
        config, cal, args, "A is fitted at the calibration's H and u(A) is the line fit's alone"
    )
    if h is None:
        return analyse_line(
            bundle, config, "tf-crds", t_cut_s=args.tcut[0], calibration=cal, noise=noise,
            **options,
        )  # fmt: skip
    result, _ = analyse_line_with_h(
        bundle, config, cal, None, args.tcut[0], h=h, noise=noise, **options
    )
    u_fit, u_h = line_area_to_cm2([result.line_fit.line_area_u, result.line_area_u_h_si])
    _say(
        f"# H: the centre of its posterior; u(A): the line fit's {u_fit:.3g} and H's {u_h:.3g} "
        "cm^-2 in quadrature"
    )
    return result


def _spectrum_line(args):
    """linefit --spectrum: the line fit of a lab's tau(nu) or alpha(nu) and its budget (no H)."""
    from bayes_tfcrds.bundle.labfolder import read_lab_spectrum
    from bayes_tfcrds.core.constants import edge_budget
    from bayes_tfcrds.fit.line_analysis import analyse_spectrum
    from bayes_tfcrds.uncertainty.spectrum_budget import spectrum_budget

    spectrum = read_lab_spectrum(args.spectrum)
    result = analyse_spectrum(
        spectrum, args.profile, physical_bounds=args.shape_bounds == "physical"
    )
    budget = spectrum_budget(result, spectrum.sample)
    _say(f"note: {result.input_note}: no H, no t_cut; the budget holds the fit and the line shape")
    for b in (budget.budget_a, budget.budget_s):  # A in cm^-2, as in linefit.json
        print(edge_budget(b).to_markdown())
    return result, dict(result.to_dict(), budget=budget.to_dict())


def _linefit_warnings(result, t_cut_s: float) -> list[str]:
    """What a reader of a line fit must be told: points left out, short records, the shape."""
    lines = []
    if result.clipped_points:
        lines.append(
            f"warning: {result.clipped_points} clipped or saturated transients were left out of "
            "the spectrum (bayes-tfcrds validate lists them)"
        )
    if result.unconverged_points:
        lines.append(
            f"warning: {result.unconverged_points} decay-time fits did not converge and were left "
            "out of the spectrum (bayes-tfcrds fit lists them as not-converged)"
        )
    if result.record_short_points:
        lines.append(
            f"warning: {result.record_short_points} decay times come from less than two decay "
            f"times of record after t_cut = {t_cut_s:g} s (offset and tau nearly degenerate)"
        )
    if result.unphysical_shape:
        lines.append(
            f"warning: {', '.join(result.unphysical_shape)} ended below 0 (on the profile's "
            "continuation): the line shape is not physical, often a sign that the model of the "
            "experiment is wrong (plain CRDS of a distorted chain?); --shape-bounds physical "
            "holds them at 0"
        )
    if result.shape_at_bound:
        lines.append(
            f"note: {', '.join(result.shape_at_bound)} held at 0 by --shape-bounds physical"
        )
    if result.noise is not None and result.noise.kappa_applied:
        lines.append(f"warning: {result.noise.summary_line()}")
    return lines


def cmd_import(args) -> int:
    """A lab folder (lab.toml + CSV/TSV/NPY/NPZ) -> bundle; or write the worked example folder."""
    from bayes_tfcrds.bundle.labfolder import (
        LabFolderError,
        import_lab_folder,
        lab_folder_exists,
        write_lab_folder,
    )
    from bayes_tfcrds.bundle.writer import save_bundle

    if not args.example:
        if args.output is None:
            raise Refused("-o BUNDLE.h5 is required (the bundle to write)", 2)
        try:
            bundle = import_lab_folder(args.folder, args.output)
        except LabFolderError as exc:
            return _fail(exc, 1)
        _say(f"wrote {args.output}: configurations {list(bundle.configs)} from {args.folder}")
        return 0
    from bayes_tfcrds.simulate.campaign import Campaign, simulate_campaign

    if lab_folder_exists(args.folder):
        raise Refused(f"{args.folder} already holds a lab.toml; choose a new folder", 2)
    # small (12 modes x 4096 samples): written and imported in about a second
    campaign = Campaign(n_points=12, n_samples=4096)
    bundle, truth = simulate_campaign(["letter-D2"], np.random.default_rng(args.seed), campaign)
    files = write_lab_folder(bundle, args.folder)
    if args.output is not None:
        save_bundle(bundle, args.output, truth=truth)
    _say(
        f"wrote {len(files)} files to {args.folder} (a simulated campaign in lab units, seed "
        f"{args.seed})"
        + (f" and the bundle they came from to {args.output}" if args.output else "")
        + f"; import it: bayes-tfcrds import {args.folder} -o bundle.h5"
    )
    return 0


def cmd_demo(args) -> int:
    """Simulate a letter-like campaign (D1-D4) and analyse it: CRDS vs TF-CRDS against CMDS."""
    from bayes_tfcrds.studies.demo import run_demo

    result = run_demo(args.output, seed=args.seed, quick=args.quick, log=_say)
    print("\n".join(result.summary_lines()))
    _say(f"wrote {result.bundle_path}, {result.results_path}, {result.summary_path}")
    return 0


def _budget_options(args):
    """The budget's options from the command line (refused with exit status 2)."""
    from bayes_tfcrds.uncertainty.line_budget import BudgetOptions

    opts = BudgetOptions(
        method=args.method,
        window=args.window,
        t_cut_s=args.tcut[0],
        profile=args.profile,
        refine_free=args.refine,
        posterior=args.posterior,
    )
    if args.steps is not None or args.max_steps is not None:
        try:
            opts = opts.with_steps(args.steps, args.max_steps)
        except ValueError as exc:
            raise Refused(exc, 2) from None
    return opts


def cmd_budget(args) -> int:
    from bayes_tfcrds.bundle.reader import load_truth
    from bayes_tfcrds.core.constants import edge_budget
    from bayes_tfcrds.fit.h_calibration import AnalysisError
    from bayes_tfcrds.fit.line_analysis import LineFitError
    from bayes_tfcrds.fit.refine import tension_lines
    from bayes_tfcrds.uncertainty.line_budget import run_budget, side_pool
    from bayes_tfcrds.uncertainty.outputs import (
        corner_job,
        discard_started,
        failed_banner,
        posterior_line,
        posterior_record,
        write_outputs,
    )

    _check_executor(args)
    if len(args.file) > 1 or args.executor != "local":
        return _budget_batch(args)
    bundle = _load(args.file[0])
    config = _config(bundle, args.config)
    opts = _budget_options(args)
    truth = load_truth(args.file[0])
    started = None
    try:
        # one pool for the budget's side steps and the corner plots, each drawn once its run is
        # sampled (the plots are the same; the pool would otherwise idle after the CMDS run)
        with side_pool(args.workers) as pool:
            on_run, started = (
                corner_job(pool, args.output, truth, config.name) if pool else (None, None)
            )
            try:
                res = run_budget(
                    bundle,
                    config,
                    opts,
                    np.random.default_rng(args.seed),
                    outdir=args.output,
                    progress=not args.quiet,
                    workers=args.workers,
                    pool=pool,
                    on_run=on_run,
                )
            except (LineFitError, AnalysisError, ValueError) as exc:
                failure = exc  # the pool was interrupted; it is shut down on leaving the block
            else:
                failure = None
                write_outputs(
                    res, args.output, seed=args.seed, truth=truth, workers=args.workers,
                    started=started,
                )  # fmt: skip
        if failure is not None:
            discard_started(started)
            return _fail(failure, 1)
    except KeyboardInterrupt:
        discard_started(started)
        print(file=sys.stderr)
        _say(
            "interrupted: the chains sampled so far are kept in "
            f"{Path(args.output) / 'chains_*.h5'}; run the same command again to resume (same "
            "seed, same result)"
        )
        return 130
    if not res.passed:
        print(failed_banner(res))
    if opts.posterior != "mcmc":
        _result(posterior_line(posterior_record(opts.posterior)))
    noise = res.summary.get("noise")
    if noise and noise.get("kappa_applied", not noise["white"]):
        what = "coloured" if not noise["white"] else "white at the 1e-3 tests but has a 1/f term"
        _say(
            f"warning: the ring-down noise is {what} (kappa = {noise['kappa_median']:.3g}): "
            "u(tau) and every ring-down likelihood use noise_v sqrt(kappa) (budget.md, "
            "'Ring-down noise')"
        )
    for line in edge_budget(res.budget_a).to_markdown().splitlines():  # A in cm^-2, as in .json
        _result(line)
    if res.refined is not None:
        for line in tension_lines(res.refined):
            _say(f"H refinement: {line}")
    if res.identification is not None:
        for line in res.identification.lines():
            _say(f"finding: H {line}")
    tfs = res.summary.get("transfer_function") or {}
    form = tfs.get("model_form")
    if form and form["asks_for_free_order"]:
        kept = (
            "the budget samples n_r (posterior {mean:.3f} +/- {sd:.3f}) and carries the n_r = 2 "
            "alternative".format(**tfs["n_r_posterior"])
            if tfs.get("n_r_sampled")
            else "the budget keeps n_r = 2 (the fit lies outside the causal n_r < 2) and carries "
            "the difference"
        )
        both = (
            f", the ring-downs with it n_r = {form['n_r_refined']:.4f} +/- "
            f"{form['n_r_refined_u']:.4f}"
            if "n_r_refined" in form
            else ""
        )
        _say(
            f"finding: the data ask for a fractional order (weight of n_r free "
            f"{form['weight_n_r_free_all_data']:.3g} from the {form['weight_source']}; beat note "
            f"alone n_r = {form['n_r_free_fit']:.3f}{both}); {kept} in A as the 'H model form' row"
        )
    for name, detail in (res.summary.get("instrument") or {}).items():
        if detail.get("finding"):
            _say(f"finding ({name}): {detail['finding']}; carried as the budget row '{name}'")
    if not res.passed:
        _say(f"FAILED: {res.status} (diagnostics: {res.summary['diagnostics']['runs']})")
        return 3
    a, q, s = res.line_area, res.ratio, res.intensity
    t_ref = res.summary["intensity"]["t_ref_k"]
    _result(
        f"A = {a.value:.6e} +/- {a.u:.2e} cm^-2;  A/A_ref = {q.value:.5f} +/- {q.u:.5f};  E_n = "
        f"{res.en:.2f};  S({t_ref:g} K) = {s.value:.5e} +/- {s.u:.2e} cm/molecule"
    )
    return 0


def cmd_compare(args) -> int:
    """Interlaboratory comparison of budget.json results and a CSV from elsewhere."""
    from bayes_tfcrds.uncertainty import comparison_inputs as ci
    from bayes_tfcrds.uncertainty.comparison import Reference, compare
    from bayes_tfcrds.uncertainty.comparison_report import write_comparison

    try:
        results = [r for spec in args.results for r in ci.read_result(spec, args.quantity)]
        labs = [r.lab for r in results]
        corr = ci.read_correlations(args.correlations, labs) if args.correlations else None
        ref = Reference()
        if args.random_effects is not None:
            if args.reference is not None:
                raise Refused("give either --reference or --random-effects, not both", 2)
            ref = Reference(
                "random-effects",
                estimator=args.random_effects,
                knapp_hartung=args.knapp_hartung or "",
            )
        elif args.knapp_hartung:
            raise Refused("--knapp-hartung adjusts a --random-effects consensus; add one", 2)
        if args.reference is not None:
            value = args.reference.split(",")
            try:
                ref = Reference("value", value=float(value[0]), u=float(value[1]))
            except (ValueError, IndexError):
                ref = Reference("laboratory", lab=args.reference)
        comp = compare(
            labs,
            [r.value for r in results],
            [r.u for r in results],
            corr,
            ref,
            args.quantity,
            ci.common_unit(results, args.quantity),
        )
    except ValueError as exc:  # ComparisonInputError is one; bad names, singular correlations
        raise Refused(str(exc)) from None
    written = write_comparison(comp, results, args.output, seed=args.seed)
    c, r = comp.consistency, comp.reference
    _say(f"wrote {', '.join(str(p) for p in written)}")
    dark = f", tau = {r.tau:.3g} {comp.unit}" if r.method.startswith("random") else ""
    _result(
        f"x_ref = {r.value:.6e} +/- {r.u:.2e} {comp.unit} ({r.method}{dark}); chi2 = "
        f"{c.chi2:.3f} ({c.dof} dof, p = {c.p_value:.3g}, R_B = {c.birge_ratio:.3f})"
    )
    if not c.passed and r.method == "weighted mean":
        _say(
            "note: the results fail the chi2 test (their scatter exceeds their u); "
            "--random-effects REML gives the consensus with a dark uncertainty"
        )
    if r.kh_q is not None and r.kh_q < 1 and "modified" not in r.method:
        _say(
            f"note: Knapp-Hartung q = {r.kh_q:.3g} < 1 shrinks u(x_ref) below the random-effects "
            "u; --knapp-hartung modified keeps it"
        )
    return 0


def _budget_batch(args) -> int:
    """Budgets of several bundles (or of one on an executor): OUT/<bundle stem>/ each, batch.json.

    Every bundle gets the same options and seed as its own ``budget`` command would; a bundle
    that is refused or fails its gates is reported and the others still run.
    """
    import json

    from bayes_tfcrds.studies.batch import BudgetJob, batch_folders, run_batch
    from bayes_tfcrds.uncertainty.outputs import posterior_line, posterior_record

    opts = _budget_options(args)
    missing = [f for f in args.file if not Path(f).is_file()]
    if missing:
        raise Refused(f"no bundle file {missing[0]} (budget reads HDF5 bundles, FORMAT.md)", 2)
    try:
        folders = batch_folders(args.file, args.output)
    except ValueError as exc:
        raise Refused(exc, 2) from None
    jobs = [
        BudgetJob(str(f), str(d), args.config, opts, args.seed) for f, d in zip(args.file, folders)
    ]
    try:
        with _executor(args) as pool:
            _say(f"# {len(jobs)} bundle budgets on {_executor_name(args)}")
            records = run_batch(jobs, pool=pool, progress=not args.quiet)
    except KeyboardInterrupt:
        _say(
            f"interrupted: each bundle's chains so far are kept in its folder under {args.output}; "
            "run the same command again to resume (same seed, same results)"
        )
        return 130
    if len(jobs) > 1:
        index = [{k: r[k] for k in ("bundle", "output", "status")} for r in records]
        out = Path(args.output) / "batch.json"
        atomic_write_text(out, json.dumps({"seed": args.seed, "budgets": index}, indent=2) + "\n")
        _say(f"wrote {out}")
    if opts.posterior != "mcmc":
        _result(posterior_line(posterior_record(opts.posterior)))
    for r in records:
        s = r["summary"]
        if r["status"] == "ok":
            q = s["ratio"]
            _result(
                f"{r['bundle']}: A = {s['line_area']['value']:.6e} +/- {s['line_area']['u']:.2e} "
                "cm^-2"
                + ("" if q is None else f";  A/A_ref = {q['value']:.5f} +/- {q['u']:.5f}")
                + f"  ({r['output']})"
            )
        else:
            _say(
                f"{'FAILED' if r['status'].startswith('failed') else 'error'}: {r['bundle']}: "
                f"{r['status']}"
            )
    if any(r["status"].startswith("error") for r in records):
        return 1
    return 3 if any(r["status"] != "ok" for r in records) else 0


def _executor_name(args) -> str:
    if args.executor == "dask":
        return f"the Dask scheduler {args.scheduler}"
    return f"{args.workers} local process{'es' if args.workers > 1 else ''}"


def _check_executor(args) -> None:
    """Refuse executor options that cannot work together, before any work."""
    if args.executor == "dask" and not args.scheduler:
        raise Refused(
            "--executor dask needs --scheduler ADDRESS, e.g. tcp://10.0.0.5:8786 (the address "
            "dask-scheduler prints)",
            2,
        )
    if args.executor != "dask" and args.scheduler:
        raise Refused("--scheduler is the Dask scheduler's address: give --executor dask too", 2)
    if args.workers < 1:
        raise Refused(f"--workers must be >= 1, got {args.workers}", 2)


@contextlib.contextmanager
def _executor(args):
    """The pool tasks run on: None (this process), local processes, or a Dask scheduler."""
    _check_executor(args)
    if args.executor == "dask":
        with _dask_executor(args.scheduler) as pool:
            yield pool
        return
    if args.workers == 1:
        yield None
        return
    from concurrent.futures import ProcessPoolExecutor

    # the workers' notes would interleave (one budget's stages with another's): warnings only,
    # unless --verbose; the parent still logs each task's end and the time left
    level = 1 if args.verbose else -1
    with ProcessPoolExecutor(
        args.workers, initializer=configure_logging, initargs=(level,)
    ) as pool:
        yield pool


DASK_TIMEOUT_S = 30  # how long to wait for the scheduler before giving up


@contextlib.contextmanager
def _dask_executor(address: str):
    """A ``concurrent.futures`` executor on the Dask scheduler at ``address`` (dask imported here).

    Its ``submit``/``map`` are what ``run_study(pool=...)`` and the batch use; the workers need
    this package installed (the same version) to run the tasks.
    """
    try:
        from distributed import Client
    except ImportError:
        raise Refused(
            "--executor dask needs dask.distributed, which is not installed here: "
            "pip install 'bayes-tfcrds[dask]'",
            2,
        ) from None
    try:
        client = Client(address, timeout=DASK_TIMEOUT_S)
    except (OSError, TimeoutError) as exc:
        raise Refused(
            f"could not reach the Dask scheduler at {address!r} ({exc}); check the address and "
            "that dask-scheduler is running",
            1,
        ) from None
    with client:
        yield client.get_executor()


def cmd_study(args) -> int:
    from bayes_tfcrds.studies.registry import run_study
    from bayes_tfcrds.studies.spec import StudyError

    try:
        with _executor(args) as pool:
            _say(f"# study {args.file} on {_executor_name(args)}")
            html_path, pdf_path = run_study(
                args.file, args.output, progress=not args.quiet, pool=pool, seed=args.seed
            )
    except StudyError as exc:
        return _fail(exc, 2)
    _say(f"wrote {html_path} and {pdf_path}")
    return 0


def cmd_discover(args) -> int:
    from bayes_tfcrds.discovery.report import write_report
    from bayes_tfcrds.discovery.workflow import DISCOVERY_T_CUTS, discover, parse_model

    bundle = _load(args.file)
    config = _config(bundle, args.config)
    try:
        if not (np.isfinite(args.threshold) and args.threshold > 0):
            raise ValueError(f"--threshold must be a Delta BIC > 0, got {args.threshold}")
        if args.tcut:
            from bayes_tfcrds.fit.line_analysis import check_t_cuts

            check_t_cuts(config, args.tcut)
            if min(args.tcut) <= 0:
                raise ValueError("t_cut must be > 0 s for discovery (its gap metrics need it)")
        start = parse_model(args.start)
        result = discover(
            bundle,
            config.name,
            start,
            t_cuts=args.tcut or DISCOVERY_T_CUTS,
            threshold=args.threshold,
            progress=None if args.quiet else _say,
            rng=np.random.default_rng(args.seed),
            alpha=args.alpha,
            n_boot=args.n_boot,
        )
    except ValueError as exc:
        return _fail(exc, 2)
    json_path, html_path = write_report(result, args.output, seed=args.seed, inputs=[args.file])
    _say(
        f"effects added: {', '.join(result.effects_added) or 'none'} ({result.seconds:.1f} s); "
        f"wrote {json_path} and {html_path}"
    )
    return 0


class _HelpWithDefaults(argparse.ArgumentDefaultsHelpFormatter):
    """Shows an option's default where it has one (not for required options, flags or None)."""

    def _get_help_string(self, action):
        if (
            action.required
            or action.default is None
            or action.default is False
            or action.help is None
        ):
            return action.help
        return super()._get_help_string(action)


#: seeds are integers in [0, 2**63), as in study files: numpy's SeedSequence refuses negative
#: ones (demo and budget stopped in its traceback), and one rule for every command
SEED_LIMIT = 2**63


def _seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = None
    if value is None or not 0 <= value < SEED_LIMIT:
        raise argparse.ArgumentTypeError(f"expected an integer in [0, 2**63), got {text!r}")
    return value


#: gas temperatures ``simulate`` accepts, K: the partition-function table's range (S(T) from
#: S(296 K) is never extrapolated)
SIM_TEMPERATURE_K = (70.0, 1000.0)


def _temperature_k(text: str) -> float:
    """A sample temperature in K inside :data:`SIM_TEMPERATURE_K`."""
    lo, hi = SIM_TEMPERATURE_K
    try:
        value = float(text)
    except ValueError:
        value = None
    if value is None or not lo <= value <= hi:  # nan fails both comparisons
        raise argparse.ArgumentTypeError(
            f"expected a temperature in kelvin in [{lo:g}, {hi:g}] (the partition-function "
            f"table), got {text!r}"
        )
    return value


def _pressure_pa(text: str) -> float:
    """A sample pressure in Pa: finite and > 0."""
    try:
        value = float(text)
    except ValueError:
        value = None
    if value is None or not (np.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(
            f"expected a pressure in pascal, finite and > 0, got {text!r}"
        )
    return value


def _common(sp, seed=0, note=""):
    """Options every command has (``--seed``, ``--quiet``, ``--verbose``), help with defaults."""
    sp.formatter_class = _HelpWithDefaults
    sp.add_argument("--seed", type=_seed, default=seed, help="random seed" + note)
    talk = sp.add_mutually_exclusive_group()
    talk.add_argument(
        "-q",
        "--quiet",
        action="store_true",
        help="no progress and no notes on stderr: warnings and errors only",
    )
    talk.add_argument(
        "-v", "--verbose", action="store_true", help="also debug lines (sampler gates, timings)"
    )
    return sp


def _executor_options(sp, workers: int) -> None:
    """Where the tasks run: local processes (--workers) or a Dask scheduler (--scheduler)."""
    sp.add_argument(
        "--executor",
        choices=["local", "dask"],
        default="local",
        help="local: --workers processes on this machine; dask: the workers of a running Dask "
        "scheduler (needs pip install 'bayes-tfcrds[dask]')",
    )
    sp.add_argument(
        "--workers",
        type=int,
        default=workers,
        help="local worker processes (2 uses both cores of a small machine)",
    )
    sp.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="the Dask scheduler's address with --executor dask, e.g. tcp://10.0.0.5:8786",
    )


def _bundle_and_model(sp, many: bool = False, file_optional: bool = False) -> None:
    """The bundle (or bundles), its configuration, and the ring-down model (method, window).

    ``file_optional``: the bundle may be absent (``linefit --spectrum`` reads a lab folder).
    """
    if many:
        sp.add_argument(
            "file",
            nargs="+",
            help="measurement bundle(s); with several, each writes into OUTPUT/<bundle stem>/",
        )
    else:
        sp.add_argument(
            "file",
            nargs="?" if file_optional else None,
            help="measurement bundle (HDF5, bayes_tfcrds/data/FORMAT.md)",
        )
    sp.add_argument("--config", help="configuration name, e.g. D2")
    sp.add_argument(
        "--method",
        choices=["crds", "tf-crds"],
        default="tf-crds",
        help="crds: pure exponential; tf-crds: exponential through the detection chain's H(f)",
    )
    sp.add_argument(
        "--window",
        choices=["extinction", "letter"],
        default="extinction",
        help="history before t = 0 in the TF-CRDS model: extinction (exact) or letter (the "
        "letter's)",
    )


def _h_names(allowed):
    def parse(text: str) -> tuple:
        names = tuple(n.strip() for n in text.split(",") if n.strip())
        bad = [n for n in names if n not in allowed]
        if not names or bad:
            raise argparse.ArgumentTypeError(
                f"expected a comma-separated list of {', '.join(allowed)}; got {text!r}"
            )
        return names

    return parse


def _refine_option(sp, allowed) -> None:
    """Which H parameters the ring-downs refine (an update of the beat note)."""
    sp.add_argument(
        "--refine",
        type=_h_names(allowed),
        default=("f_c_hz",),
        metavar="NAMES",
        help="H parameters the multi-ring-down fit updates, comma-separated (default f_c_hz, as "
        f"in the letter; any of {', '.join(allowed)}); the others stay at the beat note",
    )


def _profile_option(sp) -> None:
    """The line profile fitted to the spectrum."""
    sp.add_argument(
        "--profile",
        choices=["voigt", "sdvp", "rautian", "qsdhcp"],
        default="qsdhcp",
        help="line profile fitted to the spectrum",
    )


def _add_validate(sub) -> None:
    """The ``validate`` command's options."""
    sp = _common(
        sub.add_parser("validate", help="check a measurement bundle against FORMAT.md"),
        note=" (validate draws no random numbers)",
    )
    sp.add_argument("file", help="measurement bundle (HDF5)")
    sp.set_defaults(func=cmd_validate)


def _add_fit(sub) -> None:
    """The ``fit`` command's options."""
    sp = _common(sub.add_parser("fit", help="fit ring-down decay times (CRDS or TF-CRDS)"))
    _bundle_and_model(sp)
    sp.add_argument(
        "--tcut",
        type=_floats,
        default=[2e-6, 4e-6, 8e-6],
        help="t_cut values in s, comma-separated",
    )
    sp.add_argument(
        "--transfer-function",
        dest="h",
        choices=["refined", "beat"],
        default="refined",
        help="H for TF-CRDS: the beat-note fit refined on ring-downs, or the beat-note fit alone",
    )
    from bayes_tfcrds.physics.transfer_function import PARAM_NAMES

    _refine_option(sp, PARAM_NAMES)
    sp.add_argument("-o", "--output", required=True, help="CSV file to write")
    sp.set_defaults(func=cmd_fit)


def _add_simulate(sub) -> None:
    """The ``simulate`` command's options."""
    from bayes_tfcrds.simulate.campaign import Campaign

    sp = _common(sub.add_parser("simulate", help="simulate a letter-like campaign into a bundle"))
    sp.add_argument(
        "--preset", action="append", help="letter-D1 ... letter-D4 (repeatable; default letter-D2)"
    )
    sp.add_argument(
        "--effect",
        action="append",
        help="NAME[:key=value,...] (repeatable), e.g. static_nonlinearity:beta=-3e-3",
    )
    sp.add_argument(
        "--points",
        type=int,
        default=Campaign.n_points,
        help="spectral points requested (modes that coincide on the FSR grid are dropped: the "
        "default span of +/- 10 GHz holds 99)",
    )
    sp.add_argument("--samples", type=int, default=Campaign.n_samples, help="samples per transient")
    sp.add_argument(
        "--temperature",
        type=_temperature_k,
        metavar="K",
        help=f"gas temperature of the sample in kelvin, {SIM_TEMPERATURE_K[0]:g}-"
        f"{SIM_TEMPERATURE_K[1]:g} K (default: the campaign's {Campaign.temperature_k:g} K); the "
        "line's S(T) follows from S(296 K)",
    )
    sp.add_argument(
        "--pressure",
        type=_pressure_pa,
        metavar="PA",
        help=f"gas pressure of the sample in pascal, > 0 (default: the campaign's "
        f"{Campaign.pressure_pa:g} Pa); the gauge's stated u stays "
        f"{100 * Campaign.pressure_u_pa / Campaign.pressure_pa:.2f} %% of it",
    )
    sp.add_argument(
        "--noise",
        default="white",
        help="PSD shape of the detector noise (same per-sample sd): white, chain (through the "
        "detection chain), lowpass[:f_hz=5e6,order=2], pink[:f_knee_hz=1e5,alpha=1]",
    )
    sp.add_argument("-o", "--output", required=True, help="bundle (HDF5) to write")
    sp.set_defaults(func=cmd_simulate)


def _add_linefit(sub) -> None:
    """The ``linefit`` command's options."""
    sp = _common(
        sub.add_parser("linefit", help="fit a line profile to the CRDS spectrum and to CMDS")
    )
    _bundle_and_model(sp, file_optional=True)  # absent with --spectrum
    sp.add_argument(
        "--spectrum",
        metavar="LAB_DIR",
        help="instead of a bundle: a lab folder whose lab.toml has a [spectrum] table (tau or "
        "alpha vs nu with uncertainties); spectrum-level input, no transfer-function rows: the "
        "JSON adds its GUM budget (fit and line shape; S with p, T, x), printed on stdout",
    )
    sp.add_argument("--tcut", type=_one_float, default=[4e-6], help="the t_cut of the spectrum, s")
    _profile_option(sp)
    sp.add_argument(
        "--shape-bounds",
        choices=["free", "physical"],
        default="free",
        help="free: Gamma2 and nu_VC may go below 0 on the profile's continuation (unbiased when "
        "the model is right; such fits are flagged); physical: held at >= 0, as the letter reads "
        "its fits",
    )
    sp.add_argument("-o", "--output", required=True, help="JSON file to write")
    sp.set_defaults(func=cmd_linefit)


def _add_budget(sub) -> None:
    """The ``budget`` command's options."""
    from bayes_tfcrds.uncertainty.line_budget import BudgetOptions

    sp = _common(
        sub.add_parser("budget", help="posteriors and the GUM line-area budget against CMDS")
    )
    _bundle_and_model(sp, many=True)
    sp.add_argument("--tcut", type=_one_float, default=[4e-6], help="t_cut of the reported A, s")
    _profile_option(sp)
    from bayes_tfcrds.fit.h_calibration import BEAT_FREE

    _refine_option(sp, BEAT_FREE)
    sp.add_argument(
        "--steps",
        type=int,
        default=BudgetOptions.n_steps,
        help="MCMC steps per ensemble before the convergence gates are checked",
    )
    sp.add_argument(
        "--max-steps",
        type=int,
        help="longest run per ensemble; a run still missing a gate then is reported as failed, "
        "except H, sampled again up to twice with jumps fitted to the failed run "
        "(default max(8 x steps, 24000))",
    )
    sp.add_argument(
        "--posterior",
        choices=["mcmc", "laplace"],
        default="mcmc",
        help="mcmc: sampled and gated; laplace: the Gaussian approximation at the least-squares "
        "fits (seconds instead of minutes; labelled as an approximation, with its measured "
        "coverage, in every output)",
    )
    _executor_options(sp, workers=1)
    sp.add_argument("-o", "--output", required=True, help="output folder")
    sp.set_defaults(func=cmd_budget)


def _add_study(sub) -> None:
    """The ``study`` command's options."""
    sp = _common(
        sub.add_parser("study", help="run a declared study and write its report"),
        seed=None,
        note=" (default: the [study] seed of the file)",
    )
    sp.add_argument("file", help="study file (TOML), e.g. studies/letter_tcut.toml")
    sp.add_argument(
        "-o", "--output", required=True, help="report folder, e.g. reports/letter_tcut/"
    )
    _executor_options(sp, workers=2)
    sp.set_defaults(func=cmd_study)


def _add_discover(sub) -> None:
    """The ``discover`` command's options."""
    sp = _common(
        sub.add_parser("discover", help="find the effects missing from a model of the experiment"),
        note=" (it draws the bootstrap nulls of the gap metrics)",
    )
    sp.add_argument("file", help="measurement bundle (HDF5, bayes_tfcrds/data/FORMAT.md)")
    sp.add_argument("--config", help="configuration name, e.g. D2")
    sp.add_argument(
        "--start",
        default="crds+voigt",
        help="starting model: crds+voigt, or canonical effect names joined by ',' or '+', e.g. "
        "transfer_function,window_history,speed_dependence",
    )
    sp.add_argument(
        "--tcut", type=_floats, default=None, help="t_cut values in s (default 2e-6,4e-6,6e-6)"
    )
    sp.add_argument(
        "--threshold", type=float, default=10.0, help="Delta BIC an effect needs to be added"
    )
    sp.add_argument(
        "--alpha",
        type=float,
        default=0.05,
        help="family-wise probability of adding any effect to a model that already describes "
        "the data (spent as alpha/2, alpha/4, ... over the steps)",
    )
    sp.add_argument(
        "--n-boot",
        type=int,
        default=40,
        help="bootstrap replicates of the gap metrics' null per model state",
    )
    sp.add_argument(
        "-o", "--output", required=True, help="output folder (discovery.json, discovery.html)"
    )
    sp.set_defaults(func=cmd_discover)


def _add_import(sub) -> None:
    """The ``import`` command's options."""
    sp = _common(
        sub.add_parser(
            "import", help="a lab folder (lab.toml + ring-downs, beat note, CMDS) -> a bundle"
        ),
        note=" (import draws no random numbers; --example simulates with it)",
    )
    sp.add_argument("folder", help="lab folder holding lab.toml (README: Bringing your own data)")
    sp.add_argument(
        "--example",
        action="store_true",
        help="write a worked example lab folder (a small simulated campaign) to FOLDER instead",
    )
    sp.add_argument(
        "-o", "--output", help="bundle (HDF5) to write; with --example, the bundle it came from"
    )
    sp.set_defaults(func=cmd_import)


def _add_demo(sub) -> None:
    """The ``demo`` command's options."""
    sp = _common(
        sub.add_parser("demo", help="simulate a letter-like campaign (D1-D4) and analyse it"),
        seed=7,
    )
    sp.add_argument("-o", "--output", default="demo-out", help="output folder")
    sp.add_argument("--quick", action="store_true", help="a smaller campaign (for a first look)")
    sp.set_defaults(func=cmd_demo)


def _add_compare(sub) -> None:
    """The ``compare`` command's options."""
    sp = _common(
        sub.add_parser("compare", help="interlaboratory comparison: reference value, chi2, DoE"),
        note=" (compare draws no random numbers; the seed is recorded)",
    )
    sp.add_argument(
        "results",
        nargs="+",
        metavar="RESULT",
        help="[LABEL=]budget.json (or its folder; label defaults to the folder name), or a CSV "
        "with columns lab,value,u,unit[,dof] (or U,k in place of u)",
    )
    sp.add_argument(
        "--quantity",
        choices=["intensity", "line_area", "ratio", "other"],
        default="intensity",
        help="S(296 K) in cm/molecule, A in cm^-2, A/A_ref, or another measurand given as CSV "
        "rows in one unit",
    )
    sp.add_argument(
        "--reference",
        metavar="LAB|VALUE,u",
        help="reference value: a laboratory's result, or a stated value and its standard u in "
        "the comparison unit (default: the weighted mean)",
    )
    sp.add_argument(
        "--random-effects",
        choices=["DL", "REML", "ML"],
        help="reference value: the random-effects consensus with dark uncertainty tau estimated "
        "by DerSimonian-Laird, REML or ML (for results that fail the chi2 test)",
    )
    sp.add_argument(
        "--knapp-hartung",
        nargs="?",
        const="standard",
        choices=["standard", "modified"],
        help="with --random-effects: Knapp-Hartung u and a Student-t 95 %% interval; 'modified' "
        "never lets the adjustment shrink u below the plain random-effects u",
    )
    sp.add_argument("--correlations", metavar="FILE", help="CSV lab_a,lab_b,r of shared inputs")
    sp.add_argument("-o", "--output", required=True, help="output folder")
    sp.set_defaults(func=cmd_compare)


def build_parser() -> argparse.ArgumentParser:
    """The ``bayes-tfcrds`` argument parser: one sub-command per job."""
    p = argparse.ArgumentParser(
        prog="bayes-tfcrds",
        description="Transfer-function-corrected CRDS with honest uncertainty budgets. The data "
        "contract (HDF5 measurement bundle) is FORMAT.md, shipped in bayes_tfcrds/data/.",
    )
    p.add_argument("--version", action="version", version=f"bayes-tfcrds {__version__}")
    sub = p.add_subparsers(dest="command", required=True)
    for add in (
        _add_validate,
        _add_fit,
        _add_simulate,
        _add_linefit,
        _add_budget,
        _add_study,
        _add_discover,
        _add_demo,
        _add_compare,
        _add_import,
    ):
        add(sub)
    return p


def main(argv=None) -> int:
    from bayes_tfcrds.output.files import FolderBusyError, OutputPathError

    args = build_parser().parse_args(argv)
    configure_logging(-1 if args.quiet else 1 if args.verbose else 0)
    options = {k: v for k, v in vars(args).items() if k not in ("func", "command")}
    log.debug(f"bayes-tfcrds {__version__} {args.command}: {options}")
    try:
        _check_output(args)
        return int(args.func(args) or 0)
    except OutputPathError as exc:  # the output rule (output.files.check_replaceable), any command
        return _fail(exc, 2)
    except FolderBusyError as exc:  # another run holds -o (output.files.folder_lock)
        return _fail(exc, 1)
    except Refused as exc:
        return _fail(exc, exc.code)


_FOLDER_COMMANDS = ("cmd_budget", "cmd_study", "cmd_discover", "cmd_demo", "cmd_compare")


def _check_output(args) -> None:
    """Refuse an unusable -o before any work (not after minutes of sampling)."""
    from bayes_tfcrds.output.files import OutputPathError, check_replaceable

    out = getattr(args, "output", None)
    if out is None:
        return
    path = Path(os.path.abspath(out))
    if args.func.__name__ in _FOLDER_COMMANDS:
        if os.path.lexists(path) and not path.is_dir():
            raise OutputPathError(f"{path} exists and is not a folder; -o names the output folder")
        return
    check_replaceable(path)


if __name__ == "__main__":
    sys.exit(main())
