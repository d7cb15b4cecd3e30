"""Which H parameters the data identify: every Eq. 2 description of the posterior's H(f).

The beat note and the ring-downs see H(f) only, never the labels of Eq. 2's two paths. Where the
resonant path is overdamped it is two real poles, and the three real poles (with the main
path's) can be shared out between the paths in more than one way that gives the same H(f)
within its uncertainty: a slow pole can be the main path's f_c beside a strong resonance at the
fast one, or a weak resonant tail beside a fast f_c. Both are valid chains; no measurement of H
tells them apart. H(f), the decay times and A do not depend on the choice, but a parameter such
as f_c does, and its posterior sd then describes only the description the sampler settled in.
The check compares H where it shapes a decay (1 kHz to the ring-downs' Nyquist frequency); a
beat note reaching further sees the descriptions there too, through the posterior's draws.

:func:`identify_h` fits Eq. 2 to the posterior's H(f) from many starts (both regimes, either sign
of A_r), keeps every fit whose H lies inside the posterior's own cloud of H(f), and names the
parameters on which such a description lies clear of the posterior's centre: those are not
identified by the data. Frequencies in Hz; H normalised (dimensionless).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import optimize

from bayes_tfcrds.fit import refine
from bayes_tfcrds.fit.beat_note import default_starts
from bayes_tfcrds.physics.transfer_function import SUPPORT, TFParams, transfer_function_of_draws

#: separation, in combined standard uncertainties, beyond which two descriptions differ in a
#: parameter (the convention of the beat-note modes: 3 sigma)
SEPARATION_K = 3.0
#: the share of the posterior's own draws whose H(f) a description's H must be as close as
CLOUD_QUANTILE = 0.99
IDENTIFY_FREQUENCIES = 32  # log-spaced from 1 kHz to the ring-downs' Nyquist frequency


@dataclass(frozen=True)
class HDescription:
    """One Eq. 2 description of the posterior's H(f), other than its centre.

    ``max_z``: the largest |H - H_centre| / u(H) over the frequency grid (real and imaginary
    parts); ``u_sample`` the sd of each parameter (log for the positive ones) that H(f)'s
    uncertainty leaves it; ``differs`` the parameters on which it lies clear of the centre.
    """

    params: TFParams
    max_z: float
    u_sample: tuple
    differs: tuple


@dataclass(frozen=True)
class HIdentification:
    """The H parameters the beat note and ring-downs identify, and the descriptions that show why.

    ``names`` the sampled H parameters; ``not_identified`` those on which another description of
    the same H(f) lies more than SEPARATION_K combined u from the centre; ``threshold`` the max_z
    that the posterior's own draws stay within (CLOUD_QUANTILE of them).
    """

    names: tuple
    centre: TFParams
    threshold: float
    descriptions: tuple
    not_identified: tuple

    def identified(self, name: str) -> bool:
        """Whether no other description of the same H(f) lies clear of the centre in ``name``."""
        return name not in self.not_identified

    def lines(self) -> list:
        """Plain-text lines for a terminal or budget.md: what is not identified, and why."""
        if not self.not_identified:
            return []
        alt = "; ".join(
            ", ".join(f"{n} = {getattr(d.params, n):.4g}" for n in self.names)
            for d in self.descriptions
        )
        return [
            f"not identified by the data: {', '.join(self.not_identified)}. Another description of "
            f"Eq. 2 gives the same H(f) within its uncertainty ({alt}); the beat note and the "
            "ring-downs see H only, so they cannot tell which path holds which pole. H(f), the "
            "decay times and A do not depend on the choice; the u of these parameters describes "
            "the reported description only"
        ]

    def to_dict(self) -> dict:
        """JSON-ready: budget.json's ``transfer_function.identification``."""
        return {
            "not_identified": list(self.not_identified),
            "threshold_max_z": self.threshold,
            "descriptions": [
                {
                    **{n: float(getattr(d.params, n)) for n in self.names},
                    "max_z": d.max_z,
                    "differs_in": list(d.differs),
                }
                for d in self.descriptions
            ],
            "method": (
                "Eq. 2 fitted to the posterior's H(f) from many starts; a fit whose H stays within "
                f"the {CLOUD_QUANTILE:.0%} cloud of the posterior draws' H is another description "
                f"of the same chain; a parameter more than {SEPARATION_K:g} combined u from the "
                "centre in one is not identified by the data"
            ),
        }


def identification_grid(time_s, n: int = IDENTIFY_FREQUENCIES) -> np.ndarray:
    """The frequencies (Hz) at which two descriptions of H must agree.

    ``n`` log-spaced from 1 kHz to the Nyquist frequency of the ring-downs' sampling ``time_s``
    (s): the band in which H shapes a decay (the H sampler's gates use the same band).
    """
    nyquist = 0.5 / float(time_s[1] - time_s[0])
    return np.logspace(3.0, np.log10(nyquist), n)


def to_sample(names, values) -> np.ndarray:
    """Natural values to the search space: log of the positive parameters, A_r as it is.

    :func:`fit.refine.to_sample` with the parameters along the last axis, as draws
    (n, len(names)) hold them.
    """
    return refine.to_sample(names, np.asarray(values, float).T).T


def from_sample(names, phi) -> np.ndarray:
    """:func:`fit.refine.from_sample` with the parameters along the last axis."""
    return refine.from_sample(names, np.asarray(phi, float).T).T


def _h_of(f_hz, centre: TFParams, names, values) -> np.ndarray:
    """H(f) for each row of ``values`` (n, len(names)), the others at ``centre``; shape (n, m).

    Overflow and invalid values are silenced: a least-squares step may try an extreme point,
    whose non-finite residuals are then replaced by a large number.
    """
    with np.errstate(all="ignore"):
        return transfer_function_of_draws(f_hz, centre, names, values)


def identify_h(centre: TFParams, draws, names, f_hz, starts=()) -> HIdentification:
    """The descriptions of the posterior's H(f) and the parameters the data do not identify.

    ``centre`` the reported H; ``draws`` (n, len(names)) posterior draws of ``names`` in natural
    units; ``f_hz`` the frequencies at which H must agree (Hz); ``starts`` extra starting points
    (e.g. the beat-note optima) besides the regime grid of the beat-note fit. Deterministic.
    """
    names = tuple(names)
    f = np.asarray(f_hz, float)
    draws = np.atleast_2d(np.asarray(draws, float))
    h_c = _h_of(f, centre, names, centre.as_vector(names))[0]
    h_d = _h_of(f, centre, names, draws)
    ok = np.all(np.isfinite(h_d), axis=1)
    if not ok.any():  # the posterior's support keeps H finite: this is a caller's error
        raise ValueError("no posterior draw of H is finite: nothing to compare descriptions with")
    # u(H) from the draws, floored at 1e-9 of |H| so that a part known exactly (Im H at 0 Hz)
    # cannot make a round-off difference look significant
    floor = 1e-9 * np.maximum(np.abs(h_c), 1e-12)
    u_re = np.maximum(np.std(h_d[ok].real, axis=0), floor)
    u_im = np.maximum(np.std(h_d[ok].imag, axis=0), floor)

    def z_of(h):
        """H's difference from the centre in units of u(H), real parts then imaginary parts."""
        return np.concatenate([(h.real - h_c.real) / u_re, (h.imag - h_c.imag) / u_im], axis=-1)

    threshold = max(
        SEPARATION_K, float(np.quantile(np.max(np.abs(z_of(h_d[ok])), axis=1), CLOUD_QUANTILE))
    )
    phi_d = to_sample(names, draws[ok])
    u_centre = np.std(phi_d, axis=0)
    phi_c = to_sample(names, centre.as_vector(names))
    found = []
    for start in _starts(centre, f, h_c, starts):
        d = _describe(start, names, f, centre, z_of, threshold)
        if d is None:
            continue
        du = np.hypot(u_centre, np.asarray(d.u_sample))
        apart = np.abs(to_sample(names, d.params.as_vector(names)) - phi_c) > SEPARATION_K * du
        d = replace(d, differs=tuple(n for n, a in zip(names, apart) if a))
        if d.differs and not any(_same(d, g, names) for g in found):
            found.append(d)
    found.sort(key=lambda d: d.max_z)
    bad = tuple(n for n in names if any(n in d.differs for d in found))
    return HIdentification(names, centre, threshold, tuple(found), bad)


def _starts(centre, f, h_c, extra) -> list:
    """The beat-note fit's regime grid on |H_centre|, the extra starts, the centre's A_r mirror."""
    grid = default_starts(f, np.abs(h_c), centre.variant)
    out = [replace(s, n_r=centre.n_r) for s in grid]
    out += [replace(s, variant=centre.variant) for s in extra]
    # the A_r mirror -A_r/(1 + 2 A_r) nearly repeats |H| (fit.h_calibration.beat_note_fit): a
    # start on the other side of A_r = 0, which the regime grid reaches only for weak paths
    a = centre.a_r
    if abs(1 + 2 * a) > 1e-3:
        out.append(replace(centre, a_r=float(np.clip(-a / (1 + 2 * a), -0.98, 1e4))))
    return out


def _describe(start, names, f, centre, z_of, threshold) -> HDescription | None:
    """Eq. 2 fitted (``names`` free) to H_centre from ``start``; None unless inside the cloud."""
    base = replace(centre, **{n: getattr(start, n) for n in names})
    lo = to_sample(names, [SUPPORT[n][0] for n in names])
    hi = to_sample(names, [SUPPORT[n][1] for n in names])
    x0 = np.clip(to_sample(names, base.as_vector(names)), lo + 1e-9, hi - 1e-9)

    def resid(x):
        z = z_of(_h_of(f, centre, names, from_sample(names, x))[0])
        return np.where(np.isfinite(z), z, 1e6)

    try:
        sol = optimize.least_squares(resid, x0, bounds=(lo, hi), x_scale="jac", max_nfev=400)
    except ValueError:
        return None
    max_z = float(np.max(np.abs(sol.fun)))
    if not max_z <= threshold:
        return None
    try:
        params = base.with_vector(from_sample(names, sol.x), names)
    except ValueError:
        return None
    # the sd each parameter keeps under H's uncertainty (Gauss-Newton, z is in units of u); a
    # direction H does not see (curvature below 1e-12) gets sd 1e6: free, never "apart"
    jtj = sol.jac.T @ sol.jac
    lam, vec = np.linalg.eigh(0.5 * (jtj + jtj.T))
    cov = (vec / np.maximum(lam, 1e-12)) @ vec.T
    return HDescription(params, max_z, tuple(np.sqrt(np.diag(cov))), ())


def _same(a: HDescription, b: HDescription, names) -> bool:
    """Two descriptions in one basin: within SEPARATION_K combined u in every parameter."""
    d = to_sample(names, a.params.as_vector(names)) - to_sample(names, b.params.as_vector(names))
    return bool(np.all(np.abs(d) <= SEPARATION_K * np.hypot(a.u_sample, b.u_sample)))
