"""A learner's saved state in a run dir: written with its team, restored only for that team.

:func:`load_learner` restores saved tables or weights through the learner's own ``load``, which
checks them against the learner built for the run; any failure names the file and what is wrong.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from mrta_rl.config import short_list
from mrta_rl.learners import Learner
from mrta_rl.run_layout import (
    NUMBER,
    STR,
    TEAM_FILE,
    RunDirError,
    check_schema,
    read_json,
    write_json,
)
from mrta_rl.systems import RobotSystem

TEAM = {"robots": [STR], "task_types": [STR], "willingness": [[NUMBER]]}  # team_record's


# ---------------------------------------------------------------------------------- learner state
def team_record(system: RobotSystem) -> dict[str, Any]:
    """The team a learner state belongs to: robots, task types and willingness, in order.

    Tables and weights are indexed by robot and task type, so a state of another team of the
    same shape would load and then act for robots that cannot do what it chooses.

    Args:
        system: The team (a learner's: ``learner.env.system``).
    """
    return {
        "robots": list(system.robots),
        "task_types": list(system.task_types),
        "willingness": np.asarray(system.willingness).tolist(),
    }


def save_learner(learner: Learner, directory: Path) -> None:
    """``learner.save`` into ``directory``, with the team it was trained on (:data:`TEAM_FILE`)."""
    learner.save(directory)
    write_json(directory / TEAM_FILE, team_record(learner.env.system))


def _check_team(learner: Learner, directory: Path) -> None:
    """Refuse a learner state saved for another team, naming the first robot that differs."""
    path = directory / TEAM_FILE
    if not path.exists():
        raise RunDirError(f"{path}: missing (the team the learner state was trained on)")
    saved = read_json(path)
    check_schema(saved, TEAM, path, "")
    expected = team_record(learner.env.system)
    for key in ("robots", "task_types"):
        if saved[key] != expected[key]:
            raise RunDirError(
                f"{path}: {key}: the learner state was trained on another team "
                f"({short_list(saved[key])}), not the run's system ({short_list(expected[key])})"
            )
    if len(saved["willingness"]) != len(expected["willingness"]):
        raise RunDirError(f"{path}: willingness: {len(saved['willingness'])} rows, not one a robot")
    for robot, row, want in zip(
        expected["robots"], saved["willingness"], expected["willingness"], strict=True
    ):
        if row != want:
            raise RunDirError(
                f"{path}: willingness.{robot}: the learner state was trained on another team "
                f"({short_list(row)}), not the run's system ({short_list(want)})"
            )


def load_learner(learner: Learner, directory: Path) -> None:
    """Restore a saved learner state into the learner built for the run, or refuse it.

    The state must have been saved for the run's team (:func:`save_learner`), unless it holds
    nothing of one team (``Learner.fits_any_team``: a family run's, or ``init=`` on another
    team), and the learner's ``load`` checks the files against itself (keys, shapes, dtypes,
    consistency); any problem names the file.

    Args:
        learner: The learner built for the run.
        directory: Folder written by :func:`save_learner`.

    Raises:
        RunDirError: if the folder is missing or its content does not fit the learner.
    """
    if not directory.is_dir():
        raise RunDirError(f"no saved learner state: {directory} is missing")
    if not type(learner).fits_any_team(learner.hp):
        _check_team(learner, directory)
    try:
        learner.load(directory)
    except (OSError, ValueError, KeyError, RuntimeError, EOFError) as err:
        message = str(err)
        if str(directory) not in message:
            message = f"{directory}: {message}"
        raise RunDirError(f"saved learner state refused: {message}") from err
