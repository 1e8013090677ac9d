"""A torch learner from outside the package: one-step policy gradient on the team reward.

The module a user writes to add a torch learner (``docs/extending.md``): a
:class:`~mrta_rl.learners.neural.torch_learner.TorchLearner` that declares its regime and fills in
the loop's protocol. Its yaml names the class and its settings; the torch loop does the rest.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Annotated, Any, ClassVar

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from torchrl.modules import MaskedCategorical, ProbabilisticActor

from mrta_rl.config import Range
from mrta_rl.envs import AuctionEnv
from mrta_rl.learners.base import MemoryQuery
from mrta_rl.learners.memory import BYTES_PER_WEIGHT, ResourceEstimate, mlp_weights
from mrta_rl.learners.neural.networks import PerRobotQ
from mrta_rl.learners.neural.torch_learner import LoopSettings, TorchLearner
from mrta_rl.partition import Partition
from mrta_rl.priors import GreedyPrior

GROUP = "agents"


class ToyGradientLearner(TorchLearner):
    """Per-robot logits from an MLP, trained by ``-log pi(a) * r`` on each collected batch."""

    label: ClassVar[str] = "Toy gradient"
    on_policy: ClassVar[bool] = True

    @classmethod
    def network_weights(
        cls, env: AuctionEnv, partition: Partition | None, settings: dict[str, Any]
    ) -> int:
        """One MLP shared by the robots."""
        n_in = env.n_robots + 20  # an upper bound of the local features is enough here
        return mlp_weights(n_in, env.n_actions, int(settings["depth"]), int(settings["hidden"]))

    @classmethod
    def estimate_memory(cls, query: MemoryQuery) -> ResourceEstimate:
        """The network's weights."""
        weights = cls.network_weights(query.env, query.partition, query.settings)
        size = weights * BYTES_PER_WEIGHT
        return ResourceEstimate(cls.__name__, size, size, {"networks": size})

    def __init__(self, *, ticks: Annotated[int, Range(1)] = 10, **settings: Any) -> None:
        """Build as every torch learner.

        Args:
            ticks: Ticks per collected batch.
            **settings: Env, generator, partition and the settings of ``TorchLearner``.
        """
        super().__init__(**settings)

    @property
    def prior(self) -> GreedyPrior:
        """The plain auction's bid gets the logit bonus ``auction_prior``."""
        return GreedyPrior()

    def _build(self) -> None:
        logits = PerRobotQ(
            self.n_features,
            self.n_robots,
            self.n_actions,
            share_params=True,
            hidden=self.hp["hidden"],
            depth=self.hp["depth"],
            auction_prior=self.hp["auction_prior"],
            device=self.device,
        )
        self.networks["actor"] = logits
        self.actor = ProbabilisticActor(
            TensorDictModule(
                logits,
                in_keys=[(GROUP, "observation"), (GROUP, "prior_action")],
                out_keys=[(GROUP, "logits")],
            ),
            in_keys={"logits": (GROUP, "logits"), "mask": (GROUP, "action_mask")},
            out_keys=[(GROUP, "action")],
            distribution_class=MaskedCategorical,
            return_log_prob=True,
            log_prob_key=(GROUP, "log_prob"),
        )

    @property
    def policy(self) -> TensorDictModuleBase:
        """The actor's masked mode."""
        return self.actor

    @property
    def collection_policy(self) -> TensorDictModuleBase:
        """The actor, sampling."""
        return self.actor

    @classmethod
    def batch_frames(cls, settings: Mapping[str, Any], copies: int, horizon: int) -> int:
        """``ticks`` ticks of every copy."""
        return min(int(settings["ticks"]), horizon) * copies

    def loop_settings(self, copies: int, total_frames: int) -> LoopSettings:
        """One pass over each batch in one minibatch."""
        frames = self.batch_frames(self.hp, copies, self.env.params.horizon)
        return LoopSettings(frames, frames, frames, updates_per_batch=1, warmup_frames=0)

    def process_batch(self, data: TensorDictBase) -> TensorDictBase:
        """The flattened batch, its team reward scaled."""
        data = data.reshape(-1).exclude("collector")
        key = ("next", GROUP, "reward")
        data.set(key, data.get(key) * self.hp["reward_scale"])
        return data

    def loss(self, batch: TensorDictBase) -> tuple[torch.Tensor, dict[str, float]]:
        """``-log pi(a) * r``, the policy's log-probabilities recomputed."""
        dist = self.actor.get_dist(batch)
        log_prob = dist.log_prob(batch.get((GROUP, "action")))  # [N, m]
        reward = batch.get(("next", GROUP, "reward")).squeeze(-1)  # [N, m]
        total = -(log_prob * reward).mean()
        return total, {"train/loss": float(total.detach())}
