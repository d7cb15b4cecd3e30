"""The result of a sampling run: chains, diagnostics, gate status and arviz export."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from bayes_tfcrds.inference.diagnostics import (
    Gates,
    _arviz_major,
    _import_arviz,
    draw_layout,
    to_draws,
)
from bayes_tfcrds.inference.posteriors import to_natural
from bayes_tfcrds.output.files import atomic_path

DRAW_LAYOUT = (
    "chain = ensemble; draw = the first half of the kept steps listed walker by walker, then the "
    "middle step of an odd length, then the second half walker by walker (coordinates step and "
    "walker give each draw's origin); az.rhat and az.ess on this layout are the gated diagnostics"
)


# --------------------------------------------------------------------------- result
def _frozen(a):
    a = np.array(a)
    a.setflags(write=False)
    return a


def parameter_values(names, priors, samples) -> dict:
    """Natural-unit values {parameter: (..., ) array} of ``samples`` (..., ndim).

    With ``priors`` the sampled coordinates are mapped back through them (e.g. exp of a
    log-uniform parameter's logarithm); without, the coordinates are the parameters ``names``.
    """
    if priors:
        return to_natural(priors, samples)
    return {n: samples[..., i] for i, n in enumerate(names)}


@dataclass(frozen=True, eq=False)
class SamplingResult:
    """Post-burn-in samples of all ensembles and the diagnostics that judged them.

    ``samples`` is (n_ensembles, n_kept_steps, n_walkers, ndim) in the sampler's coordinates
    ``names``, ``log_prob`` and ``derived[name]`` are (n_ensembles, n_kept_steps, n_walkers).
    ``priors`` (one :class:`~bayes_tfcrds.inference.posteriors.Prior` per coordinate, or empty)
    map the coordinates to the natural-unit parameters that are diagnosed, gated and saved;
    ``units`` gives the unit of every reported quantity it knows. ``n_steps`` is the total length
    per ensemble, ``burn`` the discarded leading steps. ``passed`` is True only if every gate held
    for every gated quantity in ``diagnostics``.
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
    priors: tuple = ()
    units: dict = field(default_factory=dict)

    @property
    def n_ensembles(self) -> int:
        return self.samples.shape[0]

    @property
    def n_walkers(self) -> int:
        return self.samples.shape[2]

    def flat(self) -> np.ndarray:
        """All kept samples as (N, ndim), ensemble-major then step then walker."""
        return self.samples.reshape(-1, self.samples.shape[-1])

    def parameters(self) -> dict:
        """The parameters in natural units, {name: (ensembles, steps, walkers)}."""
        return parameter_values(self.names, self.priors, self.samples)

    def variables(self) -> dict:
        """Every reported quantity: the parameters (natural units), then the derived ones."""
        return {**self.parameters(), **self.derived}

    def to_inference_data(self, units=None):
        """ArviZ data whose ``az.rhat`` and ``az.ess`` are this run's gated diagnostics.

        Posterior dims (chain, draw) in :data:`DRAW_LAYOUT` (chain = ensemble), with coordinates
        ``step`` (since the start, burn-in included) and ``walker`` along draw; parameters in
        natural units. Each variable's attributes: ``units``, its diagnostics (``rhat``,
        ``ess_bulk``, ``ess_tail``, ``tau_int``, ``n_tau``, ``tau_int_ensembles``, ``gated``) and,
        for a parameter, its prior (``prior_family``, ``prior_lower``, ``prior_upper``,
        ``prior_condition``, ``sampled_as``). The group's attributes: the run and its gates.
        ``units`` ({SI unit: (shown unit, factor)}, e.g. core.constants.EDGE_UNITS) shows the
        variables in such a unit, and their prior bounds, in the outputs' unit (``units``; the
        sampler's in ``units_sampled``); R-hat and ESS do not depend on the scale.
        """
        import xarray as xr

        e, s, w = self.samples.shape[:3]
        step, walker = draw_layout(s, w)
        coords = {
            "chain": np.arange(e),
            "draw": np.arange(s * w),
            "step": ("draw", step + self.burn),
            "walker": ("draw", walker),
        }
        priors = {p.parameter: p for p in self.priors}
        gated = self.gates.gated
        data = {}
        for name, values in self.variables().items():
            unit = self.units.get(name)
            shown, f = (units or {}).get(unit, (unit, 1.0))
            attrs = {} if unit is None else {"units": shown}
            if shown != unit:
                attrs["units_sampled"] = unit  # the diagnostics do not change with the scale
            d = self.diagnostics[name]
            attrs.update({k: np.asarray(d[k], float) for k in _DIAGNOSTIC_KEYS})
            attrs["gated"] = int(gated is None or name in gated)
            if name in priors:
                attrs.update(_prior_attrs(priors[name], f))
            data[name] = (("chain", "draw"), to_draws(f * np.asarray(values)), attrs)
        attrs = dict(
            n_ensembles=e,
            n_walkers=w,
            n_steps=self.n_steps,
            burn=self.burn,
            passed=int(self.passed),
            status=self.status,
            label=self.label,
            rhat_max=self.rhat_max,
            ess_min=self.ess_min,
            gate_rhat_max=self.gates.rhat_max,
            gate_ess_min=self.gates.ess_min,
            gate_min_tau_multiple=self.gates.min_tau_multiple,
            gated=", ".join(gated) if gated is not None else "all",
            acceptance=np.asarray(self.acceptance, dtype=float),
            draw_layout=DRAW_LAYOUT,
            inference_library="emcee",
        )
        posterior = xr.Dataset(data, coords=coords, attrs=attrs)
        stats = xr.Dataset({"lp": (("chain", "draw"), to_draws(self.log_prob))}, coords=coords)
        return _make_inference_data(posterior, stats)

    def save_netcdf(self, path, units=None) -> None:
        """Write :meth:`to_inference_data` to ``path`` atomically (temp file + os.replace)."""
        with atomic_path(path) as tmp:
            self.to_inference_data(units).to_netcdf(tmp)


_DIAGNOSTIC_KEYS = ("rhat", "ess_bulk", "ess_tail", "tau_int", "n_tau", "tau_int_ensembles")


def _prior_attrs(prior, factor: float = 1.0) -> dict:
    """The prior as netCDF attributes, its bounds times ``factor`` (the variable's shown unit)."""
    return {
        "prior_family": prior.family,
        "prior_lower": factor * float(prior.lower),
        "prior_upper": factor * float(prior.upper),
        "prior_condition": prior.condition,
        "sampled_as": prior.sample_name,
    }


def _make_inference_data(posterior, sample_stats):
    """The one arviz constructor call: 0.2x ``InferenceData`` vs 1.x's ``xarray.DataTree``."""
    az = _import_arviz()
    if _arviz_major() >= 1:
        import xarray as xr

        return xr.DataTree.from_dict({"posterior": posterior, "sample_stats": sample_stats})
    return az.InferenceData(posterior=posterior, sample_stats=sample_stats)
