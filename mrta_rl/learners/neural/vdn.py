"""VDN (Sunehag et al., 2018): per-robot Q-values summed into the team Q-value (VDNMixer)."""

from __future__ import annotations

from typing import ClassVar

from tensordict.nn import TensorDictModule
from torchrl.modules import VDNMixer

from mrta_rl.learners.neural.common import MixedQLearner


class VDNLearner(MixedQLearner):
    """Value decomposition: ``Q_team(s, a) = sum_i Q_i(o_i, a_i)``, trained on the team reward.

    Everything but the mixer is :class:`~mrta_rl.learners.neural.common.MixedQLearner`.
    """

    label: ClassVar[str] = "VDN"  # its mixer, a sum, has no weights
    replay_state_bytes: ClassVar[int] = 0  # no state input: the loss reads no state

    def _mixer(self) -> TensorDictModule:
        """TorchRL ``VDNMixer``: the sum of the robots' chosen Q-values (no state input)."""
        return TensorDictModule(
            VDNMixer(n_agents=self.n_robots, device=self.device),
            in_keys=[("agents", "chosen_action_value")],
            out_keys=["chosen_action_value"],
        )
