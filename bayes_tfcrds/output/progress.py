"""Progress of long runs: bars on a terminal, periodic plain lines in a log, time left.

A carriage-return bar is right on a terminal and wrong in a log file (one budget wrote 45 kB of
redrawn bars into one). :func:`progress_bar` gives a tqdm bar when stderr is a terminal (or a
notebook), and otherwise a :class:`PlainProgress` that logs one line every 10 % of the total or
every 30 s, whichever comes first, with the elapsed time and an estimate of the time left.
:class:`StageClock` does the same for a command made of a few unequal stages (the budget's).

Lines go through :mod:`logging` (logger ``bayes_tfcrds.progress``, level INFO) and start with
``# ``, like every diagnostic line of the command line; library code never configures logging.
"""

from __future__ import annotations

import logging
import sys
import time

log = logging.getLogger(__name__)

LINE_FRACTION = 0.10  # a plain line every 10 % of the total ...
LINE_SECONDS = 30.0  # ... or every 30 s, whichever comes first


def stderr_is_live() -> bool:
    """True when stderr redraws a bar in place: a terminal, or a Jupyter kernel's output."""
    if "ipykernel" in sys.modules:
        return True
    try:
        return bool(sys.stderr.isatty())
    except (AttributeError, ValueError):  # replaced by an object without isatty, or closed
        return False


def duration(seconds: float) -> str:
    """A duration a reader takes in at a glance: '45 s', '3 min 20 s', '2 h 05 min'."""
    s = max(0, round(seconds))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {(s % 3600) // 60:02d} min"


def time_left(elapsed_s: float, done: float, total: float) -> float | None:
    """Seconds left at the mean rate so far (None before anything is done)."""
    if done <= 0 or total <= 0:
        return None
    return elapsed_s * max(total - done, 0.0) / done


class PlainProgress:
    """A progress counter that logs plain lines (no carriage returns) at intervals.

    The subset of tqdm's interface the package uses: ``update(n)``, a settable ``total``,
    ``refresh()``, ``close()`` and iteration over a wrapped iterable.
    """

    def __init__(self, iterable=None, total=None, desc="", initial=0, clock=time.monotonic):
        self.iterable = iterable
        if total is None and iterable is not None and hasattr(iterable, "__len__"):
            total = len(iterable)
        self.total = total
        self.desc = desc
        self.n = initial
        self._clock = clock
        self._start = clock()
        self._start_n = initial
        self._last_t = self._start
        self._last_n = initial
        self._closed = False

    def __iter__(self):
        for item in self.iterable:
            yield item
            self.update(1)
        self.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False

    def update(self, n: int = 1) -> None:
        self.n += n
        now = self._clock()
        step = LINE_FRACTION * self.total if self.total else float("inf")
        if self.n - self._last_n >= step or now - self._last_t >= LINE_SECONDS:
            self._emit(now)

    def refresh(self) -> None:
        """Nothing to redraw: lines are written as the count advances."""

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            if self.n != self._last_n:
                self._emit(self._clock())

    def line(self, now: float) -> str:
        """``# DESC: n/total (p %), elapsed E, about L left``."""
        elapsed = now - self._start
        head = f"# {self.desc}: " if self.desc else "# "
        if not self.total:
            return f"{head}{self.n}, elapsed {duration(elapsed)}"
        left = time_left(elapsed, self.n - self._start_n, self.total - self._start_n)
        if self.n >= self.total:
            left = None  # done: nothing left to estimate
        return (
            f"{head}{self.n}/{self.total} ({100 * self.n / self.total:.0f} %), elapsed "
            f"{duration(elapsed)}" + ("" if left is None else f", about {duration(left)} left")
        )

    def _emit(self, now: float) -> None:
        self._last_t, self._last_n = now, self.n
        log.info(self.line(now))


def progress_bar(iterable=None, total=None, desc="", initial=0, position=None):
    """A tqdm bar on a live stderr, else a :class:`PlainProgress` of periodic log lines."""
    if stderr_is_live():
        from tqdm.auto import tqdm

        return tqdm(
            iterable, total=total, desc=desc, initial=initial, position=position, leave=True
        )
    return PlainProgress(iterable, total=total, desc=desc, initial=initial)


class StageClock:
    """Elapsed time and time left over the stages of one long command.

    ``done(name)`` after each stage logs ``# LABEL: stage k/n NAME done in t; elapsed E, about L
    left``; the time left assumes the stages to come take the mean time of those done (a rough
    figure: stages differ, and the line says "about").
    """

    def __init__(self, n_stages: int, label: str = "", clock=time.monotonic):
        self.n_stages = int(n_stages)
        self.label = label
        self._clock = clock
        self._start = self._last = clock()
        self.k = 0

    def done(self, name: str) -> str:
        now = self._clock()
        self.k += 1
        elapsed = now - self._start
        left = time_left(elapsed, self.k, self.n_stages)
        text = (
            f"# {self.label + ': ' if self.label else ''}stage {self.k}/{self.n_stages} {name} "
            f"done in {duration(now - self._last)}; elapsed {duration(elapsed)}"
            + (f", about {duration(left)} left" if left and self.k < self.n_stages else "")
        )
        self._last = now
        log.info(text)
        return text
