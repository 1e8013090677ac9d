"""Neural learners built from TorchRL parts: subG-DQN, VDN, QMIX and independent DQN (IQL)."""

from __future__ import annotations

from mrta_rl.learners.neural.common import NeuralLearner
from mrta_rl.learners.neural.iql import IQLLearner
from mrta_rl.learners.neural.qmix import QMIXLearner
from mrta_rl.learners.neural.subg_dqn import SubGDQNLearner
from mrta_rl.learners.neural.vdn import VDNLearner

__all__ = ["IQLLearner", "NeuralLearner", "QMIXLearner", "SubGDQNLearner", "VDNLearner"]
