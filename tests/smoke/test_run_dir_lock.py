"""Checkpoints atomic at every instant.

A save killed at any filesystem step leaves the newest complete checkpoint to resume from.
"""

from __future__ import annotations

import itertools
import json
import os
import shutil
from pathlib import Path

import pytest

from mrta_rl.runners import build_run
from mrta_rl.runners.checkpoint import RunDirError, TrainingCheckpoint, latest_checkpoint


# ---------------------------------------------------------------------------------- defect 3
class Crash(BaseException):
    """Stands for SIGKILL at one filesystem step of a save: nothing after it runs."""


FILESYSTEM_STEPS = [
    (os, "mkdir"),
    (os, "rename"),
    (os, "replace"),
    (os, "fsync"),
    (os, "unlink"),
    (os, "rmdir"),
    (shutil, "rmtree"),
]


def crash_at(monkeypatch, step: int) -> None:
    """Raise :class:`Crash` at the ``step``-th call of any filesystem step."""
    calls = itertools.count()
    for module, name in FILESYSTEM_STEPS:
        real = getattr(module, name)

        def failing(*args, _real=real, **kwargs):
            if next(calls) == step:
                raise Crash
            return _real(*args, **kwargs)

        monkeypatch.setattr(module, name, failing)


def save(learner, run_dir: Path, episode: int) -> None:
    """A checkpoint whose loop state and loop file both say which episode it is."""
    checkpoint = TrainingCheckpoint(learner, run_dir, every=1, resume=False)

    def files(folder: Path) -> None:
        (folder / "loop_file.txt").write_text(f"episode {episode}")

    checkpoint.save({"episode": episode, "curve": [[episode]]}, files)


def resumed_episode(cfg, run_dir: Path) -> int | None:
    """The episode a new process resumes from (None: no checkpoint), checked complete."""
    learner = build_run(cfg).learner
    try:
        loop = TrainingCheckpoint(learner, run_dir, every=1, resume=True).restore()
    except RunDirError as err:
        assert "holds no training checkpoint" in str(err), err
        return None
    episode = loop["episode"]
    assert loop["curve"] == [[episode]]
    assert (latest_checkpoint(run_dir) / "loop_file.txt").read_text() == f"episode {episode}"
    return episode


@pytest.mark.parametrize("earlier", [0, 1], ids=["first_save", "second_save"])
def test_a_save_killed_at_any_step_leaves_the_newest_complete_checkpoint(
    compose_cfg, tmp_path, monkeypatch, earlier
):
    cfg = compose_cfg(["learner=subg_cql", "system=system1", "debug=smoke"])
    learner = build_run(cfg).learner
    outcomes = []
    for step in itertools.count():
        run_dir = tmp_path / f"step{step}"
        if earlier:
            save(learner, run_dir, earlier)
        crash_at(monkeypatch, step)
        try:
            save(learner, run_dir, earlier + 1)
            crashed = False
        except Crash:
            crashed = True
        monkeypatch.undo()
        episode = resumed_episode(cfg, run_dir)
        assert episode in ((earlier or None), earlier + 1)
        outcomes.append(episode)
        if crashed:  # the run goes on after a resume: the next save completes
            save(learner, run_dir, earlier + 2)
            assert resumed_episode(cfg, run_dir) == earlier + 2
        else:
            assert episode == earlier + 1
            break
    # the newest complete one: the earlier checkpoint until the new one is complete, then it
    switch = outcomes.index(earlier + 1)
    assert set(outcomes[:switch]) == {earlier or None} and set(outcomes[switch:]) == {earlier + 1}
    assert switch >= 4  # crashes before the pointer moved were tried
    assert len(outcomes) - switch >= 2  # and after it moved (removing the older version)
    assert (
        json.loads((latest_checkpoint(run_dir) / "training.json").read_text())["loop"]["episode"]
        == earlier + 1
    )
