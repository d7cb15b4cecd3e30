"""The transient model of a fitted extension state as detector voltage (a bootstrap's truth).

:func:`bayes_tfcrds.fit.extensions.fit_transient_rows` maps the data back through the model's
static nonlinearity and subtracts its drift before it fits ``b + B g(t; tau) + extra columns``.
:func:`model_transients` runs the same model forward, from decay times and linear coefficients to
the voltage a detector with that nonlinearity and drift would record, so that data simulated from
a fit go through exactly the analysis that made the fit.

Units: SI (s, V).
"""

from __future__ import annotations

import numpy as np

from bayes_tfcrds.fit.extensions import V_REF, TransientSpec, _Columns
from bayes_tfcrds.physics.forward import first_index_at


def model_transients(
    time_s: np.ndarray,
    t_cut_s: float,
    spec: TransientSpec,
    tau_s: np.ndarray,
    coef: np.ndarray,
    nu_hz: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Model voltage (n, T) of n transients from ``t_cut_s`` on, and the mask of those samples.

    Parameters
    ----------
    time_s : ndarray (T,)
        Sample times (s) relative to laser extinction.
    t_cut_s : float
        First sample time (s) the model describes; earlier samples are zero in the result.
    spec : TransientSpec
        Method, window, H and shared extension parameters of the fit.
    tau_s : ndarray (n,)
        Decay times (s).
    coef : ndarray (n, k)
        The fit's linear parameters per transient: offset b (V), amplitude B (V) at extinction,
        and the beating amplitudes (V) when ``mode_beating`` is on (``TransientResult.coef``).
    nu_hz : ndarray (n,), optional
        Optical frequencies (Hz) of the transients: needed by a detuned second mode only.

    Returns
    -------
    (ndarray, ndarray)
        Voltage (V) as recorded (drift added, nonlinearity applied) and the boolean mask of the
        samples at or after ``t_cut_s``.
    """
    t = np.asarray(time_s, float)
    tau = np.asarray(tau_s, float)
    n = tau.size
    first = first_index_at(t[0], float(t[1] - t[0]), t_cut_s)
    mask = np.broadcast_to(np.arange(t.size)[None, :] >= first, (n, t.size))
    nu = None if nu_hz is None else np.asarray(nu_hz, float)
    cols = _Columns(t, np.full(n, float(t_cut_s)), mask, spec, nu)(tau, np.arange(n))
    k = min(cols.shape[1], coef.shape[1])
    v = np.einsum("nk,nkt->nt", np.asarray(coef, float)[:, :k], cols[:, :k])
    sh = spec.shared
    drift = sh.get("baseline_drift", {})
    if "slope_v_per_s" in drift:  # the polynomial members (AC coupling is a column above)
        dt = (t - t[0])[None, :]
        v = v + drift["slope_v_per_s"] * dt + drift.get("curvature_v_per_s2", 0.0) * dt * dt
    if "static_nonlinearity" in sh:
        u = v / V_REF
        nl = sh["static_nonlinearity"]
        v = v + nl["beta"] * v * u + nl.get("gamma", 0.0) * v * u * u
    return np.where(mask, v, 0.0), np.array(mask)
