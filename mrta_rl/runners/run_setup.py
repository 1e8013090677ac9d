"""What a run is built from: :class:`RunSetup`, made by ``runners/train.py``'s ``build_run``.

The training loops and the evaluation take a run as a :class:`RunSetup`; it lives apart from
``train.py``, which imports the evaluation, so that neither imports the other.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from mrta_rl.envs import AuctionEnv, AuctionParams
from mrta_rl.learners import Learner
from mrta_rl.partition import Partition
from mrta_rl.runners.checkpoint import TrainingCheckpoint
from mrta_rl.systems import RobotSystem
from mrta_rl.systems.family import TeamFamily


@dataclass
class RunSetup:
    """Everything a run is built from, validated (:func:`~mrta_rl.runners.train.build_run`).

    Attributes:
        name: Learner name, the yaml stem (``greedy``, ``subg_cql``...).
        system: The robot team.
        params: Resolved dynamics parameters.
        partition: The subG partition if the learner requires one, else None.
        active_tasks: ``[m, n]`` bool ``Lambda_i`` of the learner's envs, None = ``Gamma_i``.
        env: The training env (``train.batch_size`` copies, capped by ``train.robot_copies``).
        learner: The learner, built on ``env``.
        checkpoint: Periodic training checkpoints and resuming (set by
            :func:`~mrta_rl.runners.train.train`; None: none).
        family: The family of teams training draws one team per episode from
            (:func:`~mrta_rl.runners.train.family_env`), else None; ``system`` is then its
            evaluation team.
        env_overrides: The run's ``env.*``, applied to every team of a family.
    """

    name: str
    system: RobotSystem
    params: AuctionParams
    partition: Partition | None
    active_tasks: np.ndarray | None
    env: AuctionEnv
    learner: Learner
    checkpoint: TrainingCheckpoint | None = None
    family: TeamFamily | None = None
    env_overrides: dict[str, Any] | None = None
