"""Chain stores.

In memory, or an HDF5 file with checksummed state slots that survives SIGINT and SIGKILL and resumes
to bit-identical samples.
"""

from __future__ import annotations

import hashlib
import os
import warnings

import emcee
import h5py
import numpy as np

_SEED_ATTR = "bayes_tfcrds_seed"


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

    def rollback(self, n):
        """Only a chain file can be rolled back (an in-memory run never resumes)."""
        raise RuntimeError(f"in-memory chains at step {self.iteration} cannot go back to {n}")

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
        self.moved_aside = False  # True: this store found the file damaged and set it aside
        fresh = True
        if os.path.exists(self.path):
            try:
                fresh = not self._resume(name, n_walkers, ndim, fingerprint)
            except _Damaged as exc:
                move_aside(self.path, f"{exc}; sampling {name} from its seed again")
                self.moved_aside = True
                self.backend = emcee.backends.HDFBackend(self.path, name=name)
        if fresh:
            self.backend.reset(n_walkers, ndim)
            with self.backend.open("a") as f:
                g = f[name]
                g.create_dataset(
                    "accepted_step", (0, n_walkers), maxshape=(None, n_walkers), dtype=np.uint8
                )
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
                    return False  # killed between creating the group and tagging it
                if stored != fingerprint:
                    raise ValueError(
                        f"{self.path}:{name} was written with another seed or setup ({stored!r} "
                        f"!= {fingerprint!r}); use a new backend_path"
                    )
                if shape != (n_walkers, ndim):
                    raise ValueError(
                        f"{self.path}:{name} holds shape {shape}, not {(n_walkers, ndim)}"
                    )
                if it == 0:
                    good = 0, None
                else:
                    good = self._last_intact(g, it)
        except (OSError, KeyError, RuntimeError) as exc:
            if "unable to lock file" in str(exc).lower():  # HDF5's lock: another run writes it
                raise RuntimeError(
                    f"{self.path} is open in another process (another run writing to the same "
                    "output?); not touched"
                ) from exc
            raise _Damaged(f"cannot be read ({type(exc).__name__}: {exc})") from exc
        if good is None:
            raise _Damaged(f"ensemble {name} has no intact commit")
        n, state = good
        if n != it:
            with self.backend.open("a") as f:
                f[name].attrs["iteration"] = n  # roll back over the incomplete commit
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
        return (
            int(g.attrs[pre + "start"]),
            int(g.attrs[pre + "iteration"]),
            str(g.attrs[pre + "sha256"]),
            state,
        )

    def _last_intact(self, g, it):
        """(iteration, generator state) of the newest commit whose rows are on disk, or None."""
        slots = [x for x in (self._slot(g, s) for s in range(self._SLOTS)) if x is not None]
        if not slots:  # written before the slots existed: emcee's own attributes
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
                g[key][it : it + k] = v
            # recomputed, not incremented: a commit repeated after an interruption counts once
            g["accepted"][:] = g["accepted_step"][: it + k].sum(axis=0)
            for i, v in enumerate(random_state):  # emcee's layout (HDFBackend readers)
                g.attrs[f"random_state_{i}"] = v
            # the slot not holding the last good commit (that one is never touched)
            s = next(
                s
                for s in range(self._SLOTS)
                if g.attrs.get(f"bayes_tfcrds_state{s}_iteration", -1) != it
            )
            pre = f"bayes_tfcrds_state{s}_"
            g.attrs[pre + "iteration"] = -1  # invalid while it is being written
            for i, v in enumerate(random_state):
                g.attrs[f"{pre}{i}"] = v
            g.attrs[pre + "n"] = len(random_state)
            g.attrs[pre + "start"] = it
            g.attrs[pre + "sha256"] = self._rows_digest(g, it, it + k)
            g.attrs[pre + "iteration"] = it + k
            g.attrs["iteration"] = it + k  # commit point: rows above become visible
            f.flush()
        self.iteration = it + k
        self._state = tuple(random_state)

    def rollback(self, n):
        """Go back to the intact commit at step ``n`` (0: empty), whose state a slot still holds.

        The ensembles are committed one after another; a kill between two of them leaves some a
        commit ahead, and resume takes all back to the last step every one of them holds.
        """
        if n == self.iteration:
            return
        with self.backend.open("a") as f:
            g = f[self.backend.name]
            state = None
            if n > 0:
                found = [
                    x
                    for x in (self._slot(g, s) for s in range(self._SLOTS))
                    if x is not None and x[1] == n and self._rows_digest(g, x[0], x[1]) == x[2]
                ]
                if not found:
                    raise _Damaged(f"ensemble {self.backend.name} holds no intact commit at {n}")
                state = found[0][3]
            # emcee's own summary of the kept rows (HDFBackend readers), then the counter
            g["accepted"][:] = g["accepted_step"][:n].sum(axis=0)
            for i, v in enumerate(state or ()):
                g.attrs[f"random_state_{i}"] = v
            g.attrs["iteration"] = n
        self.iteration, self._state = n, state

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


def move_aside(path, why: str) -> None:
    """Rename a chain file that cannot be resumed from, and say so (a new file is started)."""
    aside = f"{path}.damaged-{os.getpid()}"
    os.replace(path, aside)
    warnings.warn(
        f"{path}: {why}; moved to {aside} (the result does not depend on it)",
        RuntimeWarning,
        stacklevel=5,
    )


def _same_rng_state(a, b) -> bool:
    return (
        str(a[0]) == str(b[0])
        and np.array_equal(a[1], b[1])
        and all(x == y for x, y in zip(a[2:], b[2:]))
    )
