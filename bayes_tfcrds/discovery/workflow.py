"""Discovery: find the physical effect a model of the experiment is missing, add it, repeat.

Start from a declared model (default plain CRDS with a Voigt line), compare it with every data
block where model and data can disagree (transient residuals in time and frequency, tau and A
against t_cut, spectrum residuals, the beat note, the CRDS-CMDS gap), then try each canonical
effect as a model extension (:mod:`bayes_tfcrds.fit.extensions`) and score it by the drop of BIC
on the data block it acts on.

Evidence is ``Delta BIC = chi2_before - chi2_after - k ln n`` on the block (every extra
parameter counted, per-transient ones included); a candidate needs ``DEFAULT_THRESHOLD`` = 10
("very strong" on the Kass-Raftery scale of 2 ln B) to be considered.

When to add, and when to stop, is decided by the gaps, each against its own null measured by a
parametric bootstrap under the current model (:mod:`bayes_tfcrds.discovery.nulls`):

* a round runs only while some gap is outside its null band at level alpha/2^step (Bonferroni
  over the gaps), so a model that already describes the data gains any effect with probability
  at most alpha (``DEFAULT_ALPHA`` = 5 %): the family-wise error rate, hence also the
  false-discovery rate, of the whole selection is at most alpha;
* a candidate with evidence is acceptable when it removes at least half (``EXPLAIN_FRACTION``)
  of the open misfit of its own data block (the sum of calibrated z^2 of its open gaps); one that
  only soaks up a part of a misfit it does not describe is not;
* of the candidates so accepted (up to ``MAX_TRIES`` tried in order of evidence), the one that
  leaves the least misfit in all the data (sum of calibrated z^2 over every gap) is added:
  evidence is measured on a candidate's own block, so a term that describes the transients alone
  (a damped beat for a slow detector path, an AC-coupling undershoot for a second mode) can
  outscore the effect that also explains the beat note or keeps the decay times a line;
* a candidate of the same block whose evidence is within ``AMBIGUITY_BIC`` = 2 of the added
  one's is named beside it (the step's ``alternatives``): the data cannot tell the two apart
  (soft-collision narrowing and a quadratic speed dependence in the Doppler regime);
* when gaps stay open and no candidate explains them, discovery stops and reports "unexplained
  structure" with the open gaps and where they are, instead of adding the nearest candidates.

Units: SI inside (s, Hz, V, 1/m); cm^-2 only in the report.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np
from scipy import stats

from bayes_tfcrds.discovery.nulls import N_BOOT, gap_nulls, pre_extinction_noise
from bayes_tfcrds.fit.extensions import (
    PROFILE_DEFAULT_LABEL,
    PROFILE_FORMS,
    SPECTRUM_DEFAULT_LABEL,
    SPECTRUM_FORMS,
    LineAbsorption,
    TransientSpec,
    family_member,
    fit_family,
    fit_profile_family,
    fit_spectrum_extended,
    fit_spectrum_family,
    fit_transient_rows,
    form_of,
    shared_covariance,
)
from bayes_tfcrds.fit.h_calibration import AnalysisError, account_for_noise_colour, calibrate
from bayes_tfcrds.fit.line_analysis import doppler_of
from bayes_tfcrds.fit.refine import from_sample, sample_jacobian, to_sample
from bayes_tfcrds.fit.spectrum import absorption_from_tau
from bayes_tfcrds.physics.transfer_function import outside_support

CANDIDATES = (
    "transfer_function",
    "window_history",
    "static_nonlinearity",
    "extinction_tail",
    "second_mode",
    "baseline_drift",
    "mode_beating",
    "speed_dependence",
    "hard_collisions",
    "etalon",
    "neighbour_line",
)
TRANSIENT_LEVEL = (
    "static_nonlinearity",
    "extinction_tail",
    "second_mode",
    "baseline_drift",
    "mode_beating",
)
SPECTRUM_LEVEL = ("speed_dependence", "hard_collisions", "etalon", "neighbour_line")
#: t_cuts (s) of discovery: three suffice to see tau and A move with t_cut, and keep each round fast
DISCOVERY_T_CUTS = (2e-6, 4e-6, 6e-6)
DEFAULT_THRESHOLD = 10.0
N_TIME_BINS = 12
#: family-wise probability of adding any effect to a model that already describes the data
DEFAULT_ALPHA = 0.05
#: a candidate is added only if it removes at least this fraction of the open misfit of its block
EXPLAIN_FRACTION = 0.5
#: a gap of the CMDS or the beat note is made worse by a candidate when its model leaves it open
#: with a calibrated z higher by more than this (one null standard deviation); reported only
WORSEN_MARGIN = 1.0
#: blocks measured by other instruments than the ring-downs: the CMDS reference, the beat note
INDEPENDENT_BLOCKS = ("reference", "beat")
#: candidates with evidence tried in turn per round (each costs an evaluation and a bootstrap)
MAX_TRIES = 4
#: another candidate of the same data block whose evidence is within this of the added one's
#: explains the data as well: "not worth more than a bare mention" (Delta BIC < 2, Kass and
#: Raftery, JASA 90 (1995) 773). The step names both; e.g. soft-collision narrowing and a
#: quadratic speed dependence differ by < 1e-6 of the peak in the Doppler regime.
AMBIGUITY_BIC = 2.0
#: the data block each gap metric measures (a candidate is judged on the gaps of its blocks)
GAP_BLOCK = {
    "transient_chi2": "transients",
    "transient_time_structure": "transients",
    "transient_freq_structure": "transients",
    "tau_tcut": "transients",
    "area_tcut": "transients",
    "spectrum_chi2": "spectrum",
    "spectrum_structure": "spectrum",
    "beat_chi2": "beat",
    "crds_cmds": "reference",
}


# --------------------------------------------------------------------------- the model


@dataclass(frozen=True)
class ExperimentModel:
    """Which canonical effects the analysis model contains; the analysis choices follow."""

    effects: frozenset = frozenset()
    #: higher members of spectrum-level families in use (keys of SPECTRUM_FORMS, e.g.
    #: ``etalon_harmonic``, or of PROFILE_FORMS, e.g. ``soft_collisions``); transient-level
    #: forms live in the shared parameters
    forms: frozenset = frozenset()

    def __post_init__(self):
        bad = set(self.effects) - set(CANDIDATES)
        if bad:
            raise ValueError(f"unknown effect(s) {sorted(bad)}; choose from {list(CANDIDATES)}")
        owner = {f: v[0] for f, v in (*SPECTRUM_FORMS.items(), *PROFILE_FORMS.items())}
        bad_forms = {f for f in self.forms if owner.get(f, "") not in self.effects}
        if bad_forms:
            raise ValueError(f"form(s) {sorted(bad_forms)} need their effect in the model")
        if "window_history" in self.effects and "transfer_function" not in self.effects:
            raise ValueError(
                "window_history (letter -> extinction window) needs transfer_function in the model"
            )

    @property
    def method(self) -> str:
        return "tf-crds" if "transfer_function" in self.effects else "crds"

    @property
    def window(self) -> str | None:
        if self.method == "crds":
            return None
        return "extinction" if "window_history" in self.effects else "letter"

    @property
    def profile(self) -> str:
        sd, hc = "speed_dependence" in self.effects, "hard_collisions" in self.effects
        name = {
            (False, False): "voigt",
            (True, False): "sdvp",
            (False, True): "rautian",
            (True, True): "qsdhcp",
        }[(sd, hc)]
        for form in self.forms & set(PROFILE_FORMS):
            if PROFILE_FORMS[form][3] == name:
                return PROFILE_FORMS[form][2]
        return name

    @property
    def spectrum_extras(self) -> tuple:
        return tuple(e for e in ("etalon", "neighbour_line") if e in self.effects) + tuple(
            sorted(self.forms - set(PROFILE_FORMS))
        )

    def plus(self, effect, form=None) -> ExperimentModel:
        """The model with ``effect`` (in its family member ``form``) added.

        A line-shape member (power law, soft collisions) stands for its effect alone: with both
        speed dependence and narrowing in the model the profile is the qSDHCP.
        """
        effects = self.effects | {effect}
        forms = self.forms | ({form} if form else set())
        if {"speed_dependence", "hard_collisions"} <= effects:
            forms = forms - set(PROFILE_FORMS)
        return ExperimentModel(effects, forms)

    def label(self) -> str:
        return "+".join(
            [
                self.method,
                self.profile,
                *sorted(
                    self.effects
                    - {"transfer_function", "window_history", "speed_dependence", "hard_collisions"}
                ),
            ]
            + (["extinction-window"] if self.window == "extinction" else [])
            + sorted(self.forms)
        )


def parse_model(text: str | None) -> ExperimentModel:
    """``crds+voigt`` (the default) or a comma/plus separated list of canonical effect names."""
    if text is None:
        return ExperimentModel()
    items = [s.strip() for s in text.replace("+", ",").split(",") if s.strip()]
    items = [s for s in items if s not in ("crds", "voigt")]
    if "tf-crds" in items:
        items = [s for s in items if s != "tf-crds"] + ["transfer_function"]
    return ExperimentModel(frozenset(items))


@dataclass
class ModelState:
    """A model with its fitted shared parameters (transient extensions) and H calibration."""

    model: ExperimentModel
    shared: dict = field(default_factory=dict)
    shared_u: dict = field(default_factory=dict)
    calibration: object = None
    #: the line (LineAbsorption) a detuned second mode sees, as fitted when that mode was added
    line: object = None

    def spec(self) -> TransientSpec:
        tf = (
            self.calibration.params
            if (self.calibration is not None and self.model.method == "tf-crds")
            else None
        )
        return TransientSpec(
            self.model.method,
            self.model.window,
            tf,
            {k: v for k, v in self.shared.items() if k in self.model.effects},
            self.line,
        )


# --------------------------------------------------------------------------- comparison with data


@dataclass
class Evaluation:
    """Fits of every data block under one model state, and the gap metrics."""

    state: ModelState
    t_cuts: np.ndarray
    good: np.ndarray
    tau: np.ndarray  # (m_good, c)
    tau_u: np.ndarray
    block: dict  # name -> (chi2, n): the scoring blocks
    lines: list  # SpectrumFit per t_cut
    reference: object
    gaps: dict
    resid_first: np.ndarray  # normalised residual rows at t_cut[0]
    detuning: np.ndarray  # (m_good,) Hz
    beat: dict
    dt_s: float = 0.0
    coef_first: np.ndarray | None = None  # (m_good, k) linear parameters of the fits at t_cut[0]
    level: float | None = None  # the test level its gaps' bands are drawn at (calibrate_gaps)


def _z_from_chi2(chi2, dof):
    """Normal score of a chi2 with ``dof`` degrees of freedom (Wilson-Hilferty).

    (chi2/k)^(1/3) is close to normal with mean 1 - 2/(9k) and variance 2/(9k), so the score has
    the normal law's right tail where (chi2 - k)/sqrt(2k) has the chi2's heavier one (for k = 16,
    a spectrum of 21 points, the latter's z = 4 has p = 2e-3, not 3e-5). The bootstrap then
    calibrates location and scale only, which is all it can with its replicates. It grows without
    bound (as chi2^(1/3)), so large misfits stay ordered.
    """
    k = max(float(dof), 1.0)
    v = 2.0 / (9.0 * k)
    return float((np.cbrt(max(chi2, 0.0) / k) - (1.0 - v)) / np.sqrt(v))


def _z_two_sided(a):
    """One-sided normal score of |x|/u for a normal x/u: the same p as the two-sided test."""
    a = abs(float(a))
    return a if a > 30.0 else float(stats.norm.isf(2.0 * stats.norm.sf(a)))


def _z_from_p(p):
    return float(stats.norm.isf(np.clip(p, 1e-300, 1.0)))


def _region(det_hz, gd_hz):
    a = abs(det_hz)
    return f"detuning {det_hz / 1e6:+.0f} MHz ({'core' if a < 2 * gd_hz else 'wing'})"


def beat_block(config, state: ModelState):
    """Beat-note chi2 under the model: a flat |H| (no chain) or the fitted H."""
    tfd = config.transfer_function
    if tfd is None:
        return None
    y, u = np.asarray(tfd.h_mag, float), np.asarray(tfd.h_mag_u, float)
    if state.model.method == "tf-crds" and state.calibration is not None:
        b = state.calibration.beat
        r = b.residuals
        return {
            "chi2": float(b.chi2),
            "dof": int(b.dof),
            "n": int(y.size),
            "k": len(b.free) + 1,
            "resid": np.asarray(r),
            "f_hz": np.asarray(tfd.f_hz),
        }
    w = 1.0 / u**2
    k_hat = np.sum(w * y) / np.sum(w)
    r = (y - k_hat) / u
    return {
        "chi2": float(r @ r),
        "dof": int(y.size - 1),
        "n": int(y.size),
        "k": 1,
        "resid": r,
        "f_hz": np.asarray(tfd.f_hz),
    }


def fit_lines(bundle, config, model: ExperimentModel, nu, tau, tau_u):
    """CRDS line fit of 1/(c tau) (1/m) under the model's profile and extras."""
    gd = doppler_of(bundle.sample)
    a, ua = absorption_from_tau(tau, tau_u)
    return fit_spectrum_extended(
        "absorption", nu, a, ua, model.profile, gd, bundle.sample.nu0_hz, model.spectrum_extras
    )


_CMDS_CACHE: dict = {}


def _memo(cache: dict, key: tuple, owner, make):
    """``make()`` kept in ``cache`` under ``key``, whose first entry is ``id(owner)``.

    The entry holds ``owner`` itself, so an id reused by another object after ``owner`` is gone
    is recognised (the identity check) and never returns a stale result. The cache is emptied
    past 32 entries: a discovery touches a handful.
    """
    if key not in cache or cache[key][0] is not owner:
        if len(cache) > 32:
            cache.clear()
        cache[key] = (owner, make())
    return cache[key][1]


def fit_cmds(bundle, config, model: ExperimentModel, line):
    """CMDS reference A_ref under the same profile; a neighbour line found in CRDS is held fixed.

    Without a neighbour line the fit depends on the CMDS data, the profile and the sample alone,
    so it is made once per profile and reused: the bootstrap's 40 replicates change only the
    ring-downs (the CMDS reference is another instrument and is not resampled), and refitting
    the same spectrum took a quarter of a line-shape discovery.
    """
    if config.cmds is None:
        return None
    gd = doppler_of(bundle.sample)
    cm = config.cmds
    if "neighbour_line" in model.effects:
        extras = ("neighbour_line",)
        fixed = {
            "neighbour_offset_hz": line.value("neighbour_offset_hz"),
            "neighbour_ratio": line.value("neighbour_ratio"),
        }
        if "neighbour_width" in model.forms:
            extras += ("neighbour_width",)
            fixed["neighbour_width_scale"] = line.value("neighbour_width_scale")
        return _fit_cmds(cm, model.profile, gd, bundle.sample.nu0_hz, extras, fixed)
    key = (id(cm), model.profile, gd, bundle.sample.nu0_hz)
    return _memo(_CMDS_CACHE, key, cm, lambda: _fit_cmds(cm, model.profile, gd, key[3], (), {}))


def _fit_cmds(cm, profile, gd, nu0_hz, extras, fixed):
    return fit_spectrum_extended(
        "dispersion", cm.nu_hz, cm.shift_hz, cm.shift_u_hz, profile, gd, nu0_hz, extras, fixed=fixed
    )


def _transient_gaps(rd, res, first, spec, t_cuts, det, gd, m: int) -> tuple:
    """Transient residuals at the first t_cut (all rows start there, so they stack).

    Chi2, time structure (binned means) and frequency structure (periodogram peak). Returns (gaps,
    stacked normalised residuals).
    """
    gaps = {}
    n_lin = spec.n_row_params() + 1
    chi2_t = float(res.chi2[first].sum())
    n_t = int(res.n_used[first].sum())
    dof_t = n_t - m * n_lin - spec.n_shared()
    per_row_z = (res.chi2[first] - (res.n_used[first] - n_lin)) / np.sqrt(2 * res.n_used[first])
    i = int(np.argmax(per_row_z))
    gaps["transient_chi2"] = {
        "value": chi2_t / dof_t,
        "expected": 1.0,
        "spread": float(np.sqrt(2.0 / dof_t)),
        "z": _z_from_chi2(chi2_t, dof_t),
        "where": f"transients, t >= {t_cuts[0] * 1e6:g} us; worst at {_region(det[i], gd)}",
    }
    rn = res.resid_norm[first]
    j0 = int(np.argmax(np.any(rn != 0, axis=0)))
    rn = rn[:, j0:]
    tt = rd.time_s[j0:]
    edges = np.unique(np.geomspace(1, rn.shape[1], N_TIME_BINS + 1).astype(int)) - 1
    edges[-1] = rn.shape[1]
    s_bins = np.add.reduceat(rn, edges[:-1], axis=1) / np.sqrt(np.diff(edges))[None, :]
    tot = float((s_bins**2).sum())
    # each row's fit removes n_lin directions, which the bins resolve: nb - n_lin m degrees of
    # freedom
    nb = s_bins.size - n_lin * m
    worst = int(np.argmax((s_bins**2).sum(0)))
    gaps["transient_time_structure"] = {
        "value": tot / nb,
        "expected": 1.0,
        "spread": float(np.sqrt(2.0 / nb)),
        "z": _z_from_chi2(tot, nb),
        "where": f"transients, t in [{tt[edges[worst]] * 1e6:.2f}, "
        f"{tt[edges[worst + 1] - 1] * 1e6:.2f}] us (binned residual means, {N_TIME_BINS} "
        "log-spaced bins per transient)",
    }
    pw = np.abs(np.fft.rfft(rn, axis=1)[:, 1:]) ** 2 / rn.shape[1]
    f = np.fft.rfftfreq(rn.shape[1], rd.dt_s)[1:]
    summed = pw.sum(0)
    k = int(np.argmax(summed))
    # white unit noise: each periodogram ordinate ~ Exp(1), the sum over m rows ~ Gamma(m);
    # the largest of K ordinates: p = 1 - (1 - sf)^K
    sf = stats.gamma.sf(summed[k], m)
    p = -np.expm1(summed.size * np.log1p(-min(sf, 1 - 1e-16))) if sf > 0 else 0.0
    gaps["transient_freq_structure"] = {
        "value": float(summed[k] / m),
        "expected": 1.0,
        "spread": float(1 / np.sqrt(m)),
        "z": _z_from_p(p),
        "where": f"transients, periodogram peak at {f[k] / 1e6:.3g} MHz",
    }
    return gaps, rn


def _tcut_gaps(tau, tau_u, lines, t_cuts, det, gd, m: int) -> dict:
    """tau and A against t_cut (nested fits: var(x_last - x_first) = var_last - var_first)."""
    gaps = {}
    d = tau[:, -1] - tau[:, 0]
    ud = np.sqrt(np.maximum(tau_u[:, -1] ** 2 - tau_u[:, 0] ** 2, 1e-6 * tau_u[:, -1] ** 2))
    zt = d / ud
    i = int(np.argmax(np.abs(zt)))
    gaps["tau_tcut"] = {
        "value": float(np.median(d / tau[:, 0] / (t_cuts[-1] - t_cuts[0]))),
        "unit": "1/s",
        "expected": 0.0,
        "z": _z_from_chi2(float(zt @ zt), m),
        "where": f"tau({t_cuts[-1] * 1e6:g} us) - tau({t_cuts[0] * 1e6:g} us), largest at "
        f"{_region(det[i], gd)} ({zt[i]:+.1f} sigma)",
    }
    a0, a1 = lines[0].value("line_area"), lines[-1].value("line_area")
    u0, u1 = lines[0].stderr("line_area"), lines[-1].stderr("line_area")
    ua = np.sqrt(max(abs(u1**2 - u0**2), 1e-4 * u1**2))
    gaps["area_tcut"] = {
        "value": float((a1 - a0) / a0),
        "expected": 0.0,
        "z": _z_two_sided((a1 - a0) / ua),
        "where": f"A({t_cuts[-1] * 1e6:g} us)/A({t_cuts[0] * 1e6:g} us) - 1",
    }
    return gaps


def _spectrum_gaps(lf, det, gd, t_cuts) -> dict:
    """Spectrum residuals at the first t_cut: chi2 (core and wings) and the strongest sinusoid."""
    gaps = {}
    rz = lf.residuals_norm
    core = np.abs(det) < 2 * gd
    chi_core, chi_wing = float(rz[core] @ rz[core]), float(rz[~core] @ rz[~core])
    gaps["spectrum_chi2"] = {
        "value": lf.chi2 / lf.dof,
        "expected": 1.0,
        "spread": float(np.sqrt(2.0 / lf.dof)),
        "z": _z_from_chi2(lf.chi2, lf.dof),
        "where": f"spectrum at t_cut {t_cuts[0] * 1e6:g} us: chi2 core (|detuning| < "
        f"{2 * gd / 1e6:.0f} MHz) {chi_core:.1f} over {int(core.sum())} points, wings "
        f"{chi_wing:.1f} over {int((~core).sum())}",
    }
    from scipy.signal import lombscargle

    order = np.argsort(det)
    periods = np.geomspace(2.5 * np.median(np.diff(det[order])), np.ptp(det), 200)
    zz = rz - rz.mean()
    ls = lombscargle(det, zz, 2 * np.pi / periods) / max(float(zz @ zz) / zz.size, 1e-300)
    kk = int(np.argmax(ls))
    # normalised Lomb-Scargle power of white noise ~ Exp(1); about n/2 independent periods
    p_ls = -np.expm1((det.size / 2) * np.log1p(-min(np.exp(-ls[kk]), 1 - 1e-16)))
    gaps["spectrum_structure"] = {
        "value": float(ls[kk]),
        "expected": 1.0,
        "z": _z_from_p(p_ls),
        "where": f"spectrum residuals, strongest sinusoid period {periods[kk] / 1e9:.3g} GHz; "
        f"largest residual at {_region(det[int(np.argmax(np.abs(rz)))], gd)}",
    }
    return gaps


def _reference_gaps(beat, ref, line, t_cuts, u_h: float = 0.0) -> dict:
    """The beat note's chi2 and the CRDS-CMDS gap A/A_ref - 1 (``u_h``: u(A) from H, Hz/m)."""
    gaps = {}
    a0, u0 = line.value("line_area"), line.stderr("line_area")
    if beat is not None:
        gaps["beat_chi2"] = {
            "value": beat["chi2"] / beat["dof"],
            "expected": 1.0,
            "spread": float(np.sqrt(2.0 / beat["dof"])),
            "z": _z_from_chi2(beat["chi2"], beat["dof"]),
            "where": "beat note, largest residual at "
            f"{beat['f_hz'][int(np.argmax(np.abs(beat['resid'])))] / 1e6:.3g} MHz",
        }
    if ref is not None:
        ar, ur = ref.value("line_area"), ref.stderr("line_area")
        r = a0 / ar
        u = r * np.sqrt((u0 / a0) ** 2 + (ur / ar) ** 2 + (u_h / a0) ** 2)
        gaps["crds_cmds"] = {
            "value": float(r - 1),
            "u": float(u),
            "u_rel_from_h": float(u_h / a0),
            "expected": 0.0,
            "z": _z_two_sided((r - 1) / u),
            "where": f"A/A_ref - 1 at t_cut {t_cuts[0] * 1e6:g} us",
        }
    return gaps


def _h_covariance(cal) -> tuple[tuple, np.ndarray | None]:
    """H's joint covariance (:meth:`Calibration.covariance`), natural units; None without one.

    A calibration made without the refinement's gain (not by :func:`_calibration`), or whose
    joint covariance is not finite, has none.
    """
    try:
        names, cov = cal.covariance()
    except ValueError:
        return (), None
    return (names, cov) if np.all(np.isfinite(cov)) else ((), None)


def _marginal_u(cal) -> dict:
    """Each parameter's own u: the refinement's where it refined it, the beat note's otherwise."""
    u = {k: v for k, v in cal.beat.stderr.items() if k != "scale"}
    if cal.refined is not None:
        u.update(cal.refined.stderr)
    return {k: v for k, v in u.items() if np.isfinite(v) and v > 0}


H_EIGEN_FLOOR = 1e-12  # correlation eigenvalues below this fraction of the largest: no direction


def _h_directions(cal) -> tuple[tuple, list]:
    """(names, steps): one step per principal axis of H's covariance, 1 sigma long.

    In the refinement's parametrisation phi (log of the positive parameters, where the beat note
    and the refinement are linear): with Rho = V diag(lambda) V' the correlation of phi (sd s),
    the steps s * v_k sqrt(lambda_k) satisfy sum_k d_k d_k' = Cov(phi), so for an A linear in
    phi the squared half-differences along them sum to g' Cov g, correlations included. Without
    a joint covariance, each parameter alone by its own u (correlations neglected).
    """
    names, cov = _h_covariance(cal)
    if cov is None:
        u = _marginal_u(cal)
        names = tuple(u)
        jac = sample_jacobian(names, cal.params.as_vector(names))
        return names, [np.eye(len(names))[k] * u[n] / jac[k] for k, n in enumerate(names)]
    jac = sample_jacobian(names, cal.params.as_vector(names))
    cov = cov / np.outer(jac, jac)
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    keep = sd > 0
    names, cov, sd = tuple(n for n, k in zip(names, keep) if k), cov[np.ix_(keep, keep)], sd[keep]
    if not names:
        return (), []
    lam, vec = np.linalg.eigh(cov / np.outer(sd, sd))
    ok = lam > H_EIGEN_FLOOR * lam.max()
    return names, [sd * vec[:, k] * np.sqrt(lam[k]) for k in np.nonzero(ok)[0]]


def _stepped(params, names, step):
    """``params`` moved by ``step`` in the sampled parametrisation, or None outside H's domain."""
    try:
        phi = to_sample(names, params.as_vector(names)) + step
        tf = params.with_vector(from_sample(names, phi), names)
    except ValueError:
        return None
    return None if outside_support(tf, names) else tf


def h_area_uncertainty(
    bundle, config, state: ModelState, t_cut_s, good, tau_start, area_hz_per_m: float
) -> float:
    """u(A) (Hz/m) from H's uncertainty: A refitted with H at +/- 1 sigma along its principal axes.

    The axes are those of H's joint covariance (:meth:`Calibration.covariance`, its gain on the
    held parameters made by refits: :func:`refit_gain`).
    The refined f_c follows the resonance the beat note states (|rho| up to 1): moving each
    parameter alone by its marginal u, correlations neglected, over-stated this part 1.25-8x on
    letter and zoo chains. A side outside H's domain leaves the one-sided difference from
    ``area_hz_per_m`` (A at the state's H). 0 without a transfer function in the model.
    Without it, A/A_ref - 1 is judged against the fits' noise alone (3.6e-5 and 8.3e-5 relative
    on a reduced D2 campaign) while H's f_c alone moves A by 1.4e-4.
    """
    cal = state.calibration
    if state.model.method != "tf-crds" or cal is None:
        return 0.0
    names, steps = _h_directions(cal)
    rd = config.ringdowns
    nu = np.asarray(rd.nu_hz, float)[good]
    tc = np.full(good.size, float(t_cut_s))
    var = 0.0
    for step in steps:
        areas = []
        for sign in (-1.0, 1.0):
            tf = _stepped(cal.params, names, sign * step)
            if tf is None:  # outside H's physical domain: the other side alone
                continue
            spec = replace(state.spec(), tf=tf)
            res = fit_transient_rows(rd, tc, good, spec, tau_start)
            lf = fit_lines(bundle, config, state.model, nu, res.tau_s, res.tau_u_s)
            areas.append(lf.value("line_area"))
        if len(areas) == 2:
            var += ((areas[1] - areas[0]) / 2) ** 2
        elif areas:
            var += (areas[0] - area_hz_per_m) ** 2
    return float(np.sqrt(var))


def evaluate(
    bundle,
    config,
    state: ModelState,
    t_cuts=DISCOVERY_T_CUTS,
    tau_start=None,
    h_uncertainty: bool = True,
) -> Evaluation:
    """Fit every block of ``config`` under ``state`` and compute the gap metrics.

    ``h_uncertainty`` adds H's uncertainty to that of A/A_ref - 1 (a few more fits; the
    bootstrap, which does not resample that gap, leaves it out).
    """
    rd = config.ringdowns
    t_cuts = np.asarray(t_cuts, float)
    good = np.nonzero(~np.asarray(rd.clipped))[0]
    m, c = good.size, t_cuts.size
    rows_of = np.repeat(good, c)
    tcr = np.tile(t_cuts, m)
    spec = state.spec()
    res = fit_transient_rows(
        rd, tcr, rows_of, spec, None if tau_start is None else np.repeat(tau_start, c)
    )
    tau = res.tau_s.reshape(m, c)
    tau_u = res.tau_u_s.reshape(m, c)
    first = np.arange(m) * c
    chi2_t = float(res.chi2[first].sum())
    n_t = int(res.n_used[first].sum())
    gd = doppler_of(bundle.sample)
    nu = np.asarray(rd.nu_hz, float)[good]
    det = nu - bundle.sample.nu0_hz
    lines = [fit_lines(bundle, config, state.model, nu, tau[:, j], tau_u[:, j]) for j in range(c)]
    ref = fit_cmds(bundle, config, state.model, lines[0])
    beat = beat_block(config, state)
    gaps, rn = _transient_gaps(rd, res, first, spec, t_cuts, det, gd, m)
    gaps.update(_tcut_gaps(tau, tau_u, lines, t_cuts, det, gd, m))
    lf = lines[0]
    gaps.update(_spectrum_gaps(lf, det, gd, t_cuts))
    u_h = (
        h_area_uncertainty(
            bundle, config, state, t_cuts[0], good, tau[:, 0], lines[0].value("line_area")
        )
        if (h_uncertainty and ref is not None)
        else 0.0
    )
    gaps.update(_reference_gaps(beat, ref, lf, t_cuts, u_h))
    block = {"transients": (chi2_t, n_t), "spectrum": (lf.chi2, lf.n)}
    if beat is not None:
        block["beat"] = (beat["chi2"], beat["n"])
    return Evaluation(
        state=state,
        t_cuts=t_cuts,
        good=good,
        tau=tau,
        tau_u=tau_u,
        block=block,
        lines=lines,
        reference=ref,
        gaps=gaps,
        resid_first=rn,
        detuning=det,
        beat=beat,
        dt_s=float(rd.dt_s),
        coef_first=res.coef[first],
    )


# --------------------------------------------------------------------------- candidates


@dataclass
class Candidate:
    effect: str
    evidence: float
    delta_chi2: float
    k: int
    n: int
    block: str
    params: dict  # name -> (value, u, unit)
    state: ModelState | None
    note: str = ""
    explained: float | None = None  # fraction of its blocks' open misfit removed, when tried
    tried: bool = False  # evaluated by _choose (explained is None also when nothing was open)
    worsens: tuple = ()  # gaps of the CMDS or beat note its model leaves open and worse, when tried


def _fail(effect, note):
    return Candidate(effect, -np.inf, 0.0, 0, 0, "", {}, None, note)


_CAL_CACHE: dict = {}


def _calibration(config, window, t_cuts):
    """H calibration (beat note + refinement of f_c with ``window``), cached per configuration.

    Always with the refinement's gain on the beat-note parameters (the joint covariance of H
    that u_H(A) and the bootstrap's H draws need), so the key does not hold it.
    """
    key = (id(config), window, tuple(t_cuts))

    def make():
        # on a flat beat note (no chain) the refinement's scaling divides 0/0 before it fails;
        # the failure itself is reported by the caller, the warnings would only be noise
        with np.errstate(invalid="ignore", divide="ignore"):
            return calibrate(config, t_cuts_s=tuple(t_cuts), window=window, sensitivities=True)

    return _memo(_CAL_CACHE, key, config, make)


def _try_transient_effect(bundle, config, ev: Evaluation, effect, with_cov: bool) -> Candidate:
    """A transient-level effect, scored on the transient block.

    Its shared parameters are fitted over every transient at the first t_cut; a second mode may
    see the line as the evaluation fitted it (its detuned member).
    """
    st = ev.state
    model = st.model
    rd = config.ringdowns
    m = ev.good.size
    tc0 = np.full(m, ev.t_cuts[0])
    chi2_t, n_t = ev.block["transients"]
    base = st.spec()
    if effect == "second_mode" and ev.lines:
        line = LineAbsorption(ev.lines[0], doppler_of(bundle.sample), bundle.sample.nu0_hz)
        base = replace(base, line=line)
    try:
        fam = fit_family(
            effect, rd, tc0, ev.good, base, ev.tau[:, 0], ev.resid_first, chi2_t, with_cov
        )
    except (np.linalg.LinAlgError, ValueError, FloatingPointError) as exc:
        return _fail(effect, f"fit failed: {exc}")
    # the family's chosen member (its order by BIC inside the family), every parameter charged
    params, res, cov, k = fam.params, fam.result, fam.cov, fam.k
    dchi2 = chi2_t - float(res.chi2.sum())
    units = {s[0]: s[1] for s in family_member(effect, fam.form)[2]}
    pu = {}
    for i, (name, v) in enumerate(params.items()):
        u = float(np.sqrt(cov[i, i])) if cov is not None else float("nan")
        pu[name] = (v, u, units[name])
    new = ModelState(
        model.plus(effect),
        {**st.shared, effect: params},
        {**st.shared_u, effect: {n: pu[n][1] for n in pu}},
        st.calibration,
        base.line if "detuning_hz" in params else st.line,
    )
    return Candidate(
        effect,
        dchi2 - k * np.log(n_t),
        dchi2,
        k,
        n_t,
        "transients",
        pu,
        new,
        f"form: {fam.label} (BIC among "
        + ", ".join(f"{f}: {c + kk * np.log(fam.n):.1f}" for f, c, kk in fam.scores)
        + ")"
        + ("; per-transient beating amplitudes counted" if effect == "mode_beating" else ""),
    )


def _try_chain_effect(config, ev: Evaluation, effect, t_cuts) -> Candidate:
    """H (transfer_function) or the extinction window (window_history).

    A new calibration, the transients refitted, scored on the transients (and the beat note for
    H).
    """
    st = ev.state
    model = st.model
    rd = config.ringdowns
    tc0 = np.full(ev.good.size, ev.t_cuts[0])
    chi2_t, n_t = ev.block["transients"]
    if effect == "window_history" and "transfer_function" not in model.effects:
        return _fail(effect, "needs transfer_function in the model")
    new_model = model.plus(effect)
    try:
        cal = _calibration(config, new_model.window, t_cuts)
    except (AnalysisError, RuntimeError, ValueError) as exc:
        return _fail(effect, f"calibration failed: {exc}")
    new = ModelState(new_model, dict(st.shared), dict(st.shared_u), cal, st.line)
    if effect == "transfer_function":
        b_old, b_new = ev.beat, beat_block(config, new)
        if b_old is None or b_new is None:
            return _fail(effect, "no beat-note measurement")
        ev_beat = b_old["chi2"] - b_new["chi2"] - (b_new["k"] - b_old["k"]) * np.log(b_new["n"])
        if ev_beat < 0:
            # the beat note measures H directly (0.15 % noise): if it does not prefer a chain
            # over a flat response, an H fitted to it is noise, and its extinction grid can be
            # arbitrarily long; the transients are not refitted with it
            return Candidate(
                effect,
                ev_beat,
                b_old["chi2"] - b_new["chi2"],
                b_new["k"] - b_old["k"],
                b_new["n"],
                "beat",
                {},
                None,
                "the beat note prefers a flat |H| (beat-note block only)",
            )
    try:
        res = fit_transient_rows(rd, tc0, ev.good, new.spec(), ev.tau[:, 0])
    except (ValueError, np.linalg.LinAlgError) as exc:
        return _fail(effect, f"fit failed: {exc}")
    dchi2 = chi2_t - float(res.chi2.sum())
    n = n_t
    k = 0
    pu = {}
    if effect == "transfer_function":
        b_old = ev.beat
        b_new = beat_block(config, new)
        if b_old is None or b_new is None:
            return _fail(effect, "no beat-note measurement")
        dchi2 += b_old["chi2"] - b_new["chi2"]
        n += b_new["n"]
        k = b_new["k"] - b_old["k"]
        p = cal.params
        su = cal.beat.stderr
        for name in ("f_c_hz", "a_r", "f_r_hz", "gamma_r"):
            u = su.get(name, float("nan"))
            if cal.refined is not None and name in cal.refined.stderr:
                u = cal.refined.stderr[name]
            pu[name] = (getattr(p, name), float(u), "Hz" if name.endswith("_hz") else "1")
    return Candidate(
        effect,
        dchi2 - k * np.log(n),
        dchi2,
        k,
        n,
        "transients" + ("+beat" if k else ""),
        pu,
        new,
        "H from the beat note, f_c refined on ring-downs",
    )


def _try_spectrum_effect(bundle, config, ev: Evaluation, effect) -> Candidate:
    """A spectrum-level effect: the line refitted with it, scored on the spectrum block."""
    st = ev.state
    model = st.model
    rd = config.ringdowns
    new_model = model.plus(effect)
    lf_old = ev.lines[0]
    nu = np.asarray(rd.nu_hz, float)[ev.good]
    note = ""
    profile_family = effect in PROFILE_DEFAULT_LABEL and new_model.profile in ("sdvp", "rautian")
    try:
        if effect in SPECTRUM_DEFAULT_LABEL or profile_family:
            # a family: etalon, neighbour_line, or a line-shape effect alone in the model; the
            # member with the lowest BIC on the spectrum
            a, ua = absorption_from_tau(ev.tau[:, 0], ev.tau_u[:, 0])
            gd, nu0 = doppler_of(bundle.sample), bundle.sample.nu0_hz
            if profile_family:
                fam = fit_profile_family(
                    effect, nu, a, ua, new_model.profile, gd, nu0, new_model.spectrum_extras, lf_old
                )
            else:
                fam = fit_spectrum_family(
                    effect, nu, a, ua, model.profile, gd, nu0, model.spectrum_extras, lf_old.chi2
                )
            lf, new_model = fam.fit, model.plus(effect, fam.form)
            note = f"form: {fam.label} (BIC among " + ", ".join(
                f"{lab}: {c + kk * np.log(lf.n):.1f}" for lab, c, kk in fam.scores
            )
            note += ")"
        else:
            lf = fit_lines(bundle, config, new_model, nu, ev.tau[:, 0], ev.tau_u[:, 0])
    except (ValueError, np.linalg.LinAlgError) as exc:
        return _fail(effect, f"fit failed: {exc}")
    dchi2 = lf_old.chi2 - lf.chi2
    k = lf.k - lf_old.k
    new_names = [n for n in lf.names if n not in lf_old.names]
    units = {
        "gamma2_hz": "Hz",
        "nu_vc_hz": "Hz",
        "etalon_amplitude_per_m": "1/m",
        "etalon_period_hz": "Hz",
        "etalon_phase_rad": "rad",
        "neighbour_offset_hz": "Hz",
        "neighbour_ratio": "1",
        "etalon2_amplitude_per_m": "1/m",
        "etalon2_phase_rad": "rad",
        "neighbour_width_scale": "1",
        "sd_exponent": "1",
        "delta_sd_hz": "Hz",
    }
    pu = {n: (lf.value(n), lf.stderr(n), units.get(n, "")) for n in new_names}
    new = ModelState(new_model, dict(st.shared), dict(st.shared_u), st.calibration, st.line)
    return Candidate(effect, dchi2 - k * np.log(lf.n), dchi2, k, lf.n, "spectrum", pu, new, note)


def try_candidate(
    bundle, config, ev: Evaluation, effect, t_cuts=DISCOVERY_T_CUTS, with_cov: bool = False
) -> Candidate:
    """Fit one extension on top of the evaluated state and score it (Delta BIC on its block).

    The shared parameters' covariance (curvature of the profiled chi2, a dozen more fits) is
    computed only with ``with_cov``: discovery asks for it for the effect it adds.
    """
    if effect in TRANSIENT_LEVEL:
        return _try_transient_effect(bundle, config, ev, effect, with_cov)
    if effect in ("transfer_function", "window_history"):
        return _try_chain_effect(config, ev, effect, t_cuts)
    return _try_spectrum_effect(bundle, config, ev, effect)


# --------------------------------------------------------------------------- the loop


@dataclass
class DiscoveryResult:
    """The effects discovery added to the start model, step by step, and the gaps it left."""

    config: str
    start: ExperimentModel
    steps: list
    effects_added: list
    evaluations: list
    candidates: list  # per round: list of Candidate
    threshold: float
    seconds: float
    noise: object = None  # NoiseDiagnosis of the ring-downs at the start (fit.noise), or None
    alpha: float = DEFAULT_ALPHA
    n_boot: int = N_BOOT
    stop_reason: str = ""
    unexplained: list = field(default_factory=list)  # open gaps at the stop: gap, z_cal, where

    def summary(self) -> str:
        """Plain text: the steps (effect, evidence, fitted parameters with units), final gaps."""
        from bayes_tfcrds.discovery.views import discovery_text

        return discovery_text(self)

    def to_dict(self) -> dict:
        """The JSON record of ``discovery.json`` (same as :meth:`to_json`)."""
        return self.to_json()

    def _repr_html_(self) -> str:
        from bayes_tfcrds.discovery.views import discovery_html

        return discovery_html(self)

    def plot(self, ax=None):
        """|z| of every gap after each step (the gaps shrinking); a matplotlib Figure."""
        from bayes_tfcrds.discovery.views import plot_discovery

        return plot_discovery(self, ax)

    def to_json(self) -> dict:
        """The ``discovery.json`` record."""

        def gaps(g):
            return {
                k: {
                    kk: (
                        float(vv)
                        if isinstance(vv, (int, float, np.floating)) and not isinstance(vv, bool)
                        else vv
                    )
                    for kk, vv in v.items()
                }
                for k, v in g.items()
            }

        rounds = []
        for cands in self.candidates:
            rounds.append(
                [
                    {
                        "effect": c.effect,
                        "evidence": _finite(c.evidence),
                        "delta_chi2": _finite(c.delta_chi2),
                        "k": c.k,
                        "n": c.n,
                        "block": c.block,
                        "note": c.note,
                        "explained_fraction": c.explained,
                        "worsens": list(c.worsens),
                    }
                    for c in cands
                ]
            )
        return {
            "config": self.config,
            "start": sorted(self.start.effects),
            "start_label": self.start.label(),
            "final_label": self.evaluations[-1].state.model.label(),
            "threshold_delta_bic": self.threshold,
            "alpha": self.alpha,
            "n_boot": self.n_boot,
            "stop_reason": self.stop_reason,
            "unexplained": self.unexplained,
            "steps": [
                {**s, "gaps_before": gaps(s["gaps_before"]), "gaps_after": gaps(s["gaps_after"])}
                for s in self.steps
            ],
            "effects_added": list(self.effects_added),
            "final_gaps": gaps(self.evaluations[-1].gaps),
            "candidates_per_round": rounds,
            "seconds": self.seconds,
            "noise": None if self.noise is None else self.noise.to_dict(),
        }


def _finite(x):
    return float(x) if np.isfinite(x) else None


def _start_state(bundle, config, start, t_cuts) -> ModelState:
    """The declared start model, its calibration, its transient extensions fitted on the data."""
    model = start if isinstance(start, ExperimentModel) else parse_model(start)
    state = ModelState(model)
    if model.method == "tf-crds":
        state.calibration = _calibration(config, model.window, t_cuts)
    for eff in model.effects & set(TRANSIENT_LEVEL):
        # a declared transient extension starts with its parameters fitted on the data
        ev0 = evaluate(
            bundle,
            config,
            ModelState(
                ExperimentModel(model.effects - {eff}),
                dict(state.shared),
                {},
                state.calibration,
                state.line,
            ),
            t_cuts,
        )
        c = try_candidate(bundle, config, ev0, eff, t_cuts, with_cov=True)
        state.shared[eff] = {k: v[0] for k, v in c.params.items()}
        state.shared_u[eff] = {k: v[1] for k, v in c.params.items()}
        if c.state is not None and c.state.line is not None:
            state.line = c.state.line  # a detuned second mode keeps the line it was fitted on
    return state


def _add_shared_uncertainty(config, ev: Evaluation, best: Candidate) -> None:
    """The chosen transient effect's parameter uncertainties (profiled chi2 curvature)."""
    if best.effect not in TRANSIENT_LEVEL:
        return
    cov = shared_covariance(
        best.effect,
        config.ringdowns,
        np.full(ev.good.size, ev.t_cuts[0]),
        ev.good,
        replace(ev.state.spec(), line=best.state.line),
        {k: v[0] for k, v in best.params.items()},
        ev.tau[:, 0],
    )
    for i, k in enumerate(best.params):
        u = float(np.sqrt(cov[i, i])) if cov is not None else float("nan")
        best.params[k] = (best.params[k][0], u, best.params[k][2])
    best.state.shared_u[best.effect] = {k: v[1] for k, v in best.params.items()}


def _form_label(cand: Candidate) -> str:
    """The member of the candidate's family that was chosen ("2 exponentials"), "" if none."""
    if cand.state is None:
        return ""
    if cand.effect in TRANSIENT_LEVEL:
        params = cand.state.shared.get(cand.effect, {})
        return family_member(cand.effect, form_of(cand.effect, params))[1] if params else ""
    if cand.effect in SPECTRUM_DEFAULT_LABEL:
        forms = [
            f for f in cand.state.model.forms if SPECTRUM_FORMS.get(f, ("",))[0] == cand.effect
        ]
        return SPECTRUM_FORMS[forms[0]][1] if forms else SPECTRUM_DEFAULT_LABEL[cand.effect]
    if cand.effect in PROFILE_DEFAULT_LABEL:
        forms = [f for f in cand.state.model.forms if PROFILE_FORMS.get(f, ("",))[0] == cand.effect]
        return PROFILE_FORMS[forms[0]][1] if forms else PROFILE_DEFAULT_LABEL[cand.effect]
    return ""


def _step_record(best: Candidate, runner, ev: Evaluation, new_ev: Evaluation) -> dict:
    """One step of ``discovery.json``: the effect added, its evidence, the gaps before and after."""
    return {
        "effect": best.effect,
        "evidence": float(best.evidence),
        "delta_chi2": float(best.delta_chi2),
        "k": best.k,
        "n": best.n,
        "block": best.block,
        "form": _form_label(best),
        "note": best.note,
        "params": {k: {"value": v[0], "u": v[1], "unit": v[2]} for k, v in best.params.items()},
        "runner_up": None
        if runner is None
        else {"effect": runner.effect, "evidence": _finite(runner.evidence)},
        "gaps_before": ev.gaps,
        "gaps_after": new_ev.gaps,
    }


def discover(
    bundle,
    config_name,
    start: ExperimentModel | str | None = None,
    t_cuts=DISCOVERY_T_CUTS,
    threshold: float = DEFAULT_THRESHOLD,
    max_steps: int = 6,
    progress=None,
    rng: np.random.Generator | None = None,
    alpha: float = DEFAULT_ALPHA,
    n_boot: int = N_BOOT,
) -> DiscoveryResult:
    """Forward selection of missing effects on one configuration (see the module doc).

    Parameters
    ----------
    bundle : Bundle
        The measurement.
    config_name : str
        The configuration's name (``"D2"``).
    start : ExperimentModel or str, optional
        The declared model (default ``crds+voigt``; e.g. ``"transfer_function,speed_dependence"``).
    t_cuts : sequence of float
        Truncation times (s) the gaps are measured at.
    threshold : float
        Delta BIC a candidate needs on its data block to be considered.
    max_steps : int
        At most this many effects are added.
    progress : callable, optional
        Receives one line of text per candidate and step.
    rng : numpy.random.Generator, optional
        Draws the bootstrap nulls of the gap metrics (default ``default_rng(0)``: the same data
        give the same result).
    alpha : float
        Family-wise probability of adding any effect to a model that already describes the data
        (spent as alpha/2, alpha/4, ... over the steps).
    n_boot : int
        Bootstrap replicates per model state.

    Returns
    -------
    DiscoveryResult
        The effects added with their evidence and parameters, the gaps before and after with their
        null bands, why discovery stopped and what it left unexplained; ``summary()``,
        ``to_dict()``, ``plot()``.
    """
    t0 = time.perf_counter()
    say = progress or (lambda s: None)
    if config_name not in bundle.configs:
        raise ValueError(
            f"no configuration {config_name!r} in the bundle (it has {list(bundle.configs)})"
        )
    if not (0.0 < alpha < 1.0) or n_boot < 10:
        raise ValueError(f"alpha must be in (0, 1) and n_boot >= 10, got {alpha} and {n_boot}")
    config = bundle.configs[config_name]
    rng = np.random.default_rng(0) if rng is None else rng
    noise = _noise_diagnosis(config)
    if noise is not None:
        say(noise.summary_line())
    null = _NullSettings(rng, n_boot, pre_extinction_noise(config.ringdowns), alpha)
    state = _start_state(bundle, config, start, t_cuts)
    model = state.model
    ev = evaluate(bundle, config, state, t_cuts)
    calibrate_gaps(bundle, config, ev, null, step_alpha(alpha, 1))
    say(f"start {model.label()}: {_gap_line(ev)}")
    loop = _select(bundle, config, ev, null, t_cuts, threshold, max_steps, say)
    return DiscoveryResult(
        config=config_name,
        start=model,
        steps=loop["steps"],
        effects_added=loop["added"],
        evaluations=loop["evaluations"],
        candidates=loop["rounds"],
        threshold=threshold,
        seconds=time.perf_counter() - t0,
        noise=noise,
        alpha=alpha,
        n_boot=n_boot,
        stop_reason=loop["stop"],
        unexplained=loop["unexplained"],
    )


@dataclass(frozen=True)
class _NullSettings:
    rng: np.random.Generator
    n_boot: int
    noise: object  # nulls.NoiseModel
    alpha: float


def step_alpha(alpha: float, step: int) -> float:
    """The level of step ``step`` (1, 2, ...): alpha/2^step, so the levels sum to at most alpha."""
    return alpha / 2.0**step


def calibrate_gaps(bundle, config, ev: Evaluation, null: _NullSettings, level: float) -> None:
    """Add each gap's bootstrap null to ``ev``: z_cal, p, band, open (Bonferroni at ``level``)."""
    nulls = gap_nulls(bundle, config, ev, evaluate, null.rng, null.n_boot, null.noise)
    p_gap = level / len(nulls)
    for name, g in nulls.items():
        lo, hi = g.band(p_gap)
        ev.gaps[name].update(
            z_cal=float(g.z_cal),
            p=float(g.p_value()),
            band=[float(lo), float(hi)],
            open=bool(g.p_value() < p_gap),
            null="bootstrap" if g.resampled else "analytic",
            null_n=g.n,
        )
    ev.level = level


def open_gaps(ev: Evaluation, level: float | None = None) -> list:
    """Names of the gaps outside their null band (p below ``level`` / number of gaps)."""
    p_gap = (ev.level if level is None else level) / len(ev.gaps)
    return [k for k, g in ev.gaps.items() if g.get("p", 1.0) < p_gap]


def block_excess(ev: Evaluation, blocks: set, level: float) -> float:
    """Sum of z_cal^2 over the open gaps of the data ``blocks`` (the misfit left to explain)."""
    return float(
        sum(ev.gaps[k]["z_cal"] ** 2 for k in open_gaps(ev, level) if GAP_BLOCK[k] in blocks)
    )


def _gap_line(ev: Evaluation) -> str:
    return ", ".join(
        f"{k} z={v['z']:.1f}" + (" OPEN" if v.get("open") else "") for k, v in ev.gaps.items()
    )


def _explains(bundle, config, ev, cand: Candidate, null, t_cuts, level, next_level):
    """The candidate's model, evaluated and calibrated, and the share of misfit it removes.

    The share is of the open misfit of the candidate's data blocks (None if nothing there is open).
    """
    _add_shared_uncertainty(config, ev, cand)
    new_ev = evaluate(bundle, config, cand.state, t_cuts, tau_start=ev.tau[:, 0])
    calibrate_gaps(bundle, config, new_ev, null, next_level)
    blocks = set(cand.block.split("+"))
    before = block_excess(ev, blocks, level)
    if before <= 0.0:
        return new_ev, None
    return new_ev, 1.0 - block_excess(new_ev, blocks, level) / before


def _unexplained(ev: Evaluation) -> list:
    return [
        {"gap": k, "z_cal": ev.gaps[k]["z_cal"], "where": ev.gaps[k]["where"]}
        for k in open_gaps(ev)
    ]


def _select(bundle, config, ev, null, t_cuts, threshold, max_steps, say) -> dict:
    """The selection loop; stops at the first round that adds nothing, and says why.

    While a gap is open, one candidate with evidence is added (:func:`_choose`).
    """
    out = {"steps": [], "added": [], "evaluations": [ev], "rounds": [], "unexplained": []}
    out["stop"] = f"max_steps ({max_steps}) reached"
    for step in range(1, max_steps + 1):
        level = step_alpha(null.alpha, step)
        if not open_gaps(ev):
            out["stop"] = f"every gap inside its null band (level {level:.3g}, Bonferroni)"
            break
        cands = _round(bundle, config, ev, t_cuts, say)
        out["rounds"].append(cands)
        passing = [c for c in cands if np.isfinite(c.evidence) and c.evidence >= threshold]
        chosen = _choose(bundle, config, ev, passing, null, t_cuts, step, say)
        if chosen is None:
            out["unexplained"] = _unexplained(ev)
            out["stop"] = _stop_reason(passing, threshold)
            say(out["stop"])
            break
        best, new_ev = chosen
        runner = next((c for c in cands if c is not best), None)
        alternatives = indistinguishable(best, passing)
        out["steps"].append(
            {
                **_step_record(best, runner, ev, new_ev),
                "level": level,
                "explained_fraction": best.explained,
                "alternatives": alternatives,
            }
        )
        out["added"].append(best.effect)
        say(f"added {best.effect} (evidence {best.evidence:.1f}): {_gap_line(new_ev)}")
        if alternatives:
            say(
                "  the data do not tell it from "
                + ", ".join(f"{a['effect']} (evidence {a['evidence']:.1f})" for a in alternatives)
            )
        ev = new_ev
        out["evaluations"].append(ev)
    return out


def indistinguishable(best: Candidate, passing: list) -> list:
    """Candidates of ``best``'s data block whose evidence is within :data:`AMBIGUITY_BIC` of its.

    Each as {effect, form, evidence}: the step names them beside the effect it adds, which is
    the one whose model left the least misfit (the data cannot tell them apart). A candidate
    tried and not accepted (it explained too little of the open misfit) is not one.
    """
    return [
        {"effect": c.effect, "form": _form_label(c), "evidence": float(c.evidence)}
        for c in passing
        if c is not best
        and c.block == best.block
        and abs(c.evidence - best.evidence) < AMBIGUITY_BIC
        and (not c.tried or _accepted(c))
    ]


def worsened_gaps(before: Evaluation, after: Evaluation, block: str) -> list:
    """Gaps of the independent measurements that the candidate's model leaves open and worse.

    Independent measurements (:data:`INDEPENDENT_BLOCKS`): the CMDS reference and the beat note,
    which no ring-down effect changes; worse: calibrated z up by more than
    :data:`WORSEN_MARGIN`. Reported beside each candidate, not a veto: an effect that needs a
    second one (H before its extinction window) moves A away from CMDS for a step, and the
    choice by the misfit left in all the data (:func:`_choose`) already counts it.
    """
    blocks = set(block.split("+"))
    out = []
    for k, g in after.gaps.items():
        if GAP_BLOCK[k] not in INDEPENDENT_BLOCKS or GAP_BLOCK[k] in blocks:
            continue
        if not g.get("open") or k not in before.gaps:
            continue
        b = before.gaps[k]
        if g["z_cal"] > b.get("z_cal", b["z"]) + WORSEN_MARGIN:
            out.append(k)
    return out


def _accepted(c: Candidate) -> bool:
    return c.explained is not None and c.explained >= EXPLAIN_FRACTION


def _worse(c: Candidate) -> str:
    return f"; worsens {', '.join(c.worsens)}" if c.worsens else ""


def total_misfit(ev: Evaluation) -> float:
    """Sum over every gap of max(z_cal, 0)^2: the misfit a model leaves in all the data."""
    return float(sum(max(g.get("z_cal", g["z"]), 0.0) ** 2 for g in ev.gaps.values()))


def _choose(bundle, config, ev, passing, null, t_cuts, step, say):
    """The candidate to add this round and its evaluated model, or None.

    The candidates with evidence are tried in order of evidence (at most :data:`MAX_TRIES`); of
    those accepted (:func:`_accepted`), the one that leaves the least misfit in all the data
    (:func:`total_misfit`) is added. Evidence is measured on a candidate's own block, and a term
    that describes the transients alone can outscore the effect that also explains an
    independent measurement: a damped beat fits a slow resonant path of the detector as well as
    H does, but only H also fits the beat note. Trying stops at the first candidate whose model
    leaves every gap inside its band.
    """
    level, next_level = step_alpha(null.alpha, step), step_alpha(null.alpha, step + 1)
    accepted = []
    for c in passing[:MAX_TRIES]:
        new_ev, frac = _explains(bundle, config, ev, c, null, t_cuts, level, next_level)
        c.explained, c.tried = frac, True
        c.worsens = tuple(worsened_gaps(ev, new_ev, c.block))
        misfit = total_misfit(new_ev)
        say(
            f"  {c.effect}: explains {_pct(frac)} of the open misfit of its block{_worse(c)}; "
            f"misfit left in all the data {misfit:.1f}"
        )
        if _accepted(c):
            accepted.append((misfit, c, new_ev))
            if not open_gaps(new_ev):
                break
    if not accepted:
        return None
    best = min(accepted, key=lambda a: a[0])
    return best[1], best[2]


def _pct(frac):
    return "nothing (no open gap there)" if frac is None else f"{100 * frac:.0f} %"


def _stop_reason(passing, threshold) -> str:
    if not passing:
        return f"unexplained structure: gaps open, no candidate reaches Delta BIC {threshold:g}"
    names = ", ".join(f"{c.effect} ({_pct(c.explained)}{_worse(c)})" for c in passing[:MAX_TRIES])
    return (
        "unexplained structure: gaps open, and the candidates with evidence explain less than "
        f"{100 * EXPLAIN_FRACTION:.0f} % of the misfit of their block: {names}"
    )


def _round(bundle, config, ev, t_cuts, say) -> list:
    """Every candidate not yet in the model, tried and sorted by evidence (best first)."""
    cands = []
    for eff in CANDIDATES:
        if eff in ev.state.model.effects:
            continue
        c = try_candidate(bundle, config, ev, eff, t_cuts)
        cands.append(c)
        say(f"  {eff:20s} evidence {c.evidence:12.1f} (dchi2 {c.delta_chi2:.1f}, k {c.k}) {c.note}")
    cands.sort(key=lambda c: -c.evidence if np.isfinite(c.evidence) else np.inf)
    return cands


def _noise_diagnosis(config):
    """Whiteness of the ring-down residuals (TF-CRDS at the beat-note H): a flag, never applied.

    Coloured noise makes every slow effect's chi2 gain about kappa times too large; structure an
    effect leaves in the transients looks the same to the test, so discovery reports it beside its
    gaps and leaves the evidence as it is. None where the diagnosis cannot run.
    """
    try:
        with np.errstate(invalid="ignore", divide="ignore"):
            return account_for_noise_colour(config, confirm=False)[1]
    except (AnalysisError, ValueError, RuntimeError, np.linalg.LinAlgError):
        return None
