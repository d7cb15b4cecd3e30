"""Command-line interface: bayes-tfcrds COMMAND ...

Every command takes ``--seed`` (the same inputs and seed give the same numbers) and reports
bad input as one clear message naming what is wrong, with exit status 1 or 2.
"""

from __future__ import annotations

import argparse
import os
import sys
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


def _say(line: str) -> None:
    """Print one line of progress, warning or error to stderr, control characters escaped."""
    print(_printable(line), file=sys.stderr)


def _fail(message, code: int) -> int:
    """Report a refusal as the one line ``error: MESSAGE``; returns the exit status."""
    _say(f"error: {message}")
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
    if name is None:
        if len(bundle.configs) != 1:
            raise Refused(
                f"the bundle has configurations {list(bundle.configs)}; choose one with --config"
            )
        return next(iter(bundle.configs.values()))
    if name not in bundle.configs:
        raise Refused(f"no configuration {name!r} in the bundle (it has {list(bundle.configs)})")
    return bundle.configs[name]


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


def cmd_fit(args) -> int:
    from bayes_tfcrds.fit.h_calibration import (
        AnalysisError,
        account_for_noise_colour,
        calibrate,
        fit_config,
    )
    from bayes_tfcrds.fit.line_analysis import check_t_cuts
    from bayes_tfcrds.fit.refine import tension_lines

    bundle = _load(args.file)
    config = _config(bundle, args.config)
    cal = None
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
            p = cal.params
            _say(
                f"# H: f_c={p.f_c_hz:.6g} Hz a_r={p.a_r:.6g} f_r={p.f_r_hz:.6g} Hz "
                f"gamma_r={p.gamma_r:.4g} n_r={p.n_r:.3g} ({args.h})"
            )
            if cal.refined is not None:
                for line in tension_lines(cal.refined):
                    _say(f"# {line}")
        fits = fit_config(
            config, args.tcut, method=args.method, window=args.window, calibration=cal
        )
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


def cmd_linefit(args) -> int:
    import json

    from bayes_tfcrds.fit.line_analysis import LineFitError, analyse_line

    bundle = _load(args.file)
    config = _config(bundle, args.config)
    try:
        result = analyse_line(
            bundle,
            config,
            method=args.method,
            window=args.window,
            t_cut_s=args.tcut[0],
            profile_name=args.profile,
            physical_bounds=args.shape_bounds == "physical",
        )
    except (LineFitError, ValueError) as exc:
        return _fail(exc, 1)
    atomic_write_text(Path(args.output), json.dumps(result.to_dict(), indent=2) + "\n")
    for line in _linefit_warnings(result, args.tcut[0]):
        _say(line)
    la, ra, q = result.line_area, result.reference_area, result.ratio
    _say(
        f"A = {la.value:.6e} +/- {la.u:.2e} {la.unit}; "
        + (
            "no CMDS reference in this configuration"
            if ra is None
            else f"A_ref = {ra.value:.6e} +/- {ra.u:.2e}; A/A_ref = {q.value:.5f} +/- {q.u:.5f}"
        )
    )
    return 0


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
    if result.noise is not None and not result.noise.white:
        lines.append(f"warning: {result.noise.summary_line()}")
    return lines


def cmd_demo(args) -> int:
    """Simulate a letter-like campaign (D1-D4) and analyse it: CRDS vs TF-CRDS against CMDS."""
    from bayes_tfcrds.studies.demo import run_demo

    result = run_demo(args.output, seed=args.seed, quick=args.quick, log=_say)
    print("\n".join(result.summary_lines()))
    print(file=sys.stderr)
    _say(f"wrote {result.bundle_path}, {result.results_path}, {result.summary_path}")
    return 0


def cmd_budget(args) -> int:
    from bayes_tfcrds.bundle.reader import load_truth
    from bayes_tfcrds.fit.h_calibration import AnalysisError
    from bayes_tfcrds.fit.line_analysis import LineFitError
    from bayes_tfcrds.fit.refine import tension_lines
    from bayes_tfcrds.uncertainty.line_budget import BudgetOptions, run_budget
    from bayes_tfcrds.uncertainty.outputs import failed_banner, write_outputs

    bundle = _load(args.file)
    config = _config(bundle, args.config)
    opts = BudgetOptions(
        method=args.method,
        window=args.window,
        t_cut_s=args.tcut[0],
        profile=args.profile,
        refine_free=args.refine,
    )
    if args.steps is not None or args.max_steps is not None:
        try:
            opts = opts.with_steps(args.steps, args.max_steps)
        except ValueError as exc:
            return _fail(exc, 2)
    try:
        try:
            res = run_budget(
                bundle,
                config,
                opts,
                np.random.default_rng(args.seed),
                outdir=args.output,
                progress=not args.quiet,
            )
        except (LineFitError, AnalysisError, ValueError) as exc:
            return _fail(exc, 1)
        write_outputs(res, args.output, seed=args.seed, truth=load_truth(args.file))
    except KeyboardInterrupt:
        print(file=sys.stderr)
        _say(
            "interrupted: the chains sampled so far are kept in "
            f"{Path(args.output) / 'chains_*.h5'}; run the same command again to resume (same "
            "seed, same result)"
        )
        return 130
    if not res.passed:
        print(failed_banner(res))
    noise = res.summary.get("noise")
    if noise and not noise["white"]:
        _say(
            f"warning: the ring-down noise is coloured (kappa = {noise['kappa_median']:.3g}): "
            "u(tau) and every ring-down likelihood use noise_v sqrt(kappa) (budget.md, "
            "'Ring-down noise')"
        )
    print(res.budget_a.to_markdown())
    if res.refined is not None:
        for line in tension_lines(res.refined):
            _say(f"H refinement: {line}")
    form = (res.summary.get("transfer_function") or {}).get("model_form")
    if form and form["asks_for_free_order"]:
        _say(
            f"finding: the beat note asks for a fractional order n_r = {form['n_r_free_fit']:.3f} "
            f"(BIC weight {form['weight_n_r_free']:.3g}); the budget keeps n_r = 2 and carries the "
            "difference in A as the 'H model form' row"
        )
    if not res.passed:
        _say(f"FAILED: {res.status} (diagnostics: {res.summary['diagnostics']['runs']})")
        return 3
    a, q, s = res.line_area, res.ratio, res.intensity
    t_ref = res.summary["intensity"]["t_ref_k"]
    print(file=sys.stderr)
    _say(
        f"A = {a.value:.6e} +/- {a.u:.2e} cm^-2;  A/A_ref = {q.value:.5f} +/- {q.u:.5f};  E_n = "
        f"{res.en:.2f};  S({t_ref:g} K) = {s.value:.5e} +/- {s.u:.2e} cm/molecule"
    )
    return 0


def cmd_study(args) -> int:
    from concurrent.futures import ProcessPoolExecutor

    from bayes_tfcrds.studies.registry import run_study
    from bayes_tfcrds.studies.spec import StudyError

    try:
        if args.workers > 1:
            with ProcessPoolExecutor(max_workers=args.workers) as pool:
                html_path, pdf_path = run_study(
                    args.file, args.output, progress=not args.quiet, pool=pool, seed=args.seed
                )
        else:
            html_path, pdf_path = run_study(
                args.file, args.output, progress=not args.quiet, seed=args.seed
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


def _common(sp, seed=0, note=""):
    """Options every command has (``--seed``), and help that shows defaults."""
    sp.formatter_class = _HelpWithDefaults
    sp.add_argument("--seed", type=_seed, default=seed, help="random seed" + note)
    return sp


def _bundle_and_model(sp) -> None:
    """The bundle, its configuration, and the ring-down model (method and window)."""
    sp.add_argument("file")
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
    _bundle_and_model(sp)
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
    _bundle_and_model(sp)
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
        help="longest run per ensemble; a run still missing a gate then is reported as failed "
        "(default max(8 x steps, 24000))",
    )
    sp.add_argument("--quiet", action="store_true", help="no progress bars")
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
    sp.add_argument("--quiet", action="store_true", help="no progress bars")
    sp.add_argument(
        "--workers", type=int, default=2, help="local worker processes (2 uses both cores)"
    )
    sp.set_defaults(func=cmd_study)


def _add_discover(sub) -> None:
    """The ``discover`` command's options."""
    sp = _common(
        sub.add_parser("discover", help="find the effects missing from a model of the experiment"),
        note=" (discovery is deterministic; the seed is recorded)",
    )
    sp.add_argument("file")
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
    sp.add_argument("--quiet", action="store_true", help="no progress bars")
    sp.add_argument(
        "-o", "--output", required=True, help="output folder (discovery.json, discovery.html)"
    )
    sp.set_defaults(func=cmd_discover)


def _add_demo(sub) -> None:
    """The ``demo`` command's options."""
    sp = _common(
        sub.add_parser("demo", help="simulate a letter-like campaign (D1-D4) and analyse it"),
        seed=7,
    )
    sp.add_argument("-o", "--output", default="demo-out", help="output folder")
    sp.add_argument("--quick", action="store_true", help="a smaller campaign (for a first look)")
    sp.set_defaults(func=cmd_demo)


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
    ):
        add(sub)
    return p


def main(argv=None) -> int:
    from bayes_tfcrds.output.files import FolderBusyError, OutputPathError

    args = build_parser().parse_args(argv)
    try:
        _check_output(args)
        return int(args.func(args) or 0)
    except OutputPathError as exc:  # the output rule (output.files.check_replaceable), any command
        return _fail(exc, 2)
    except FolderBusyError as exc:  # another run holds -o (output.files.folder_lock)
        return _fail(exc, 1)
    except Refused as exc:
        return _fail(exc, exc.code)


_FOLDER_COMMANDS = ("cmd_budget", "cmd_study", "cmd_discover", "cmd_demo")


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
