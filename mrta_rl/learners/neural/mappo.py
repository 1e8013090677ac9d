"""MAPPO (Yu et al. 2022): shared masked actor, centralised critic, TorchRL's MAPPOLoss."""

from __future__ import annotations

from typing import ClassVar

from torchrl.objectives.multiagent import MAPPOLoss

from mrta_rl.learners.neural.ppo import PPOLearner


class MAPPOLearner(PPOLearner):
    """Multi-agent PPO with a centralised critic: each robot's value also reads the global state.

    The actor acts on each robot's own inputs; the critic sees the whole team (the global
    ``state`` next to the robot's features), trained on the team reward. Everything else is
    :class:`~mrta_rl.learners.neural.ppo.PPOLearner`.
    """

    label: ClassVar[str] = "MAPPO"
    centralized_critic: ClassVar[bool] = True
    loss_class: ClassVar[type[MAPPOLoss]] = MAPPOLoss
