"""The sampler runner: independent emcee ensembles extended until every gate passes."""

from __future__ import annotations

import json
import logging
import math
import signal
import threading
from collections.abc import Callable, Sequence

import emcee
import numpy as np

from bayes_tfcrds.inference.diagnostics import Gates, _gate_failures, burn_in, chain_diagnostics
from bayes_tfcrds.inference.posteriors import sample_names
from bayes_tfcrds.inference.result import SamplingResult, _frozen, parameter_values
from bayes_tfcrds.inference.stores import _HDFStore, _MemoryStore, _same_rng_state, _StepRecorder
from bayes_tfcrds.output.progress import progress_bar

log = logging.getLogger(__name__)


class _Ensemble:
    """One emcee ensemble advanced in committed chunks with a continuous random stream."""

    def __init__(
        self,
        index,
        seed,
        log_prob,
        p0_fn,
        n_walkers,
        ndim,
        vectorize,
        pool,
        backend_path,
        chunk_steps,
        moves=None,
    ):
        init_rng, mcmc_rng = seed.spawn(2)
        ss = mcmc_rng.bit_generator.seed_seq
        fingerprint = json.dumps([str(ss.entropy), list(map(int, ss.spawn_key)), n_walkers, ndim])
        self.index, self.chunk_steps = index, chunk_steps
        self._p0 = lambda: p0_fn(init_rng, n_walkers)  # only needed for a fresh start
        self.rng0 = np.random.RandomState(np.random.MT19937(ss)).get_state()
        self.sampler = emcee.EnsembleSampler(
            n_walkers,
            ndim,
            log_prob,
            pool=pool,
            moves=moves,
            vectorize=vectorize,
            backend=_StepRecorder(),
        )
        self.store = (
            _MemoryStore(n_walkers, ndim, fingerprint)
            if backend_path is None
            else _HDFStore(backend_path, f"ensemble{index}", n_walkers, ndim, fingerprint)
        )
        self.state = None

    def _initial_state(self):
        if self.store.iteration > 0:
            coords, lp, rs = self.store.last()
            return emcee.State(np.array(coords), log_prob=np.array(lp), random_state=rs)
        p0 = np.array(self._p0(), dtype=float)
        shape = (self.sampler.nwalkers, self.sampler.ndim)
        if p0.shape != shape:
            raise ValueError(f"p0_fn returned shape {p0.shape}, need {shape}")
        lp, _ = self.sampler.compute_log_prob(p0)
        if not np.all(np.isfinite(lp)):
            raise ValueError(
                f"ensemble {self.index}: p0_fn returned walkers with non-finite log_prob "
                f"{lp[~np.isfinite(lp)]} (outside the prior?)"
            )
        return emcee.State(p0, log_prob=lp, random_state=self.rng0)

    def advance_to(self, n_total, pbar=None, stop=None):
        """Run until the committed chain holds ``n_total`` steps (no-op if it already does).

        On a ``stop`` request commit the steps taken so far and raise KeyboardInterrupt.
        """
        while self.store.iteration < n_total:
            if self.state is None:
                self.state = self._initial_state()
            self.sampler.random_state = self.state.random_state
            if not _same_rng_state(self.sampler.random_state, self.state.random_state):
                raise RuntimeError("could not restore the sampler's random state")
            k = min(self.chunk_steps, n_total - self.store.iteration)
            rec = self.sampler.backend
            rec.reset(self.sampler.nwalkers, self.sampler.ndim)
            for st in self.sampler.sample(  # noqa: B007 - st is read after the loop
                self.state,
                iterations=k,
                store=True,
                skip_initial_state_check=self.store.iteration > 0,
            ):
                if pbar is not None:
                    pbar.update(1)
                if stop is not None and stop.requested:
                    break  # the chain does not depend on where chunks end
            rs = self.sampler.random_state
            self.store.append(rec.get_chain(), rec.get_log_prob(), np.array(rec.accepted_steps), rs)
            self.state = emcee.State(st.coords.copy(), log_prob=st.log_prob.copy(), random_state=rs)
            if stop is not None and stop.requested:
                raise KeyboardInterrupt

    def read(self, n):
        return self.store.read(n)


class _StopRequest:
    """Ctrl-C while sampling: finish and commit the step in progress, then stop.

    Python's default handler would raise KeyboardInterrupt inside log_prob, where emcee prints
    a traceback and discards the chunk. Installed only over the default handler and in the
    main thread; a second Ctrl-C interrupts at once.
    """

    def __init__(self):
        self.requested = False
        self._old = None

    def __enter__(self):
        if (
            threading.current_thread() is threading.main_thread()
            and signal.getsignal(signal.SIGINT) is signal.default_int_handler
        ):
            self._old = signal.signal(signal.SIGINT, self._handle)
        return self

    def _handle(self, signum, frame):
        self.requested = True
        signal.signal(signal.SIGINT, self._old)

    def __exit__(self, *exc):
        if self._old is not None:
            signal.signal(signal.SIGINT, self._old)
        return False


# --------------------------------------------------------------------------- runner
GROWTH_MIN, GROWTH_MAX = 1.2, 3.0  # bounds of one extension (factor on the chain length)
GROWTH_MARGIN = 1.1  # aim past the gate: tau_int and ESS are themselves estimates
GROWTH_RHAT = 1.5  # an R-hat failure says nothing about how much longer: half again


def _gated(diagnostics: dict, gates: Gates) -> dict:
    """The diagnostics of the quantities the gates apply to (all when none is named)."""
    return {
        k: d for k, d in diagnostics.items() if gates.gated is None or k in gates.gated
    } or diagnostics


def extended_length(result: SamplingResult, n: int, gates: Gates, max_steps: int) -> int:
    """The chain length to extend to after ``result`` (``n`` steps) failed a gate.

    Only the kept length matters to the tau and ESS gates (ESS grows in proportion to it, and
    the kept share of the chain is about constant), so the chain grows by the largest factor
    they report missing, times a margin; an R-hat failure grows it by half. The factor is held
    within [1.2, 3]: a little growth is not worth a round of diagnostics, and too much on a
    noisy tau estimate wastes work.
    """
    gated = _gated(result.diagnostics, gates)
    factor = GROWTH_MIN
    for d in gated.values():
        if not d["rhat"] < gates.rhat_max:
            factor = max(factor, GROWTH_RHAT)
        for key, need in (
            ("n_tau", gates.min_tau_multiple),
            ("ess_bulk", gates.ess_min),
            ("ess_tail", gates.ess_min),
        ):
            have = d[key]
            if not have > need:
                missing = need / have if have > 0 and math.isfinite(have) else GROWTH_MAX
                factor = max(factor, GROWTH_MARGIN * missing)
    factor = min(factor, GROWTH_MAX)
    return min(int(max_steps), math.ceil(round(factor * n, 6)))


def _evaluate(
    names, chains, log_prob, accepted, derived_fn, gates, label, priors=(), units=None
) -> SamplingResult:
    n = chains.shape[1]
    burn = burn_in(chains)
    kept, lp_kept, acc_kept = chains[:, burn:], log_prob[:, burn:], accepted[:, burn:]
    # diagnosed in natural units, as the files hold them (the tail R-hat folds about the median,
    # which is not invariant under the log of a log-uniform parameter)
    values = parameter_values(names, priors, kept)
    diagnostics = {nm: chain_diagnostics(v) for nm, v in values.items()}
    derived = {}
    if derived_fn is not None:
        shape = kept.shape[:3]
        for nm, v in derived_fn(kept.reshape(-1, kept.shape[-1])).items():
            if nm in diagnostics:
                raise ValueError(f"derived quantity {nm!r} clashes with a parameter name")
            derived[nm] = _frozen(np.asarray(v, dtype=float).reshape(shape))
            diagnostics[nm] = chain_diagnostics(derived[nm])
    gated = _gated(diagnostics, gates)
    failures = _gate_failures(gated, gates)
    status = "passed" if not failures else f"failed after {n} steps: " + "; ".join(failures)
    rh = [d["rhat"] for d in gated.values()]
    es = [min(d["ess_bulk"], d["ess_tail"]) for d in gated.values()]
    return SamplingResult(
        names=tuple(names),
        samples=_frozen(kept),
        log_prob=_frozen(lp_kept),
        diagnostics=diagnostics,
        rhat_max=float(np.nan if np.any(np.isnan(rh)) else max(rh)),
        ess_min=float(np.nan if np.any(np.isnan(es)) else min(es)),
        passed=not failures,
        status=status,
        n_steps=n,
        burn=burn,
        acceptance=_frozen(acc_kept.mean(axis=(1, 2))),
        derived=derived,
        gates=gates,
        label=label,
        priors=tuple(priors),
        units={**{p.parameter: p.unit for p in priors}, **(units or {})},
    )


def run_ensembles(
    log_prob: Callable,
    p0_fn: Callable,
    names: Sequence[str],
    rng: np.random.Generator,
    n_ensembles: int = 4,
    n_walkers: int | None = None,
    n_steps: int = 2000,
    max_steps: int = 20000,
    vectorize: bool = False,
    backend_path=None,
    progress: bool = False,
    label: str = "",
    pool=None,
    gates: Gates = Gates(),
    *,
    derived_fn: Callable | None = None,
    chunk_steps: int = 100,
    moves=None,
    priors: Sequence = (),
    units: dict | None = None,
) -> SamplingResult:
    """Sample ``log_prob`` with independent emcee ensembles until the gates pass or ``max_steps``.

    log_prob: ``theta (ndim,) -> float``, or with ``vectorize=True``
        ``thetas (n_walkers, ndim) -> (n_walkers,)``; ``-inf`` outside the prior.
    p0_fn: ``(rng, n_walkers) -> (n_walkers, ndim)`` starting positions (finite log_prob).
    rng: a ``numpy.random.Generator``; a fresh ``default_rng(seed)`` reproduces the run bit
        for bit (children are spawned from it, so reusing one object gives new chains).
    n_walkers: default ``max(32, 4 * ndim)``.
    n_steps, max_steps: first and largest total length per ensemble (burn-in included).
    backend_path: HDF5 file to commit chunks to and resume from (see module docstring).
    progress: one bar per ensemble, labelled with ``label`` (periodic log lines when stderr is
        not a terminal: :func:`bayes_tfcrds.output.progress.progress_bar`).
    pool: object with ``map`` passed to emcee (ignored by emcee when ``vectorize``).
    derived_fn: ``samples (n, ndim) -> {name: (n,) array}``; derived quantities get the
        same diagnostics and gates as the parameters.
    chunk_steps: steps between commits; the chains do not depend on it.
    priors: the :class:`~bayes_tfcrds.inference.posteriors.Prior` of each coordinate (their
        ``sample_name`` must be ``names``): the natural-unit parameters they map to are
        diagnosed, gated and saved, and the priors are recorded in the result.
    units: the unit of each derived quantity (the parameters' come from ``priors``).

    Returns a :class:`SamplingResult`; a failed gate is reported there (``passed=False``),
    never raised and never hidden.
    """
    names = tuple(str(n) for n in names)
    ndim = len(names)
    if len(set(names)) != ndim or ndim == 0:
        raise ValueError(f"need unique, non-empty parameter names, got {names}")
    if n_ensembles < 4:
        raise ValueError("R-hat needs at least 4 independent ensembles")
    n_walkers = max(32, 4 * ndim) if n_walkers is None else int(n_walkers)
    if n_walkers < 2 * ndim:
        raise ValueError(f"emcee's stretch move needs n_walkers >= 2*ndim = {2 * ndim}")
    if not 1 <= n_steps <= max_steps:
        raise ValueError(f"need 1 <= n_steps ({n_steps}) <= max_steps ({max_steps})")
    if chunk_steps < 1:
        raise ValueError("chunk_steps must be >= 1")
    if priors and sample_names(priors) != names:
        raise ValueError(f"priors sample {sample_names(priors)}, not the names {names}")

    ensembles = [
        _Ensemble(
            i,
            s,
            log_prob,
            p0_fn,
            n_walkers,
            ndim,
            vectorize,
            pool,
            backend_path,
            moves=moves,
            chunk_steps=int(chunk_steps),
        )
        for i, s in enumerate(rng.spawn(n_ensembles))
    ]
    bars = []
    if progress:
        prefix = f"{label} " if label else ""
        bars = [
            progress_bar(
                total=n_steps,
                initial=min(e.store.iteration, n_steps),
                desc=f"{prefix}ensemble {e.index}",
                position=e.index,
            )
            for e in ensembles
        ]
    stop = _StopRequest()
    try:
        stop.__enter__()
        target = int(n_steps)
        while True:
            for i, e in enumerate(ensembles):
                if bars:
                    bars[i].total = target
                    bars[i].refresh()
                e.advance_to(target, bars[i] if bars else None, stop)
            parts = [e.read(target) for e in ensembles]
            chains, lps, acc = (np.stack(p) for p in zip(*parts))
            result = _evaluate(
                names, chains, lps, acc, derived_fn, gates, label, tuple(priors), units
            )
            log.debug(
                "%s: %d steps per ensemble, R-hat max %.4g, ESS min %.4g: %s",
                label or "sampler",
                target,
                result.rhat_max,
                result.ess_min,
                result.status,
            )
            if result.passed or target >= max_steps:
                return result
            target = extended_length(result, target, gates, int(max_steps))
    finally:
        stop.__exit__()
        for b in bars:
            b.close()
