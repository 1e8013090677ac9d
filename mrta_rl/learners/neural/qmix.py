"""QMIX (Rashid et al., 2018): per-robot Q-values mixed monotonically, conditioned on the state."""

from __future__ import annotations

from typing import Annotated, Any, ClassVar

from tensordict.nn import TensorDictModule
from torchrl.modules import QMixer

from mrta_rl.config import Range
from mrta_rl.envs import AuctionEnv
from mrta_rl.learners.memory import feature_sizes
from mrta_rl.learners.neural.common import MixedQLearner
from mrta_rl.partition import Partition


class QMIXLearner(MixedQLearner):
    """Monotonic mixing: ``Q_team = f_s(Q_1, ..., Q_m)`` with ``df/dQ_i >= 0``, hypernetworks on s.

    The mixer reads the global ``state`` (:func:`~mrta_rl.envs.encodings.global_features`);
    everything else is :class:`~mrta_rl.learners.neural.common.MixedQLearner`.
    """

    label: ClassVar[str] = "QMIX"

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

    def __init__(
        self, *, mixing_embed_dim: Annotated[int, Range(1)] = 32, **hyperparameters
    ) -> None:
        """Keep the mixer width, then build as every mixed learner.

        Args:
            mixing_embed_dim: Width of the QMIX mixing layer (hypernetwork output).
            **hyperparameters: Those of :class:`~mrta_rl.learners.neural.common.NeuralLearner`.
        """
        self.mixing_embed_dim = mixing_embed_dim
        super().__init__(**hyperparameters)

    def _mixer(self) -> TensorDictModule:
        """TorchRL ``QMixer`` over the robots' chosen Q-values and the global state."""
        return TensorDictModule(
            QMixer(
                state_shape=(self.state_size,),
                mixing_embed_dim=self.mixing_embed_dim,
                n_agents=self.n_robots,
                device=self.device,
            ),
            in_keys=[("agents", "chosen_action_value"), "state"],
            out_keys=["chosen_action_value"],
        )
