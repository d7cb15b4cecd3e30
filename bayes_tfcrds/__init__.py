"""bayes-tfcrds: transfer-function-corrected CRDS with honest uncertainty budgets.

The pipeline, one subpackage per stage (imports go one way, down this list)::

    core        constants and units, linear algebra, GUM arithmetic, Quantity
    output      atomic files, plotting backend, HTML/PDF reports
    bundle      the HDF5 measurement bundle (FORMAT.md): records, reader, writer, summary
    physics     H(f), the detection chain, the ring-down forward model, line shapes, line data
    simulate    the simulator of the whole experiment
    fit         beat note, ring-downs, Appendix B refinement, H calibration, spectra, line fits
    inference   emcee runner, diagnostics, chain stores, posterior densities
    uncertainty propagation of H into tau and A, the line-area budget and its outputs
    discovery   discovery of the effect a model of the experiment is missing
    studies     declarative studies, the coverage study and the demo
    cli         ``bayes-tfcrds``: parses, calls, prints

The main job in Python (the README's "Python" section runs it in a notebook)::

    import numpy as np
    import bayes_tfcrds as bt

    bundle, truth = bt.simulate_campaign(["letter-D2"], np.random.default_rng(7))
    config = bundle.configs["D2"]
    calibration = bt.calibrate(config)                    # H: beat note, refined on ring-downs
    fits = bt.fit_config(config, [4e-6], calibration=calibration)       # every decay time
    fits, h = bt.fit_decay_times(config, [4e-6], calibration, np.random.default_rng(0))  # + u_H
    line = bt.analyse_line(bundle, config, t_cut_s=4e-6, calibration=calibration)  # at its H
    line, h = bt.analyse_line_with_h(bundle, config, calibration, np.random.default_rng(0))  # + u_H
    budget = bt.run_budget(bundle, config, bt.BudgetOptions(), np.random.default_rng(0))
    found = bt.discover(bundle, "D2")

Every result has ``summary()`` (text), ``to_dict()`` (JSON, units labelled), an HTML table in
Jupyter and ``plot()`` (a matplotlib Figure).

Names are imported on first use, so ``import bayes_tfcrds`` (and the CLI) start fast.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from bayes_tfcrds._version import __version__

#: public name -> the module that defines it
_API = {
    "load_bundle": "bayes_tfcrds.bundle.reader",
    "load_truth": "bayes_tfcrds.bundle.reader",
    "validate_file": "bayes_tfcrds.bundle.reader",
    "BundleError": "bayes_tfcrds.bundle.records",
    "Bundle": "bayes_tfcrds.bundle.records",
    "save_bundle": "bayes_tfcrds.bundle.writer",
    "TFParams": "bayes_tfcrds.physics.transfer_function",
    "transfer_function": "bayes_tfcrds.physics.transfer_function",
    "Campaign": "bayes_tfcrds.simulate.campaign",
    "simulate_campaign": "bayes_tfcrds.simulate.campaign",
    "calibrate": "bayes_tfcrds.fit.h_calibration",
    "Calibration": "bayes_tfcrds.fit.h_calibration",
    "fit_config": "bayes_tfcrds.fit.h_calibration",
    "fit_ringdowns": "bayes_tfcrds.fit.ringdown",
    "RingdownFits": "bayes_tfcrds.fit.ringdown",
    "fit_line": "bayes_tfcrds.fit.line",
    "LineFit": "bayes_tfcrds.fit.line",
    "analyse_line": "bayes_tfcrds.fit.line_analysis",
    "LineAnalysis": "bayes_tfcrds.fit.line_analysis",
    "Quantity": "bayes_tfcrds.core.quantity",
    "fit_decay_times": "bayes_tfcrds.uncertainty.decay_times",
    "analyse_line_with_h": "bayes_tfcrds.uncertainty.line_area",
    "BudgetOptions": "bayes_tfcrds.uncertainty.line_budget",
    "BudgetResult": "bayes_tfcrds.uncertainty.line_budget",
    "run_budget": "bayes_tfcrds.uncertainty.line_budget",
    "write_outputs": "bayes_tfcrds.uncertainty.outputs",
    "discover": "bayes_tfcrds.discovery.workflow",
    "DiscoveryResult": "bayes_tfcrds.discovery.workflow",
    "run_study": "bayes_tfcrds.studies.registry",
    "run_demo": "bayes_tfcrds.studies.demo",
}

__all__ = [
    "__version__",
    "load_bundle",
    "load_truth",
    "validate_file",
    "BundleError",
    "Bundle",
    "save_bundle",
    "TFParams",
    "transfer_function",
    "Campaign",
    "simulate_campaign",
    "calibrate",
    "Calibration",
    "fit_config",
    "fit_ringdowns",
    "RingdownFits",
    "fit_line",
    "LineFit",
    "analyse_line",
    "LineAnalysis",
    "Quantity",
    "fit_decay_times",
    "analyse_line_with_h",
    "BudgetOptions",
    "BudgetResult",
    "run_budget",
    "write_outputs",
    "discover",
    "DiscoveryResult",
    "run_study",
    "run_demo",
]


def __getattr__(name: str):
    module = _API.get(name)
    if module is None:
        raise AttributeError(f"module 'bayes_tfcrds' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__():
    return sorted(__all__)


if TYPE_CHECKING:  # pragma: no cover - for type checkers and IDEs only
    from bayes_tfcrds.bundle.reader import load_bundle, load_truth, validate_file
    from bayes_tfcrds.bundle.records import Bundle, BundleError
    from bayes_tfcrds.bundle.writer import save_bundle
    from bayes_tfcrds.core.quantity import Quantity
    from bayes_tfcrds.discovery.workflow import DiscoveryResult, discover
    from bayes_tfcrds.fit.h_calibration import Calibration, calibrate, fit_config
    from bayes_tfcrds.fit.line import LineFit, fit_line
    from bayes_tfcrds.fit.line_analysis import LineAnalysis, analyse_line
    from bayes_tfcrds.fit.ringdown import RingdownFits, fit_ringdowns
    from bayes_tfcrds.physics.transfer_function import TFParams, transfer_function
    from bayes_tfcrds.simulate.campaign import Campaign, simulate_campaign
    from bayes_tfcrds.studies.demo import run_demo
    from bayes_tfcrds.studies.registry import run_study
    from bayes_tfcrds.uncertainty.decay_times import fit_decay_times
    from bayes_tfcrds.uncertainty.line_area import analyse_line_with_h
    from bayes_tfcrds.uncertainty.line_budget import BudgetOptions, BudgetResult, run_budget
    from bayes_tfcrds.uncertainty.outputs import write_outputs
