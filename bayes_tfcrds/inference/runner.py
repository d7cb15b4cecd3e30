"""The sampler runner: independent emcee ensembles stepped together until every gate passes."""

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
from bayes_tfcrds.inference.moves import DifferentialEvolutionMove, ensemble_local
from bayes_tfcrds.inference.posteriors import sample_names
from bayes_tfcrds.inference.result import SamplingResult, _frozen, parameter_values
from bayes_tfcrds.inference.stores import (
    _Damaged,
    _HDFStore,
    _MemoryStore,
    _same_rng_state,
    _StepRecorder,
    move_aside,
)
from bayes_tfcrds.output.progress import progress_bar

log = logging.getLogger(__name__)


class _Lockstep:
    """The ensembles advanced together, committed in chunks with one continuous random stream.

    One emcee sampler holds every ensemble's walkers, one ensemble after the other, and its
    moves act within each ensemble (:func:`bayes_tfcrds.inference.moves.ensemble_local`), so the
    ensembles stay independent chains; their proposals go to the posterior in one call per half
    step, which is what makes a step cheap. Each ensemble has its own store (its own HDF5 group);
    every commit writes all of them with the sampler's generator state.
    """

    def __init__(
        self, seeds, log_prob, p0_fn, n_walkers, ndim, vectorize, pool, backend_path, chunk_steps,
        moves,
    ):  # fmt: skip
        self.n_walkers, self.chunk_steps = n_walkers, chunk_steps
        pairs = [s.spawn(2) for s in seeds]  # (starts, stream) per ensemble
        self._p0 = [
            (lambda r=init: p0_fn(r, n_walkers)) for init, _ in pairs
        ]  # only needed for a fresh start
        # the sampler's one stream is the first ensemble's (every commit stores it with each)
        ss = pairs[0][1].bit_generator.seed_seq
        self.rng0 = np.random.RandomState(np.random.MT19937(ss)).get_state()
        n_ens = len(seeds)
        self.sampler = emcee.EnsembleSampler(
            n_ens * n_walkers,
            ndim,
            log_prob,
            pool=pool,
            moves=moves,
            vectorize=vectorize,
            backend=_StepRecorder(),
        )
        fingerprints = []
        for _, stream in pairs:
            sq = stream.bit_generator.seed_seq
            fingerprints.append(
                json.dumps(
                    [str(sq.entropy), list(map(int, sq.spawn_key)), n_walkers, ndim, "lockstep"]
                    + [n_ens]
                )
            )
        self._open = lambda: [
            _MemoryStore(n_walkers, ndim, fp)
            if backend_path is None
            else _HDFStore(backend_path, f"ensemble{i}", n_walkers, ndim, fp)
            for i, fp in enumerate(fingerprints)
        ]
        self.backend_path = backend_path
        self.stores = self._open()
        if any(getattr(st, "moved_aside", False) for st in self.stores[1:]):
            self.stores = self._open()  # a later group set the file aside under the earlier ones
        self.state = None

    @property
    def iteration(self) -> int:
        return min(st.iteration for st in self.stores)

    def _initial_state(self):
        n = self.iteration
        try:
            for st in self.stores:  # a kill between the groups' writes of one commit: roll back
                if st.iteration > n:
                    st.rollback(n)
        except _Damaged as exc:  # the common step is gone from a group that is ahead
            move_aside(self.backend_path, str(exc))
            self.stores, n = self._open(), 0
        if n > 0:
            parts = [st.last() for st in self.stores]
            coords = np.concatenate([np.array(p[0]) for p in parts])
            lp = np.concatenate([np.array(p[1]) for p in parts])
            return emcee.State(coords, log_prob=lp, random_state=parts[0][2])
        starts = [np.array(f(), dtype=float) for f in self._p0]
        shape = (self.n_walkers, self.sampler.ndim)
        for e, p in enumerate(starts):
            if p.shape != shape:
                raise ValueError(f"p0_fn returned shape {p.shape}, need {shape}")
            if not emcee.ensemble.walkers_independent(p):  # emcee checks the pooled walkers only
                raise ValueError(f"ensemble {e}: p0_fn returned walkers that are not independent")
        p0 = np.concatenate(starts)
        lp, _ = self.sampler.compute_log_prob(p0)
        if not np.all(np.isfinite(lp)):
            bad = np.nonzero(~np.isfinite(lp))[0] // self.n_walkers
            raise ValueError(
                f"ensemble {int(bad[0])}: p0_fn returned walkers with non-finite log_prob "
                f"{lp[~np.isfinite(lp)]} (outside the prior?)"
            )
        return emcee.State(p0, log_prob=lp, random_state=self.rng0)

    def advance_to(self, n_total, bars=(), stop=None):
        """Run until every committed chain holds ``n_total`` steps (no-op if they already do).

        On a ``stop`` request commit the steps taken so far and raise KeyboardInterrupt.
        """
        while self.iteration < n_total:
            if self.state is None:
                self.state = self._initial_state()
            self.sampler.random_state = self.state.random_state
            if not _same_rng_state(self.sampler.random_state, self.state.random_state):
                raise RuntimeError("could not restore the sampler's random state")
            k = min(self.chunk_steps, n_total - self.iteration)
            rec = self.sampler.backend
            rec.reset(self.sampler.nwalkers, self.sampler.ndim)
            for st in self.sampler.sample(  # noqa: B007 - st is read after the loop
                self.state,
                iterations=k,
                store=True,
                skip_initial_state_check=self.iteration > 0,
            ):
                for bar in bars:
                    bar.update(1)
                if stop is not None and stop.requested:
                    break  # the chain does not depend on where chunks end
            rs = self.sampler.random_state
            chain, lp = rec.get_chain(), rec.get_log_prob()
            acc = np.array(rec.accepted_steps)
            w = self.n_walkers
            for e, store in enumerate(self.stores):
                cols = slice(e * w, (e + 1) * w)
                store.append(chain[:, cols], lp[:, cols], acc[:, cols], rs)
            self.state = emcee.State(st.coords.copy(), log_prob=st.log_prob.copy(), random_state=rs)
            if stop is not None and stop.requested:
                raise KeyboardInterrupt

    def read(self, n):
        """(chains, log_probs, accepted) of the first ``n`` steps, ensembles stacked first."""
        parts = [st.read(n) for st in self.stores]
        return tuple(np.stack(p) for p in zip(*parts))


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
    moves: emcee (move, weight) pairs that keep to each ensemble (see
        :func:`bayes_tfcrds.inference.moves.ensemble_local`); default differential evolution.
        All ensembles step together in one sampler: one posterior call per half step for all.
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
        raise ValueError(
            f"need n_walkers >= 2*ndim = {2 * ndim}: each half of an ensemble proposes moves for "
            "the other and must span the parameter space"
        )
    if not 1 <= n_steps <= max_steps:
        raise ValueError(f"need 1 <= n_steps ({n_steps}) <= max_steps ({max_steps})")
    if chunk_steps < 1:
        raise ValueError("chunk_steps must be >= 1")
    if priors and sample_names(priors) != names:
        raise ValueError(f"priors sample {sample_names(priors)}, not the names {names}")

    moves = ensemble_local(
        moves if moves is not None else [(DifferentialEvolutionMove(), 1.0)], n_ensembles
    )
    lock = _Lockstep(
        rng.spawn(n_ensembles),
        log_prob,
        p0_fn,
        n_walkers,
        ndim,
        vectorize,
        pool,
        backend_path,
        int(chunk_steps),
        moves,
    )
    bars = []
    if progress:
        prefix = f"{label} " if label else ""
        bars = [
            progress_bar(
                total=n_steps,
                initial=min(lock.iteration, n_steps),
                desc=f"{prefix}ensemble {e}",
                position=e,
            )
            for e, st in enumerate(lock.stores)
        ]
    stop = _StopRequest()
    try:
        stop.__enter__()
        target = int(n_steps)
        while True:
            for bar in bars:
                bar.total = target
                bar.refresh()
            lock.advance_to(target, bars, stop)
            chains, lps, acc = lock.read(target)
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
                break
            target = extended_length(result, target, gates, int(max_steps))
    finally:
        stop.__exit__()
        for b in bars:
            b.close()
    if stop.requested:
        # Ctrl-C after the last step (in the diagnostics): the chains are committed; stop as
        # the user asked instead of carrying on with the rest of the command
        raise KeyboardInterrupt
    return result
