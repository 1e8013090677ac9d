"""SubG-DQN, the neural counterpart of subG-CQL (paper §4): a joint-action Q-net per sub-group."""

from __future__ import annotations

from typing import Annotated, Any, ClassVar

from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.modules import QValueModule
from torchrl.objectives import DQNLoss

from mrta_rl.config import Choices
from mrta_rl.envs import AuctionEnv
from mrta_rl.envs.torchrl_env import PRIOR_KEY
from mrta_rl.learners.memory import (
    GROUP_ADVICE,
    NEURAL_ADVICE,
    check_joint_actions,
    feature_sizes,
    mlp_weights,
    robot_groups,
)
from mrta_rl.learners.neural.networks import JointDecode, JointQ
from mrta_rl.learners.neural.q_learning import JOINT, Prior, QLearner
from mrta_rl.learners.neural.torch_learner import TorchLearner
from mrta_rl.partition import Partition
from mrta_rl.priors import JOINT_PRIORS, PRIOR_ORDERS, GreedyPrior, SpreadWaitPrior
from mrta_rl.types import GroupMap


class SubGDQNLearner(QLearner):
    """Centralised DQN inside each subG sub-group ``L_g`` over its joint actions.

    The partition (paper §4) splits the robots into sub-groups ``G1, G2, ...`` with active task
    sets ``Lambda_i``; these are the TorchRL groups (``partition.group_map()``). Sub-group ``g``
    has a Q-network from the concatenated local features of its ``m_g`` robots (its sub-group
    state) to the ``(K + 1)^{m_g}`` joint actions (spec "Observations": the joint action is the
    tuple of the robots' actions). Invalid joint actions are masked: the joint mask is the
    product of the robots' masks, applied by ``QValueModule`` (argmax and target max) and by
    :class:`~mrta_rl.learners.neural.q_learning.EpsilonGreedy` (random joint actions among valid
    ones, drawn per robot). Each group is trained with its own
    TorchRL ``DQNLoss`` on the sub-group reward (spec step 8), as subG-CQL learns one table per
    sub-group. Joint keys live under the root ``("joint", group)`` (batch ``[*]``).
    """

    label: ClassVar[str] = "subG-DQN"
    requires_partition: ClassVar[bool] = True
    memory_advice: ClassVar[str] = f"{GROUP_ADVICE}, or {NEURAL_ADVICE}"

    @classmethod
    def network_weights(
        cls, env: AuctionEnv, partition: Partition | None, settings: dict[str, Any]
    ) -> int:
        """One network per sub-group, from its robots' features to its joint actions.

        Raises:
            Unfit: if a sub-group's joint actions pass the int64 codes.
        """
        n_in, _ = feature_sizes(env, settings)
        depth, hidden = int(settings["depth"]), int(settings["hidden"])
        weights = 0
        for group, robots in robot_groups(env, partition).items():
            check_joint_actions(group, len(robots), env.n_actions)
            weights += mlp_weights(len(robots) * n_in, env.n_actions ** len(robots), depth, hidden)
        return weights

    def __init__(
        self,
        *,
        prior: Annotated[str, Choices(*JOINT_PRIORS)],
        prior_order: Annotated[str, Choices(*PRIOR_ORDERS)],
        **hp,
    ):
        """Build as every Q-learner (:class:`~mrta_rl.learners.neural.q_learning.QLearner`).

        Args:
            prior: What the untrained networks play (``priors.JOINT_PRIORS``): ``greedy``
                (the plain auction) or ``spread_wait`` (subG-CQL's prior, docs/neural.md).
            prior_order: ``spread_wait``: which idle robot is asked first
                (``priors.PRIOR_ORDERS``), as subG-CQL's ``prior_order``.
            **hp: Env, generator, partition and the settings of ``QLearner``.

        Raises:
            ValueError: on an unknown prior or prior order.
        """
        super().__init__(prior=prior, **hp)

    def _prior(self, env: AuctionEnv) -> Prior:
        """``greedy`` or subG-CQL's ``spread_wait`` per sub-group, computed from ``env``."""
        if self.hp["prior"] != "spread_wait":
            return GreedyPrior()
        robots = env.system.robots
        groups = [[robots.index(r) for r in ids] for ids in self.partition.group_map().values()]
        return SpreadWaitPrior(env, groups, self.hp["prior_order"])

    @property
    def inputs(self) -> dict[str, Any]:
        """The networks' inputs and the prior (its action is part of the Q-function)."""
        return {
            **TorchLearner.inputs.fget(self),
            "prior": self.hp["prior"],
            "prior_order": self.hp["prior_order"],
        }

    def _group_map(self) -> GroupMap:
        assert self.partition is not None  # checked by Learner.__init__ (requires_partition)
        return {g: list(ids) for g, ids in self.partition.group_map().items()}

    def _build(self) -> None:
        greedy, explore = [], []
        A = self.n_actions
        n_features = self.n_features
        for group, ids in self.group_map.items():
            n_g = len(ids)
            qnet = JointQ(
                n_features,
                n_g,
                A,
                hidden=self.hp["hidden"],
                depth=self.hp["depth"],
                auction_prior=self.hp["auction_prior"],
                device=self.device,
            )
            self.networks[group] = qnet
            qvalues = TensorDictModule(
                qnet,
                in_keys=[(group, "observation"), (group, "action_mask"), (group, PRIOR_KEY)],
                out_keys=[(JOINT, group, "action_value"), (JOINT, group, "action_mask")],
            )
            value = TensorDictSequential(
                qvalues,
                QValueModule(
                    action_space="categorical",
                    action_value_key=(JOINT, group, "action_value"),
                    action_mask_key=(JOINT, group, "action_mask"),
                    out_keys=[
                        (JOINT, group, "action"),
                        (JOINT, group, "action_value"),
                        (JOINT, group, "chosen_action_value"),
                    ],
                ),
            )
            decode = TensorDictModule(
                JointDecode(n_g, A),
                in_keys=[(JOINT, group, "action")],
                out_keys=[(group, "action")],
            )
            # collection: masked joint argmax, epsilon-greedy, decode, in one module
            egreedy = TensorDictModule(
                self._egreedy(joint=(n_g, A)),
                in_keys=[
                    (JOINT, group, "action_value"),
                    (JOINT, group, "action_mask"),
                    (group, "action_mask"),
                ],
                out_keys=[(JOINT, group, "action"), (group, "action")],
            )
            greedy += [value, decode]
            explore += [qvalues, egreedy]
            self.losses[group] = self._td_loss(
                DQNLoss,
                value,
                action_value=(JOINT, group, "action_value"),
                value=(JOINT, group, "chosen_action_value"),
                action=(JOINT, group, "action"),
                reward=(JOINT, group, "reward"),  # sub-group reward (spec step 8)
                done=(JOINT, group, "done"),
                terminated=(JOINT, group, "terminated"),
            )
        self._policy = TensorDictSequential(*greedy)
        self._collection = TensorDictSequential(*explore)

    def process_batch(self, data: TensorDictBase) -> TensorDictBase:
        """Replay transitions with the sub-group's reward and flags under ``("joint", group)``.

        The sub-group reward ``[N, 1]`` and the episode flags are what each group's
        ``DQNLoss`` reads; joint values and masks are dropped (the loss recomputes them).

        Args:
            data: ``[B, T]`` collector output.

        Returns:
            ``[B * T]`` transitions.
        """
        data = super().process_batch(data)
        drop = []
        for group in self.group_map:
            for prefix in ((), ("next",)):
                for key in ("done", "terminated"):
                    data.set((*prefix, JOINT, group, key), data.get((*prefix, key)).clone())
            # every robot of the group carries the same sub-group reward: take robot 0's
            data.set(
                ("next", JOINT, group, "reward"), data.get(("next", group, "group_reward"))[:, 0]
            )
            drop += [
                (JOINT, group, k) for k in ("action_value", "chosen_action_value", "action_mask")
            ]
        return data.exclude(*drop)
