"""Linear propagation maps against full refits (finite differences)."""

from dataclasses import replace

import numpy as np
import pytest

from bayes_tfcrds.core.constants import C, wavenumber_cm_to_hz
from bayes_tfcrds.fit.line import fit_line
from bayes_tfcrds.fit.refine import refine_transfer_function
from bayes_tfcrds.fit.ringdown import fit_transients
from bayes_tfcrds.fit.spectrum import SpectrumData
from bayes_tfcrds.physics.detection_chain import chain_from_tf
from bayes_tfcrds.physics.lineshape import doppler_hwhm_hz, profile
from bayes_tfcrds.physics.transfer_function import transfer_function_derivatives
from bayes_tfcrds.simulate.campaign import PRESETS
from bayes_tfcrds.uncertainty.propagate import (
    h_change,
    line_gain,
    tau_h_kernels,
    tau_sensitivities,
)

DT, K, T0 = 20e-9, 8192, -2e-6
T = T0 + DT * np.arange(K)
TF = PRESETS["letter-D4"].tf
NAMES = ("f_c_hz", "a_r", "f_r_hz", "gamma_r")


def _data(rng, taus, sigma=1.3e-4):
    return (
        0.002
        + 0.6 * chain_from_tf(TF).ringdown_response(T, taus)
        + sigma * rng.standard_normal((taus.size, K))
    )


def test_tau_sensitivities_match_refits():
    rng = np.random.default_rng(1)
    taus = np.array([3.7e-6, 8e-6, 30e-6])
    sig = _data(rng, taus)
    tc = np.full(taus.size, 4e-6)
    base = fit_transients(T, sig, tc, "tf-crds", TF, "extinction")
    s = tau_sensitivities(T, sig, tc, base.tau_s, base.amplitude_v, TF, NAMES)
    for j, name in enumerate(NAMES):
        v = getattr(TF, name)
        h = 1e-4 * abs(v)
        up = fit_transients(T, sig, tc, "tf-crds", replace(TF, **{name: v + h}), "extinction").tau_s
        dn = fit_transients(T, sig, tc, "tf-crds", replace(TF, **{name: v - h}), "extinction").tau_s
        fd = (up - dn) / (2 * h)
        # first order in a tiny step: agreement to 1e-3 of the sensitivity is the FD error budget
        np.testing.assert_allclose(s[:, j], fd, rtol=2e-3, atol=1e-6 * np.max(np.abs(fd)))
    # f_c matters most at short tau (the slow tail): the map is not trivially constant
    assert abs(s[0, 0] / taus[0]) > 3 * abs(s[2, 0] / taus[2])


@pytest.mark.parametrize("window", ["extinction", "letter"])
def test_function_space_kernels_reproduce_parameter_sensitivities_and_refits(window):
    """d tau/d H(f) times dH/dtheta is d tau/d theta; a finite H draw moves tau as refits do."""
    rng = np.random.default_rng(2)
    taus = np.array([3.7e-6, 8e-6, 30e-6])
    sig = _data(rng, taus)
    tc = np.array([2e-6, 4e-6, 8e-6])
    base = fit_transients(T, sig, tc, "tf-crds", TF, window)
    s = tau_sensitivities(T, sig, tc, base.tau_s, base.amplitude_v, TF, NAMES, window)
    kern = tau_h_kernels(T, tc, base.tau_s, base.amplitude_v, TF, window)
    for rows, f_hz, k in kern.groups:
        via_h = (transfer_function_derivatives(f_hz, TF, NAMES) @ k.T).real.T
        np.testing.assert_allclose(via_h, s[rows], rtol=1e-7)  # same chain rule, other order
    draw = TF.as_vector(NAMES) * (1 + np.array([0.02, 0.01, 0.03, -0.02]))
    moved = kern.shifts(h_change(draw[None, :], NAMES, TF), taus.size)[0]
    full = fit_transients(T, sig, tc, "tf-crds", TF.with_vector(draw, NAMES), window).tau_s
    # a 1-3 % H move: the first-order shift agrees with the refit to 3 % (second order)
    np.testing.assert_allclose(moved, full - base.tau_s, rtol=0.03)


def test_line_gain_matches_refits():
    nu0 = float(wavenumber_cm_to_hz(6410.88))
    gd = float(doppler_hwhm_hz(nu0, 296.0, 27.995))
    g0 = 9.3e6
    nu = nu0 + np.arange(-40, 41) * 203e6
    alpha = (
        3.93e5
        * profile(
            "qsdhcp", nu - nu0, 0.0, gd, gamma0_hz=g0, gamma2_hz=0.1 * g0, nu_vc_hz=0.4 * g0
        ).real
    )
    alpha = alpha + 1.0 / (C * 32e-6)
    u = 2e-5 * alpha
    s = SpectrumData("absorption", nu, alpha, u)
    fit = fit_line([s], "qsdhcp", gd, nu0)
    k = line_gain(fit)
    rng = np.random.default_rng(3)
    dy = 0.05 * u * rng.standard_normal(nu.size)  # a small correlated-free perturbation
    refit = fit_line(
        [SpectrumData("absorption", nu, alpha + dy, u)],
        "qsdhcp",
        gd,
        nu0,
        start=dict(zip(fit.names, fit.values)),
    )
    ia = fit.names.index("line_area")
    predicted = k[ia] @ dy
    assert abs((refit.line_area - fit.line_area) - predicted) < 0.02 * abs(predicted)


def test_refinement_conditional_follows_the_other_parameters():
    """Moving a_r (held fixed in the refinement) moves the refined f_c as the gain predicts."""
    rng = np.random.default_rng(5)
    taus = np.array([3.7e-6, 6e-6, 10e-6, 30e-6])
    sig = _data(rng, taus)
    tcs = np.tile([2e-6, 4e-6, 8e-6], taus.size)
    rows = np.repeat(np.arange(taus.size), 3)
    noise = np.full(taus.size, 1.3e-4)
    ref = refine_transfer_function(
        T, sig, tcs, TF, free=("f_c_hz",), noise_v=noise, rows_of=rows, sens_names=NAMES
    )
    gain, _ = ref.conditional({"a_r": None})
    da = 0.02 * TF.a_r
    ref2 = refine_transfer_function(
        T,
        sig,
        tcs,
        replace(ref.params, a_r=TF.a_r + da),
        free=("f_c_hz",),
        noise_v=noise,
        rows_of=rows,
    )
    moved = ref2.params.f_c_hz - ref.params.f_c_hz
    assert abs(moved - gain[0, 0] * da) < 0.05 * abs(moved) + 0.2 * ref.stderr["f_c_hz"]
    assert abs(moved) > 3 * ref.stderr["f_c_hz"]  # the coupling is real, not noise
