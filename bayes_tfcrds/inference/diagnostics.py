"""Convergence diagnostics of ensemble MCMC (emcee) that can say "no", and their gates.

Every Bayesian result in the toolkit is sampled through :func:`run_ensembles`. It runs
``n_ensembles`` (>= 4) *independent* emcee ensembles, because the walkers of one ensemble
are coupled by the ensemble moves and are not independent chains; a convergence check
needs chains that could have disagreed. The ensembles step together in one emcee sampler
whose moves never use another ensemble's walkers (``inference.moves.ensemble_local``).

Diagnostics (per parameter and per derived quantity, :func:`chain_diagnostics`)
    All are arviz's, computed on the layout the netCDF files store (:func:`draw_layout`), so
    ``az.rhat`` and ``az.ess`` on a saved posterior give the numbers the gates judged:
    one chain per ensemble; its draws are the first half of the kept steps listed walker by
    walker (all those steps of walker 0, then of walker 1, ...), then the middle step of an odd
    length, then the second half the same way.
    R-hat and the ESS are arviz 0.2x's, operation for operation, computed here
    (:func:`_rhat_and_ess`) so that tau_int, the bulk R-hat and the bulk ESS share one ranking
    of the draws (arviz's functions rank them three times, tau_int a fourth). Tests keep them
    equal to ``arviz.rhat``/``arviz.ess`` to the bit. Where arviz computes otherwise (its numba
    variances when numba is installed, arviz >= 1) arviz's own functions are called.

    * ``rhat``: rank-normalised split R-hat (Vehtari et al. 2021, ``az.rhat(method="rank")``).
      R-hat only sees which draws fall in which half of each chain, and the halves are the first
      and second half in time, so it equals the R-hat of the ensemble's samples flattened
      step-major.
    * ``ess_bulk``, ``ess_tail``: ``az.ess`` (methods "bulk" and "tail"). Listed walker by
      walker, a lag of k draws within a half is a lag of k steps of one walker, so the
      autocovariance arviz estimates is the walkers' averaged about the ensemble's mean. The
      step-major order is *not* used: there the neighbours of a draw are the other walkers of
      its step, nearly uncorrelated with it, while its own walker's next step lies n_walkers
      draws away; Geyer's sum stops at the first lags and ESS comes out about tau_int times too
      large (measured: 126 000 for an AR(1) ensemble with 6 700 effective draws; 6 600 with this
      layout).
    * ``tau_int``: integrated autocorrelation time in steps, largest over the ensembles,
      of the rank-normalised values, with emcee's Sokal window (``c = 5``).
    * ``n_tau``: kept chain length in units of ``tau_int``.

    The per-ensemble tau_int is emcee's estimator with one change: the autocovariance of
    every walker is taken about the *ensemble* mean and averaged over walkers before
    normalising. emcee's ``integrated_time`` centres each walker on its own mean, which biases
    tau low by ~2*window/n (for an AR(1) chain with tau = 39: -14 % at 2000 steps, -43 % at
    500) and returns NaN when a walker never visits a 5 % tail.

Gates (:class:`Gates`): every reported quantity needs R-hat < ``rhat_max``, bulk and tail
ESS > ``ess_min`` and kept length > ``min_tau_multiple`` * tau_int. If a gate fails, all
ensembles are extended, up to ``max_steps``, by what the failed gates say is missing (the
tau and ESS gates scale with the kept length: 1.1 x the largest shortfall factor; an R-hat
failure: half again; each extension between 1.2x and 3x, see
:func:`bayes_tfcrds.inference.runner.extended_length`); after ``max_steps`` the result comes
back with ``passed=False`` and a ``status`` naming the gate and quantity.

Burn-in rule: ``burn = min(max(ceil(0.2 n), ceil(2 tau_pilot)), n // 2)`` where
``tau_pilot`` is the largest tau_int over parameters and ensembles measured on steps
``ceil(0.2 n):n``. The 20 % floor protects against a tau estimate that is itself still
biased by the initial transient; the ``n // 2`` cap keeps something to diagnose (a chain
whose burn-in hits the cap fails the tau gate anyway).

Determinism and resume
    Each ensemble gets two child seeds from ``rng.spawn``: one generator for ``p0_fn`` and one
    stream; the first ensemble's stream, an MT19937 ``RandomState``, is installed as the
    sampler's generator (emcee 3.1 has no ``seed=`` argument and would otherwise start from the
    global ``np.random`` state). Sampling proceeds in chunks of ``chunk_steps``; after every
    chunk each ensemble's positions, log-probabilities, per-step acceptances *and* the
    generator state are committed together (the ensembles one after another; a kill between
    them is rolled back on resume to the step all of them hold). The random stream is
    continuous across chunks (emcee draws no random numbers when a run starts from a state with
    known log-probabilities), so the chain does not depend on where chunks, extensions or
    interruptions fall: a run that is interrupted (KeyboardInterrupt, SIGKILL) and rerun with
    the same arguments is bit for bit the uninterrupted run. Ctrl-C while sampling commits the
    steps already taken and then raises KeyboardInterrupt (a second Ctrl-C stops at once).

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

import functools
import math
import warnings
from dataclasses import dataclass

import numpy as np
from emcee.autocorr import auto_window
from scipy.fft import next_fast_len
from scipy.special import ndtri


@dataclass(frozen=True)
class Gates:
    """Convergence requirements that every reported quantity must meet."""

    rhat_max: float = 1.01
    ess_min: float = 400.0
    min_tau_multiple: float = 50.0
    # the quantities gated (parameter or derived names; None: all). A model whose parameters are
    # not identifiable while what it predicts is (the poles of Eq. 2 can trade roles and give one
    # H(f)) is gated on its predictions; the parameters' diagnostics are still reported
    gated: tuple | None = None


# --------------------------------------------------------------------------- diagnostics
def _import_arviz():
    """Import arviz lazily (slow import) and without its 1.x-refactor FutureWarning."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        import arviz
    return arviz


def _arviz_major() -> int:
    return int(_import_arviz().__version__.split(".")[0])


def _as_chains(chains) -> np.ndarray:
    x = np.asarray(chains, dtype=float)
    if x.ndim != 2 or x.shape[0] < 2:
        raise ValueError(f"need (n_chains >= 2, n_draws), got {x.shape}")
    return x


def rhat_rank(chains) -> float:
    """Rank-normalised split R-hat of ``chains`` (n_chains, n_draws).

    The only place arviz's R-hat is called: arviz 0.2x takes a (chain, draw) ndarray in
    ``arviz.rhat``; arviz >= 1.0 moved array functions to ``arviz_stats.base.array_stats``.
    """
    x = _as_chains(chains)
    if _arviz_major() >= 1:
        from arviz_stats.base import array_stats

        return float(array_stats.rhat(x, chain_axis=0, draw_axis=1, method="rank"))
    return float(_import_arviz().rhat(x, method="rank"))


def ess(chains, method: str) -> float:
    """arviz's effective sample size of ``chains`` (n_chains, n_draws); ``method`` bulk or tail."""
    x = _as_chains(chains)
    if _arviz_major() >= 1:
        from arviz_stats.base import array_stats

        return float(array_stats.ess(x, chain_axis=0, draw_axis=1, method=method))
    return float(_import_arviz().ess(x, method=method))


def draw_layout(n_steps: int, n_walkers: int) -> tuple:
    """(step, walker) index of each draw of one chain in the files' order (see module doc).

    The first ``n_steps // 2`` steps walker by walker, the middle step of an odd length walker
    by walker, then the last ``n_steps // 2`` steps walker by walker. arviz splits a chain of
    n_steps * n_walkers draws into its first and last ``n_steps * n_walkers // 2``: the same
    sets of draws as the step-major order, so split R-hat is that of the step-major chain.
    """
    h = n_steps // 2

    def block(steps):
        return np.tile(steps, n_walkers), np.repeat(np.arange(n_walkers), steps.size)

    parts = [
        block(np.arange(h)),
        block(np.arange(h, n_steps - h)),
        block(np.arange(n_steps - h, n_steps)),
    ]
    return tuple(np.concatenate(p) for p in zip(*parts))


def to_draws(x) -> np.ndarray:
    """(ensembles, steps, walkers) samples as (chain, draw) in :func:`draw_layout` order."""
    x = np.asarray(x)
    step, walker = draw_layout(x.shape[1], x.shape[2])
    return x[:, step, walker]


def integrated_time(x) -> float:
    """Integrated autocorrelation time (in steps) of one ensemble's series ``x`` (steps, walkers).

    emcee's estimator (FFT autocovariance, Sokal window with c = 5) but centred on the
    ensemble mean and averaged over walkers before normalisation (see module docstring).
    Returns ``inf`` for a constant series, and for one of fewer than two steps (what a burn-in
    leaves of a one-step run): neither carries information about the quantity.
    """
    x = np.asarray(x, dtype=float)
    n = x.shape[0]
    if n < 2:
        return math.inf
    y = x - x.mean()
    nfft = 1 << max(0, (2 * n - 1).bit_length())
    f = np.fft.rfft(y, n=nfft, axis=0)
    acov = np.fft.irfft(f * np.conj(f), n=nfft, axis=0)[:n].mean(axis=1)
    if not acov[0] > 0.0:
        return math.inf
    taus = 2.0 * np.cumsum(acov / acov[0]) - 1.0
    return float(taus[auto_window(taus, 5.0)])


def _average_ranks(x) -> np.ndarray:
    """1-based ranks of the flattened ``x``, ties sharing their average rank.

    ``scipy.stats.rankdata(x, axis=None)`` to the bit (the ranks are integers or halves), about
    4x faster: an unstable argsort suffices because tied values get one rank whatever their order.
    """
    flat = np.ravel(x)
    order = np.argsort(flat)
    ordered = flat[order]
    first = np.empty(flat.size, dtype=bool)
    first[:1] = True
    np.not_equal(ordered[1:], ordered[:-1], out=first[1:])
    start = np.flatnonzero(first)
    stop = np.append(start[1:], flat.size)
    ranks = np.empty(flat.size)
    ranks[order] = ((start + stop + 1) / 2.0)[np.cumsum(first) - 1]
    return ranks.reshape(np.shape(x))


def _rank_normal(x):
    """Rank-normalised values (Vehtari et al. 2021): Phi^-1((r - 3/8) / (N + 1/4)), pooled."""
    return ndtri((_average_ranks(x) - 0.375) / (np.size(x) + 0.25))


# ------------------------------------------------------------ arviz's R-hat and ESS, shared work
# chain_diagnostics needs R-hat, bulk and tail ESS and tau_int of one quantity. Through arviz's
# public functions the same draws are ranked three times (bulk R-hat, folded R-hat, bulk ESS),
# and once more for tau_int. The functions below are arviz 0.2x's (``arviz.stats.diagnostics.
# _rhat_rank``, ``_ess_bulk``, ``_ess_tail``) operation for operation, with the bulk ranks shared
# by tau_int, R-hat and ESS; tests hold them equal to ``arviz.rhat``/``arviz.ess`` to the bit on
# chains with ties, odd lengths and the runner's layout.
@functools.cache
def _arviz_major_installed() -> int:
    from importlib.metadata import version

    return int(version("arviz").split(".")[0])


def _arviz_computes_as_here() -> bool:
    """Whether arviz's R-hat/ESS use the numpy arithmetic copied below (bit-equal results).

    Not with arviz >= 1 (another implementation) nor with arviz's numba variances, which it
    switches on by itself when numba is importable (``arviz.utils.Numba.numba_flag``).
    """
    import sys
    from importlib.util import find_spec

    if _arviz_major_installed() >= 1:
        return False
    utils = sys.modules.get("arviz.utils")  # imported: its flag; not yet: what it will start with
    return not (utils.Numba.numba_flag if utils is not None else find_spec("numba") is not None)


def _split(draws) -> np.ndarray:
    """arviz's split chains: the first and last ``n // 2`` draws of each chain as two chains."""
    half = draws.shape[1] // 2
    return np.vstack((draws[:, :half], draws[:, -half:]))


def _split_rhat(z) -> float:
    """R-hat of already split (and normalised) chains ``z`` (arviz's ``_rhat`` without numba)."""
    n = z.shape[1]
    between = n * np.var(np.mean(z, axis=1), ddof=1)
    within = np.mean(np.var(z, axis=1, ddof=1))
    return float(np.sqrt((between / within + n - 1) / n))


def _geyer_ess(chains) -> float:
    """ESS of (chain, draw) values by Geyer's initial monotone sequence (arviz's ``_ess``)."""
    x = np.asarray(chains, dtype=float)
    if np.max(x) - np.min(x) < np.finfo(float).resolution:
        return float(x.size)
    n_chain, n = x.shape
    m = next_fast_len(2 * n, real=True)  # = scipy.fftpack.next_fast_len, arviz's padding
    y = x - x.mean(axis=1, keepdims=True)
    f = np.fft.rfft(y, n=m, axis=1)
    f *= np.conjugate(f)
    acov = np.fft.irfft(f, n=m, axis=1)[:, :n]
    acov /= n
    mean_var = np.mean(acov[:, 0]) * n / (n - 1.0)
    var_plus = mean_var * (n - 1.0) / n
    if n_chain > 1:
        var_plus += np.var(x.mean(axis=1), ddof=1)
    # 1 - (mean_var - <acov_t>) / var_plus for every lag at once, elementwise as arviz's loop
    # forms it; the mean over chains on contiguous rows sums in the same order as arviz's columns
    rho_all = 1.0 - (mean_var - np.mean(np.ascontiguousarray(acov.T), axis=1)) / var_plus
    rho = np.zeros(n)
    rho[0] = even = 1.0
    rho[1] = odd = rho_all[1]
    t = 1
    while t < n - 3 and even + odd > 0.0:  # initial positive sequence
        even, odd = rho_all[t + 1], rho_all[t + 2]
        if even + odd >= 0:
            rho[t + 1], rho[t + 2] = even, odd
        t += 2
    max_t = t - 2
    if even > 0:
        rho[max_t + 1] = even
    t = 1
    while t <= max_t - 2:  # initial monotone sequence
        if rho[t + 1] + rho[t + 2] > rho[t - 1] + rho[t]:
            rho[t + 1] = (rho[t - 1] + rho[t]) / 2.0
            rho[t + 2] = rho[t + 1]
        t += 2
    n_total = n_chain * n
    tau = -1.0 + 2.0 * np.sum(rho[: max_t + 1]) + np.sum(rho[max_t + 1 : max_t + 2])
    tau = max(tau, 1 / np.log10(n_total))
    return float("nan") if np.isnan(rho).any() else float(n_total / tau)


def _quantile_type7(ordered, p: float) -> float:
    """R's type-7 quantile of sorted values, as ``scipy.stats.mstats.mquantiles(a, p, 1, 1)``."""
    n = ordered.size
    # mquantiles' m = alphap + p (1 - alphap - betap) with alphap = betap = 1, in its own order
    aleph = n * p + (1.0 + p * (1.0 - 1.0 - 1.0))
    k = int(np.floor(np.clip(aleph, 1, n - 1)))
    gamma = np.clip(aleph - k, 0, 1)
    return float((1.0 - gamma) * ordered[k - 1] + gamma * ordered[k])


def _rhat_and_ess(x, z) -> tuple:
    """(rank R-hat, bulk ESS, tail ESS) of (ensembles, steps, walkers) ``x`` in the files' layout.

    ``z`` is ``x``'s pooled rank-normal values; arviz's numbers on :func:`to_draws`.
    """
    step, walker = draw_layout(x.shape[1], x.shape[2])
    draws = x[:, step, walker]
    split = _split(draws)
    if draws.shape[1] % 2 == 0:  # the split keeps every draw: its ranks are the pooled ones
        # C order, as arviz's ranks are: numpy's sums depend on the memory layout in the last bit
        z_split = np.ascontiguousarray(_split(z[:, step, walker]))
    else:  # arviz drops the middle draw and ranks the rest
        z_split = _rank_normal(split)
    folded = _rank_normal(np.abs(split - np.median(split)))
    rhat = max(_split_rhat(z_split), _split_rhat(folded))
    ordered = np.sort(draws, axis=None)
    ess_tail = min(_geyer_ess(_split(draws <= _quantile_type7(ordered, p))) for p in (0.05, 0.95))
    return rhat, _geyer_ess(z_split), ess_tail


def chain_diagnostics(x) -> dict:
    """R-hat, bulk/tail ESS and tau_int of one quantity sampled as ``x``.

    ``x`` has shape (ensembles, steps, walkers).

    Returns plain floats (JSON-able): ``rhat``, ``ess_bulk``, ``ess_tail`` (arviz's, on
    :func:`to_draws`), ``tau_int`` (largest over ensembles, steps), ``n_tau`` (steps / tau_int)
    and ``tau_int_ensembles``. Non-finite values give NaN throughout; a chain of fewer than two
    kept steps, or a constant one, has tau_int = inf and n_tau = 0 (the length gate fails
    whatever arviz makes of it).
    """
    x = np.asarray(x, dtype=float)
    if x.ndim != 3:
        raise ValueError(f"need (ensembles, steps, walkers), got {x.shape}")
    n_ens, n, _ = x.shape
    nan = float("nan")
    if not np.all(np.isfinite(x)):
        return dict(
            rhat=nan,
            ess_bulk=nan,
            ess_tail=nan,
            tau_int=nan,
            n_tau=nan,
            tau_int_ensembles=[nan] * n_ens,
        )
    z = _rank_normal(x)
    tau = [integrated_time(z[e]) for e in range(n_ens)]
    tau_max = float(max(tau))
    if n_ens >= 2 and n * x.shape[2] >= 4 and _arviz_computes_as_here():
        rhat, ess_bulk, ess_tail = _rhat_and_ess(x, z)
    else:  # arviz's own: fewer than 4 draws (NaN and a warning), one chain (refused), numba
        draws = to_draws(x)
        rhat, ess_bulk, ess_tail = rhat_rank(draws), ess(draws, "bulk"), ess(draws, "tail")
    return dict(
        rhat=rhat,
        ess_bulk=ess_bulk,
        ess_tail=ess_tail,
        tau_int=tau_max,
        n_tau=float(n / tau_max) if tau_max > 0 else math.inf,
        tau_int_ensembles=[float(t) for t in tau],
    )


def burn_in(chains) -> int:
    """Steps to discard from ``chains`` (ensembles, steps, walkers, ndim); see the module doc."""
    n = chains.shape[1]
    start = math.ceil(0.2 * n)
    pilot = chains[:, start:]
    tau = max(
        integrated_time(z[e])
        for d in range(chains.shape[3])
        for z in [_rank_normal(pilot[..., d])]
        for e in range(chains.shape[0])
    )
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
            out.append(
                f"n_tau({name})={d['n_tau']:.4g} <= {gates.min_tau_multiple:g} (kept length / "
                f"tau_int, tau_int={d['tau_int']:.4g} steps)"
            )
    return out
