"""Model extensions: the analysis model with one instrument effect switched on.

Transient-level and spectrum-level fitters. The discovery workflow selects among them; the budget
uses the static nonlinearity, the spectral baseline slope and the etalon to size its instrument
rows from the data.

Each canonical effect of :mod:`bayes_tfcrds.simulate` has a fitter here that adds its physics to
the analysis model, with its own parameters (charged for by the discovery's evidence):

Transient level (model ``y = b + B g(t; tau, shared) + per-transient extra columns``; b, B and
the extra amplitudes are solved exactly per transient, tau by a batched Gauss-Newton with the
linear parameters projected out, and the *shared* parameters, one set per configuration, by a
small optimisation of the total chi2):

* ``static_nonlinearity``: shared beta; the data are mapped back through V' = V + beta V^2/V_ref
  (V_ref = 1 V) and fitted with the unchanged model.
* ``baseline_drift``: shared drift slope (V/s) subtracted from the data.
* ``second_mode``: g -> (1 - f) g(tau) + f g(r tau); shared fraction f and decay-time ratio r
  (its decay time scales with tau). Its detuned member lets the mode sit delta away from the
  probed one and see the line there, 1/tau_2 = 1/tau + d + c (alpha(nu + delta) - alpha(nu)),
  alpha from the line as last fitted (:class:`LineAbsorption`, ``TransientSpec.line``).
* ``extinction_tail``: the cavity fed by f exp(-t/tau_x) after extinction; shared f and tau_x
  (the tail time is the same at every spectral point).
* ``mode_beating``: exp(-t/tau) cos / sin (2 pi f_b t) columns with per-transient amplitudes and
  one shared beat frequency f_b, started from the residual periodogram.
* ``transfer_function`` / ``window_history``: TF-CRDS with the calibrated H instead of CRDS, and
  the extinction instead of the letter window (these only change ``method``/``window``).

Each effect is a family of forms (:data:`FAMILIES`, :data:`SPECTRUM_FORMS`), so that one
candidate can absorb an effect whose physical form differs from its default: a cubic detector
response; a quadratic drift or an AC-coupling undershoot (a per-transient column
exp(-t/tau_hp)); a second mode with 1/tau_2 = r/tau + d; a tail of two exponentials; a damped,
chirped beat; an etalon with its second harmonic; a neighbour with its own widths.
:func:`fit_family` / :func:`fit_spectrum_family` fit the members in order and keep the lowest
BIC (chi2 + k ln n on the effect's block, every shared and per-transient parameter charged);
higher members are tried only where the default already beats the model without the effect.
The default member's fit is the same as before the families existed.

With TF-CRDS the extension terms pass through H as well: exponentials through the exact
forward model of :mod:`bayes_tfcrds.physics.forward`, the beating columns by one FFT on the
extinction grid (for the ``letter`` window too: the window approximation is the main term's, not the
small extension's).

Spectrum level (:func:`fit_spectrum_extended`): the line profile follows the model (voigt,
sdvp for ``speed_dependence``, rautian for ``hard_collisions``, qsdhcp for both), plus
``etalon`` (a sinusoidal alpha baseline: amplitude, period, phase), ``neighbour_line`` (a
second line of the same shape: offset and area ratio) and ``baseline_slope`` (a linear alpha
baseline in the detuning; the dispersion model always has its slope).

Units: SI throughout (s, V, Hz, 1/m).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy import fft as sfft
from scipy import optimize

from bayes_tfcrds.core.constants import C
from bayes_tfcrds.core.linalg import central_jacobian, covariance_from_fisher
from bayes_tfcrds.fit.ringdown import fit_transients
from bayes_tfcrds.physics.collision_profiles import galatry, power_law_sdvoigt
from bayes_tfcrds.physics.forward import (
    extinction_grid,
    filtered_response,
    first_index_at,
    grid_transfer_function,
    model_grids,
    ramp_shape,
)
from bayes_tfcrds.physics.lineshape import profile
from bayes_tfcrds.physics.transfer_function import TFParams

V_REF = 1.0  # V, the nonlinearity's reference level (as in the simulator)

# shared parameters of each transient extension: (name, unit, lower, upper)
SHARED = {
    "static_nonlinearity": (("beta", "1", -0.05, 0.05),),
    "baseline_drift": (("slope_v_per_s", "V/s", -200.0, 200.0),),
    "second_mode": (("fraction", "1", 0.0, 0.3), ("tau_ratio", "1", 0.05, 0.95)),
    "extinction_tail": (("fraction", "1", 0.0, 0.3), ("tau_s", "s", 2e-7, 2e-4)),
    "mode_beating": (("freq_hz", "Hz", 1e4, 2.4e7),),
}
SHAPE_EFFECTS = ("second_mode", "extinction_tail", "mode_beating")

#: each transient effect as a family of forms, in order of complexity: (form, label, shared
#: parameters). The first member is the effect's default (``SHARED``); a higher member adds
#: parameters to it and is kept only where the information criterion on the transient block
#: prefers it (:func:`fit_family`), so an effect whose physical form differs from the default can
#: be absorbed by one candidate instead of leaving a misfit for spurious ones.
FAMILIES = {
    "static_nonlinearity": (
        ("quadratic", "quadratic", SHARED["static_nonlinearity"]),
        # V' = V + beta V^2/V_ref + gamma V^3/V_ref^2 (a saturating or expanding detector)
        ("cubic", "cubic", (*SHARED["static_nonlinearity"], ("gamma", "1", -0.2, 0.2))),
    ),
    "baseline_drift": (
        ("linear", "linear drift", SHARED["baseline_drift"]),
        # drift bending over the record (thermal settling of the detector baseline)
        (
            "quadratic",
            "quadratic drift",
            (*SHARED["baseline_drift"], ("curvature_v_per_s2", "V/s^2", -2e7, 2e7)),
        ),
        # AC coupling / detector recovery: the step at extinction leaves an undershoot
        # -kappa B exp(-t/tau_hp), proportional to each transient's own amplitude B: one column
        # exp(-t/tau_hp) per transient (its amplitude free, so it is charged per transient) with
        # one shared time constant
        ("ac_coupling", "AC-coupling undershoot", (("tau_hp_s", "s", 1e-6, 1e-2),)),
    ),
    "second_mode": (
        ("ratio", "decay time tau_ratio tau", SHARED["second_mode"]),
        # 1/tau_2 = r/tau + d: partial overlap r with the absorber (the mode sees r alpha c) and
        # its own mirror losses (d, relative to r times the main mode's)
        (
            "overlap_and_rate",
            "1/tau_2 = r/tau + d",
            (
                ("fraction", "1", 0.0, 0.3),
                ("overlap", "1", 0.0, 25.0),
                ("extra_rate_per_s", "1/s", -1e6, 2e6),
            ),
        ),
        # the same decay, with the mode's share free per transient (the coupling into the
        # transverse mode changes with the laser's alignment and frequency): a column per transient
        (
            "free_amplitude",
            "1/tau_2 = r/tau + d, amplitude per transient",
            (("overlap", "1", 0.0, 25.0), ("extra_rate_per_s", "1/s", -1e6, 2e6)),
        ),
        # a transverse mode delta above or below the probed one fills the same gas but samples
        # the line at nu + delta, with its own mirror/diffraction losses d: 1/tau_2 = 1/tau + d +
        # c (alpha(nu + delta) - alpha(nu)), alpha the line as fitted (needs TransientSpec.line)
        (
            "detuned",
            "detuned mode: 1/tau_2 = 1/tau + d + c [alpha(nu + delta) - alpha(nu)]",
            (
                ("fraction", "1", 0.0, 0.3),
                ("extra_rate_per_s", "1/s", -1e6, 2e6),
                ("detuning_hz", "Hz", -2e9, 2e9),
            ),
        ),
    ),
    "extinction_tail": (
        ("one_exponential", "1 exponential", SHARED["extinction_tail"]),
        (
            "two_exponentials",
            "2 exponentials",
            (
                *SHARED["extinction_tail"],
                ("fraction2", "1", 0.0, 0.3),
                ("tau2_s", "s", 2e-7, 2e-4),
            ),
        ),
    ),
    "mode_beating": (
        ("steady", "steady beat", SHARED["mode_beating"]),
        # the beat decays faster than the main mode (the beating modes' own losses) and its
        # frequency drifts linearly (a chirp from the cavity length settling)
        (
            "damped",
            "damped beat",
            (*SHARED["mode_beating"], ("damping_per_s", "1/s", -2e5, 2e6)),
        ),
        (
            "damped_chirped",
            "damped, chirped beat",
            (
                *SHARED["mode_beating"],
                ("damping_per_s", "1/s", -2e5, 2e6),
                ("chirp_hz_per_s", "Hz/s", -1e12, 1e12),
            ),
        ),
    ),
}
#: first simplex step of each added parameter (its physically small scale)
_ADDED_STEP = {
    "gamma": 1e-3,
    "curvature_v_per_s2": 2e5,
    "extra_rate_per_s": 2e4,
    "overlap": 0.1,
    "damping_per_s": 2e4,
    "chirp_hz_per_s": 1e10,
}


def family_member(name, form=None):
    """(form, label, shared parameters) of effect ``name``'s member ``form`` (None: default)."""
    members = FAMILIES[name]
    if form is None:
        return members[0]
    for mem in members:
        if mem[0] == form:
            return mem
    raise ValueError(f"{name} has no form {form!r}; choose from {[m[0] for m in members]}")


def member_row_params(name, form) -> int:
    """Linear parameters a member adds to every transient (charged once per transient)."""
    if name == "mode_beating":
        return 2
    return (
        1
        if (name, form) in (("baseline_drift", "ac_coupling"), ("second_mode", "free_amplitude"))
        else 0
    )


def form_of(name, params) -> str:
    """The member of effect ``name`` whose parameters are exactly the keys of ``params``."""
    keys = tuple(params)
    for form, _, pars in FAMILIES[name]:
        if tuple(p[0] for p in pars) == keys:
            return form
    raise ValueError(f"parameters {list(keys)} match no form of {name}")


SPECTRUM_EXTRAS = ("etalon", "neighbour_line")
#: higher members of the spectrum-level families: the extra each one adds on top of its effect
#: (label, parameters). ``etalon_harmonic``: the fringe's second harmonic (an Airy fringe of a
#: finesse above ~1 is not a sinusoid); ``neighbour_width``: the neighbour's widths (Doppler and
#: collisional) scaled by a free factor (another molecule, mass or broadening).
SPECTRUM_FORMS = {
    "etalon_harmonic": (
        "etalon",
        "sinusoid + 2nd harmonic",
        ("etalon2_amplitude_per_m", "etalon2_phase_rad"),
    ),
    "neighbour_width": ("neighbour_line", "free width scale", ("neighbour_width_scale",)),
}
SPECTRUM_DEFAULT_LABEL = {"etalon": "sinusoid", "neighbour_line": "same widths"}


def invert_nonlinearity(v, beta, gamma=0.0, newton_steps=3):
    """V from V' = V + beta V^2/V_ref + gamma V^3/V_ref^2 (V), the root continuous at 0.

    The quadratic's root is exact; a cubic term is then taken by Newton steps from it (for
    |gamma V^2| << 1 each step squares the relative error, 3 steps reach machine precision).
    """
    v = np.asarray(v, float)
    if beta == 0.0 and gamma == 0.0:
        return v
    x = 2.0 * v / (1.0 + np.sqrt(np.maximum(1.0 + 4.0 * beta * v / V_REF, 1e-12)))
    if gamma == 0.0:
        return x
    for _ in range(newton_steps):
        u = x / V_REF
        x = x - (x + beta * x * u + gamma * x * u * u - v) / nonlinearity_slope(x, beta, gamma)
    return x


def nonlinearity_slope(v, beta, gamma=0.0):
    """dV'/dV = 1 + 2 beta V/V_ref + 3 gamma V^2/V_ref^2 at the true voltage V."""
    u = np.asarray(v, float) / V_REF
    return 1.0 + 2.0 * beta * u + 3.0 * gamma * u * u


# --------------------------------------------------------------------------- transient model


@dataclass(frozen=True)
class TransientSpec:
    """Which transient-level extensions are on, with their shared parameters (dict per effect)."""

    method: str = "crds"
    window: str | None = None
    tf: TFParams | None = None
    shared: dict = field(default_factory=dict)
    #: the gas absorption of the line as last fitted (a :class:`LineAbsorption`), or None: lets a
    #: second mode detuned from the probed one see the line where it sits
    line: object = None

    def has(self, name):
        return name in self.shared

    def n_row_params(self) -> int:
        """Linear parameters per transient besides tau: b, B and the extensions' amplitudes."""
        return (
            2
            + (2 if self.has("mode_beating") else 0)
            + (1 if "tau_hp_s" in self.shared.get("baseline_drift", {}) else 0)
            + (1 if self.has("second_mode") and "fraction" not in self.shared["second_mode"] else 0)
        )

    def n_shared(self) -> int:
        return sum(len(v) for v in self.shared.values())


class _Columns:
    """Design columns (n rows, k, T samples) of the transient model for given decay times."""

    def __init__(self, t, t_cut_rows, mask, spec: TransientSpec, nu_rows=None):
        self.t, self.mask, self.spec = t, mask, spec
        self.nu_rows = nu_rows  # optical frequency (Hz) of each row's transient
        self._shifts = {}  # detuning (Hz) -> c (alpha(nu + delta) - alpha(nu)) of every row (1/s)
        self.tp = np.clip(t, 0.0, None)
        self.tf = spec.tf if spec.method == "tf-crds" else None
        if self.tf is not None:
            dt = float(t[1] - t[0])
            uniq, self.group = np.unique(t_cut_rows, return_inverse=True)
            self.grids = model_grids(float(t[0]), dt, t.size, uniq, self.tf, spec.window)
            self.h = [grid_transfer_function(g, self.tf) for g in self.grids]
            self.xgrid = extinction_grid(float(t[0]), dt, t.size, self.tf)
            self.xh = grid_transfer_function(self.xgrid, self.tf)
            ts = self.xgrid.start_s + dt * np.arange(self.xgrid.n_fft)
            taper = np.ones(self.xgrid.n_fft)
            if self.xgrid.n_ramp:
                taper[self.xgrid.m_ramp :] = 1.0 - ramp_shape(self.xgrid.n_ramp)
            self.xt = ts
            self.xtaper = np.where(ts >= 0, taper, 0.0)
            self.xcols = np.arange(t.size) + self.xgrid.data_offset

    def main(self, tau, rows):
        """Response to the ring-down input (1 before extinction, exp(-t/tau) after)."""
        if self.tf is None:
            return np.where(self.t[None, :] >= 0, np.exp(-self.tp[None, :] / tau[:, None]), 1.0)
        g = np.empty((rows.size, self.t.size))
        grp = self.group[rows]
        for gi in np.unique(grp):
            sel = np.nonzero(grp == gi)[0]
            g[sel] = filtered_response(tau[sel], self.grids[gi], self.h[gi], fill=0.0)
        return g

    def filtered(self, x_fn, tau):
        """A term that starts at extinction, x(t; tau) for t >= 0, through the chain."""
        if self.tf is None:
            return np.where(self.t[None, :] >= 0, x_fn(self.tp[None, :], tau[:, None]), 0.0)
        x = x_fn(np.clip(self.xt, 0, None)[None, :], tau[:, None]) * self.xtaper[None, :]
        out = sfft.irfft(sfft.rfft(x, axis=-1) * self.xh[None, :], n=self.xgrid.n_fft, axis=-1)
        return out[:, self.xcols]

    def _rate_shift(self, detuning_hz) -> np.ndarray:
        """The detuned mode's extra loss rate at every row (1/s), once per detuning."""
        key = float(detuning_hz)
        if key not in self._shifts:
            if self.spec.line is None or self.nu_rows is None:
                raise ValueError("a detuned second mode needs the line and the rows' frequencies")
            self._shifts[key] = self.spec.line.rate_shift(self.nu_rows, key)
        return self._shifts[key]

    def __call__(self, tau, rows):
        sh = self.spec.shared
        g = g_main = self.main(tau, rows)
        second = None
        if "second_mode" in sh:
            p = sh["second_mode"]
            if "detuning_hz" in p:
                # the mode delta away sees the line there: 1/tau_2 = 1/tau + d + c (alpha(nu +
                # delta) - alpha(nu)), kept positive as below
                shift = self._rate_shift(p["detuning_hz"])[rows]
                tau2 = 1.0 / np.maximum(1.0 / tau + p["extra_rate_per_s"] + shift, 1e-2 / tau)
            elif "overlap" in p:
                # 1/tau_2 = r/tau + d, kept positive (tau_2 <= 100 tau: a mode cannot gain)
                tau2 = 1.0 / np.maximum(p["overlap"] / tau + p["extra_rate_per_s"], 1e-2 / tau)
            else:
                tau2 = p["tau_ratio"] * tau
            if "fraction" in p:
                g = (1.0 - p["fraction"]) * g + p["fraction"] * self.main(tau2, rows)
            else:
                second = self.main(tau2, rows)  # its own amplitude per transient
        if "extinction_tail" in sh:
            p = sh["extinction_tail"]
            g0 = g_main
            for fk, tk in (("fraction", "tau_s"), ("fraction2", "tau2_s")):
                if fk not in p:
                    continue
                f, tx = p[fk], p[tk]
                d = 1.0 / tau - 1.0 / tx
                # keep away from tau = tau_x, where the coefficient's pole cancels the difference's
                # zero
                d = np.where(np.abs(tau * d) < 1e-4, 1e-4 / tau, d)
                txe = 1.0 / (1.0 / tau - d)
                g = g + (f / (tau * d))[:, None] * (self.main(txe, rows) - g0)
        cols = [np.ones_like(g), g]
        if "mode_beating" in sh:
            p = sh["mode_beating"]
            w = 2 * np.pi * p["freq_hz"]
            gam = p.get("damping_per_s", 0.0)
            chirp = np.pi * p.get("chirp_hz_per_s", 0.0)
            if gam == 0.0 and chirp == 0.0:
                cols.append(self.filtered(lambda t, ta: np.exp(-t / ta) * np.cos(w * t), tau))
                cols.append(self.filtered(lambda t, ta: np.exp(-t / ta) * np.sin(w * t), tau))
            else:

                def env(t, ta):
                    return np.exp(-t / ta - gam * t)

                cols.append(
                    self.filtered(lambda t, ta: env(t, ta) * np.cos((w + chirp * t) * t), tau)
                )
                cols.append(
                    self.filtered(lambda t, ta: env(t, ta) * np.sin((w + chirp * t) * t), tau)
                )
        if second is not None:
            cols.append(second)
        if "tau_hp_s" in sh.get("baseline_drift", {}):
            thp = sh["baseline_drift"]["tau_hp_s"]
            cols.append(self.filtered(lambda t, ta: np.exp(-t / thp) + 0.0 * ta, tau))
        out = np.stack(cols, axis=1)
        out *= self.mask[rows][:, None, :]
        return out


@dataclass(frozen=True)
class TransientResult:
    """Fits of n rows (spectral point x t_cut, flattened point-major) under a TransientSpec."""

    tau_s: np.ndarray
    tau_u_s: np.ndarray
    coef: np.ndarray  # (n, k) linear parameters: b, B(, beating cos, sin)
    chi2: np.ndarray
    n_used: np.ndarray
    converged: np.ndarray
    resid_norm: np.ndarray  # (n, T) residual / noise, zero outside the fit range


def _solve(m, v):
    """Batched solve of (n, k, k) systems for (n, k) right-hand sides."""
    return np.linalg.solve(m, v[..., None])[..., 0]


def _varpro_tau(cols, y, wm, tau0, max_iter=40, rtol=1e-8, rel_step=1e-6):
    """Gauss-Newton on tau per row with all linear columns projected out (batched).

    The step uses Kaufman's approximation of the variable-projection Jacobian: the
    derivative of the model at fixed linear parameters, projected orthogonally to the
    columns. rtol 1e-8 is far below any decay time's statistical uncertainty (~1e-4).
    """
    tau = np.asarray(tau0, float).copy()
    n = tau.size
    rows = np.arange(n)
    conv = np.zeros(n, bool)
    active = np.ones(n, bool)

    def linear(idx, t_):
        c = cols(t_, idx)
        dc = (cols(t_ * (1 + rel_step), idx) - c) / (t_ * rel_step)[:, None, None]
        w, yy = wm[idx], y[idx]
        wc = c * w[:, None, :]
        m = wc @ c.transpose(0, 2, 1)
        a = _solve(m, (wc @ yy[:, :, None])[..., 0])
        r = yy - (a[:, None, :] @ c)[:, 0]
        j = (a[:, None, :] @ dc)[:, 0]
        p = _solve(m, (wc @ j[:, :, None])[..., 0])
        jp = j - (p[:, None, :] @ c)[:, 0]
        return a, r, jp, w

    out = None  # a, r, jp of every row, at the tau returned for it

    def keep(idx, a, r, jp):
        nonlocal out
        if out is None:
            out = (np.empty((n, a.shape[1])), np.empty((n, r.shape[1])), np.empty((n, r.shape[1])))
        for dst, src in zip(out, (a, r, jp)):
            dst[idx] = src

    for _ in range(max_iter):
        idx = rows[active]
        if idx.size == 0:
            break
        a, r, jp, w = linear(idx, tau[idx])
        keep(idx, a, r, jp)
        num, den = (w * jp * r).sum(-1), (w * jp * jp).sum(-1)
        ok = np.isfinite(num) & (den > 0)
        step = np.clip(
            np.where(ok, num / np.where(ok, den, 1.0), 0.0), -0.3 * tau[idx], 0.5 * tau[idx]
        )
        done = ok & (np.abs(step) <= rtol * (tau[idx] + step))
        # a row that has converged keeps the tau its columns were just computed at: the step
        # left (<= rtol tau) is far below u(tau), and the final columns need no recomputation
        tau[idx] += np.where(done, 0.0, step)
        conv[idx[done]] = True
        active[idx[done | ~ok]] = False
    left = rows[active] if out is not None else rows  # out of iterations (or no rows at all)
    if left.size or out is None:
        a, r, jp, _ = linear(left, tau[left])
        keep(left, a, r, jp)
    a, r, jp = out
    tau_u = 1.0 / np.sqrt((wm * jp * jp).sum(-1))
    return tau, tau_u, a, r, conv


def fit_transient_rows(
    ringdowns, t_cut_rows, rows_of, spec: TransientSpec, tau_start_s=None
) -> TransientResult:
    """Fit rows (transient ``rows_of[i]`` from ``t_cut_rows[i]``, s) under ``spec``.

    Noise per sample is the bundle's ``noise_v`` (V); the chi2 is the weighted sum of squares.
    """
    t = ringdowns.time_s
    y = np.asarray(ringdowns.signal_v, float)[rows_of]
    sh = spec.shared
    if ringdowns.fit_noise_v is None or np.ndim(ringdowns.fit_noise_v) != 1:
        raise ValueError(
            "discovery needs one noise level per transient (/ringdowns/noise_v of shape (m,))"
        )
    noise_rows = np.asarray(ringdowns.fit_noise_v, float)[rows_of]
    noise2 = np.broadcast_to(noise_rows[:, None], y.shape)
    if "static_nonlinearity" in sh:
        beta = sh["static_nonlinearity"]["beta"]
        gamma = sh["static_nonlinearity"].get("gamma", 0.0)
        y = invert_nonlinearity(y, beta, gamma)
        # the noise is mapped back too, by 1/(dV'/dV): without it the chi2 of the mapped data
        # would drop for beta > 0 merely because the mapping shrinks the noise
        if gamma == 0.0:
            noise2 = noise2 / np.abs(1.0 + 2.0 * beta * y / V_REF)
        else:
            noise2 = noise2 / np.abs(nonlinearity_slope(y, beta, gamma))
    if "baseline_drift" in sh and "slope_v_per_s" in sh["baseline_drift"]:
        y = y - sh["baseline_drift"]["slope_v_per_s"] * (t - t[0])[None, :]
        if "curvature_v_per_s2" in sh["baseline_drift"]:
            y = y - sh["baseline_drift"]["curvature_v_per_s2"] * ((t - t[0]) ** 2)[None, :]
    dt = t[1] - t[0]
    first = np.array([first_index_at(t[0], dt, tc) for tc in t_cut_rows])
    mask = np.arange(t.size)[None, :] >= first[:, None]
    wm = mask / noise2**2
    shaped = any(k in sh for k in SHAPE_EFFECTS) or "tau_hp_s" in sh.get("baseline_drift", {})
    if not shaped:
        fits = fit_transients(
            t,
            y,
            t_cut_rows,
            method=spec.method,
            tf=spec.tf,
            window=spec.window if spec.method == "tf-crds" else None,
            noise_v=np.ascontiguousarray(noise2),
            keep_residuals=True,
            tau_start_s=tau_start_s,
        )
        # B of the CRDS model is its amplitude at t_cut; report both models' B at t = 0 alike
        amp = (
            fits.amplitude_v
            if spec.method == "tf-crds"
            else fits.amplitude_v * np.exp(t_cut_rows / fits.tau_s)
        )
        return TransientResult(
            tau_s=fits.tau_s,
            tau_u_s=fits.tau_u_s,
            coef=np.stack([fits.offset_v, amp], axis=1),
            chi2=fits.chi2,
            n_used=mask.sum(-1),
            converged=fits.converged,
            resid_norm=fits.residuals_v / noise2,
        )
    nu_rows = np.asarray(ringdowns.nu_hz, float)[np.asarray(rows_of)]
    cols = _Columns(t, np.asarray(t_cut_rows, float), mask, spec, nu_rows)
    if tau_start_s is None:
        base = fit_transients(t, y, t_cut_rows, method="crds", noise_v=noise_rows)
        tau_start_s = base.tau_s
    tau, tau_u, a, r, conv = _varpro_tau(cols, y, wm, np.asarray(tau_start_s, float))
    r = np.where(mask, r, 0.0)
    chi2 = (wm * r * r).sum(-1)
    return TransientResult(
        tau_s=tau,
        tau_u_s=tau_u,
        coef=a,
        chi2=chi2,
        n_used=mask.sum(-1),
        converged=conv,
        resid_norm=r / noise2,
    )


def residual_periodogram_peak(resid_norm, dt_s, f_min_hz=2e5):
    """Frequency (Hz) of the largest summed periodogram power of normalised residual rows."""
    p = np.abs(np.fft.rfft(resid_norm, axis=-1)) ** 2
    f = np.fft.rfftfreq(resid_norm.shape[-1], dt_s)
    s = p.sum(0)
    ok = f >= f_min_hz
    return float(f[ok][np.argmax(s[ok])])


def bin_ringdowns(rd, k: int):
    """Average k consecutive samples (noise / sqrt(k)): a coarser record for parameter searches.

    Decay times are >= 3 us and dt is tens of ns, so averaging k = 8 samples (160 ns) changes an
    exponential's shape by < (k dt / tau)^2 / 24 ~ 1e-4: enough to locate the minimum, which is
    then re-evaluated on the full record.
    """
    n = rd.n_samples // k
    sig = np.asarray(rd.signal_v, float)[:, : n * k].reshape(rd.n_points, n, k).mean(-1)
    # the record's own type (fit reads bundle records by their fields, never imports them); the
    # noise colour is already in fit_noise_v
    return replace(
        rd,
        signal_v=sig,
        dt_s=rd.dt_s * k,
        t0_s=rd.t0_s + 0.5 * (k - 1) * rd.dt_s,
        noise_v=np.asarray(rd.fit_noise_v, float) / np.sqrt(k),
        noise_kappa=None,
    )


def _search_two_exponential(name, chi2, lo, hi) -> np.ndarray:
    """(fraction, time parameter) of a weak second exponential minimising ``chi2``.

    The chi2 surface has a long curved valley (a larger fraction with a decay time closer to tau
    mimics a smaller, faster one), so the fraction is profiled out by a bounded 1-d search inside
    a bounded search over the time parameter (log tau_x for the tail), started from the best
    point of a coarse grid.
    """
    inner = {}

    def profile_f(g):
        # at fixed time parameter the model is nearly linear in the fraction, so chi2(f) is
        # nearly a parabola: two parabolic steps from f = 0 locate its minimum
        if g not in inner:
            fmax = hi[0] / 3
            pts = {0.0: chi2([0.0, g]), 2e-3: chi2([2e-3, g]), 4e-3: chi2([4e-3, g])}
            for _ in range(2):
                f3 = sorted(pts, key=lambda f: pts[f])[:3]
                fa, fb, fc = sorted(f3)
                ca, cb, cc = pts[fa], pts[fb], pts[fc]
                den = (fb - fa) * (cb - cc) - (fb - fc) * (cb - ca)
                if den == 0:
                    break
                fn = fb - 0.5 * ((fb - fa) ** 2 * (cb - cc) - (fb - fc) ** 2 * (cb - ca)) / den
                fn = float(np.clip(fn, 0.0, fmax)) if np.isfinite(fn) else 0.0
                if any(abs(fn - f) < 1e-7 for f in pts):
                    break
                pts[fn] = chi2([fn, g])
            fbest = min(pts, key=lambda f: pts[f])
            inner[g] = (pts[fbest], fbest)
        return inner[g][0]

    if name == "second_mode":
        to_g, grid = (lambda z: z), np.array([0.2, 0.4, 0.6, 0.75, 0.9])
    else:
        to_g, grid = np.exp, np.log([1e-6, 3e-6, 1e-5, 3e-5, 1e-4])
    vals = [profile_f(float(to_g(z))) for z in grid]
    b = int(np.argmin(vals))
    zlo, zhi = grid[max(b - 1, 0)], grid[min(b + 1, grid.size - 1)]
    sol = optimize.minimize_scalar(
        lambda z: profile_f(float(to_g(z))),
        bounds=(zlo, zhi),
        method="bounded",
        options={"xatol": 3e-3, "maxiter": 12},
    )
    g_best = float(to_g(sol.x)) if sol.fun <= vals[b] else float(to_g(grid[b]))
    x = np.array([inner[g_best][1], g_best])
    return x


def optimise_shared(
    name,
    ringdowns,
    t_cut_rows,
    rows_of,
    base: TransientSpec,
    tau_start_s,
    resid_norm=None,
    search_bin: int = 8,
    with_cov: bool = True,
    form: str | None = None,
    start: dict | None = None,
):
    """Fit the shared parameters of extension ``name`` on the rows' total chi2.

    Returns (params dict, TransientResult, covariance of the shared parameters or None).
    Starting points come from the data (the residual periodogram for the beating frequency)
    and, for two-parameter extensions, a small grid, since the chi2 surface of a weak second
    exponential is flat along a valley and has more than one local minimum.

    ``form`` picks a member of the effect's family (:data:`FAMILIES`; None: the default). A
    higher member that extends the default starts from ``start``, the default member's fitted
    parameters, with its added parameters at 0 (fitted by :func:`_fit_member`).
    """
    full = ringdowns
    if search_bin > 1 and name != "mode_beating":
        ringdowns = bin_ringdowns(ringdowns, search_bin)
    form = family_member(name)[0] if form is None else form
    default = form == family_member(name)[0]
    pars = family_member(name, form)[2]
    names = [s[0] for s in pars]
    lo = np.array([s[2] for s in pars])
    hi = np.array([s[3] for s in pars])
    cache = {}
    warm = {"tau": np.asarray(tau_start_s, float)}

    def spec_at(x):
        return replace(base, shared={**base.shared, name: dict(zip(names, map(float, x)))})

    def key_of(x):
        x = np.clip(np.asarray(x, float), lo, hi)
        if default and name in ("second_mode", "extinction_tail") and x[0] == 0.0:
            x = np.array([0.0, lo[1]])  # no second exponential: the time parameter is moot
        return x, tuple(np.round(x, 14))

    def chi2(x):
        x, key = key_of(x)
        if key not in cache:
            res = fit_transient_rows(ringdowns, t_cut_rows, rows_of, spec_at(x), warm["tau"])
            cache[key] = (float(res.chi2.sum()), res)
            if np.all(res.converged):
                warm["tau"] = res.tau_s
        return cache[key][0]

    if not default:
        x = _fit_member(name, form, chi2, names, lo, hi, start, ringdowns, resid_norm)
    elif name == "static_nonlinearity":
        sol = optimize.minimize_scalar(
            lambda b: chi2([b]), bounds=(lo[0], hi[0]), method="bounded", options={"xatol": 1e-7}
        )
        x = np.array([sol.x])
    elif name == "baseline_drift":
        sol = optimize.minimize_scalar(
            lambda s: chi2([s]), bounds=(lo[0], hi[0]), method="bounded", options={"xatol": 1e-4}
        )
        x = np.array([sol.x])
    elif name == "mode_beating":
        dt = float(ringdowns.dt_s)
        f0 = residual_periodogram_peak(resid_norm, dt) if resid_norm is not None else 1e6
        n_eff = resid_norm.shape[-1] if resid_norm is not None else ringdowns.n_samples
        df = 1.0 / (n_eff * dt)
        sol = optimize.minimize_scalar(
            lambda f: chi2([f]),
            bounds=(max(lo[0], f0 - 3 * df), min(hi[0], f0 + 3 * df)),
            method="bounded",
            options={"xatol": 1e-3 * df},
        )
        x = np.array([sol.x])
    else:
        x = _search_two_exponential(name, chi2, lo, hi)
    x = np.clip(x, lo, hi)
    if ringdowns is not full:
        ringdowns = full
        cache.clear()
        warm["tau"] = np.asarray(tau_start_s, float)
        if not default and form in ("cubic", "quadratic"):
            # fits without a shape term are cheap: polish on the full record
            x = _newton_steps(chi2, x, 0.1 * _member_steps(names, x), lo, hi)
        elif name in ("static_nonlinearity", "baseline_drift") and default:
            # one-parameter searches are cheap: polish on the full record
            w = 0.05 * (np.abs(x[0]) + (1e-4 if name == "static_nonlinearity" else 0.05))
            x = np.array(
                [
                    optimize.minimize_scalar(
                        lambda v: chi2([v]),
                        bounds=(x[0] - w, x[0] + w),
                        method="bounded",
                        options={"xatol": 1e-3 * w},
                    ).x
                ]
            )
    chi2(x)
    res = cache[key_of(x)[1]][1]
    cov = _shared_covariance(chi2, x, lo, hi) if with_cov else None
    return dict(zip(names, map(float, x))), res, cov


def _member_steps(names, x):
    """First simplex steps: 20 % of each fitted value, or the added parameter's small scale."""
    return np.array(
        [
            max(0.2 * abs(v), _ADDED_STEP.get(n, 0.0), 1e-6 * abs(v) + 1e-12)
            for n, v in zip(names, x)
        ]
    )


def _nelder_mead(chi2, x0, steps, lo, hi, max_fev):
    """Bounded Nelder-Mead from x0 with a simplex of the given steps (a local polish).

    A step that would leave the bounds is taken the other way, so the simplex starts inside
    them (a clipped vertex would collapse it onto the bound).
    """
    x0 = np.clip(np.asarray(x0, float), lo, hi)
    steps = np.where(x0 + steps > hi, -steps, steps)
    simplex = np.clip(np.vstack([x0, x0 + np.diag(steps)]), lo, hi)
    sol = optimize.minimize(
        lambda x: chi2(np.clip(x, lo, hi)),
        x0,
        method="Nelder-Mead",
        bounds=list(zip(lo, hi)),
        options={"initial_simplex": simplex, "maxfev": max_fev, "xatol": 1e-9, "fatol": 1e-3},
    )
    x = np.clip(sol.x, lo, hi)
    return x if chi2(x) <= chi2(x0) else x0


def _newton_steps(chi2, x0, steps, lo, hi, n_iter=4):
    """Newton steps on chi2 from x0 with its gradient and Hessian by central differences.

    For members whose parameters act (nearly) linearly on the data (a polynomial detector
    response, a polynomial drift) chi2 is nearly quadratic in them, and a correlated valley that
    a simplex crawls along is crossed in one or two steps. A step that does not lower chi2 ends
    the iteration.
    """
    x = np.clip(np.asarray(x0, float), lo, hi)
    f = chi2(x)
    for _ in range(n_iter):
        # the stencil's centre kept a step inside the bounds (the chi2 is clipped at them)
        xc = np.clip(x, lo + steps, hi - steps)
        if not np.array_equal(xc, x):
            x, f = xc, chi2(xc)
        k = x.size
        g, hess = np.empty(k), np.empty((k, k))
        for i in range(k):
            ei = np.zeros(k)
            ei[i] = steps[i]
            fp, fm = chi2(x + ei), chi2(x - ei)
            g[i] = (fp - fm) / (2 * steps[i])
            hess[i, i] = (fp - 2 * f + fm) / steps[i] ** 2
            for j in range(i):
                ej = np.zeros(k)
                ej[j] = steps[j]
                hess[i, j] = hess[j, i] = (
                    chi2(x + ei + ej) - chi2(x + ei - ej) - chi2(x - ei + ej) + chi2(x - ei - ej)
                ) / (4 * steps[i] * steps[j])
        try:
            x_new = np.clip(x - np.linalg.solve(hess, g), lo, hi)
        except np.linalg.LinAlgError:
            break
        f_new = chi2(x_new)
        if not f_new < f:
            break
        done = f - f_new < 1e-3
        x, f = x_new, f_new
        if done:
            break
    return x


def _fit_member(name, form, chi2, names, lo, hi, start, ringdowns, resid_norm):
    """Shared parameters of a higher family member (see :data:`FAMILIES`).

    Members extending the default start from its fit (``start``) with the added parameters at 0;
    a second exponential of the tail is searched like the first (fraction profiled inside a
    search over log tau), then the first re-searched with the second held, then both polished
    together. The AC-coupling undershoot (its amplitudes linear) is a 1-d search over log tau_hp.
    """
    if name == "baseline_drift" and form == "ac_coupling":
        grid = np.log([2e-6, 5e-6, 1.5e-5, 5e-5, 2e-4, 1e-3, 1e-2])
        vals = [chi2([np.exp(z)]) for z in grid]
        b = int(np.argmin(vals))
        sol = optimize.minimize_scalar(
            lambda z: chi2([np.exp(z)]),
            bounds=(grid[max(b - 1, 0)], grid[min(b + 1, grid.size - 1)]),
            method="bounded",
            options={"xatol": 1e-3},
        )
        return np.array([np.exp(sol.x if sol.fun <= vals[b] else grid[b])])
    if start is None:
        raise ValueError(f"the {form} form of {name} starts from the default member's fit")
    start = dict(start)
    if form == "detuned":
        return _search_detuned(chi2, names, lo, hi, start)
    if name == "second_mode":
        # the default's tau_2 = tau_ratio tau is r = 1/tau_ratio, d = 0
        start.setdefault("overlap", 1.0 / start["tau_ratio"])
    x0 = np.array([start.get(n, 0.0) for n in names], float)
    if name == "extinction_tail":
        x = x0.copy()
        x[2:] = _search_two_exponential(
            name, lambda z: chi2([x[0], x[1], z[0], z[1]]), lo[2:], hi[2:]
        )
        x[:2] = _search_two_exponential(
            name, lambda z: chi2([z[0], z[1], x[2], x[3]]), lo[:2], hi[:2]
        )
        # the two terms trade amplitude against time: polish jointly, the times in log
        llo, lhi = (
            np.r_[lo[0], np.log(lo[1]), lo[2], np.log(lo[3])],
            np.r_[hi[0], np.log(hi[1]), hi[2], np.log(hi[3])],
        )

        def chi2_log(z):
            return chi2([z[0], np.exp(z[1]), z[2], np.exp(z[3])])

        z0 = np.r_[x[0], np.log(x[1]), x[2], np.log(x[3])]
        steps = np.r_[0.3 * x[0] + 2e-3, 0.3, 0.3 * x[2] + 2e-3, 0.3]
        z = _nelder_mead(chi2_log, z0, steps, llo, lhi, 300)
        return np.r_[z[0], np.exp(z[1]), z[2], np.exp(z[3])]
    steps = _member_steps(names, x0)
    if form in ("cubic", "quadratic"):
        return _newton_steps(chi2, x0, steps, lo, hi)
    if name == "mode_beating":
        dt = float(ringdowns.dt_s)
        n_eff = resid_norm.shape[-1] if resid_norm is not None else ringdowns.n_samples
        steps[0] = 0.1 / (n_eff * dt)  # a tenth of a periodogram bin
    # restarts with a fresh simplex: the members' parameters are strongly correlated (e.g. the
    # overlap r and the rate d: 1/tau varies by a factor < 2 over a line), where one simplex
    # collapses early
    x = x0
    for _ in range(3):
        f_old = chi2(x)
        x = _nelder_mead(
            chi2, x, _member_steps(names, x) if x is not x0 else steps, lo, hi, 40 * x0.size
        )
        if f_old - chi2(x) < 0.1:
            break
    return x


#: detunings (Hz) at which the detuned mode's search starts: transverse-mode offsets from tens
#: of MHz to a GHz, either side (the chi2 has a minimum per side of the line's slope)
DETUNING_GRID_HZ = tuple(s * d for d in (2e7, 5e7, 1e8, 2e8, 4e8, 8e8) for s in (-1.0, 1.0))


def _search_detuned(chi2, names, lo, hi, start) -> np.ndarray:
    """(fraction, extra rate, detuning) of a detuned second mode minimising ``chi2``.

    Every start of :data:`DETUNING_GRID_HZ`, with the fraction and rate of the default member's
    fit (its rate d = (1/tau_ratio - 1)/tau is unknown per row; 0 here), is polished by a bounded
    Nelder-Mead; the best is kept.
    """
    fraction = float(np.clip(start.get("fraction", 0.01), 1e-3, 0.2))
    best = None
    for det in DETUNING_GRID_HZ:
        at = {"fraction": fraction, "extra_rate_per_s": 0.0, "detuning_hz": det}
        x0 = np.array([at[n] for n in names])
        if best is None or chi2(x0) < best[0]:
            best = (chi2(x0), x0)
    x = best[1]
    scale = {"fraction": 0.5 * fraction, "extra_rate_per_s": 5e3}
    steps = np.array([scale.get(n, 0.3 * abs(x[names.index(n)])) for n in names])
    for _ in range(3):
        f_old = chi2(x)
        x = _nelder_mead(chi2, x, steps, lo, hi, 120)
        if f_old - chi2(x) < 0.1:
            break
    return x


@dataclass(frozen=True)
class FamilyFit:
    """The member of an effect's family the information criterion chose, and every member's score.

    ``scores`` holds (form, chi2, k) for each member fitted, k counting every parameter the member
    adds to the model (shared and per-transient); BIC = chi2 + k ln n on the transient block.
    """

    name: str
    form: str
    label: str
    params: dict
    result: TransientResult
    cov: np.ndarray | None
    k: int
    n: int
    scores: tuple


def fit_family(
    name,
    ringdowns,
    t_cut_rows,
    rows_of,
    base: TransientSpec,
    tau_start_s,
    resid_norm=None,
    chi2_before=None,
    with_cov: bool = False,
    search_bin: int = 8,
) -> FamilyFit:
    """Fit effect ``name``'s family member by member and keep the lowest BIC (chi2 + k ln n).

    Higher members are fitted only if the default member already beats the model without the
    effect (``chi2_before``; Delta BIC > 0): where the effect's simplest form is not supported,
    more flexible forms would only chase noise and cost fits. The covariance (``with_cov``) is
    computed for the chosen member only.
    """
    n_rows = len(rows_of)
    scores, fits = [], {}
    start = None
    for form, _, pars in FAMILIES[name]:
        if form == "detuned" and base.line is None:
            continue  # no line to see from another frequency
        per_row = n_rows * member_row_params(name, form)
        params, res, _ = optimise_shared(
            name,
            ringdowns,
            t_cut_rows,
            rows_of,
            base,
            tau_start_s,
            resid_norm,
            search_bin=search_bin,
            with_cov=False,
            form=form,
            start=start,
        )
        k = len(pars) + per_row
        n = int(res.n_used.sum())
        chi2 = float(res.chi2.sum())
        scores.append((form, chi2, k))
        fits[form] = (params, res)
        start = {**(start or {}), **params}  # a member starts from the ones before it
        if len(scores) == 1:
            if chi2_before is not None and chi2_before - chi2 - k * np.log(n) <= 0:
                break
    n = int(fits[scores[0][0]][1].n_used.sum())
    best = min(scores, key=lambda s: s[1] + s[2] * np.log(n))
    params, res = fits[best[0]]
    cov = None
    if with_cov:
        cov = shared_covariance(name, ringdowns, t_cut_rows, rows_of, base, params, res.tau_s)
    return FamilyFit(
        name, best[0], family_member(name, best[0])[1], params, res, cov, best[2], n, tuple(scores)
    )


def shared_covariance(
    name, ringdowns, t_cut_rows, rows_of, base: TransientSpec, params: dict, tau_start_s
):
    """Covariance of extension ``name``'s shared parameters at ``params`` (profiled chi2).

    The parameters' names say which member of the effect's family they belong to.
    """
    pars = family_member(name, form_of(name, params))[2]
    names = [s[0] for s in pars]
    warm = {"tau": np.asarray(tau_start_s, float)}

    def chi2(x):
        spec = replace(base, shared={**base.shared, name: dict(zip(names, map(float, x)))})
        res = fit_transient_rows(ringdowns, t_cut_rows, rows_of, spec, warm["tau"])
        return float(res.chi2.sum())

    lo = np.array([s[2] for s in pars])
    hi = np.array([s[3] for s in pars])
    return _shared_covariance(chi2, np.array([params[n] for n in names], float), lo, hi)


def _shared_covariance(chi2, x, lo, hi):
    """Covariance 2 H^-1 of the profiled chi2 at its minimum (central second differences)."""
    k = x.size
    h = 1e-3 * np.maximum(np.abs(x), np.where(np.abs(x) > 0, 0, 1e-6))
    hess = np.empty((k, k))
    f0 = chi2(x)
    for i in range(k):
        ei = np.zeros(k)
        ei[i] = h[i]
        hess[i, i] = (chi2(x + ei) - 2 * f0 + chi2(x - ei)) / h[i] ** 2
        for j in range(i):
            ej = np.zeros(k)
            ej[j] = h[j]
            hess[i, j] = hess[j, i] = (
                chi2(x + ei + ej) - chi2(x + ei - ej) - chi2(x - ei + ej) + chi2(x - ei - ej)
            ) / (4 * h[i] * h[j])
    try:
        cov = 2.0 * np.linalg.inv(hess)
    except np.linalg.LinAlgError:
        return None
    if np.any(np.diag(cov) <= 0) or not np.all(np.isfinite(cov)):
        return None
    return cov


# --------------------------------------------------------------------------- spectrum model

PROFILE_SHAPE_FREE = {
    "voigt": ("gamma0_hz",),
    "sdvp": ("gamma0_hz", "gamma2_hz"),
    "rautian": ("gamma0_hz", "nu_vc_hz"),
    "qsdhcp": ("gamma0_hz", "gamma2_hz", "nu_vc_hz"),
    "sdvp_power": ("gamma0_hz", "sd_exponent", "delta_sd_hz"),
    "galatry": ("gamma0_hz", "nu_vc_hz"),
}

#: the other members of the line-shape families: form -> (effect, label, profile, default
#: profile it replaces). Power-law speed dependence Gamma(v) ~ v^m (its shift's speed-dependent
#: part delta_sd with the same law) beside the quadratic one;
#: soft (Galatry) beside hard (Rautian) velocity-changing collisions, its nu_VC the velocity-
#: diffusion rate beta/(2 pi). Each replaces its default only while it is the one line-shape
#: effect in the model (both effects together: qSDHCP).
PROFILE_FORMS = {
    "sd_power_law": ("speed_dependence", "power law v^m", "sdvp_power", "sdvp"),
    "soft_collisions": ("hard_collisions", "soft collisions (Galatry)", "galatry", "rautian"),
}
PROFILE_DEFAULT_LABEL = {"speed_dependence": "quadratic", "hard_collisions": "hard (Rautian)"}


def _line_profile(profile_name, det, offset_hz, doppler_hwhm_hz, shape):
    """Complex profile (1/Hz) of the spectrum model's line, the family members included."""
    if profile_name == "sdvp_power":
        return power_law_sdvoigt(
            det,
            offset_hz,
            doppler_hwhm_hz,
            shape["gamma0_hz"],
            shape["sd_exponent"],
            delta_sd_hz=shape["delta_sd_hz"],
        )
    if profile_name == "galatry":
        return galatry(det, offset_hz, doppler_hwhm_hz, shape["gamma0_hz"], 0.0, shape["nu_vc_hz"])
    return profile(profile_name, det, offset_hz, doppler_hwhm_hz, **shape)


@dataclass(frozen=True)
class SpectrumFit:
    """A line fit with optional etalon and neighbour line (SI: Hz/m, Hz, 1/m or Hz)."""

    kind: str
    profile: str
    names: tuple
    values: np.ndarray
    cov: np.ndarray
    chi2: float
    n: int
    residuals_norm: np.ndarray
    nu_hz: np.ndarray

    @property
    def k(self) -> int:
        return len(self.names)

    @property
    def dof(self) -> int:
        return self.n - self.k

    def value(self, name):
        return float(self.values[self.names.index(name)])

    def stderr(self, name):
        i = self.names.index(name)
        return float(np.sqrt(max(self.cov[i, i], 0.0)))


@dataclass(frozen=True)
class LineAbsorption:
    """The gas absorption alpha(nu) (1/m) of a fitted CRDS line: its profile (and neighbour).

    Baseline, slope and etalon are the cavity's, not the gas's, and are left out. ``rate_shift``
    gives c (alpha(nu + delta) - alpha(nu)) (1/s): the extra loss rate of a mode delta away.
    """

    fit: SpectrumFit
    doppler_hwhm_hz: float
    nu_ref_hz: float

    def __call__(self, nu_hz):
        values = dict(zip(self.fit.names, self.fit.values))
        for name in ("baseline", "slope", "etalon_amplitude_per_m", "etalon2_amplitude_per_m"):
            if name in values:
                values[name] = 0.0
        theta = np.array([values[n] for n in self.fit.names])
        nu = np.atleast_1d(np.asarray(nu_hz, float))
        return spectrum_model(
            theta,
            self.fit.names,
            "absorption",
            self.fit.profile,
            nu,
            self.nu_ref_hz,
            self.doppler_hwhm_hz,
        )

    def rate_shift(self, nu_hz, detuning_hz):
        nu = np.asarray(nu_hz, float)
        return C * (self(nu + detuning_hz) - self(nu))


def _names(kind, profile_name, extras):
    names = ["line_area", "position_offset_hz", *PROFILE_SHAPE_FREE[profile_name], "baseline"]
    if kind == "dispersion" or "baseline_slope" in extras:
        names.append("slope")
    if "etalon" in extras:
        names += ["etalon_amplitude_per_m", "etalon_period_hz", "etalon_phase_rad"]
    if "neighbour_line" in extras:
        names += ["neighbour_offset_hz", "neighbour_ratio"]
    for form, (effect, _, added) in SPECTRUM_FORMS.items():
        if form in extras and effect in extras:
            names += list(added)
    return tuple(names)


def spectrum_model(theta, names, kind, profile_name, nu_hz, nu_ref_hz, doppler_hwhm_hz, fixed=None):
    """Model spectrum: absorption (1/m) or dispersion mode shift (Hz) at nu_hz."""
    p = dict(zip(names, theta))
    p.update(fixed or {})
    shape = {k: p[k] for k in PROFILE_SHAPE_FREE[profile_name]}
    det = nu_hz - nu_ref_hz
    g = _line_profile(profile_name, det, p["position_offset_hz"], doppler_hwhm_hz, shape)
    if "neighbour_offset_hz" in p:
        ws = p.get("neighbour_width_scale", 1.0)
        n_shape = {k: (v * ws if k in ("gamma0_hz", "gamma2_hz") else v) for k, v in shape.items()}
        g = g + p["neighbour_ratio"] * _line_profile(
            profile_name,
            det,
            p["position_offset_hz"] + p["neighbour_offset_hz"],
            doppler_hwhm_hz * ws,
            n_shape,
        )
    if kind == "absorption":
        y = p["line_area"] * g.real + p["baseline"] + p.get("slope", 0.0) * det
    else:
        y = C * p["line_area"] * g.imag / (4 * np.pi) + p["baseline"] + p["slope"] * det
    if "etalon_amplitude_per_m" in p and kind == "absorption":
        y = y + p["etalon_amplitude_per_m"] * np.sin(
            2 * np.pi * det / p["etalon_period_hz"] + p["etalon_phase_rad"]
        )
        if "etalon2_amplitude_per_m" in p:
            y = y + p["etalon2_amplitude_per_m"] * np.sin(
                4 * np.pi * det / p["etalon_period_hz"] + p["etalon2_phase_rad"]
            )
    return y


#: lower bounds of the spectrum parameters (others unbounded below)
_LOWER_BOUNDS = {
    "line_area": 0.0,
    "gamma0_hz": 0.0,
    "gamma2_hz": 0.0,
    "nu_vc_hz": 0.0,
    "etalon_period_hz": 1e8,
    "neighbour_ratio": 0.0,
    "etalon_amplitude_per_m": 0.0,
    "etalon2_amplitude_per_m": 0.0,
    "neighbour_width_scale": 0.2,
    "sd_exponent": -0.5,
}


def _absolute_scales(doppler_hwhm_hz) -> dict:
    """Absolute scales added to |theta| where a spectrum parameter may be 0."""
    return {
        "position_offset_hz": 1e-3 * doppler_hwhm_hz,
        "etalon_phase_rad": 1.0,
        "neighbour_offset_hz": doppler_hwhm_hz,
        "slope": 1e-9,
        "baseline": 0.0,
        "etalon_amplitude_per_m": 1e-8,
        "neighbour_ratio": 1e-4,
        "etalon2_amplitude_per_m": 1e-8,
        "etalon2_phase_rad": 1.0,
        "sd_exponent": 0.1,
        "delta_sd_hz": 1e-3 * doppler_hwhm_hz,
    }


def _default_start(kind, nu_hz, y, doppler_hwhm_hz) -> dict:
    """Starting values of every spectrum parameter: the area and baseline from the data."""
    order = np.argsort(nu_hz)
    if kind == "absorption":
        base0 = float(np.median(np.concatenate([y[order][:4], y[order][-4:]])))
        area0 = float(np.trapezoid(y[order] - base0, nu_hz[order]))
    else:
        base0 = 0.0
        area0 = float((y.max() - y.min()) * 4 * np.pi / C * np.pi * doppler_hwhm_hz * 0.9)
    default = {
        "line_area": area0,
        "position_offset_hz": 0.0,
        "gamma0_hz": 0.05 * doppler_hwhm_hz,
        "gamma2_hz": 0.01 * doppler_hwhm_hz,
        "nu_vc_hz": 0.01 * doppler_hwhm_hz,
        "baseline": base0,
        "slope": 0.0,
        "etalon_amplitude_per_m": 0.0,
        "etalon_period_hz": 2e9,
        "etalon_phase_rad": 0.0,
        "neighbour_offset_hz": 1e9,
        "neighbour_ratio": 0.0,
        "etalon2_amplitude_per_m": 0.0,
        "etalon2_phase_rad": 0.0,
        "neighbour_width_scale": 1.0,
        "sd_exponent": 0.2,
        "delta_sd_hz": 0.0,
    }
    return default


def _extra_starts(kind, nu_hz, y, u, profile_name, doppler_hwhm_hz, nu_ref_hz, extras, start, span):
    """Starts for the etalon period and the neighbour's position.

    From the residuals of the fit without the extras: the strongest sinusoids, the largest bumps
    away from the line.
    """
    det = nu_hz - nu_ref_hz
    # residuals of the fit without the extras point at the period / the neighbour's position
    plain = fit_spectrum_extended(
        kind, nu_hz, y, u, profile_name, doppler_hwhm_hz, nu_ref_hz, (), fixed=None
    )
    r = -plain.residuals_norm * u  # data minus model
    st = {**start, **dict(zip(plain.names, plain.values))}
    starts = []
    periods = _periodogram_periods(det, r / u, span) if "etalon" in extras else [None]
    far = np.abs(det) > 2 * doppler_hwhm_hz
    bumps = det[far][np.argsort(-(r / u)[far])][:3] if "neighbour_line" in extras else [None]
    for per in periods:
        for b in bumps:
            s = dict(st)
            if per is not None:
                amp, ph = _sinusoid_at(det, r, u, per)
                s.update(
                    etalon_period_hz=per,
                    etalon_amplitude_per_m=max(amp, 1e-12),
                    etalon_phase_rad=ph,
                )
            if b is not None:
                s.update(neighbour_offset_hz=float(b), neighbour_ratio=1e-3)
            starts.append(s)
    return starts


def fit_spectrum_extended(
    kind, nu_hz, y, u, profile_name, doppler_hwhm_hz, nu_ref_hz, extras=(), fixed=None, start=None
) -> SpectrumFit:
    """Weighted least squares of a line (+ extras) to one spectrum; covariance from the Jacobian.

    ``fixed`` holds parameters not fitted (e.g. the neighbour line's position and ratio in the
    CMDS fit, taken from the CRDS fit). Several starts are tried for the etalon period and the
    neighbour position (from the residuals of the fit without them), keeping the best.
    """
    nu_hz, y, u = (np.asarray(a, float) for a in (nu_hz, y, u))
    fixed = dict(fixed or {})
    extras = tuple(e for e in extras if not (e == "etalon" and kind == "dispersion"))
    names_all = _names(kind, profile_name, extras)
    names = tuple(n for n in names_all if n not in fixed)
    default = _default_start(kind, nu_hz, y, doppler_hwhm_hz)
    user_start = start is not None
    start = {**default, **(start or {})}
    lo = {**_LOWER_BOUNDS, "delta_sd_hz": -0.2 * doppler_hwhm_hz}
    lo_v = np.array([lo.get(n, -np.inf) for n in names])
    span = float(np.ptp(nu_hz))
    # the power law's exponent: inverse-power potentials r^-q give m = (q - 3)/(q - 1), 0 to 1
    # for q >= 3, with room either side; its shift's speed-dependent part within a fifth of the
    # Doppler HWHM (at m -> 0 it has no effect, and unbounded it would wander)
    upper = {
        "etalon_period_hz": 2 * span,
        "neighbour_ratio": 0.5,
        "neighbour_width_scale": 5.0,
        "sd_exponent": 1.0,
        "delta_sd_hz": 0.2 * doppler_hwhm_hz,
    }
    hi_v = np.array([upper.get(n, np.inf) for n in names])
    nonsc = _absolute_scales(doppler_hwhm_hz)

    def run(st):
        th0 = np.array([st[n] for n in names], float)
        th0 = np.clip(th0, np.where(np.isfinite(lo_v), lo_v + 1e-300, -np.inf), hi_v)
        sc = np.abs(th0) + np.array([nonsc.get(n, 0.0) for n in names])
        sc = np.where(sc > 0, sc, 1.0)

        def resid(x):
            th = x * sc
            return (
                spectrum_model(
                    th, names, kind, profile_name, nu_hz, nu_ref_hz, doppler_hwhm_hz, fixed
                )
                - y
            ) / u

        sol = optimize.least_squares(
            resid,
            th0 / sc,
            bounds=(lo_v / sc, hi_v / sc),
            x_scale="jac",
            xtol=1e-12,
            ftol=1e-12,
            gtol=1e-12,
            max_nfev=3000,
        )
        return float(2 * sol.cost), sol.x * sc

    starts = [start]
    free_forms = [
        f for f in extras if f in SPECTRUM_FORMS and any(n in names for n in SPECTRUM_FORMS[f][2])
    ]
    if free_forms:
        # a higher family member starts from its default member's fit
        if not user_start:
            base = tuple(e for e in extras if e not in SPECTRUM_FORMS)
            fit0 = fit_spectrum_extended(
                kind, nu_hz, y, u, profile_name, doppler_hwhm_hz, nu_ref_hz, base, fixed=fixed
            )
            starts = [{**start, **_form_start(fit0, free_forms, u, nu_ref_hz)}]
    elif "etalon" in extras or "neighbour_line" in extras:
        starts = _extra_starts(
            kind, nu_hz, y, u, profile_name, doppler_hwhm_hz, nu_ref_hz, extras, start, span
        )
    best = min((run(s) for s in starts), key=lambda c: c[0])
    chi2, theta = best

    def model(th):
        return spectrum_model(
            th, names, kind, profile_name, nu_hz, nu_ref_hz, doppler_hwhm_hz, fixed
        )

    steps = 1e-6 * np.maximum(
        np.abs(theta), np.array([nonsc.get(n, 1e-3 * abs(t) + 1e-30) for n, t in zip(names, theta)])
    )
    # a width within 1e-6 Doppler HWHM (0.2 kHz here) of 0 is on its bound
    width_tol = np.array([1e-6 * doppler_hwhm_hz if n in _WIDTHS else 0.0 for n in names])
    cov = _covariance_off_bounds(model, theta, steps, u, lo_v, hi_v, width_tol)
    r = (model(theta) - y) / u
    return SpectrumFit(
        kind=kind,
        profile=profile_name,
        names=names,
        values=theta,
        cov=cov,
        chi2=float(r @ r),
        n=y.size,
        residuals_norm=r,
        nu_hz=nu_hz,
    )


_WIDTHS = ("gamma0_hz", "gamma2_hz", "nu_vc_hz")


def _covariance_off_bounds(model, theta, steps, u, lo, hi, tol) -> np.ndarray:
    """Covariance from the Jacobian, with the parameters that sit on a bound held there.

    A parameter on its bound (Gamma2 or nu_VC at 0 when the data want less narrowing than the
    model allows) has no Gaussian uncertainty, and a central difference across the bound leaves
    the profile's domain (NaN). The others get the covariance conditional on it (the active
    constraint's treatment in bounded least squares); its own row and column are NaN. On a bound:
    within a central step or ``tol`` of it.
    """
    near = np.maximum(steps, tol)
    on_bound = (np.isfinite(lo) & (theta - lo <= near)) | (np.isfinite(hi) & (hi - theta <= near))
    free = ~on_bound
    cov = np.full((theta.size, theta.size), np.nan)
    if not free.any():
        return cov

    def model_free(th_free):
        th = theta.copy()
        th[free] = th_free
        return model(th)

    jac = central_jacobian(model_free, theta[free], steps[free]) / u[:, None]
    try:
        cov[np.ix_(free, free)] = covariance_from_fisher(jac.T @ jac)
    except np.linalg.LinAlgError:
        pass
    return cov


def _periodogram_periods(det, z, span, n_best=3):
    """Periods (Hz) of the strongest sinusoids in residuals z on the uneven grid det.

    Lomb-Scargle periodogram (the detunings are not evenly spaced).
    """
    from scipy.signal import lombscargle

    periods = np.geomspace(2.5 * np.median(np.diff(np.sort(det))), span, 300)
    pw = lombscargle(det, z - z.mean(), 2 * np.pi / periods)
    idx = np.argsort(-pw)
    out = []
    for i in idx:
        if all(abs(np.log(periods[i] / p)) > 0.15 for p in out):
            out.append(float(periods[i]))
        if len(out) == n_best:
            break
    return out


def _sinusoid_at(det, r, u, period):
    """Amplitude and phase of the best sinusoid of a given period in residuals r (weighted)."""
    x = 2 * np.pi * det / period
    a = np.stack([np.sin(x), np.cos(x)], 1) / u[:, None]
    c, *_ = np.linalg.lstsq(a, r / u, rcond=None)
    return float(np.hypot(*c)), float(np.arctan2(c[1], c[0]))


@dataclass(frozen=True)
class SpectrumFamilyFit:
    """The member of a spectrum-level effect's family the BIC chose, and each member's score.

    ``form`` is None for the default member, else a key of :data:`SPECTRUM_FORMS`; ``scores``
    holds (form label, chi2, number of line-fit parameters) per member fitted.
    """

    effect: str
    form: str | None
    label: str
    fit: SpectrumFit
    scores: tuple


def fit_spectrum_family(
    effect, nu_hz, y, u, profile_name, doppler_hwhm_hz, nu_ref_hz, extras=(), chi2_before=None
) -> SpectrumFamilyFit:
    """Fit ``effect`` (etalon or neighbour_line) on top of ``extras``, member by member.

    The default member first; its higher member (:data:`SPECTRUM_FORMS`) starts from it, with
    the added harmonic's amplitude and phase from the default fit's residuals at half the period,
    or the neighbour's width scale at 1. The member with the lowest BIC (chi2 + k ln n) is kept;
    the higher member is fitted only where the default beats ``chi2_before`` (Delta BIC > 0).
    """
    args = ("absorption", nu_hz, y, u, profile_name, doppler_hwhm_hz, nu_ref_hz)
    extras = tuple(extras)
    fit0 = fit_spectrum_extended(*args, (*extras, effect))
    n = fit0.n
    scores = [(SPECTRUM_DEFAULT_LABEL[effect], fit0.chi2, fit0.k)]
    best = (None, SPECTRUM_DEFAULT_LABEL[effect], fit0)
    k_before = len(_names("absorption", profile_name, extras))
    if chi2_before is not None and chi2_before - fit0.chi2 - (fit0.k - k_before) * np.log(n) <= 0:
        return SpectrumFamilyFit(effect, None, best[1], fit0, tuple(scores))
    for form, (eff, label, _) in SPECTRUM_FORMS.items():
        if eff != effect:
            continue
        start = _form_start(fit0, [form], np.asarray(u, float), nu_ref_hz)
        fit1 = fit_spectrum_extended(*args, (*extras, effect, form), start=start)
        scores.append((label, fit1.chi2, fit1.k))
        if fit1.chi2 + fit1.k * np.log(n) < best[2].chi2 + best[2].k * np.log(n):
            best = (form, label, fit1)
    return SpectrumFamilyFit(effect, best[0], best[1], best[2], tuple(scores))


#: the other line-shape member replaces the default only when its BIC is lower by more than this:
#: where the data do not resolve the narrowing both become a Voigt and differ by rounding
MEMBER_MARGIN_BIC = 2.0


def fit_profile_family(
    effect, nu_hz, y, u, default_profile, doppler_hwhm_hz, nu_ref_hz, extras=(), before=None
) -> SpectrumFamilyFit:
    """Fit the line with ``effect``'s line-shape family (speed dependence or narrowing).

    The default member (``default_profile``: sdvp or rautian) first, then the other member of
    :data:`PROFILE_FORMS` started from it (the power law's exponent from the quadratic's slope at
    the most probable speed, m = 2 Gamma2/Gamma0; Galatry's rate from Rautian's). The other
    member is kept when its BIC (chi2 + k ln n) is lower by more than :data:`MEMBER_MARGIN_BIC`;
    one whose fit fails leaves the default. As for the other families, the other member is tried
    only where the default beats the line fit without the effect (``before``, a SpectrumFit;
    Delta BIC > 0): a more flexible shape would otherwise only chase other structure.
    """
    args = ("absorption", nu_hz, y, u)
    fit0 = fit_spectrum_extended(*args, default_profile, doppler_hwhm_hz, nu_ref_hz, extras)
    n = fit0.n
    label0 = PROFILE_DEFAULT_LABEL[effect]
    scores = [(label0, fit0.chi2, fit0.k)]
    best = (None, label0, fit0)
    if before is not None and before.chi2 - fit0.chi2 - (fit0.k - before.k) * np.log(n) <= 0:
        return SpectrumFamilyFit(effect, None, label0, fit0, tuple(scores))
    for form, (eff, label, prof, default) in PROFILE_FORMS.items():
        if eff != effect or default != default_profile:
            continue
        start = dict(zip(fit0.names, fit0.values))
        if "gamma2_hz" in start:
            ratio = start.pop("gamma2_hz") / max(start["gamma0_hz"], 1e-30)
            start["sd_exponent"] = float(np.clip(2.0 * ratio, 0.02, 1.0))
        try:
            fit1 = fit_spectrum_extended(
                *args, prof, doppler_hwhm_hz, nu_ref_hz, extras, start=start
            )
        except (ValueError, OverflowError, np.linalg.LinAlgError):
            continue  # the default member stands
        scores.append((label, fit1.chi2, fit1.k))
        bic0 = best[2].chi2 + best[2].k * np.log(n)
        if fit1.chi2 + fit1.k * np.log(n) < bic0 - MEMBER_MARGIN_BIC:
            best = (form, label, fit1)
    return SpectrumFamilyFit(effect, best[0], best[1], best[2], tuple(scores))


def _form_start(fit0: SpectrumFit, forms, u, nu_ref_hz) -> dict:
    """Start of a higher spectrum member from its default member's fit ``fit0``.

    The second harmonic's amplitude and phase from the residuals at half the fringe period
    (at amplitude 0 the phase would have no gradient); the neighbour's width scale at 1.
    """
    start = dict(zip(fit0.names, fit0.values))
    if "etalon_harmonic" in forms:
        r = -fit0.residuals_norm * u  # data minus model
        det = fit0.nu_hz - nu_ref_hz
        amp, ph = _sinusoid_at(det, r, u, 0.5 * start["etalon_period_hz"])
        start.update(etalon2_amplitude_per_m=max(amp, 1e-12), etalon2_phase_rad=ph)
    if "neighbour_width" in forms:
        start["neighbour_width_scale"] = 1.0
    return start
