"""Progress lines in the log when no bar is shown: how often, and what they say."""

from __future__ import annotations

import logging
import re

import pytest

from mrta_rl.runners import train
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


def test_lines_keep_coming_during_a_run(compose_cfg, tmp_path, caplog):
    """About a second of training with a 0.1 s interval: no silence longer than the interval."""
    every_s, slack_s = 0.1, 0.3  # slack: the tick that crosses the interval, a busy machine
    overrides = ["learner=dql", "debug=smoke", "env.horizon=1000", "train.episodes=20"]
    overrides.append(f"train.log_every_s={every_s}")
    caplog.set_level(logging.INFO, logger="mrta_rl.runners")
    train(compose_cfg(overrides), run_dir=tmp_path)
    lines = [r for r in caplog.records if LINE.match(r.getMessage())]
    (end,) = [r for r in caplog.records if r.getMessage().startswith("trained 20 episodes")]
    times = [r.created for r in [*lines, end]]
    assert len(lines) >= 3
    assert max(b - a for a, b in zip(times, times[1:], strict=False)) <= every_s + slack_s
