"""Command-line interface: bayes-tfcrds COMMAND ...

Every command takes ``--seed`` (the same inputs and seed give the same numbers) and reports
bad input as one clear message naming what is wrong, with exit status 1 or 2.
"""
from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np

from . import __version__


def _floats(text: str):
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers in seconds, got {text!r}")


def _one_float(text: str):
    v = _floats(text)
    if len(v) != 1:
        raise argparse.ArgumentTypeError(f"expected one number in seconds, got {text!r}")
    return v


def _config(bundle, name):
    if name is None:
        if len(bundle.configs) != 1:
            raise SystemExit(f"error: the bundle has configurations {list(bundle.configs)}; choose one with --config")
        return next(iter(bundle.configs.values()))
    if name not in bundle.configs:
        raise SystemExit(f"error: no configuration {name!r} in the bundle (it has {list(bundle.configs)})")
    return bundle.configs[name]


def _load(path):
    from .bundle import BundleError, load_bundle
    try:
        return load_bundle(path)
    except BundleError as exc:
        raise SystemExit(f"error: {exc}")


def atomic_write_text(path: Path, text: str):
    """Write text to ``path`` through a temporary name and a rename (never half-written)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    tmp.replace(path)


def cmd_validate(args) -> int:
    from .bundle import main_validate
    return main_validate(args.file)


def cmd_fit(args) -> int:
    from .analysis import AnalysisError, calibrate, fit_config
    bundle = _load(args.file)
    config = _config(bundle, args.config)
    cal = None
    try:
        if args.method == "tf-crds":
            cal = calibrate(config, window=args.window, refine=args.h == "refined")
            p = cal.params
            print(f"# H: f_c={p.f_c_hz:.6g} Hz a_r={p.a_r:.6g} f_r={p.f_r_hz:.6g} Hz gamma_r={p.gamma_r:.4g} "
                  f"n_r={p.n_r:.3g} ({args.h})", file=sys.stderr)
        fits = fit_config(config, args.tcut, method=args.method, window=args.window, calibration=cal)
    except (AnalysisError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    import io
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["nu_hz", "t_cut_s", "tau_s", "tau_u_s", "chi2_red", "status"])
    for nu, tc, tau, tau_u, chi2r, status in fits.rows():
        w.writerow([f"{nu:.3f}", f"{tc:.6e}", f"{tau:.10e}", f"{tau_u:.4e}", f"{chi2r:.5f}", status])
    atomic_write_text(Path(args.output), buf.getvalue())
    n_clip = int(fits.clipped.sum())
    n_sat = int(np.sum(config.ringdowns.saturated))
    n_short = sum(row[-1] == "record-short" for row in fits.rows())
    print(f"wrote {args.output}: {fits.tau_s.size} fits ({args.method}"
          f"{', ' + args.window if args.method == 'tf-crds' else ''})"
          + (f"; {n_clip} clipped transients not fitted (status clipped"
             + (f"; {n_sat} of them saturated below the digitizer rails" if n_sat else "")
             + "; bayes-tfcrds validate lists them)" if n_clip else "")
          + (f"; warning: {n_short} fits have less than two decay times of record after t_cut "
             "(status record-short)" if n_short else ""), file=sys.stderr)
    return 0


def cmd_simulate(args) -> int:
    from .bundle import save_bundle
    from .simulate import Campaign, parse_effect, simulate_campaign
    effects = {}
    try:
        for text in args.effect or []:
            name, params = parse_effect(text)
            effects[name] = params
        campaign = Campaign(n_points=args.points, n_samples=args.samples)
        rng = np.random.default_rng(args.seed)
        bundle, truth = simulate_campaign(args.preset or ["letter-D2"], rng, campaign, effects)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    save_bundle(bundle, args.output, truth=truth)
    m = next(iter(bundle.configs.values())).ringdowns.n_points
    print(f"wrote {args.output}: configurations {list(bundle.configs)}, "
          f"{m} cavity modes x {campaign.n_samples} samples, seed {args.seed}", file=sys.stderr)
    return 0


def cmd_linefit(args) -> int:
    import json
    from .linefit import LineFitError, analyse_line
    bundle = _load(args.file)
    config = _config(bundle, args.config)
    try:
        result = analyse_line(bundle, config, method=args.method, window=args.window, t_cut_s=args.tcut[0],
                              profile_name=args.profile, physical_bounds=args.shape_bounds == "physical")
    except (LineFitError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    atomic_write_text(Path(args.output), json.dumps(result, indent=2) + "\n")
    if result["clipped_points"]:
        print(f"warning: {result['clipped_points']} clipped or saturated transients were left out of the "
              "spectrum (bayes-tfcrds validate lists them)", file=sys.stderr)
    if result["unconverged_points"]:
        print(f"warning: {result['unconverged_points']} decay-time fits did not converge and were left out of "
              "the spectrum (bayes-tfcrds fit lists them as not-converged)", file=sys.stderr)
    if result["record_short_points"]:
        print(f"warning: {result['record_short_points']} decay times come from less than two decay times of "
              f"record after t_cut = {args.tcut[0]:g} s (offset and tau nearly degenerate)", file=sys.stderr)
    if result["unphysical_shape"]:
        print(f"warning: {', '.join(result['unphysical_shape'])} ended below 0 (on the profile's continuation): "
              "the line shape is not physical, often a sign that the model of the experiment is wrong "
              "(plain CRDS of a distorted chain?); --shape-bounds physical holds them at 0", file=sys.stderr)
    if result["shape_at_bound"]:
        print(f"note: {', '.join(result['shape_at_bound'])} held at 0 by --shape-bounds physical", file=sys.stderr)
    la, ra = result["line_area"], result["reference_area"]
    print(f"A = {la['value']:.6e} +/- {la['u']:.2e} {la['unit']}; "
          + ("no CMDS reference in this configuration" if ra is None else
             f"A_ref = {ra['value']:.6e} +/- {ra['u']:.2e}; "
             f"A/A_ref = {result['ratio']['value']:.5f} +/- {result['ratio']['u']:.5f}"), file=sys.stderr)
    return 0


def cmd_demo(args) -> int:
    """Simulate a letter-like campaign (D1-D4) and analyse it: CRDS vs TF-CRDS against CMDS."""
    import json
    from dataclasses import replace
    from .bundle import load_bundle, save_bundle
    from .simulate import Campaign, simulate_campaign, spectral_points
    from .linefit import analyse_line
    from .analysis import calibrate
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    campaign = Campaign() if not args.quick else replace(Campaign(), n_points=41, n_samples=8192, n_avg=20)
    presets = ["letter-D1", "letter-D2", "letter-D3", "letter-D4"]
    print(f"simulating {', '.join(presets)} (seed {args.seed}, {spectral_points(campaign).size} cavity modes x "
          f"{campaign.n_samples} samples, {campaign.n_avg} averages) ...", file=sys.stderr)
    bundle, truth = simulate_campaign(presets, np.random.default_rng(args.seed), campaign)
    path = out / "campaign.h5"
    save_bundle(bundle, path, truth=truth)
    bundle = load_bundle(path)
    results = []
    # The letter reads its CRDS line fits as physical line shapes (Gamma2, nu_VC >= 0), and so does
    # the demo: on the distorted D3/D4 spectra the free estimator would follow the distortion to
    # nu_VC < 0 (the column names any shape parameter the bound holds at 0). TF-CRDS fits are the
    # same either way: the bounds are not reached when the model is right.
    lines = ["| config | method | t_cut (us) | A (cm^-2) | A/A_ref - 1 (%) | u (%) | chi2_red | held at 0 |",
             "|---|---|---|---|---|---|---|---|"]
    for name, cfg in bundle.configs.items():
        cal = calibrate(cfg)
        for method in ("crds", "tf-crds"):
            for tc in (4e-6, 8e-6):
                r = analyse_line(bundle, cfg, method=method, t_cut_s=tc, physical_bounds=True,
                                 calibration=cal if method == "tf-crds" else None)
                results.append(r)
                held = ", ".join(r["shape_at_bound"]) or "-"
                lines.append(f"| {name} | {method} | {tc * 1e6:g} | {r['line_area']['value']:.6e} | "
                             f"{100 * (r['ratio']['value'] - 1):+.3f} | {100 * r['ratio']['u']:.3f} | "
                             f"{r['chi2_red']:.2f} | {held} |")
                print(f"  {name} {method} t_cut {tc * 1e6:g} us done", file=sys.stderr)
    atomic_write_text(out / "results.json", json.dumps(results, indent=2) + "\n")
    atomic_write_text(out / "summary.md", "# bayes-tfcrds demo: simulated letter campaign\n\n" + "\n".join(lines) + "\n")
    print("\n".join(lines))
    print(f"\nwrote {path}, {out / 'results.json'}, {out / 'summary.md'}", file=sys.stderr)
    return 0


def cmd_budget(args) -> int:
    from .uncertainty import BudgetOptions, run_budget, write_outputs
    from .linefit import LineFitError
    from .analysis import AnalysisError
    bundle = _load(args.file)
    config = _config(bundle, args.config)
    opts = BudgetOptions(method=args.method, window=args.window, t_cut_s=args.tcut[0], profile=args.profile)
    if args.steps is not None or args.max_steps is not None:
        from dataclasses import replace
        n_steps = opts.n_steps if args.steps is None else args.steps
        max_steps = max(n_steps * 8, opts.max_steps) if args.max_steps is None else args.max_steps
        if not 1 <= n_steps <= max_steps:
            print(f"error: need 1 <= --steps ({n_steps}) <= --max-steps ({max_steps})", file=sys.stderr)
            return 2
        opts = replace(opts, n_steps=n_steps, max_steps=max_steps)
    try:
        try:
            res = run_budget(bundle, config, opts, np.random.default_rng(args.seed), outdir=args.output,
                             progress=not args.quiet)
        except (LineFitError, AnalysisError, ValueError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 1
        write_outputs(res, args.output, seed=args.seed)
    except KeyboardInterrupt:
        print(f"\ninterrupted: the chains sampled so far are kept in {Path(args.output) / 'chains_*.h5'}; "
              "run the same command again to resume (same seed, same result)", file=sys.stderr)
        return 130
    s = res.summary
    print(res.budget_a.to_markdown())
    if s["status"] != "ok":
        print(f"FAILED: {s['status']} (diagnostics: {s['diagnostics']['runs']})", file=sys.stderr)
        return 3
    print(f"\nA = {s['line_area']['value']:.6e} +/- {s['line_area']['u']:.2e} cm^-2;  "
          f"A/A_ref = {s['ratio']['value']:.5f} +/- {s['ratio']['u']:.5f};  E_n = {s['en']:.2f};  "
          f"S = {s['intensity']['value']:.5e} +/- {s['intensity']['u']:.2e} cm/molecule", file=sys.stderr)
    return 0


def cmd_study(args) -> int:
    from .study import StudyError, run_study
    from concurrent.futures import ProcessPoolExecutor
    try:
        if args.workers > 1:
            with ProcessPoolExecutor(max_workers=args.workers) as pool:
                html_path, pdf_path = run_study(args.file, args.output, progress=not args.quiet, pool=pool,
                                                seed=args.seed)
        else:
            html_path, pdf_path = run_study(args.file, args.output, progress=not args.quiet, seed=args.seed)
    except StudyError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {html_path} and {pdf_path}", file=sys.stderr)
    return 0


def cmd_discover(args) -> int:
    from .discover import DEFAULT_T_CUTS, discover, parse_model, write_report
    bundle = _load(args.file)
    config = _config(bundle, args.config)
    try:
        start = parse_model(args.start)
        result = discover(bundle, config.name, start, t_cuts=args.tcut or DEFAULT_T_CUTS, threshold=args.threshold,
                          progress=None if args.quiet else (lambda s: print(s, file=sys.stderr, flush=True)))
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    json_path, html_path = write_report(result, args.output, seed=args.seed, inputs=[args.file])
    print(f"effects added: {', '.join(result.effects_added) or 'none'} ({result.seconds:.1f} s); "
          f"wrote {json_path} and {html_path}", file=sys.stderr)
    return 0


class _HelpWithDefaults(argparse.ArgumentDefaultsHelpFormatter):
    """Shows an option's default where it has one (not for required options, flags or None)."""

    def _get_help_string(self, action):
        if action.required or action.default is None or action.default is False or action.help is None:
            return action.help
        return super()._get_help_string(action)


def build_parser() -> argparse.ArgumentParser:
    from .simulate import Campaign
    from .uncertainty import BudgetOptions
    p = argparse.ArgumentParser(prog="bayes-tfcrds",
                                description="Transfer-function-corrected CRDS with honest uncertainty budgets. "
                                            "The data contract (HDF5 measurement bundle) is FORMAT.md, shipped in "
                                            "bayes_tfcrds/data/.")
    p.add_argument("--version", action="version", version=f"bayes-tfcrds {__version__}")
    sub = p.add_subparsers(dest="command", required=True)

    def common(sp, seed=0, note=""):
        sp.formatter_class = _HelpWithDefaults
        sp.add_argument("--seed", type=int, default=seed, help="random seed" + note)
        return sp

    sp = common(sub.add_parser("validate", help="check a measurement bundle against FORMAT.md"),
                note=" (validate draws no random numbers)")
    sp.add_argument("file", help="measurement bundle (HDF5)")
    sp.set_defaults(func=cmd_validate)

    sp = common(sub.add_parser("fit", help="fit ring-down decay times (CRDS or TF-CRDS)"))
    sp.add_argument("file")
    sp.add_argument("--config", help="configuration name, e.g. D2")
    sp.add_argument("--method", choices=["crds", "tf-crds"], default="tf-crds",
                    help="crds: pure exponential; tf-crds: exponential through the detection chain's H(f)")
    sp.add_argument("--window", choices=["extinction", "letter"], default="extinction",
                    help="history before t = 0 in the TF-CRDS model: extinction (exact) or letter (the letter's)")
    sp.add_argument("--tcut", type=_floats, default=[2e-6, 4e-6, 8e-6], help="t_cut values in s, comma-separated")
    sp.add_argument("--transfer-function", dest="h", choices=["refined", "beat"], default="refined",
                    help="H for TF-CRDS: the beat-note fit refined on ring-downs, or the beat-note fit alone")
    sp.add_argument("-o", "--output", required=True, help="CSV file to write")
    sp.set_defaults(func=cmd_fit)

    sp = common(sub.add_parser("simulate", help="simulate a letter-like campaign into a bundle"))
    sp.add_argument("--preset", action="append", help="letter-D1 ... letter-D4 (repeatable; default letter-D2)")
    sp.add_argument("--effect", action="append", help="NAME[:key=value,...] (repeatable), e.g. "
                    "static_nonlinearity:beta=-3e-3")
    sp.add_argument("--points", type=int, default=Campaign.n_points,
                    help="spectral points requested (modes that coincide on the FSR grid are dropped: the "
                         "default span of +/- 10 GHz holds 99)")
    sp.add_argument("--samples", type=int, default=Campaign.n_samples, help="samples per transient")
    sp.add_argument("-o", "--output", required=True, help="bundle (HDF5) to write")
    sp.set_defaults(func=cmd_simulate)

    sp = common(sub.add_parser("linefit", help="fit a line profile to the CRDS spectrum and to CMDS"))
    sp.add_argument("file")
    sp.add_argument("--config", help="configuration name, e.g. D2")
    sp.add_argument("--method", choices=["crds", "tf-crds"], default="tf-crds",
                    help="crds: pure exponential; tf-crds: exponential through the detection chain's H(f)")
    sp.add_argument("--window", choices=["extinction", "letter"], default="extinction",
                    help="history before t = 0 in the TF-CRDS model: extinction (exact) or letter (the letter's)")
    sp.add_argument("--tcut", type=_one_float, default=[4e-6], help="the t_cut of the spectrum, s")
    sp.add_argument("--profile", choices=["voigt", "sdvp", "rautian", "qsdhcp"], default="qsdhcp", help="line profile fitted to the spectrum")
    sp.add_argument("--shape-bounds", choices=["free", "physical"], default="free",
                    help="free: Gamma2 and nu_VC may go below 0 on the profile's continuation (unbiased when the "
                         "model is right; such fits are flagged); physical: held at >= 0, as the letter reads its fits")
    sp.add_argument("-o", "--output", required=True, help="JSON file to write")
    sp.set_defaults(func=cmd_linefit)
    sp = common(sub.add_parser("budget", help="posteriors and the GUM line-area budget against CMDS"))
    sp.add_argument("file")
    sp.add_argument("--config", help="configuration name, e.g. D2")
    sp.add_argument("--method", choices=["crds", "tf-crds"], default="tf-crds",
                    help="crds: pure exponential; tf-crds: exponential through the detection chain's H(f)")
    sp.add_argument("--window", choices=["extinction", "letter"], default="extinction",
                    help="history before t = 0 in the TF-CRDS model: extinction (exact) or letter (the letter's)")
    sp.add_argument("--tcut", type=_one_float, default=[4e-6], help="t_cut of the reported A, s")
    sp.add_argument("--profile", choices=["voigt", "sdvp", "rautian", "qsdhcp"], default="qsdhcp", help="line profile fitted to the spectrum")
    sp.add_argument("--steps", type=int, default=BudgetOptions.n_steps,
                    help="MCMC steps per ensemble before the convergence gates are checked")
    sp.add_argument("--max-steps", type=int, help="longest run per ensemble; a run still missing a gate then is "
                                                  "reported as failed (default max(8 x steps, 24000))")
    sp.add_argument("--quiet", action="store_true", help="no progress bars")
    sp.add_argument("-o", "--output", required=True, help="output folder")
    sp.set_defaults(func=cmd_budget)

    sp = common(sub.add_parser("study", help="run a declared study and write its report"), seed=None,
                note=" (default: the [study] seed of the file)")
    sp.add_argument("file", help="study file (TOML), e.g. studies/letter_tcut.toml")
    sp.add_argument("-o", "--output", required=True, help="report folder, e.g. reports/letter_tcut/")
    sp.add_argument("--quiet", action="store_true", help="no progress bars")
    sp.add_argument("--workers", type=int, default=2, help="local worker processes (2 uses both cores)")
    sp.set_defaults(func=cmd_study)

    sp = common(sub.add_parser("discover", help="find the effects missing from a model of the experiment"),
                note=" (discovery is deterministic; the seed is recorded)")
    sp.add_argument("file")
    sp.add_argument("--config", help="configuration name, e.g. D2")
    sp.add_argument("--start", default="crds+voigt",
                    help="starting model: crds+voigt, or canonical effect names joined by ',' or '+', "
                         "e.g. transfer_function,window_history,speed_dependence")
    sp.add_argument("--tcut", type=_floats, default=None, help="t_cut values in s (default 2e-6,4e-6,6e-6)")
    sp.add_argument("--threshold", type=float, default=10.0, help="Delta BIC an effect needs to be added")
    sp.add_argument("--quiet", action="store_true", help="no progress bars")
    sp.add_argument("-o", "--output", required=True, help="output folder (discovery.json, discovery.html)")
    sp.set_defaults(func=cmd_discover)

    sp = common(sub.add_parser("demo", help="simulate a letter-like campaign (D1-D4) and analyse it"), seed=7)
    sp.add_argument("-o", "--output", default="demo-out", help="output folder")
    sp.add_argument("--quick", action="store_true", help="a smaller campaign (for a first look)")
    sp.set_defaults(func=cmd_demo)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
