"""IPPO (de Witt et al. 2020): shared masked actor, per-robot critic, TorchRL's IPPOLoss."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

from torchrl.objectives.multiagent import IPPOLoss, MAPPOLoss

from mrta_rl.learners.neural.ppo import PPOLearner


class IPPOLearner(PPOLearner):
    """Independent PPO: each robot's value reads only its own inputs (no global state).

    Same actor, team reward and update as MAPPO (:class:`~mrta_rl.learners.neural.ppo.PPOLearner`);
    the critic is decentralised. With ``network=set`` nothing of it depends on the team, so it
    trains on a family of teams and plays any team.
    """

    label: ClassVar[str] = "IPPO"
    centralized_critic: ClassVar[bool] = False
    loss_class: ClassVar[type[MAPPOLoss]] = IPPOLoss

    @classmethod
    def fits_any_team(cls, settings: Mapping[str, Any]) -> bool:
        """With the set network: actor and critic read robot, slot and type tokens only."""
        return settings.get("network") == "set"
