"""H's part of u(A) in discovery, against a Monte Carlo of the refinement itself.

Discovery judges A/A_ref - 1 against the fits' noise plus H's part, u_H(A)
(:func:`bayes_tfcrds.discovery.workflow.h_area_uncertainty`: A refitted with H moved +/- 1 sigma
along the principal axes of H's joint covariance). Here that number is checked against what it
stands for: the spread of A when the beat note's parameters are drawn from their covariance, the
ring-down refinement is rerun at each draw (the refined f_c follows them), the refined
parameters get their scatter given the others, and the decay times and the line are refitted.
The Monte Carlo shares the refinement, its beat-note prior and Cov(R | O) with the shipped path,
and the fits of A: it checks the gain, the linearisation and the principal-axis propagation, not
the refinement's own covariance (``benchmarks/budget_replicas.py`` and the coverage study check
that).

Cases: the letter's four chains, then chain-zoo draws (``tail`` and ``pole`` regimes in turn),
each with discovery's start model ``transfer_function`` (the letter's window, which these
ring-downs do not fully follow) and with ``transfer_function,window_history`` (the extinction
window, which they do). Reported per
case: u_H(A) as shipped (gain by refits), with the refinement's implicit gain, with each
parameter alone (correlations neglected: the earlier shipped path), and the Monte Carlo's, all
relative to A.

PASS when every shipped u_H(A) lies within 3 standard errors of the Monte Carlo's
(se = 1/sqrt(2 N) relative, N draws; a 3-sigma band for each of a dozen cases).

Usage:  python benchmarks/h_area_uncertainty.py --zoo 4 --draws 100 --seed 5 --workers 2
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace

import numpy as np

PRESETS = ("letter-D1", "letter-D2", "letter-D3", "letter-D4")
T_CUTS = (2e-6, 4e-6, 6e-6)
WINDOWS = {"letter": "transfer_function", "extinction": "transfer_function,window_history"}


def _campaign_of(index: int, seed: int, n_zoo: int):
    """(bundle, config name, label) of case ``index``: a preset, then zoo chains."""
    from bayes_tfcrds.simulate.campaign import Campaign, ChainPreset, simulate_campaign
    from bayes_tfcrds.simulate.zoo import draw_chain

    rng = np.random.default_rng([seed, index])
    campaign = replace(Campaign(), n_points=21, n_samples=4096)
    effects = {"transfer_function": {}}
    if index < len(PRESETS):
        bundle, _ = simulate_campaign(
            [PRESETS[index]], rng, campaign, effects, line_effects_default=False
        )
        return bundle, PRESETS[index].split("-")[1], PRESETS[index]
    regime = ("tail", "pole")[(index - len(PRESETS)) % 2]
    tf = draw_chain(rng, regime)
    pre = ChainPreset("Z", f"zoo chain {index} ({regime})", tf)
    bundle, _ = simulate_campaign([pre], rng, campaign, effects, line_effects_default=False)
    return bundle, "Z", f"zoo {regime} {index}"


def _area(bundle, cfg, state, tf, ev) -> float:
    """A (Hz/m) at the first t_cut with the transient fits made under ``tf``."""
    from bayes_tfcrds.discovery.workflow import fit_lines
    from bayes_tfcrds.fit.extensions import fit_transient_rows

    rd = cfg.ringdowns
    res = fit_transient_rows(
        rd, np.full(ev.good.size, T_CUTS[0]), ev.good, replace(state.spec(), tf=tf), ev.tau[:, 0]
    )
    nu = np.asarray(rd.nu_hz, float)[ev.good]
    return fit_lines(bundle, cfg, state.model, nu, res.tau_s, res.tau_u_s).value("line_area")


def monte_carlo(bundle, cfg, state, ev, window: str, n: int, rng) -> np.ndarray:
    """A at n draws of H: beat-note others drawn, the refinement rerun, its scatter added."""
    from bayes_tfcrds.fit.h_calibration import refine_on_records
    from bayes_tfcrds.fit.refine import HPrior
    from bayes_tfcrds.physics.transfer_function import outside_support

    cal = state.calibration
    ref, beat = cal.refined, cal.beat
    others = cal.others
    io = [beat.free.index(o) for o in others]
    s_oo = beat.param_cov[np.ix_(io, io)]
    prior = HPrior.from_beat(beat)
    areas = []
    tries = 0
    while len(areas) < n and tries < 3 * n:
        tries += 1
        o = rng.multivariate_normal(ref.params.as_vector(others), s_oo, method="eigh")
        start = ref.params.with_vector(o, others)
        if outside_support(start, others):
            continue
        try:
            r, _ = refine_on_records(cfg, start, ref.free, window, T_CUTS, 6, prior)
        except (ValueError, np.linalg.LinAlgError):
            continue
        if not r.converged:
            continue
        e = rng.multivariate_normal(np.zeros(len(ref.free)), ref.cov, method="eigh")
        tf = r.params.with_vector(r.params.as_vector(ref.free) + e, ref.free)
        if outside_support(tf, ref.free):
            continue
        areas.append(_area(bundle, cfg, state, tf, ev))
    return np.array(areas)


def run_case(args) -> dict:
    from bayes_tfcrds.discovery.workflow import _start_state, evaluate, h_area_uncertainty

    index, window, seed, n_zoo, n_draws = args
    t0 = time.perf_counter()
    bundle, name, label = _campaign_of(index, seed, n_zoo)
    cfg = bundle.configs[name]
    rec = {"index": index, "case": label, "window": window}
    try:
        state = _start_state(bundle, cfg, WINDOWS[window], T_CUTS)
        cal = state.calibration
        ev = evaluate(bundle, cfg, state, T_CUTS, h_uncertainty=False)
        area = ev.lines[0].value("line_area")

        def u_with(c):
            st = replace(state, calibration=c)
            return h_area_uncertainty(bundle, cfg, st, T_CUTS[0], ev.good, ev.tau[:, 0], area)

        u_ship = u_with(cal)
        u_implicit = u_with(replace(cal, gain=None))
        u_marg = u_with(replace(cal, gain=None, refined=replace(cal.refined, gain_sample=None)))
        mc = monte_carlo(
            bundle, cfg, state, ev, window, n_draws, np.random.default_rng([seed, index, 7])
        )
        u_mc = float(np.std(mc, ddof=1))
        names, cov = cal.covariance()
        sd = np.sqrt(np.diag(cov))
        rho = cov / np.outer(sd, sd)
        nr = len(cal.refined.free)
        rec.update(
            status="ok",
            area_hz_per_m=area,
            u_shipped_rel=u_ship / area,
            u_implicit_rel=u_implicit / area,
            u_marginal_rel=u_marg / area,
            u_mc_rel=u_mc / area,
            n_mc=int(mc.size),
            max_abs_rho=float(np.abs(rho[:nr, nr:]).max()),
            chi2_red=float(cal.refined.chi2 / cal.refined.dof),
        )
    except Exception as exc:  # noqa: BLE001 - a case that fails is reported, not hidden
        rec.update(status=f"failed: {type(exc).__name__}: {exc}")
    rec["seconds"] = time.perf_counter() - t0
    return rec


def verdict(records) -> dict:
    ok = [r for r in records if r["status"] == "ok"]
    within = []
    for r in ok:
        se = 1.0 / np.sqrt(2 * r["n_mc"])
        within.append(abs(r["u_shipped_rel"] / r["u_mc_rel"] - 1) < 3 * se)
    return {
        "cases": len(records),
        "ok": len(ok),
        "within_3se": int(sum(within)),
        "pass": bool(ok) and len(ok) == len(records) and all(within),
    }


def table(records) -> str:
    head = (
        "| case | window | chi2_red | max |rho| | u_H(A)/A shipped | implicit gain | "
        "each alone | Monte Carlo (N) | shipped/MC |\n|---|---|---|---|---|---|---|---|---|\n"
    )
    rows = []
    for r in records:
        if r["status"] != "ok":
            rows.append(f"| {r['case']} | {r['window']} | {r['status']} |||||||")
            continue
        rows.append(
            f"| {r['case']} | {r['window']} | {r['chi2_red']:.3f} | {r['max_abs_rho']:.2f} | "
            f"{r['u_shipped_rel']:.2e} | {r['u_implicit_rel']:.2e} | {r['u_marginal_rel']:.2e} | "
            f"{r['u_mc_rel']:.2e} ({r['n_mc']}) | {r['u_shipped_rel'] / r['u_mc_rel']:.2f} |"
        )
    return head + "\n".join(rows) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--zoo", type=int, default=4, help="zoo chains after the four presets")
    ap.add_argument("--draws", type=int, default=100, help="Monte Carlo draws per case")
    ap.add_argument("--windows", default="letter,extinction")
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("-o", "--output", help="write the records (JSON) here")
    args = ap.parse_args(argv)
    windows = [w for w in args.windows.split(",") if w]
    bad = [w for w in windows if w not in WINDOWS]
    if bad:
        ap.error(f"unknown windows {bad}; choose from {sorted(WINDOWS)}")
    tasks = [
        (i, w, args.seed, args.zoo, args.draws)
        for i in range(len(PRESETS) + args.zoo)
        for w in windows
    ]
    t0 = time.perf_counter()
    records = []

    def keep(rec):
        records.append(rec)
        print(
            f"{rec['case']} ({rec['window']}): {rec['status']} ({rec['seconds']:.0f} s; "
            f"{time.perf_counter() - t0:.0f} s elapsed)",
            file=sys.stderr,
            flush=True,
        )

    parallel = args.workers > 1
    with ProcessPoolExecutor(args.workers) if parallel else contextlib.nullcontext() as pool:
        for rec in (pool.map if parallel else map)(run_case, tasks):
            keep(rec)
    v = verdict(records)
    print(table(records))
    print(
        f"{v['within_3se']} of {v['ok']} cases within 3 s.e. of the Monte Carlo "
        f"({v['cases']} run); {time.perf_counter() - t0:.0f} s; {'PASS' if v['pass'] else 'FAIL'}"
    )
    if args.output:
        with open(args.output, "w") as fh:
            json.dump({"verdict": v, "records": records}, fh, indent=1)
    return 0 if v["pass"] else 1


if __name__ == "__main__":
    sys.exit(main())
