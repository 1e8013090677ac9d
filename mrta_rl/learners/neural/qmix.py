"""QMIX (Rashid et al., 2018): per-robot Q-values mixed monotonically, conditioned on the state."""

from __future__ import annotations

from typing import Annotated, Any, ClassVar

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torchrl.modules import QMixer

from mrta_rl.config import Range
from mrta_rl.envs import AuctionEnv
from mrta_rl.learners.memory import feature_sizes
from mrta_rl.learners.neural.q_learning import MixedQLearner
from mrta_rl.partition import Partition


class QMIXLearner(MixedQLearner):
    """Monotonic mixing: ``Q_team = f_s(Q_1, ..., Q_m)`` with ``df/dQ_i >= 0``, hypernetworks on s.

    The mixer reads the global ``state`` (:func:`~mrta_rl.envs.encodings.global_features`);
    everything else is :class:`~mrta_rl.learners.neural.q_learning.MixedQLearner`.
    """

    label: ClassVar[str] = "QMIX"
    replay_state_bytes: ClassVar[int] = 1  # the state is stored as bool (process_batch)

    @classmethod
    def network_weights(
        cls, env: AuctionEnv, partition: Partition | None, settings: dict[str, Any]
    ) -> int:
        """The shared robot network and the mixer's hypernetworks."""
        m, E = env.n_robots, int(settings["mixing_embed_dim"])
        _, S = feature_sizes(env, settings)
        # TorchRL QMixer: hypernetworks W1 (S -> E m), W_final and b1 (S -> E), V (S -> E -> 1)
        mixer = (S * E * m + E * m) + 3 * (S * E + E) + (E + 1)
        return super().network_weights(env, partition, settings) + mixer

    def __init__(self, *, mixing_embed_dim: Annotated[int, Range(1)], **hyperparameters) -> None:
        """Keep the mixer width, then build as every mixed learner.

        Args:
            mixing_embed_dim: Width of the QMIX mixing layer (hypernetwork output).
            **hyperparameters: Those of :class:`~mrta_rl.learners.neural.q_learning.MixedQLearner`.
        """
        super().__init__(**hyperparameters)

    def _mixer(self) -> TensorDictModule:
        """TorchRL ``QMixer`` over the robots' chosen Q-values and the global state."""
        return TensorDictModule(
            BoolStateQMixer(
                state_shape=(self.state_size,),
                mixing_embed_dim=self.hp["mixing_embed_dim"],
                n_agents=self.n_robots,
                device=self.device,
            ),
            in_keys=[("agents", "chosen_action_value"), "state"],
            out_keys=["chosen_action_value"],
        )

    def process_batch(self, data: TensorDictBase) -> TensorDictBase:
        """The mixed learners' transitions, the state and next state kept as bool.

        The global features are 0/1 (one-hots and bits, ``encodings.global_features``), so a
        bool copy is exact at a quarter of the bytes; :class:`BoolStateQMixer` reads it back
        as float.

        Raises:
            RuntimeError: if a state holds a value other than 0 and 1 (an encoding that is not
                binary cannot be stored so).
        """
        data = super().process_batch(data)
        for key in ("state", ("next", "state")):
            state = data.get(key)
            stored = state.bool()
            if not torch.equal(stored.to(state.dtype), state):
                raise RuntimeError(f"{key}: the global features are not 0/1, cannot be bool")
            data.set(key, stored)
        return data


class BoolStateQMixer(QMixer):
    """TorchRL's ``QMixer`` over the state as the replay buffer keeps it (bool, exact 0/1)."""

    def forward(self, chosen_action_value: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        """Mix the robots' chosen Q-values ``[*, m, 1]`` under ``state`` ``[*, G]`` (any dtype)."""
        return super().forward(chosen_action_value, state.to(chosen_action_value.dtype))
