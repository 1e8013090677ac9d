"""Independent DQN per robot (IQL, Tan 1993 / Tampuu et al. 2017): the neural counterpart of DQL."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

from tensordict import TensorDictBase
from torchrl.objectives import DQNLoss

from mrta_rl.learners.neural.q_learning import PerRobotQLearner

GROUP = "agents"


class IQLLearner(PerRobotQLearner):
    """Each robot learns its Q-values on its own individual reward.

    One TorchRL group holds every robot. With ``network=mlp`` (default) its ``MultiAgentMLP``
    (``share_params=False``) holds one independent network per robot over its local view
    (vectorised), so this is ``m`` independent DQNs. With ``network=set`` the robots share the
    parameters of one robot-set network (``set_network.py``), which also lets each robot's
    Q-values read the other robots' tokens: parameter-shared independent learners. Either way
    TorchRL's ``DQNLoss`` trains on the per-robot reward ``(agents, "robot_reward")`` (spec step
    8) with the episode flags repeated per robot.
    """

    label: ClassVar[str] = "IQL"
    shared_mlp: ClassVar[bool] = False  # network=mlp: one independent network per robot

    @classmethod
    def fits_any_team(cls, settings: Mapping[str, Any]) -> bool:
        """With the set network: shared weights, no robot id, a loss per robot of any team."""
        return settings.get("network") == "set"

    def _build(self) -> None:
        self._policy, self._collection = self._per_robot_policy(GROUP, share_params=False)
        self.losses[GROUP] = self._td_loss(
            DQNLoss,
            self._policy,
            action_value=(GROUP, "action_value"),
            value=(GROUP, "chosen_action_value"),
            action=(GROUP, "action"),
            reward=(GROUP, "robot_reward"),  # individual reward of each robot
            done=(GROUP, "done"),
            terminated=(GROUP, "terminated"),
        )

    def process_batch(self, data: TensorDictBase) -> TensorDictBase:
        """Scaled rewards, root episode flags repeated for every robot (``[N, m, 1]``)."""
        data = super().process_batch(data)
        n = self.n_robots
        for key in ("done", "terminated"):
            for prefix in ((), ("next",)):
                flag = data.get((*prefix, key))  # [N, 1]
                data.set((*prefix, GROUP, key), flag.unsqueeze(-2).expand(-1, n, 1).clone())
        return data.exclude((GROUP, "action_value"), (GROUP, "chosen_action_value"))
