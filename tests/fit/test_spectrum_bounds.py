"""A spectrum fit whose shape parameter lands on its bound keeps the others' uncertainties.

Speed dependence fitted to a line whose core is broader than a Voigt's (a weak, wider Gaussian
underneath) drives Gamma2 to its bound 0 (speed dependence can only narrow the core). The fit
there is the Voigt fit, so the covariance of the other parameters must be the Voigt fit's (the
active constraint holds Gamma2 at 0); before, one central difference left the profile's domain
and every uncertainty was NaN.
"""

from __future__ import annotations

import numpy as np

from bayes_tfcrds.fit.extensions import fit_spectrum_extended
from bayes_tfcrds.physics.lineshape import profile

DOP, G0, NU0 = 2.3e8, 1.0e7, 0.0


def _broad_wing_spectrum():
    det = np.linspace(-3e9, 3e9, 41)
    area = 4e5  # Hz/m
    g = profile("voigt", det, 0.0, DOP, gamma0_hz=G0).real
    wing = profile("gaussian", det, 0.0, 1.3 * DOP).real
    y = area * (0.995 * g + 0.005 * wing) + 1e-4
    u = np.full(det.size, 2e-8)  # 1/m: a relative noise of 1e-5 at the peak, no noise drawn
    return det, y, u


def test_parameter_on_its_bound_is_held_and_the_rest_keep_their_covariance():
    det, y, u = _broad_wing_spectrum()
    sd = fit_spectrum_extended("absorption", det, y, u, "sdvp", DOP, NU0)
    vo = fit_spectrum_extended("absorption", det, y, u, "voigt", DOP, NU0)
    assert sd.value("gamma2_hz") < 1.0  # Hz: on its bound (the core wants Gamma2 < 0)
    assert np.isnan(sd.stderr("gamma2_hz"))
    for name in ("line_area", "gamma0_hz", "position_offset_hz", "baseline"):
        # the same fit: values within 1e-3 of their u (the optimiser's tolerance), uncertainties
        # to the Jacobian's central differences (1e-6 relative steps)
        assert abs(sd.value(name) - vo.value(name)) < 1e-3 * vo.stderr(name), name
        assert np.isclose(sd.stderr(name), vo.stderr(name), rtol=1e-4), name
