"""IPPO (de Witt et al. 2020): shared masked actor, per-robot critic, TorchRL's IPPOLoss."""

from __future__ import annotations

from typing import ClassVar

from torchrl.objectives.multiagent import IPPOLoss, MAPPOLoss

from mrta_rl.learners.neural.ppo import PPOLearner


class IPPOLearner(PPOLearner):
    """Independent PPO: each robot's value reads only its own inputs (no global state).

    Same actor, team reward and update as MAPPO (:class:`~mrta_rl.learners.neural.ppo.PPOLearner`);
    the critic is decentralised.
    """

    label: ClassVar[str] = "IPPO"
    centralized_critic: ClassVar[bool] = False
    loss_class: ClassVar[type[MAPPOLoss]] = IPPOLoss
