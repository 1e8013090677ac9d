"""Progress lines in the log when no bar is shown: how often, and what they say."""

from __future__ import annotations

import io
import logging
import re
from datetime import timedelta

import pytest

from mrta_rl.runners import progress, train
from mrta_rl.runners.progress import ProgressLog, progress_bar

LINE = re.compile(
    r"train (\w+): episode (\d+)/(\d+), return (\S+), .*?(\d+) (tick|frame)/s, (\S+) left$"
)


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_a_line_every_interval_while_the_loop_advances(caplog):
    clock = FakeClock()
    log = ProgressLog(
        total=1000, unit="tick", desc="train dql", every_s=30, episode_units=100, clock=clock
    )
    caplog.set_level(logging.INFO, logger="mrta_rl.runners.progress")
    times = []
    for _ in range(1000):  # one tick every 0.7 s: 700 s in all
        clock.now += 0.7
        log.set_postfix({"return": "12.5", "eps": "0.300"})
        before = log.lines
        log.update(1)
        if log.lines > before:
            times.append(clock.now)
            last_n = log.n
    assert len(times) == len(caplog.records) == 700 // 30
    gaps = [b - a for a, b in zip([100.0, *times], times, strict=False)]
    assert max(gaps) <= 30 + 0.7  # at the first tick after the interval
    line = caplog.records[-1].getMessage()
    episode, total, ret, rate, _, left = LINE.match(line).group(2, 3, 4, 5, 6, 7)
    assert (episode, total, ret, rate) == (str(last_n // 100), "10", "12.5", "1")
    assert "eps 0.300" in line
    hours, minutes, seconds = map(int, left.split(":"))  # the rest at the rate so far
    assert abs(3600 * hours + 60 * minutes + seconds - (1000 - last_n) * 0.7) <= 1


def test_no_lines_under_a_bar():
    assert not isinstance(
        progress_bar(total=10, unit="tick", desc="x", enabled=True, log_every_s=0.0), ProgressLog
    )


@pytest.mark.parametrize("learner", ["dql", "reserve_es", "vdn", "greedy"])
def test_every_training_loop_logs_progress(learner, compose_cfg, tmp_path, caplog):
    overrides = [f"learner={learner}", "debug=smoke", "train.log_every_s=1e-9"]
    cfg = compose_cfg(overrides)
    caplog.set_level(logging.INFO, logger="mrta_rl.runners")
    train(cfg, run_dir=tmp_path)
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("train ")]
    if learner == "greedy":  # a fixed policy trains for no time: one line says so
        assert lines == ["train greedy: a fixed policy, nothing to train"]
        return
    matches = [LINE.match(line) for line in lines]
    assert matches and all(matches), lines
    assert {m.group(1) for m in matches} == {learner}
    assert matches[-1].group(3) == str(cfg.train.episodes)
    assert matches[-1].group(2) == str(cfg.train.episodes)  # the last tick ends the last episode


def test_the_interval_is_checked(compose_cfg, tmp_path):
    cfg = compose_cfg(["debug=smoke", "train.log_every_s=0"])
    with pytest.raises(ValueError, match=r"train.log_every_s: must be a number > 0, got 0"):
        train(cfg, run_dir=tmp_path)


class StepClock(FakeClock):
    """A clock that moves ``step`` seconds at each reading: one reading per update of the loop."""

    def __init__(self, step: float) -> None:
        super().__init__()
        self.step = step

    def __call__(self) -> float:
        self.now += self.step
        return self.now


class ClockTimes(logging.Handler):
    """The fake clock's time at each progress line."""

    def __init__(self, clock: FakeClock) -> None:
        super().__init__()
        self.clock, self.times = clock, []

    def emit(self, record: logging.LogRecord) -> None:
        if LINE.match(record.getMessage()):
            self.times.append(self.clock.now)


def test_lines_keep_coming_during_a_run(compose_cfg, tmp_path, monkeypatch):
    """Lines come within episodes, at the first tick after each interval: the loop updates the
    progress every tick. The clock is fake (0.01 s per tick): no wall clock is timed."""
    step, every_s, horizon = 0.01, 0.5, 200  # a line every 50 ticks, 4 per episode
    clock = StepClock(step)
    monkeypatch.setattr(progress, "CLOCK", clock)
    overrides = ["learner=dql", "debug=smoke", f"env.horizon={horizon}", "train.episodes=5"]
    overrides.append(f"train.log_every_s={every_s}")
    lines = ClockTimes(clock)
    progress.logger.addHandler(lines)
    monkeypatch.setattr(progress.logger, "level", logging.INFO)
    try:
        train(compose_cfg(overrides), run_dir=tmp_path)
    finally:
        progress.logger.removeHandler(lines)
    start = clock.now - 5 * horizon * step  # one clock reading at the start, one per tick
    times = [round(t - start, 6) for t in lines.times]
    assert len(times) == 5 * horizon * step // every_s  # 20 lines: 4 in each episode
    assert max(b - a for a, b in zip([0.0, *times], times, strict=False)) <= every_s + step


def test_the_rate_leaves_out_the_first_tick(caplog):
    """The first tick compiles (a minute on a cold numba cache): the rate and the time left
    count from its end, as the ticks after it go (10 ticks/s)."""
    clock = FakeClock()
    log = ProgressLog(
        total=1000, unit="tick", desc="train dql", every_s=30, episode_units=100, clock=clock
    )
    caplog.set_level(logging.INFO, logger="mrta_rl.runners.progress")
    clock.now += 60.0  # compiling
    log.update(1)
    for _ in range(400):
        clock.now += 0.1
        log.update(1)
    # lines at ticks 1 (the interval has passed) and 301 (30 s later)
    first, line = (r.getMessage() for r in caplog.records)
    assert LINE.match(first).group(5, 7) == ("0", "?")  # no tick timed yet
    rate, left = LINE.match(line).group(5, 7)
    assert rate == "10"  # ticks after the first / seconds after the first: 300 / 30
    assert left == str(timedelta(seconds=round((1000 - 301) * 0.1)))  # 0:01:10


def test_the_time_left_of_any_run_is_hours_minutes_and_seconds(caplog):
    """A run of 2**62 episodes at 10 ticks/s: its hours counted on, past what a timedelta
    holds (a billion days)."""
    clock = FakeClock()
    log = ProgressLog(
        total=2**62, unit="tick", desc="train dql", every_s=30, episode_units=1, clock=clock
    )
    caplog.set_level(logging.INFO, logger="mrta_rl.runners.progress")
    clock.now += 60.0
    log.update(1)
    for _ in range(400):
        clock.now += 0.1
        log.update(1)
    left = LINE.match(caplog.records[-1].getMessage()).group(7)  # the line of tick 301
    hours, minutes, seconds = map(int, left.split(":"))
    assert minutes < 60 and seconds < 60
    assert hours == pytest.approx(2**62 / 10 / 3600, rel=1e-6)  # 1.3e14 hours


def test_the_bar_rate_leaves_out_the_first_tick():
    """The tqdm bar's rate and time left too (here: 10 ticks in 1 s after a first tick of 60 s)."""
    bar = progress_bar(
        total=1000, unit="tick", desc="x", enabled=True, log_every_s=30.0, file=io.StringIO()
    )
    clock = FakeClock()
    clock.now = bar.start_t = bar.last_print_t  # tqdm's own clock, from the bar's start
    bar._time = clock
    with bar:
        clock.now += 60.0  # compiling
        bar.update(1)
        for _ in range(10):
            clock.now += 0.1
            bar.update(1)
        shown = bar.format_meter(**bar.format_dict)
    assert "10.00tick/s" in shown and "<01:38," in shown  # 989 ticks left at 10 per second
