"""VDN (Sunehag et al., 2018): per-robot Q-values summed into the team Q-value (VDNMixer)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import torch
from tensordict.nn import TensorDictModule
from torchrl.modules import VDNMixer

from mrta_rl.learners.neural.q_learning import MixedQLearner


class VDNLearner(MixedQLearner):
    """Value decomposition: ``Q_team(s, a) = sum_i Q_i(o_i, a_i)``, trained on the team reward.

    Everything but the mixer is :class:`~mrta_rl.learners.neural.q_learning.MixedQLearner`. The
    sum has no weights, so with ``network=set`` nothing of the learner depends on the team: it
    trains on a family of teams (the mixer sums whichever robots the team has).
    """

    label: ClassVar[str] = "VDN"  # its mixer, a sum, has no weights
    replay_state_bytes: ClassVar[int] = 0  # no state input: the loss reads no state

    @classmethod
    def fits_any_team(cls, settings: Mapping[str, Any]) -> bool:
        """With the set network: no robot id, and the sum fits any number of robots."""
        return settings.get("network") == "set"

    def _mixer(self) -> TensorDictModule:
        """TorchRL's ``VDNMixer`` sum of the robots' chosen Q-values (no state input)."""
        return TensorDictModule(
            TeamSum(n_agents=self.n_robots, device=self.device),
            in_keys=[("agents", "chosen_action_value")],
            out_keys=["chosen_action_value"],
        )


class TeamSum(VDNMixer):
    """TorchRL's ``VDNMixer`` over however many robots a batch has.

    ``VDNMixer`` checks the robots against the count it was built with; on a family of teams a
    replayed batch holds the robots of the team it was collected on.
    """

    def forward(self, chosen_action_value: torch.Tensor) -> torch.Tensor:
        """The sum over the robots: ``[*, m, 1]`` -> ``[*, 1]``."""
        return self.mix(chosen_action_value, None)
