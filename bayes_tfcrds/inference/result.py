"""The result of a sampling run: chains, diagnostics, gate status and arviz export."""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np

from bayes_tfcrds.inference.diagnostics import Gates, _arviz_major, _import_arviz
from bayes_tfcrds.output.files import atomic_path


# --------------------------------------------------------------------------- result
def _frozen(a):
    a = np.array(a)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class SamplingResult:
    """Post-burn-in samples of all ensembles and the diagnostics that judged them.

    ``samples`` is (n_ensembles, n_kept_steps, n_walkers, ndim), ``log_prob`` and
    ``derived[name]`` are (n_ensembles, n_kept_steps, n_walkers). ``n_steps`` is the total
    length per ensemble, ``burn`` the discarded leading steps. ``passed`` is True only if
    every gate held for every quantity in ``diagnostics``.
    """

    names: tuple
    samples: np.ndarray
    log_prob: np.ndarray
    diagnostics: dict
    rhat_max: float
    ess_min: float
    passed: bool
    status: str
    n_steps: int
    burn: int
    acceptance: np.ndarray
    derived: dict = field(default_factory=dict)
    gates: Gates = Gates()
    label: str = ""

    @property
    def n_ensembles(self) -> int:
        return self.samples.shape[0]

    @property
    def n_walkers(self) -> int:
        return self.samples.shape[2]

    def flat(self) -> np.ndarray:
        """All kept samples as (N, ndim), ensemble-major then step then walker."""
        return self.samples.reshape(-1, self.samples.shape[-1])

    def to_inference_data(self):
        """ArviZ data with posterior dims (chain, draw), chain = ensemble * n_walkers + walker.

        That is emcee's convention for arviz (a walker is a "chain"); note that arviz's own
        R-hat/ESS on these chains are not the gated diagnostics, which are in the attrs.
        """

        def chains(a):  # (E, S, W) -> (E * W, S)
            return np.swapaxes(np.asarray(a), 1, 2).reshape(-1, a.shape[1])

        posterior = {n: chains(self.samples[..., i]) for i, n in enumerate(self.names)}
        posterior.update({n: chains(v) for n, v in self.derived.items()})
        attrs = dict(
            n_ensembles=self.n_ensembles,
            n_walkers=self.n_walkers,
            n_steps=self.n_steps,
            burn=self.burn,
            passed=int(self.passed),
            status=self.status,
            label=self.label,
            diagnostics=json.dumps(self.diagnostics),
            gates=json.dumps(self.gates.__dict__),
            acceptance=np.asarray(self.acceptance, dtype=float),
        )
        return _make_inference_data(posterior, {"lp": chains(self.log_prob)}, attrs)

    def save_netcdf(self, path) -> None:
        """Write :meth:`to_inference_data` to ``path`` atomically (temp file + os.replace)."""
        with atomic_path(path) as tmp:
            self.to_inference_data().to_netcdf(tmp)


def _make_inference_data(posterior: dict, sample_stats: dict, attrs: dict):
    """The one arviz constructor call: 0.2x ``from_dict(posterior=...)`` vs 1.x group dict."""
    az = _import_arviz()
    if _arviz_major() >= 1:
        return az.from_dict(
            {"posterior": posterior, "sample_stats": sample_stats}, attrs={"posterior": attrs}
        )
    return az.from_dict(posterior=posterior, sample_stats=sample_stats, posterior_attrs=attrs)
