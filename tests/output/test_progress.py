"""Progress as plain lines when stderr is not a terminal, and the time-left arithmetic."""

import io
import logging

import pytest

from bayes_tfcrds.output import progress as pg


class FakeClock:
    """A clock the test advances by hand (seconds)."""

    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


@pytest.fixture
def lines(caplog):
    caplog.set_level(logging.INFO, logger="bayes_tfcrds.output.progress")
    return lambda: [r.getMessage() for r in caplog.records]


def test_a_line_every_tenth_of_the_total_with_the_time_left_at_the_mean_rate(lines):
    clock = FakeClock()
    bar = pg.PlainProgress(total=100, desc="campaigns", clock=clock)
    for _ in range(100):
        clock.t += 2.0  # 2 s per item: after 10 items 20 s elapsed, 90 items x 2 s = 180 s left
        bar.update(1)
    bar.close()
    got = lines()
    assert len(got) == 10  # one per 10 %, none repeated by close()
    assert got[0] == "# campaigns: 10/100 (10 %), elapsed 20 s, about 3 min 00 s left"
    assert got[4] == "# campaigns: 50/100 (50 %), elapsed 1 min 40 s, about 1 min 40 s left"
    assert got[-1] == "# campaigns: 100/100 (100 %), elapsed 3 min 20 s"
    assert not any("\r" in line for line in got)


def test_a_line_every_30_s_when_the_total_moves_slowly(lines):
    clock = FakeClock()
    bar = pg.PlainProgress(total=10_000, desc="H ensemble 0", clock=clock)
    for _ in range(3):
        clock.t += pg.LINE_SECONDS + 1  # far below 10 % of the total, past 30 s each time
        bar.update(1)
    assert len(lines()) == 3
    bar.update(1)  # no time passed, 1 item: no line
    assert len(lines()) == 3


def test_a_grown_total_counts_in_the_time_left(lines):
    # the sampler runner extends its target: the bar's total is set again mid-run
    clock = FakeClock()
    bar = pg.PlainProgress(total=10, desc="x", clock=clock)
    bar.total = 20
    clock.t += 10.0
    bar.update(2)  # 2 of 20 in 10 s: 18 left at 5 s each
    assert lines()[-1].endswith("2/20 (10 %), elapsed 10 s, about 1 min 30 s left")


def test_iterating_yields_every_item_and_logs_the_end(lines):
    assert list(pg.PlainProgress(range(3), desc="bundles")) == [0, 1, 2]
    assert lines()[-1].startswith("# bundles: 3/3 (100 %)")


def test_stage_clock_estimates_the_rest_from_the_stages_done(lines):
    clock = FakeClock()
    stages = pg.StageClock(8, "budget D2", clock=clock)
    clock.t += 3.0
    stages.done("H posterior")
    clock.t += 1.0
    text = stages.done("decay times")
    # 2 of 8 stages in 4 s: 6 stages at 2 s each = 12 s left
    assert text == "# budget D2: stage 2/8 decay times done in 1 s; elapsed 4 s, about 12 s left"
    for name in "abcdef":
        stages.done(name)
    assert lines()[-1] == "# budget D2: stage 8/8 f done in 0 s; elapsed 4 s"


@pytest.mark.parametrize(
    ("seconds", "text"),
    [(0.4, "0 s"), (59.6, "1 min 00 s"), (754, "12 min 34 s"), (7500, "2 h 05 min")],
)
def test_durations_read_at_a_glance(seconds, text):
    assert pg.duration(seconds) == text


class _Tty(io.StringIO):
    def isatty(self):
        return True


def test_bars_on_a_terminal_plain_lines_elsewhere(monkeypatch):
    monkeypatch.delitem(__import__("sys").modules, "ipykernel", raising=False)
    monkeypatch.setattr("sys.stderr", io.StringIO())
    assert isinstance(pg.progress_bar(total=5, desc="x"), pg.PlainProgress)
    monkeypatch.setattr("sys.stderr", _Tty())
    bar = pg.progress_bar(total=5, desc="x")
    assert not isinstance(bar, pg.PlainProgress) and hasattr(bar, "update")
    bar.close()
