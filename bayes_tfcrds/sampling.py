"""Ensemble MCMC (emcee) with convergence diagnostics that can say "no".

Every Bayesian result in the toolkit is sampled through :func:`run_ensembles`. It runs
``n_ensembles`` (>= 4) *independent* emcee ensembles, because the walkers of one ensemble
are coupled by the stretch move and are not independent chains; a convergence check
needs chains that could have disagreed.

Diagnostics (per parameter and per derived quantity, :func:`chain_diagnostics`)
    * ``rhat``: rank-normalised split R-hat (Vehtari et al. 2021, via arviz) with one
      chain per ensemble, i.e. the ensemble's post-burn-in samples flattened step-major
      (all walkers at step 1, then step 2, ...).
    * ``tau_int``: integrated autocorrelation time in steps, largest over the ensembles,
      of the rank-normalised values, with emcee's Sokal window (``c = 5``).
    * ``ess_bulk`` = sum over ensembles of ``n_kept * n_walkers / tau_e``; ``ess_tail`` =
      the smaller of the same for the indicator series 1[x <= q05] and 1[x >= q95] (pooled
      quantiles). ArviZ's per-chain ESS on flattened walkers is *not* used: it would treat
      the coupled walkers of one step as consecutive draws of one chain.
    * ``n_tau``: kept chain length in units of ``tau_int``.

    tau_e is emcee's estimator with one change: the autocovariance of every walker is
    taken about the *ensemble* mean and averaged over walkers before normalising. emcee's
    ``integrated_time`` centres each walker on its own mean, which biases tau low by
    ~2*window/n (for an AR(1) chain with tau = 39: -14 % at 2000 steps, -43 % at 500)
    and returns NaN when a walker never visits a 5 % tail; both would make ESS
    optimistic. For long chains the two agree.

Gates (:class:`Gates`): every reported quantity needs R-hat < ``rhat_max``, bulk and tail
ESS > ``ess_min`` and kept length > ``min_tau_multiple`` * tau_int. If a gate fails, all
ensembles are extended by 50 % of the current length, up to ``max_steps``; after that the
result comes back with ``passed=False`` and a ``status`` naming the gate and quantity.

Burn-in rule: ``burn = min(max(ceil(0.2 n), ceil(2 tau_pilot)), n // 2)`` where
``tau_pilot`` is the largest tau_int over parameters and ensembles measured on steps
``ceil(0.2 n):n``. The 20 % floor protects against a tau estimate that is itself still
biased by the initial transient; the ``n // 2`` cap keeps something to diagnose (a chain
whose burn-in hits the cap fails the tau gate anyway).

Determinism and resume
    Each ensemble gets two child seeds from ``rng.spawn``: one generator for ``p0_fn`` and
    one MT19937 ``RandomState`` that is installed as the sampler's generator (emcee 3.1
    has no ``seed=`` argument and would otherwise start from the global ``np.random``
    state). Sampling proceeds in chunks of ``chunk_steps``; after every chunk the
    positions, log-probabilities, per-step acceptances *and* the generator state are
    committed together. The random stream is continuous across chunks (emcee draws no
    random numbers when a run starts from a state with known log-probabilities), so the
    chain does not depend on where chunks, extensions or interruptions fall: a run that
    is interrupted (KeyboardInterrupt, SIGKILL) and rerun with the same arguments is bit
    for bit the uninterrupted run. Ctrl-C while sampling commits the steps already taken
    and then raises KeyboardInterrupt (a second Ctrl-C stops at once).

    With ``backend_path`` the commits go to an HDF5 file in emcee's ``HDFBackend`` layout
    (group ``ensemble{i}``: ``chain``, ``log_prob``, ``accepted``, attrs ``iteration`` and
    ``random_state_*``) plus a dataset ``accepted_step`` and a seed fingerprint, so the
    file can be read with ``emcee.backends.HDFBackend(path, name="ensemble0")``. The file
    is open only while a finished chunk is written (never while log_prob runs); rows are
    written first and the ``iteration`` counter that makes them visible last, then the
    file is flushed and closed. HDF5 is not journaled, so a kill inside that write is
    recovered from on resume rather than excluded: each commit stores the generator state
    in one of two alternating slots with a checksum of its rows, and resume takes the
    newest commit whose rows check out (see ``_HDFStore``). Reusing a file with a
    different seed raises instead of silently mixing chains.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import secrets
import signal
import threading
import warnings
from dataclasses import dataclass, field
from typing import Callable, Optional, Sequence

import emcee
import h5py
import numpy as np
from emcee.autocorr import auto_window
from scipy.special import ndtri
from scipy.stats import rankdata

__all__ = ["Gates", "SamplingResult", "run_ensembles", "chain_diagnostics", "rhat_rank",
           "integrated_time"]

_SEED_ATTR = "bayes_tfcrds_seed"


@dataclass(frozen=True)
class Gates:
    """Convergence requirements that every reported quantity must meet."""

    rhat_max: float = 1.01
    ess_min: float = 400.0
    min_tau_multiple: float = 50.0


# --------------------------------------------------------------------------- diagnostics
def _import_arviz():
    """Import arviz lazily (slow import) and without its 1.x-refactor FutureWarning."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        import arviz
    return arviz


def _arviz_major() -> int:
    return int(_import_arviz().__version__.split(".")[0])


def rhat_rank(chains) -> float:
    """Rank-normalised split R-hat of ``chains`` (n_chains, n_draws).

    The only place arviz's R-hat is called: arviz 0.2x takes a (chain, draw) ndarray in
    ``arviz.rhat``; arviz >= 1.0 moved array functions to ``arviz_stats.base.array_stats``.
    """
    x = np.asarray(chains, dtype=float)
    if x.ndim != 2 or x.shape[0] < 2:
        raise ValueError(f"need (n_chains >= 2, n_draws), got {x.shape}")
    if _arviz_major() >= 1:
        from arviz_stats.base import array_stats
        return float(array_stats.rhat(x, chain_axis=0, draw_axis=1, method="rank"))
    return float(_import_arviz().rhat(x, method="rank"))


def integrated_time(x) -> float:
    """Integrated autocorrelation time (in steps) of one ensemble's series ``x`` (steps, walkers).

    emcee's estimator (FFT autocovariance, Sokal window with c = 5) but centred on the
    ensemble mean and averaged over walkers before normalisation (see module docstring).
    Returns ``inf`` for a constant series: it carries no information about the quantity.
    """
    x = np.asarray(x, dtype=float)
    n = x.shape[0]
    y = x - x.mean()
    nfft = 1 << max(0, (2 * n - 1).bit_length())
    f = np.fft.rfft(y, n=nfft, axis=0)
    acov = np.fft.irfft(f * np.conj(f), n=nfft, axis=0)[:n].mean(axis=1)
    if not acov[0] > 0.0:
        return math.inf
    taus = 2.0 * np.cumsum(acov / acov[0]) - 1.0
    return float(taus[auto_window(taus, 5.0)])


def _rank_normal(x):
    """Rank-normalised values (Vehtari et al. 2021): Phi^-1((r - 3/8) / (N + 1/4)), pooled."""
    r = rankdata(x, axis=None).reshape(np.shape(x))
    return ndtri((r - 0.375) / (np.size(x) + 0.25))


def _ess_from_taus(taus, n_steps, n_walkers):
    taus = np.asarray(taus, dtype=float)
    return float(np.sum(np.where(np.isfinite(taus) & (taus > 0), n_steps * n_walkers / taus, 0.0)))


def chain_diagnostics(x) -> dict:
    """R-hat, bulk/tail ESS and tau_int of one quantity sampled as ``x`` (ensembles, steps, walkers).

    Returns plain floats (JSON-able): ``rhat``, ``ess_bulk``, ``ess_tail``, ``tau_int``
    (largest over ensembles, steps), ``n_tau`` (steps / tau_int) and ``tau_int_ensembles``.
    """
    x = np.asarray(x, dtype=float)
    if x.ndim != 3:
        raise ValueError(f"need (ensembles, steps, walkers), got {x.shape}")
    n_ens, n, n_w = x.shape
    if not np.all(np.isfinite(x)):
        nan = float("nan")
        return dict(rhat=nan, ess_bulk=nan, ess_tail=nan, tau_int=nan, n_tau=nan,
                    tau_int_ensembles=[nan] * n_ens)
    z = _rank_normal(x)
    tau = [integrated_time(z[e]) for e in range(n_ens)]
    q05, q95 = np.quantile(x, [0.05, 0.95])
    tails = []
    for ind in (x <= q05, x >= q95):
        tails.append(_ess_from_taus([integrated_time(ind[e]) for e in range(n_ens)], n, n_w))
    tau_max = float(max(tau))
    return dict(
        rhat=rhat_rank(x.reshape(n_ens, n * n_w)),
        ess_bulk=_ess_from_taus(tau, n, n_w),
        ess_tail=float(min(tails)),
        tau_int=tau_max,
        n_tau=float(n / tau_max) if tau_max > 0 else math.inf,
        tau_int_ensembles=[float(t) for t in tau],
    )


def burn_in(chains) -> int:
    """Steps to discard from ``chains`` (ensembles, steps, walkers, ndim); rule in module docstring."""
    n = chains.shape[1]
    start = math.ceil(0.2 * n)
    pilot = chains[:, start:]
    tau = max(integrated_time(z[e]) for d in range(chains.shape[3])
              for z in [_rank_normal(pilot[..., d])] for e in range(chains.shape[0]))
    if not math.isfinite(tau):
        return n // 2
    return min(max(start, math.ceil(2.0 * tau)), n // 2)


def _gate_failures(diagnostics: dict, gates: Gates) -> list:
    """Human-readable list of failed gates; NaN never passes."""
    out = []
    for name, d in diagnostics.items():
        if not d["rhat"] < gates.rhat_max:
            out.append(f"rhat({name})={d['rhat']:.4g} >= {gates.rhat_max:g}")
        for key in ("ess_bulk", "ess_tail"):
            if not d[key] > gates.ess_min:
                out.append(f"{key}({name})={d[key]:.4g} <= {gates.ess_min:g}")
        if not d["n_tau"] > gates.min_tau_multiple:
            out.append(f"n_tau({name})={d['n_tau']:.4g} <= {gates.min_tau_multiple:g} "
                       f"(kept length / tau_int, tau_int={d['tau_int']:.4g} steps)")
    return out


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
            n_ensembles=self.n_ensembles, n_walkers=self.n_walkers, n_steps=self.n_steps,
            burn=self.burn, passed=int(self.passed), status=self.status, label=self.label,
            diagnostics=json.dumps(self.diagnostics), gates=json.dumps(self.gates.__dict__),
            acceptance=np.asarray(self.acceptance, dtype=float),
        )
        return _make_inference_data(posterior, {"lp": chains(self.log_prob)}, attrs)

    def save_netcdf(self, path) -> None:
        """Write :meth:`to_inference_data` to ``path`` atomically (temp file + os.replace)."""
        path = os.path.abspath(os.fspath(path))
        # not mkstemp: its 0600 mode would stick to the result; this one follows the umask
        tmp = os.path.join(os.path.dirname(path),
                           f".{os.path.basename(path)}.{secrets.token_hex(6)}.tmp")
        os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
        try:
            self.to_inference_data().to_netcdf(tmp)
            with open(tmp, "rb+") as f:
                os.fsync(f.fileno())
            os.replace(tmp, path)
        except BaseException:
            if os.path.exists(tmp):
                os.unlink(tmp)
            raise


def _make_inference_data(posterior: dict, sample_stats: dict, attrs: dict):
    """The one arviz constructor call: 0.2x ``from_dict(posterior=...)`` vs 1.x group dict."""
    az = _import_arviz()
    if _arviz_major() >= 1:
        return az.from_dict({"posterior": posterior, "sample_stats": sample_stats},
                            attrs={"posterior": attrs})
    return az.from_dict(posterior=posterior, sample_stats=sample_stats, posterior_attrs=attrs)


# --------------------------------------------------------------------------- storage
class _StepRecorder(emcee.backends.Backend):
    """In-memory emcee backend for one chunk that also keeps per-step acceptance."""

    def reset(self, nwalkers, ndim):
        super().reset(nwalkers, ndim)
        self.accepted_steps = []

    def save_step(self, state, accepted):
        super().save_step(state, accepted)
        self.accepted_steps.append(np.array(accepted, dtype=bool))


class _MemoryStore:
    """Committed chunks of one ensemble, kept in memory (no resume across processes)."""

    def __init__(self, n_walkers, ndim, fingerprint):
        self.iteration = 0
        self._chunks = []
        self._rng = None

    def append(self, chain, log_prob, accepted, random_state):
        self._chunks.append((chain.copy(), log_prob.copy(), accepted.copy()))
        self._rng = random_state
        self.iteration += chain.shape[0]

    def last(self):
        chain, lp, _ = self._chunks[-1]
        return chain[-1], lp[-1], self._rng

    def read(self, n):
        parts = [np.concatenate(p)[:n] for p in zip(*self._chunks)]
        return tuple(parts)


class _HDFStore:
    """Committed chunks of one ensemble in an HDF5 file, emcee ``HDFBackend`` layout.

    HDF5 is not journaled and a kill (or Ctrl-C) can land between any two writes of a
    commit, so a commit does not rely on write order. The generator state that continues
    the chain is kept in two slots used alternately, each tagged with the iteration it
    belongs to and a SHA-256 of the rows of the chunk that ends there; the slot holding the
    last good commit is never overwritten. On resume the slot matching ``iteration`` is
    checked against the stored rows; if the last commit is incomplete the store rolls back
    to the previous one, and a file that cannot be read at all is moved aside and the
    ensemble restarts from its seed. The chain is a deterministic function of the seed, so
    every one of these paths ends in the same samples.
    """

    _SLOTS = 2

    def __init__(self, path, name, n_walkers, ndim, fingerprint):
        self.path = os.fspath(path)
        self.backend = emcee.backends.HDFBackend(self.path, name=name)
        self._state = None
        fresh = True
        if os.path.exists(self.path):
            try:
                fresh = not self._resume(name, n_walkers, ndim, fingerprint)
            except _Damaged as exc:
                aside = f"{self.path}.damaged-{os.getpid()}"
                os.replace(self.path, aside)
                warnings.warn(f"{self.path}: {exc}; moved to {aside} and sampling {name} from its "
                              "seed again (the result does not depend on it)", RuntimeWarning,
                              stacklevel=4)
                self.backend = emcee.backends.HDFBackend(self.path, name=name)
        if fresh:
            self.backend.reset(n_walkers, ndim)
            with self.backend.open("a") as f:
                g = f[name]
                g.create_dataset("accepted_step", (0, n_walkers), maxshape=(None, n_walkers),
                                 dtype=np.uint8)
                g.attrs[_SEED_ATTR] = fingerprint
            self.iteration = 0

    def _resume(self, name, n_walkers, ndim, fingerprint) -> bool:
        """Pick up the last intact commit; False if the group is absent or holds nothing."""
        try:
            with h5py.File(self.path, "r") as f:
                if name not in f:
                    return False
                g = f[name]
                stored = g.attrs.get(_SEED_ATTR)
                it = int(g.attrs["iteration"])
                shape = (int(g.attrs["nwalkers"]), int(g.attrs["ndim"]))
                if stored is None and it == 0:
                    return False          # killed between creating the group and tagging it
                if stored != fingerprint:
                    raise ValueError(f"{self.path}:{name} was written with another seed or setup "
                                     f"({stored!r} != {fingerprint!r}); use a new backend_path")
                if shape != (n_walkers, ndim):
                    raise ValueError(f"{self.path}:{name} holds shape {shape}, not "
                                     f"{(n_walkers, ndim)}")
                if it == 0:
                    good = 0, None
                else:
                    good = self._last_intact(g, it)
        except (OSError, KeyError, RuntimeError) as exc:
            if "unable to lock file" in str(exc).lower():   # HDF5's lock: another run writes it
                raise RuntimeError(f"{self.path} is open in another process (another run writing to the "
                                   "same output?); not touched") from exc
            raise _Damaged(f"cannot be read ({type(exc).__name__}: {exc})") from exc
        if good is None:
            raise _Damaged(f"ensemble {name} has no intact commit")
        n, state = good
        if n != it:
            with self.backend.open("a") as f:
                f[name].attrs["iteration"] = n    # roll back over the incomplete commit
        self.iteration, self._state = n, state
        return n > 0

    @staticmethod
    def _rows_digest(g, lo, hi) -> str:
        h = hashlib.sha256()
        for key in ("chain", "log_prob", "accepted_step"):
            h.update(np.ascontiguousarray(g[key][lo:hi]).tobytes())
        return h.hexdigest()

    def _slot(self, g, s):
        pre = f"bayes_tfcrds_state{s}_"
        if pre + "iteration" not in g.attrs:
            return None
        state = tuple(g.attrs[f"{pre}{i}"] for i in range(int(g.attrs[pre + "n"])))
        return int(g.attrs[pre + "start"]), int(g.attrs[pre + "iteration"]), \
            str(g.attrs[pre + "sha256"]), state

    def _last_intact(self, g, it):
        """(iteration, generator state) of the newest commit whose rows are on disk, or None."""
        slots = [x for x in (self._slot(g, s) for s in range(self._SLOTS)) if x is not None]
        if not slots:   # written before the slots existed: emcee's own attributes
            return it, tuple(v for k, v in sorted(g.attrs.items()) if k.startswith("random_state_"))
        n_rows = min(g[k].shape[0] for k in ("chain", "log_prob", "accepted_step"))
        for lo, hi, digest, state in sorted(slots, key=lambda x: -x[1]):
            if hi <= it and hi <= n_rows and self._rows_digest(g, lo, hi) == digest:
                return hi, state
        return None

    def append(self, chain, log_prob, accepted, random_state):
        k = chain.shape[0]
        it = self.iteration
        with self.backend.open("a") as f:
            g = f[self.backend.name]
            for key, v in (("chain", chain), ("log_prob", log_prob), ("accepted_step", accepted)):
                g[key].resize(it + k, axis=0)
                g[key][it:it + k] = v
            # recomputed, not incremented: a commit repeated after an interruption counts once
            g["accepted"][:] = g["accepted_step"][:it + k].sum(axis=0)
            for i, v in enumerate(random_state):       # emcee's layout (HDFBackend readers)
                g.attrs[f"random_state_{i}"] = v
            # the slot not holding the last good commit (that one is never touched)
            s = next(s for s in range(self._SLOTS)
                     if g.attrs.get(f"bayes_tfcrds_state{s}_iteration", -1) != it)
            pre = f"bayes_tfcrds_state{s}_"
            g.attrs[pre + "iteration"] = -1             # invalid while it is being written
            for i, v in enumerate(random_state):
                g.attrs[f"{pre}{i}"] = v
            g.attrs[pre + "n"] = len(random_state)
            g.attrs[pre + "start"] = it
            g.attrs[pre + "sha256"] = self._rows_digest(g, it, it + k)
            g.attrs[pre + "iteration"] = it + k
            g.attrs["iteration"] = it + k      # commit point: rows above become visible
            f.flush()
        self.iteration = it + k
        self._state = tuple(random_state)

    def last(self):
        with self.backend.open() as f:
            g = f[self.backend.name]
            n = self.iteration
            return g["chain"][n - 1], g["log_prob"][n - 1], self._state

    def read(self, n):
        with self.backend.open() as f:
            g = f[self.backend.name]
            n = min(n, self.iteration)
            return g["chain"][:n], g["log_prob"][:n], g["accepted_step"][:n].astype(bool)


class _Damaged(Exception):
    """A chain file that cannot be resumed from (killed inside a write, or not HDF5)."""


def _same_rng_state(a, b) -> bool:
    return (str(a[0]) == str(b[0]) and np.array_equal(a[1], b[1])
            and all(x == y for x, y in zip(a[2:], b[2:])))


class _Ensemble:
    """One emcee ensemble advanced in committed chunks with a continuous random stream."""

    def __init__(self, index, seed, log_prob, p0_fn, n_walkers, ndim, vectorize, pool,
                 backend_path, chunk_steps, moves=None):
        init_rng, mcmc_rng = seed.spawn(2)
        ss = mcmc_rng.bit_generator.seed_seq
        fingerprint = json.dumps([str(ss.entropy), list(map(int, ss.spawn_key)), n_walkers, ndim])
        self.index, self.chunk_steps = index, chunk_steps
        self._p0 = lambda: p0_fn(init_rng, n_walkers)  # only needed for a fresh start
        self.rng0 = np.random.RandomState(np.random.MT19937(ss)).get_state()
        self.sampler = emcee.EnsembleSampler(n_walkers, ndim, log_prob, pool=pool, moves=moves,
                                             vectorize=vectorize, backend=_StepRecorder())
        self.store = (_MemoryStore(n_walkers, ndim, fingerprint) if backend_path is None else
                      _HDFStore(backend_path, f"ensemble{index}", n_walkers, ndim, fingerprint))
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
            raise ValueError(f"ensemble {self.index}: p0_fn returned walkers with non-finite "
                             f"log_prob {lp[~np.isfinite(lp)]} (outside the prior?)")
        return emcee.State(p0, log_prob=lp, random_state=self.rng0)

    def advance_to(self, n_total, pbar=None, stop=None):
        """Run until the committed chain holds ``n_total`` steps (no-op if it already does);
        on a ``stop`` request commit the steps taken so far and raise KeyboardInterrupt."""
        while self.store.iteration < n_total:
            if self.state is None:
                self.state = self._initial_state()
            self.sampler.random_state = self.state.random_state
            if not _same_rng_state(self.sampler.random_state, self.state.random_state):
                raise RuntimeError("could not restore the sampler's random state")
            k = min(self.chunk_steps, n_total - self.store.iteration)
            rec = self.sampler.backend
            rec.reset(self.sampler.nwalkers, self.sampler.ndim)
            for st in self.sampler.sample(self.state, iterations=k, store=True,
                                          skip_initial_state_check=self.store.iteration > 0):
                if pbar is not None:
                    pbar.update(1)
                if stop is not None and stop.requested:
                    break                  # the chain does not depend on where chunks end
            rs = self.sampler.random_state
            self.store.append(rec.get_chain(), rec.get_log_prob(),
                              np.array(rec.accepted_steps), rs)
            self.state = emcee.State(st.coords.copy(), log_prob=st.log_prob.copy(),
                                     random_state=rs)
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
        if (threading.current_thread() is threading.main_thread()
                and signal.getsignal(signal.SIGINT) is signal.default_int_handler):
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
def _evaluate(names, chains, log_prob, accepted, derived_fn, gates, label) -> SamplingResult:
    n = chains.shape[1]
    burn = burn_in(chains)
    kept, lp_kept, acc_kept = chains[:, burn:], log_prob[:, burn:], accepted[:, burn:]
    diagnostics = {nm: chain_diagnostics(kept[..., i]) for i, nm in enumerate(names)}
    derived = {}
    if derived_fn is not None:
        shape = kept.shape[:3]
        for nm, v in derived_fn(kept.reshape(-1, kept.shape[-1])).items():
            if nm in diagnostics:
                raise ValueError(f"derived quantity {nm!r} clashes with a parameter name")
            derived[nm] = _frozen(np.asarray(v, dtype=float).reshape(shape))
            diagnostics[nm] = chain_diagnostics(derived[nm])
    failures = _gate_failures(diagnostics, gates)
    status = "passed" if not failures else f"failed after {n} steps: " + "; ".join(failures)
    rh = [d["rhat"] for d in diagnostics.values()]
    es = [min(d["ess_bulk"], d["ess_tail"]) for d in diagnostics.values()]
    return SamplingResult(
        names=tuple(names), samples=_frozen(kept), log_prob=_frozen(lp_kept),
        diagnostics=diagnostics,
        rhat_max=float(np.nan if np.any(np.isnan(rh)) else max(rh)),
        ess_min=float(np.nan if np.any(np.isnan(es)) else min(es)),
        passed=not failures, status=status, n_steps=n, burn=burn,
        acceptance=_frozen(acc_kept.mean(axis=(1, 2))), derived=derived, gates=gates,
        label=label,
    )


def run_ensembles(
    log_prob: Callable,
    p0_fn: Callable,
    names: Sequence[str],
    rng: np.random.Generator,
    n_ensembles: int = 4,
    n_walkers: Optional[int] = None,
    n_steps: int = 2000,
    max_steps: int = 20000,
    vectorize: bool = False,
    backend_path=None,
    progress: bool = False,
    label: str = "",
    pool=None,
    gates: Gates = Gates(),
    *,
    derived_fn: Optional[Callable] = None,
    chunk_steps: int = 100,
    moves=None,
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
    progress: one tqdm bar per ensemble, labelled with ``label``.
    pool: object with ``map`` passed to emcee (ignored by emcee when ``vectorize``).
    derived_fn: ``samples (n, ndim) -> {name: (n,) array}``; derived quantities get the
        same diagnostics and gates as the parameters.
    chunk_steps: steps between commits; the chains do not depend on it.

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

    ensembles = [
        _Ensemble(i, s, log_prob, p0_fn, n_walkers, ndim, vectorize, pool, backend_path, moves=moves, chunk_steps=
                  int(chunk_steps))
        for i, s in enumerate(rng.spawn(n_ensembles))
    ]
    bars = []
    if progress:
        from tqdm.auto import tqdm
        prefix = f"{label} " if label else ""
        bars = [tqdm(total=n_steps, initial=min(e.store.iteration, n_steps),
                     desc=f"{prefix}ensemble {e.index}", position=e.index, leave=True)
                for e in ensembles]
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
            result = _evaluate(names, chains, lps, acc, derived_fn, gates, label)
            if result.passed or target >= max_steps:
                return result
            target = min(int(max_steps), target + math.ceil(0.5 * target))
    finally:
        stop.__exit__()
        for b in bars:
            b.close()
