"""QMIX (Rashid et al., 2018): per-robot Q-values mixed monotonically, conditioned on the state."""

from __future__ import annotations

from typing import Annotated

from tensordict.nn import TensorDictModule
from torchrl.modules import QMixer

from mrta_rl.config import Range
from mrta_rl.learners.neural.common import MixedQLearner


class QMIXLearner(MixedQLearner):
    """Monotonic mixing: ``Q_team = f_s(Q_1, ..., Q_m)`` with ``df/dQ_i >= 0``, hypernetworks on s.

    The mixer reads the global ``state`` (:func:`~mrta_rl.envs.encodings.global_features`);
    everything else is :class:`~mrta_rl.learners.neural.common.MixedQLearner`.
    """

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
