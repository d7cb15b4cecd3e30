"""A chain zoo: seeded random detection chains over the regimes Eq. 2 covers.

The letter's four chains (our presets) share one shape: a slow first-order tail carrying
1/(1 + A_r) of the gain beside a fast resonant main path. Other laboratories' chains are often
the other way round: a fast main pole of a few MHz beside a weak, slower resonant path, with the
resonance above or below f_c. An analysis that is right only where it was tuned fails there, so
tests and ``benchmarks/chain_zoo.py`` draw chains from both regimes.

``tail``  slow tail + fast resonance: f_c ~ logU(10 kHz, 200 kHz), A_r ~ logU(2, 50),
          f_r ~ logU(2 MHz, 10 MHz).
``pole``  fast pole + weaker resonance: f_c ~ logU(1 MHz, 40 MHz), A_r ~ logU(0.01, 1),
          f_r ~ logU(50 kHz, 10 MHz) (below or above f_c).

Both: Gamma_r ~ U(0.2, 1.5) away from critical damping (|Gamma_r - 0.5| > 0.02: a double pole
has no partial-fraction form), n_r = 2. The simulator's truth is the exact response of the
rational chain (:mod:`bayes_tfcrds.physics.detection_chain`), so only n_r = 2 can be simulated
exactly; fractional orders have no finite pole set.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bayes_tfcrds.physics.transfer_function import TFParams

ZOO_REGIMES = ("tail", "pole")


@dataclass(frozen=True)
class ZooRanges:
    """Ranges of one regime (Hz; dimensionless A_r and Gamma_r); log-uniform except Gamma_r."""

    f_c_hz: tuple
    a_r: tuple
    f_r_hz: tuple
    gamma_r: tuple = (0.2, 1.5)


ZOO_RANGES = {
    "tail": ZooRanges(f_c_hz=(1.0e4, 2.0e5), a_r=(2.0, 50.0), f_r_hz=(2.0e6, 1.0e7)),
    "pole": ZooRanges(f_c_hz=(1.0e6, 4.0e7), a_r=(0.01, 1.0), f_r_hz=(5.0e4, 1.0e7)),
}
CRITICAL_GAP = 0.02  # |Gamma_r - 1/2| below this is redrawn (double pole)


def _log_uniform(rng: np.random.Generator, lo_hi: tuple) -> float:
    return float(np.exp(rng.uniform(np.log(lo_hi[0]), np.log(lo_hi[1]))))


def draw_chain(rng: np.random.Generator, regime: str) -> TFParams:
    """One causal Eq. 2 chain (n_r = 2) drawn from ``regime``'s ranges."""
    if regime not in ZOO_RANGES:
        raise ValueError(f"unknown chain regime {regime!r}; choose from {ZOO_REGIMES}")
    r = ZOO_RANGES[regime]
    f_c = _log_uniform(rng, r.f_c_hz)
    a_r = _log_uniform(rng, r.a_r)
    f_r = _log_uniform(rng, r.f_r_hz)
    gamma_r = float(rng.uniform(*r.gamma_r))
    while abs(gamma_r - 0.5) < CRITICAL_GAP:
        gamma_r = float(rng.uniform(*r.gamma_r))
    return TFParams(f_c_hz=f_c, a_r=a_r, f_r_hz=f_r, gamma_r=gamma_r, n_r=2.0, variant="causal")


def zoo_chains(rng: np.random.Generator, n: int, regimes=ZOO_REGIMES) -> list:
    """``n`` (regime, TFParams) pairs, the regimes taken in turn."""
    regimes = tuple(regimes)
    picks = [regimes[i % len(regimes)] for i in range(n)]
    return [(regime, draw_chain(rng, regime)) for regime in picks]
